"""Parameters of the mapper core (:class:`~mogs_node.mapper.mapper.GaussianMapper`) and the device
it runs on."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from mogs_node.errors import ConfigError
from mogs_node.mapper.insertion import (
    InsertionParams,
)
from mogs_node.mapper.rasterizer import RasterParams

__all__ = ["MapperParams", "resolve_device"]


@dataclass(frozen=True)
class MapperParams:
    """Mapper settings (MonoGS defaults where they exist; learning rates for metric scenes)."""

    raster: RasterParams = field(default_factory=RasterParams)  # rasterizer settings
    insertion: InsertionParams = field(default_factory=InsertionParams)  # insertion settings
    window_size: int = 8  # keyframes in the optimisation window
    overlap_min: float = 0.3  # window keyframes seeing less of the newest one's Gaussians leave
    n_random_past: int = 2  # random past (non-window) keyframes among the views an iteration
    # samples from (against forgetting): odd iterations pick uniformly from the older window
    # keyframes plus this many past keyframes drawn afresh
    train_downsample: int = 1  # optimise at 1/n of the resolution (area-averaged targets)
    insert_downsample: int = 1  # the insertion render at 1/n of the resolution (nearest-upsampled)
    converge_rel: float = 0.0  # end a round once the newest view's L1 error fell by less than
    # this fraction since its previous iteration (0: always run every iteration asked for)
    min_iters: int = 4  # ... but never before this many iterations of the round
    device: str = "cpu"  # cpu | cuda | cuda:N (cuda: gsplat rasterizer, needs CUDA + gsplat)
    lambda_depth: float = 0.1  # weight of the confidence-weighted relative depth L1
    lambda_iso: float = 0.05  # weight of the isotropic regulariser on log-scales
    lambda_ssim: float = 0.0  # weight of the D-SSIM term in the photometric loss (3DGS eq. 7:
    # (1 - l) L1 + l (1 - SSIM); 3DGS and MonoGS's colour refinement use 0.2)
    refine_lambda_ssim: float = 0.0  # ... in the final refinement (:meth:`refine`; MonoGS's
    # colour refinement uses 0.2 there and none while mapping)
    refine_lr_scale: float = 1.0  # the final refinement's map learning rates at its start ...
    refine_lr_final: float = 1.0  # ... decay exponentially to this fraction of that at its end
    # (3DGS decays its position step 100x over training: large steps early, a settled map last)
    refine_lambda_depth: float = (
        -1.0
    )  # depth-loss weight in the final refinement (-1: lambda_depth)
    lr_means_m: float = 0.002  # Adam step size of positions (metres)
    lr_colors: float = 0.01  # of colours
    lr_opacity: float = 0.05  # of opacity logits
    lr_log_scales: float = 0.01  # of log-scales
    lr_quats: float = 0.002  # of quaternions
    exposure: bool = True  # per-keyframe affine exposure compensation exp(a) c + b
    lr_exposure: float = 0.005  # Adam step size of (a, b)
    exposure_gauge: bool = False  # the first keyframe's exposure stays the identity: the map's
    # colours are in its brightness (without it the map colours and every exposure drift together
    # and a render without exposure, such as the report's, is off by that drift)
    refine_poses: bool = False  # optimise window keyframe poses (SE(3) tangents)
    lr_pose: float = 1e-4  # Adam step size of pose tangents
    prune_opacity: float = 0.005  # Gaussians below this opacity are removed
    prune_size_ratio: float = 0.2  # removed when largest sigma > ratio * distance to the newest kf
    support_kfs: int = 3  # after this many newer keyframes, a Gaussian must have ...
    support_min_obs: int = 1  # ... been seen by at least this many window keyframes (MonoGS: 3;
    # 1 here: under forward motion image borders are seen by one keyframe only)
    prune_contrib_px: float = 1.0  # redundant below this summed blending weight (pixels) over
    # the window views; applies to Gaussians the window sees, born before the newest keyframe
    prune_min_steps: int = 1  # support and redundancy are judged only for Gaussians optimised
    # (drawn by a training iteration) at least this many times; opacity and size always
    densify: bool = False  # clone Gaussians with large view-space positional gradient
    densify_grad_px: float = 0.0005  # mean |d loss / d mean| * depth / f threshold for cloning
    seed: int = 0  # random past keyframe choice

    def __post_init__(self) -> None:
        if self.window_size < 1 or self.n_random_past < 0:
            raise ConfigError("MapperParams: window_size >= 1, n_random_past >= 0")
        if not all(
            0 <= v <= 1 for v in (self.lambda_depth, self.lambda_ssim, self.refine_lambda_ssim)
        ):
            raise ConfigError(
                "MapperParams: lambda_depth, lambda_ssim, refine_lambda_ssim must be in [0, 1]"
            )
        if self.refine_lr_scale <= 0 or self.refine_lr_final <= 0:
            raise ConfigError("MapperParams: refine_lr_scale and refine_lr_final must be > 0")
        if not (self.refine_lambda_depth == -1.0 or 0 <= self.refine_lambda_depth <= 1):
            raise ConfigError("MapperParams.refine_lambda_depth: -1 or in [0, 1]")
        if (
            self.train_downsample < 1
            or self.insert_downsample < 1
            or self.converge_rel < 0
            or self.min_iters < 1
        ):
            raise ConfigError(
                "MapperParams: train_downsample, insert_downsample >= 1, converge_rel >= 0, min_iters >= 1"
            )
        if self.device != "cpu" and not self.device.startswith("cuda"):
            raise ConfigError(f"MapperParams.device: 'cpu' or 'cuda[:N]', got {self.device!r}")


def resolve_device(name: str) -> torch.device:
    """The torch device for ``MapperParams.device``; :class:`ConfigError` when CUDA is asked for
    but this machine has none (or not that index)."""
    if name == "cpu":
        return torch.device("cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as err:
        raise ConfigError(f"mapper device: not a torch device: {name!r}") from err
    if dev.type != "cuda":
        raise ConfigError(f"mapper device: 'cpu' or 'cuda[:N]', got {name!r}")
    if not torch.cuda.is_available():
        raise ConfigError(f"mapper device {name!r}: CUDA is not available on this machine")
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ConfigError(
            f"mapper device {name!r}: only {torch.cuda.device_count()} CUDA device(s) here"
        )
    return dev
