"""Slow per-pixel reference rasterizer (tests only; ``RasterParams(backend="reference")``): every
pixel looks at every Gaussian.

Written independently of the tile path: full 3x3 covariances, the perspective Jacobian as an
explicit matrix, the 2D covariance inverted with ``torch.linalg.inv``, no tiles, no support
radius. The compositing is the literal 3DGS per-pixel loop (Kerbl et al. 2023, section 6;
skip alphas below ``alpha_min``, clamp at ``alpha_max``, stop before the transmittance drops below
``t_min``), vectorised over pixels and looping over the depth-sorted Gaussians. Differentiable by
autograd, so it also serves as the gradient reference.
"""

from __future__ import annotations

import torch

from mogs_node.mapper.projection import ScreenView, quat_wxyz_to_rotmat_torch
from mogs_node.mapper.raster_types import GaussianTensors, RasterParams, RenderOutput

__all__ = ["render_reference"]


def render_reference(
    gaussians: GaussianTensors, view: ScreenView, background: torch.Tensor, params: RasterParams
) -> RenderOutput:
    """The ``"reference"`` backend of :func:`mogs_node.mapper.rasterizer.render` (pose applied,
    ``background`` [3] given): same contract; O(H W N), small scenes only."""
    fx, fy, cx, cy = (float(v) for v in view.K)
    width, height = view.width, view.height
    g = gaussians
    dt = g.means.dtype
    T = view.T_cam_world.to(dt)
    bg = background.to(dt)
    R_cw, t_cw = T[:3, :3], T[:3, 3]
    p = g.means @ R_cw.T + t_cw
    n = p.shape[0]
    z = p[:, 2]
    front = z > params.near_m
    zs = torch.where(front, z, torch.ones_like(z))
    xs = torch.where(front, p[:, 0], torch.zeros_like(z))
    ys = torch.where(front, p[:, 1], torch.zeros_like(z))
    R = quat_wxyz_to_rotmat_torch(g.quats_wxyz)
    S = torch.diag_embed(torch.exp(g.log_scales.clamp(params.log_scale_min, params.log_scale_max)))
    Sigma = R @ S @ S @ R.transpose(1, 2)
    Sigma_cam = R_cw @ Sigma @ R_cw.T
    lim_x, lim_y = view.tan_limits()
    tx = (xs / zs).clamp(-lim_x, lim_x) * zs
    ty = (ys / zs).clamp(-lim_y, lim_y) * zs
    J = torch.zeros(n, 2, 3, dtype=dt)
    J[:, 0, 0] = fx / zs
    J[:, 0, 2] = -fx * tx / (zs * zs)
    J[:, 1, 1] = fy / zs
    J[:, 1, 2] = -fy * ty / (zs * zs)
    cov2 = J @ Sigma_cam @ J.transpose(1, 2) + params.eps2d_px2 * torch.eye(2, dtype=dt)
    conic = torch.linalg.inv(cov2)
    mean2 = torch.stack([fx * xs / zs + cx, fy * ys / zs + cy], -1)
    opacity = torch.sigmoid(g.opacity_logit)
    vv, uu = torch.meshgrid(
        torch.arange(height, dtype=dt), torch.arange(width, dtype=dt), indexing="ij"
    )
    pix = torch.stack([uu.flatten(), vv.flatten()], -1)  # [P, 2]
    color = torch.zeros(pix.shape[0], 3, dtype=dt)
    depth = torch.zeros(pix.shape[0], dtype=dt)
    alpha_acc = torch.zeros(pix.shape[0], dtype=dt)
    Tr = torch.ones(pix.shape[0], dtype=dt)
    done = torch.zeros(pix.shape[0], dtype=torch.bool)
    counts = torch.zeros(n, dtype=torch.int32)
    weights = torch.zeros(n, dtype=dt)
    for i in torch.argsort(z.detach(), stable=True).tolist():
        if not bool(front[i]) or float(opacity[i].detach()) < params.alpha_min:
            continue
        d = mean2[i] - pix
        power = -0.5 * (d[:, 0] ** 2 * conic[i, 0, 0] + d[:, 1] ** 2 * conic[i, 1, 1])
        power = power - d[:, 0] * d[:, 1] * conic[i, 0, 1]
        a = torch.clamp_max(opacity[i] * torch.exp(power.clamp_max(0.0)), params.alpha_max)
        use = (power <= 0) & (a >= params.alpha_min) & ~done
        stop = use & (Tr * (1 - a) < params.t_min)
        done = done | stop
        use = use & ~stop
        a = torch.where(use, a, torch.zeros_like(a))
        w = a * Tr
        color = color + w[:, None] * g.colors[i]
        depth = depth + w * z[i]
        alpha_acc = alpha_acc + w
        Tr = Tr * (1 - a)
        counts[i] = int(use.sum())
        weights[i] = w.detach().sum()
    color = color + Tr[:, None] * bg
    return RenderOutput(
        color.reshape(height, width, 3),
        depth.reshape(height, width),
        alpha_acc.reshape(height, width),
        counts,
        weights,
    )
