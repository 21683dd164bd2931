"""Differentiable projection of 3D Gaussians to screen-space 2D Gaussians, and tile binning.

This is the first half of 3D Gaussian splatting (Kerbl et al. 2023, section 4; EWA splatting of
Zwicker et al. 2002): every Gaussian ``N(mu, Sigma)`` with ``Sigma = R S S^T R^T`` is moved into
the camera frame and linearised around its centre, ``Sigma_2d = J W Sigma W^T J^T + eps I``. The
second half (front-to-back alpha compositing) lives in :mod:`mogs_node.mapper.composite`.

Everything here is plain PyTorch, vectorised over Gaussians, differentiable with autograd for
the Gaussian parameters and for a 6-DoF camera pose tangent (:func:`se3_exp_torch`).

Support radius: a Gaussian contributes to a pixel only where ``opacity * G >= alpha_min``
(3DGS skips smaller alphas). That region is the ellipse ``d^T Sigma_2d^-1 d <= 2 ln(opacity /
alpha_min)``, whose axis-aligned extents are ``sqrt(2 ln(opacity / alpha_min) Sigma_2d[i, i])``.
Binning with this exact extent (instead of the usual 3-sigma) makes the tiled rasterizer agree
exactly with a per-pixel reference that looks at every Gaussian.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

from mogs_node.geometry import view_tan_limits
from mogs_node.mapper.raster_types import RasterParams, TileBins

__all__ = [
    "CameraPoints",
    "Projected",
    "ScreenView",
    "TileBins",
    "bin_tiles",
    "cull_gaussians",
    "project_gaussians",
    "quat_wxyz_to_rotmat_torch",
    "se3_exp_torch",
]


def quat_wxyz_to_rotmat_torch(quats_wxyz: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[N, 3, 3]`` from (not necessarily unit) quaternions ``[N, 4]`` wxyz."""
    q = quats_wxyz / quats_wxyz.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def _hat(v: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(v[..., 0])
    return torch.stack(
        [z, -v[..., 2], v[..., 1], v[..., 2], z, -v[..., 0], -v[..., 1], v[..., 0], z], -1
    ).reshape(v.shape[:-1] + (3, 3))


def se3_exp_torch(xi: torch.Tensor) -> torch.Tensor:
    """SE(3) exponential of tangents ``xi = [rho, phi]`` (``[..., 6]``) -> ``[..., 4, 4]``.

    Same convention as :func:`mogs_node.geometry.se3_exp`; differentiable everywhere, including
    at ``xi = 0`` (Taylor expansions below a small angle, with NaN-safe branches).
    """
    rho, phi = xi[..., :3], xi[..., 3:]
    th2 = (phi * phi).sum(-1)
    small = th2 < 1e-8
    th2_safe = torch.where(small, torch.ones_like(th2), th2)
    th = th2_safe.sqrt()
    A = torch.where(small, 1 - th2 / 6, torch.sin(th) / th)
    B = torch.where(small, 0.5 - th2 / 24, (1 - torch.cos(th)) / th2_safe)
    C = torch.where(small, 1.0 / 6 - th2 / 120, (th - torch.sin(th)) / (th2_safe * th))
    Phi = _hat(phi)
    Phi2 = Phi @ Phi
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(Phi.shape)
    R = eye + A[..., None, None] * Phi + B[..., None, None] * Phi2
    V = eye + B[..., None, None] * Phi + C[..., None, None] * Phi2
    t = (V @ rho[..., None])[..., 0]
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros(xi.shape[:-1] + (1, 4), dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


@dataclass
class Projected:
    """Screen-space Gaussians (all ``[N, ...]``, differentiable except ``valid`` / ``extent_px``).

    ``means2d_px`` [N, 2] pixel centre (pixel centres at integer coordinates); ``conics`` [N, 3]
    the upper triangle ``(a, b, c)`` of ``Sigma_2d^-1``; ``depths_m`` [N] camera z; ``opacity``
    [N] in (0, 1); ``valid`` [N] bool (in front of the near plane, opaque enough, on screen);
    ``extent_px`` [N, 2] half widths of the support box (exact, see module docstring).
    """

    means2d_px: torch.Tensor
    conics: torch.Tensor
    depths_m: torch.Tensor
    opacity: torch.Tensor
    valid: torch.Tensor
    extent_px: torch.Tensor


class CameraPoints(NamedTuple):
    """Gaussian centres in a camera, all [N]: ``x``, ``y``, ``z_safe`` the camera coordinates
    with x = y = 0, z = 1 behind the near plane (nothing divides by a non-positive depth), ``z``
    the true depth, ``in_front`` (beyond the near plane), ``u``, ``v`` the centre's pixel."""

    x: torch.Tensor
    y: torch.Tensor
    z_safe: torch.Tensor
    z: torch.Tensor
    in_front: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor


@dataclass(frozen=True)
class ScreenView:
    """What a Gaussian is projected onto: the camera ``T_cam_world`` [4, 4] (world -> camera),
    ``K = (fx, fy, cx, cy)`` pixels and the image size, with the projection's settings:
    ``near_m`` (nearer Gaussians are not drawn), ``eps2d_px2`` (screen-space dilation),
    ``alpha_min`` (smaller alphas are skipped), ``log_scale_range`` (log-scales clamped into it,
    so that degenerate or exploding scales stay finite) and ``fov_clamp`` (the view-direction
    clamp of the Jacobian, as a fraction of the half field of view)."""

    T_cam_world: torch.Tensor
    K: tuple[float, float, float, float]
    width: int
    height: int
    near_m: float
    eps2d_px2: float
    alpha_min: float
    log_scale_range: tuple[float, float]
    fov_clamp: float = 1.3

    @classmethod
    def of(
        cls,
        T_cam_world: torch.Tensor,
        K: tuple[float, float, float, float],
        size: tuple[int, int],
        params: RasterParams,
    ) -> ScreenView:
        """The view of a camera (``size = (width, height)``) with a rasterizer's settings."""
        return cls(
            T_cam_world,
            K,
            size[0],
            size[1],
            near_m=params.near_m,
            eps2d_px2=params.eps2d_px2,
            alpha_min=params.alpha_min,
            log_scale_range=(params.log_scale_min, params.log_scale_max),
        )

    def camera_points(self, means: torch.Tensor) -> CameraPoints:
        """``means`` [N, 3] world -> their camera coordinates and centre pixels."""
        fx, fy, cx, cy = (float(v) for v in self.K)
        dt = means.dtype
        p_cam = means @ self.T_cam_world[:3, :3].to(dt).T + self.T_cam_world[:3, 3].to(dt)
        z = p_cam[:, 2]
        in_front = z > self.near_m
        z_s = torch.where(in_front, z, torch.ones_like(z))
        x_s = torch.where(in_front, p_cam[:, 0], torch.zeros_like(z))
        y_s = torch.where(in_front, p_cam[:, 1], torch.zeros_like(z))
        return CameraPoints(x_s, y_s, z_s, z, in_front, fx * x_s / z_s + cx, fy * y_s / z_s + cy)

    def tan_limits(self) -> tuple[float, float]:
        """The clamp of the view direction's tangents (x, y) in the Jacobian."""
        fx, fy, cx, cy = (float(v) for v in self.K)
        return view_tan_limits(fx, fy, cx, cy, self.width, self.height, self.fov_clamp)


def project_gaussians(
    means: torch.Tensor,
    quats_wxyz: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logit: torch.Tensor,
    view: ScreenView,
) -> Projected:
    """Project Gaussians (EWA, 3DGS section 4) onto ``view``.

    ``means`` [N, 3] world, ``quats_wxyz`` [N, 4], ``log_scales`` [N, 3], ``opacity_logit``
    [N]. Gaussians behind ``view.near_m`` are marked invalid and get zero gradients (NaN-safe
    ``where`` branches, never a division by a non-positive depth).
    """
    fx, fy = float(view.K[0]), float(view.K[1])
    width, height, alpha_min, eps2d_px2 = view.width, view.height, view.alpha_min, view.eps2d_px2
    R_cw = view.T_cam_world[:3, :3].to(means.dtype)
    x_s, y_s, z_s, z, in_front, u, v = view.camera_points(means)
    # Jacobian of the perspective map at a clamped view direction (3DGS: avoids huge J off-screen)
    lim_x, lim_y = view.tan_limits()
    tx = (x_s / z_s).clamp(-lim_x, lim_x)
    ty = (y_s / z_s).clamp(-lim_y, lim_y)
    inv_z = 1.0 / z_s
    zero = torch.zeros_like(z)
    J = torch.stack(
        [fx * inv_z, zero, -fx * tx * inv_z, zero, fy * inv_z, -fy * ty * inv_z], -1
    ).reshape(-1, 2, 3)
    R = quat_wxyz_to_rotmat_torch(quats_wxyz)
    s = torch.exp(log_scales.clamp(*view.log_scale_range))
    M = (J @ R_cw) @ (R * s[:, None, :])  # [N, 2, 3]
    cov = M @ M.transpose(1, 2)
    a = cov[:, 0, 0] + eps2d_px2
    b = cov[:, 0, 1]
    c = cov[:, 1, 1] + eps2d_px2
    det = (a * c - b * b).clamp_min(1e-12)
    conics = torch.stack([c / det, -b / det, a / det], -1)
    opacity = torch.sigmoid(opacity_logit)
    with torch.no_grad():
        ln_ratio = torch.log((opacity / alpha_min).clamp_min(1.0))
        ext = torch.stack([(2 * ln_ratio * a).sqrt(), (2 * ln_ratio * c).sqrt()], -1) + 1e-3
        valid = in_front & (opacity >= alpha_min) & torch.isfinite(ext).all(-1)
        valid &= (u + ext[:, 0] >= 0) & (u - ext[:, 0] <= width - 1)
        valid &= (v + ext[:, 1] >= 0) & (v - ext[:, 1] <= height - 1)
    return Projected(torch.stack([u, v], -1), conics, z, opacity, valid, ext)


@torch.no_grad()
def cull_gaussians(
    means: torch.Tensor, log_scales: torch.Tensor, opacity_logit: torch.Tensor, view: ScreenView
) -> torch.Tensor:
    """[N] bool, a superset of :func:`project_gaussians`'s ``valid`` from centres and the largest
    scale only (no rotations, no 2D covariances): the cheap visibility test of a training view.

    The EWA support half-width ``sqrt(2 ln(o / alpha_min) Sigma_2d[0, 0])`` is bounded with
    ``Sigma_2d[0, 0] <= |J_0|^2 s_max^2 + eps`` and ``|J_0|^2 <= fx^2 (1 + lim_x^2) / z^2`` (the
    clamped view direction of :func:`project_gaussians`), with 0.1 % slack for rounding."""
    fx, fy = float(view.K[0]), float(view.K[1])
    width, height, alpha_min, eps2d_px2 = view.width, view.height, view.alpha_min, view.eps2d_px2
    _, _, zs, _, in_front, u, v = view.camera_points(means)
    lim_x, lim_y = view.tan_limits()
    s2 = torch.exp(2.0 * log_scales.amax(1).clamp(*view.log_scale_range))
    opacity = torch.sigmoid(opacity_logit)
    ln2 = 2.0 * torch.log((opacity / alpha_min).clamp_min(1.0))
    bx = (ln2 * (fx * fx * (1 + lim_x * lim_x) * s2 / (zs * zs) + eps2d_px2)).sqrt() * 1.001
    by = (ln2 * (fy * fy * (1 + lim_y * lim_y) * s2 / (zs * zs) + eps2d_px2)).sqrt() * 1.001
    bx, by = bx + 0.01, by + 0.01
    return (
        in_front
        & (opacity >= alpha_min)
        & (u + bx >= 0)
        & (u - bx <= width - 1)
        & (v + by >= 0)
        & (v - by <= height - 1)
    )


@torch.no_grad()
def bin_tiles(proj: Projected, width: int, height: int, tile_px: int, cpp: bool = True) -> TileBins:
    """Assign every valid Gaussian to the tiles its support box overlaps, sorted by depth.

    On the CPU the compiled extension does it (``cpp``, when it is available: a counting sort by
    tile, the same lists exactly, ~5x less time than the torch ops below at the demo's size);
    otherwise, or for NaN centres or extents, the torch path."""
    tiles_x, tiles_y = math.ceil(width / tile_px), math.ceil(height / tile_px)
    n_tiles = tiles_x * tiles_y
    if cpp and proj.means2d_px.device.type == "cpu":
        from mogs_node.mapper.composite import load_cpp_extension  # (composite imports us)

        ext = load_cpp_extension()
        if ext is not None:
            res = ext.bin_tiles(
                proj.depths_m.detach().float().contiguous(),
                proj.valid.contiguous(),
                proj.means2d_px.detach(),
                proj.extent_px,
                width,
                height,
                tile_px,
            )
            if res:
                return TileBins(res[0], res[1], tiles_x, tiles_y, tile_px, proj.extent_px)
    order = torch.argsort(proj.depths_m.detach().float(), stable=True)
    order = order[proj.valid[order]]
    uv = proj.means2d_px.detach()[order].double()
    ext = proj.extent_px[order].double()
    x0 = torch.ceil(uv[:, 0] - ext[:, 0]).clamp(0, width - 1).long() // tile_px
    x1 = torch.floor(uv[:, 0] + ext[:, 0]).clamp(0, width - 1).long() // tile_px
    y0 = torch.ceil(uv[:, 1] - ext[:, 1]).clamp(0, height - 1).long() // tile_px
    y1 = torch.floor(uv[:, 1] + ext[:, 1]).clamp(0, height - 1).long() // tile_px
    nx = (x1 - x0 + 1).clamp_min(0)
    ny = (y1 - y0 + 1).clamp_min(0)
    counts = nx * ny
    total = int(counts.sum())
    if total == 0:
        return TileBins(
            torch.zeros(n_tiles + 1, dtype=torch.long),
            torch.zeros(0, dtype=torch.long),
            tiles_x,
            tiles_y,
            tile_px,
            proj.extent_px,
        )
    owner = torch.repeat_interleave(torch.arange(len(order)), counts)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(total) - start[owner]
    tx = x0[owner] + local % nx[owner]
    ty = y0[owner] + local // nx[owner]
    tile_id = ty * tiles_x + tx
    tile_sorted, perm = torch.sort(tile_id, stable=True)  # stable: keeps depth order per tile
    gauss_ids = order[owner[perm]]
    per_tile = torch.bincount(tile_sorted, minlength=n_tiles)
    offsets = torch.zeros(n_tiles + 1, dtype=torch.long)
    offsets[1:] = torch.cumsum(per_tile, 0)
    return TileBins(offsets, gauss_ids, tiles_x, tiles_y, tile_px, proj.extent_px)
