"""The rasterizer interface: render colour, depth and alpha of a Gaussian set for one camera.

:func:`render` = :func:`~mogs_node.mapper.projection.project_gaussians` (EWA projection, 3DGS
section 4) + :func:`~mogs_node.mapper.projection.bin_tiles` + front-to-back compositing
(:mod:`mogs_node.mapper.composite`, 3DGS section 6). It is differentiable for every Gaussian
parameter and for a 6-DoF camera pose tangent ``pose_tangent`` (left perturbation,
``T_cam_world <- exp(xi) T_cam_world``, as MonoGS uses for tracking and window pose refinement).

Backends (``RasterParams.backend``): ``"auto"`` picks ``"gsplat"`` when the tensors live on a CUDA
device and gsplat imports, else the CPU tile rasterizer (C++/OpenMP extension when it compiles,
pure PyTorch otherwise); ``"cpp"``, ``"torch"``, ``"gsplat"`` force one; ``"reference"`` is the
slow per-pixel reference (:mod:`mogs_node.mapper.raster_reference`, tests and small scenes).
"""

from __future__ import annotations

import logging

import torch

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.mapper.composite import CompositeJob, composite
from mogs_node.mapper.projection import ScreenView, bin_tiles, project_gaussians, se3_exp_torch
from mogs_node.mapper.raster_types import GaussianTensors, RasterParams, RenderOutput

__all__ = ["GaussianTensors", "RasterParams", "RenderOutput", "check_gaussians", "render"]

log = logging.getLogger(__name__)


def check_gaussians(g: GaussianTensors) -> None:
    """Raise :class:`ShapeError` naming the field if shapes/dtypes are inconsistent."""
    n = g.means.shape[0] if g.means.ndim == 2 else -1
    want = {
        "means": (n, 3),
        "quats_wxyz": (n, 4),
        "log_scales": (n, 3),
        "opacity_logit": (n,),
        "colors": (n, 3),
    }
    for name, shape in want.items():
        t = getattr(g, name)
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
            got = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            raise ShapeError(f"gaussians.{name}: expected shape {list(shape)}, got {got}")
        if not t.is_floating_point() or t.dtype != g.means.dtype:
            raise ShapeError(f"gaussians.{name}: expected dtype {g.means.dtype}, got {t.dtype}")


def render(
    gaussians: GaussianTensors,
    T_cam_world: torch.Tensor,
    K: tuple[float, float, float, float],
    width: int,
    height: int,
    *,
    background: torch.Tensor | None = None,
    pose_tangent: torch.Tensor | None = None,
    params: RasterParams = RasterParams(),  # noqa: B008 - frozen dataclass
) -> RenderOutput:
    """Render ``gaussians`` seen from ``T_cam_world`` [4, 4] (world -> camera).

    ``K = (fx, fy, cx, cy)`` pixels; ``background`` [3] rgb (default black); ``pose_tangent``
    [6] optional SE(3) tangent ``[rho, phi]`` applied on the left of ``T_cam_world`` (pass a
    zero tensor with ``requires_grad`` to get the pose gradient).
    """
    check_gaussians(gaussians)
    if not isinstance(T_cam_world, torch.Tensor) or tuple(T_cam_world.shape) != (4, 4):
        raise ShapeError("T_cam_world: expected a [4, 4] tensor")
    if width <= 0 or height <= 0:
        raise ShapeError(f"width/height: must be positive, got {width}x{height}")
    dt, dev = gaussians.means.dtype, gaussians.means.device
    T = T_cam_world.to(dtype=dt, device=dev)
    if pose_tangent is not None:
        if tuple(pose_tangent.shape) != (6,):
            raise ShapeError("pose_tangent: expected shape [6]")
        T = se3_exp_torch(pose_tangent.to(dtype=dt, device=dev)) @ T
    bg = (
        torch.zeros(3, dtype=dt, device=dev)
        if background is None
        else background.to(dtype=dt, device=dev)
    )
    backend = params.backend
    if backend == "reference":
        from mogs_node.mapper.raster_reference import render_reference

        return render_reference(gaussians, ScreenView.of(T, K, (width, height), params), bg, params)
    if backend == "gsplat" or (backend == "auto" and dev.type == "cuda"):
        from mogs_node.mapper.raster_gsplat import gsplat_available, render_gsplat

        if gsplat_available() and dev.type == "cuda":
            return render_gsplat(gaussians, T, K, width, height, bg, params)
        raise ConfigError(
            "RasterParams.backend: CUDA tensors need gsplat (pip install 'mogs-node[cuda]'); "
            "gsplat needs CUDA tensors and a usable gsplat install"
        )
    proj = project_gaussians(
        gaussians.means,
        gaussians.quats_wxyz,
        gaussians.log_scales,
        gaussians.opacity_logit,
        ScreenView.of(T, K, (width, height), params),
    )
    bins = bin_tiles(proj, width, height, params.tile_px)
    ones = torch.ones_like(proj.depths_m)[:, None]
    feats = torch.cat([gaussians.colors, proj.depths_m[:, None], ones], 1)
    bg5 = torch.cat([bg, torch.zeros(2, dtype=dt, device=dev)])
    job = CompositeJob(
        proj.means2d_px,
        proj.conics,
        proj.opacity,
        feats,
        bg5,
        bins,
        width,
        height,
        (params.alpha_min, params.alpha_max, params.t_min),
        params.threads,
    )
    out, _, counts, weights = composite(job, backend="torch" if backend == "torch" else "auto")
    return RenderOutput(out[..., :3], out[..., 3], out[..., 4], counts, weights)
