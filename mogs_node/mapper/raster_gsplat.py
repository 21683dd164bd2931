"""CUDA backend of the rasterizer through gsplat (``pip install mogs-node[cuda]``).

Imported lazily by :func:`mogs_node.mapper.rasterizer.render` only for CUDA tensors. gsplat 1.x
compiles its CUDA kernels on first use (needs nvcc matching the CUDA build of torch).

Differences from the CPU backend, by design of gsplat: the support radius is gsplat's (3 sigma
based) instead of the exact 1/255 ellipse, so images agree to a small tolerance rather than
bit-for-bit; ``counts`` is 1 for every Gaussian gsplat projected on screen (radius > 0) and 0
otherwise, a visibility flag rather than a pixel count (occlusion is not considered).
"""

from __future__ import annotations

import functools

import torch

from mogs_node.mapper.raster_types import GaussianTensors, RasterParams, RenderOutput

__all__ = ["gsplat_available", "render_gsplat"]


@functools.cache
def gsplat_available() -> bool:
    """True when CUDA is available and gsplat imports."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:  # noqa: BLE001 - any import failure means: not usable
        return False
    return True


def render_gsplat(
    gaussians: GaussianTensors,
    T_cam_world: torch.Tensor,
    K: tuple[float, float, float, float],
    width: int,
    height: int,
    background: torch.Tensor,
    params: RasterParams,
) -> RenderOutput:
    """Same contract as :func:`~mogs_node.mapper.rasterizer.render` (pose already applied)."""
    from gsplat import rasterization

    g = gaussians
    dev, dt = g.means.device, torch.float32
    if g.means.shape[0] == 0:
        # gsplat's launch configuration divides by the Gaussian count (SIGFPE on an empty map)
        zeros = torch.zeros(height, width, dtype=g.means.dtype, device=dev)
        color = background.to(device=dev, dtype=g.means.dtype).expand(height, width, 3).clone()
        return RenderOutput(
            color, zeros, zeros.clone(), torch.zeros(0, dtype=torch.int32, device=dev)
        )
    fx, fy, cx, cy = (float(v) for v in K)
    # our pixel centres lie at integer coordinates, gsplat's at +0.5: shift the principal point
    cx, cy = cx + 0.5, cy + 0.5
    Ks = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], device=dev, dtype=dt)[None]
    viewmat = T_cam_world.to(device=dev, dtype=dt)[None]
    scales = torch.exp(g.log_scales.clamp(params.log_scale_min, params.log_scale_max)).to(dt)
    # rgb only: with render_mode "RGB+D" gsplat appends the depth channel's zero background itself
    bg = background.to(device=dev, dtype=dt)
    img, alpha, meta = rasterization(
        means=g.means.to(dt),
        quats=g.quats_wxyz.to(dt),
        scales=scales,
        opacities=torch.sigmoid(g.opacity_logit).to(dt),
        colors=g.colors.to(dt),
        viewmats=viewmat,
        Ks=Ks,
        width=width,
        height=height,
        near_plane=params.near_m,
        eps2d=params.eps2d_px2,
        tile_size=params.tile_px,
        render_mode="RGB+D",
        backgrounds=bg[None],
        packed=False,
    )
    radii = meta["radii"][0]
    visible = (radii > 0).reshape(radii.shape[0], -1).all(-1) if radii.ndim > 1 else radii > 0
    return RenderOutput(
        color=img[0, ..., :3].to(g.means.dtype),
        depth=img[0, ..., 3].to(g.means.dtype),
        alpha=alpha[0, ..., 0].to(g.means.dtype),
        counts=visible.to(torch.int32),
    )
