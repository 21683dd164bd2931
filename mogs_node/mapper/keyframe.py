"""What the mapper keeps per keyframe (:class:`KeyframeState`) and its small dense Adam.

Images are kept as received (uint8, a quarter of f32's memory for the whole drive); the training
targets at a fraction of the resolution are derived once and cached
(:meth:`KeyframeState.targets`). The visibility record (ids and blending weights of the Gaussians
the keyframe's latest render drew) feeds the covisibility window and pruning without extra
rendering passes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from mogs_node.geometry import se3_inverse

__all__ = ["KeyframeState"]


class _SmallAdam:
    """Adam for one small dense tensor (exposure, pose tangent)."""

    def __init__(self, n: int) -> None:
        self.m = torch.zeros(n, dtype=torch.float64)
        self.v = torch.zeros(n, dtype=torch.float64)
        self.t = 0

    def step(self, grad: torch.Tensor, lr: float) -> torch.Tensor:
        self.t += 1
        g = torch.nan_to_num(grad.detach().double().cpu())
        self.m = 0.9 * self.m + 0.1 * g
        self.v = 0.999 * self.v + 0.001 * g * g
        mh = self.m / (1 - 0.9**self.t)
        vh = self.v / (1 - 0.999**self.t)
        return -lr * mh / (vh.sqrt() + 1e-12)


@dataclass
class KeyframeState:
    """One keyframe as the mapper keeps it."""

    keyframe_id: int
    index: int  # insertion order
    image: torch.Tensor  # [H, W, 3] uint8 as received: a quarter of f32's memory per keyframe
    # kept for the whole drive; :attr:`image_f32` converts on use (exactly the same values)
    depth_m: torch.Tensor  # [H, W] f32, 0 = no value
    confidence: torch.Tensor  # [H, W] f32 in [0, 1]
    T_cam_world: torch.Tensor  # [4, 4] f64
    exposure_ab: torch.Tensor = field(default_factory=lambda: torch.zeros(2, dtype=torch.float64))
    exposure_adam: _SmallAdam = field(default_factory=lambda: _SmallAdam(2))
    pose_adam: _SmallAdam = field(default_factory=lambda: _SmallAdam(6))
    # from the keyframe's latest render: ids of the Gaussians it drew, their blending weights
    # sum_p alpha T (full-resolution pixels), and the map's next id then (newer ids: unknown)
    visible_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    visible_weights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    weights_next_id: int = 0
    iterations: int = 0  # training iterations on this keyframe so far (owed ones go to the least)
    train_targets: tuple[torch.Tensor, ...] | None = None  # (image, depth, conf) when downsampled

    @property
    def T_world_cam(self) -> np.ndarray:
        return se3_inverse(self.T_cam_world.numpy())

    @property
    def image_f32(self) -> torch.Tensor:
        """[H, W, 3] f32 in [0, 1] (u8 / 255 in f32, as the image was stored before)."""
        return self.image.to(torch.float32) / 255.0

    def targets(self, factor: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(image [h, w, 3], depth_m [h, w], confidence [h, w]) at 1/``factor`` resolution.

        Image and confidence are area averages of ``factor`` x ``factor`` blocks (a trailing
        partial block is cropped); depth is the mean of the block's valid (> 0) depths, 0 where the
        block has none. ``factor`` 1 returns the stored tensors (nothing cached)."""
        if factor == 1:
            return self.image_f32, self.depth_m, self.confidence
        H, W = self.depth_m.shape
        cached = self.train_targets
        if cached is None or tuple(cached[1].shape) != (H // factor, W // factor):
            f = factor
            img = self.image_f32.permute(2, 0, 1)[None]
            img = torch.nn.functional.avg_pool2d(img, f)[0].permute(1, 2, 0).contiguous()
            valid = (self.depth_m > 0).to(torch.float32)[None, None]
            d_sum = torch.nn.functional.avg_pool2d(self.depth_m[None, None] * valid, f)
            n = torch.nn.functional.avg_pool2d(valid, f)
            depth = torch.where(n > 0, d_sum / n.clamp_min(1e-12), torch.zeros_like(n))[0, 0]
            conf = torch.nn.functional.avg_pool2d(self.confidence[None, None], f)[0, 0]
            made = (img, depth.contiguous(), conf.contiguous())
            if cached is None:  # the first factor asked for (the training one) is kept
                self.train_targets = made
            return made
        return cached  # type: ignore[return-value]
