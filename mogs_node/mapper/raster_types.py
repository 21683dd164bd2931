"""The rasterizer's value types, shared by every backend (CPU tiles, gsplat): the settings, a
Gaussian set as tensors, and what a render returns. Apart from :mod:`mogs_node.mapper.rasterizer`
so that a backend module needs nothing of the dispatcher that imports it."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mogs_node.errors import ConfigError

__all__ = ["GaussianTensors", "RasterParams", "RenderOutput"]


@dataclass(frozen=True)
class RasterParams:
    """Rasterizer settings (defaults follow 3DGS / MonoGS)."""

    backend: str = "auto"  # auto | cpp | torch | gsplat | reference (per pixel, tests only)
    tile_px: int = 16  # square tile size in pixels
    near_m: float = 0.01  # Gaussians with camera z <= near_m are not drawn
    eps2d_px2: float = 0.3  # screen-space dilation added to the 2D covariance (anti-aliasing)
    alpha_min: float = 1.0 / 255.0  # smaller per-Gaussian alphas are skipped
    alpha_max: float = 0.99  # per-Gaussian alpha clamp
    t_min: float = 1e-4  # a pixel stops when its transmittance would fall below this
    log_scale_min: float = -12.0  # log-scales are clamped into [min, max] before exp
    log_scale_max: float = 8.0
    # threads of the C++ compositing passes (0: torch.get_num_threads()); a speed setting only:
    # their results are bitwise the same for any thread count (csrc/composite_cpu.cpp)
    threads: int = 0

    def __post_init__(self) -> None:
        if self.backend not in ("auto", "cpp", "torch", "gsplat", "reference"):
            raise ConfigError(f"RasterParams.backend: unknown backend {self.backend!r}")
        if self.tile_px <= 0 or self.near_m <= 0 or not 0 < self.alpha_min < self.alpha_max < 1:
            raise ConfigError(
                "RasterParams: tile_px, near_m must be > 0; 0 < alpha_min < alpha_max < 1"
            )
        if self.threads < 0:
            raise ConfigError(f"RasterParams.threads: must be >= 0, got {self.threads}")


@dataclass
class GaussianTensors:
    """A set of N Gaussians as tensors (world frame).

    ``means`` [N, 3], ``quats_wxyz`` [N, 4] (normalised inside), ``log_scales`` [N, 3],
    ``opacity_logit`` [N], ``colors`` [N, 3] (rgb in [0, 1], used as-is).
    """

    means: torch.Tensor
    quats_wxyz: torch.Tensor
    log_scales: torch.Tensor
    opacity_logit: torch.Tensor
    colors: torch.Tensor

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def tensors(self) -> tuple[torch.Tensor, ...]:
        """The five parameter tensors in field order (for gradients and optimisers)."""
        return (self.means, self.quats_wxyz, self.log_scales, self.opacity_logit, self.colors)


@dataclass
class RenderOutput:
    """``color`` [H, W, 3], ``depth`` [H, W] (z-depth weighted by alpha, not normalised: divide
    by ``alpha`` for the expected depth of the covered part), ``alpha`` [H, W] accumulated opacity,
    ``counts`` [N] int32 number of pixels each Gaussian contributed to (visibility), ``weights``
    [N] each Gaussian's summed blending weight ``sum_p alpha_i T_i`` over the image (pixels; no
    gradient), ``None`` where the backend does not produce it (gsplat)."""

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    counts: torch.Tensor
    weights: torch.Tensor | None = None


@dataclass
class TileBins:
    """Per-tile depth-sorted Gaussian lists: ``gauss_ids[tile_offsets[t]:tile_offsets[t+1]]``.

    ``tile_offsets`` [n_tiles + 1] int64, ``gauss_ids`` [M] int64; tiles are row-major,
    ``tiles_x * tiles_y`` of ``tile_px`` square pixels. ``extent_px`` [N, 2] the support half
    widths (:attr:`Projected.extent_px`), which the C++ kernel uses to visit only covered pixels.
    """

    tile_offsets: torch.Tensor
    gauss_ids: torch.Tensor
    tiles_x: int
    tiles_y: int
    tile_px: int
    extent_px: torch.Tensor
