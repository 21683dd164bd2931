"""Object-guided insertion: one flat, surface-aligned Gaussian per locally planar depth patch.

Paper section III-D's argument for Table II: with accurate metric geometry the map needs fewer
Gaussians, because the geometry is right from the start. The metrizer fits planes, cylinders and
ellipsoids per object (MSC, Algorithm 1) and propagates them to every pixel of the object, so its
depth is piecewise smooth; random depth is rough everywhere. This policy reads the *depth map
itself* (never its source or confidence), the same rule for every depth source: the insertion mask
is tiled in square patches (coarse to fine, ``patch_px`` halving down to ``patch_min_px``); a patch
whose pixels all have depth and are all to be inserted, whose inverse depth is a plane within
``patch_rel_tol`` (relative RMS residual of the least-squares fit ``1/z = a du + b dv + c``; a
plane in the camera frame is exactly linear in inverse depth) and, optionally, whose colour is flat
(``patch_max_color_std``), becomes one Gaussian: centred on the fitted plane at the patch centre,
its two in-plane axes the back-projected patch edges (``patch_sigma_frac`` of their length), its
normal axis ``patch_thickness`` of their mean (a surfel, 2DGS-style), its colour the patch's mean.
Pixels that no patch covers keep the pixel-grid sampling of :func:`insertion.sample_gaussians`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mogs_node.geometry import pixel_to_normalized, quat_wxyz_from_rotmat, transform_points

__all__ = ["PatchGaussians", "PlanePatches", "plane_patches", "surface_patches"]


@dataclass(frozen=True)
class PlanePatches:
    """Square patches of one size that fit a plane in inverse depth (arrays over patches [n])."""

    u0: np.ndarray  # top-left pixel column [n] int
    v0: np.ndarray  # top-left pixel row [n] int
    a: np.ndarray  # d(1/z)/du per px [n]
    b: np.ndarray  # d(1/z)/dv per px [n]
    c: np.ndarray  # 1/z at the patch centre [n] (1/m)
    rel_rms: np.ndarray  # RMS residual of 1/z over c [n] (relative depth residual, 1st order)
    color_std: np.ndarray  # grey-level standard deviation over the patch [n] (0-255 scale)
    mean_rgb: np.ndarray  # mean colour [n, 3] (0-255)
    complete: np.ndarray  # every pixel usable (depth, in the mask, not covered) [n] bool


@dataclass(frozen=True)
class PatchGaussians:
    """The accepted patches' Gaussians and the pixels they cover."""

    means_world: np.ndarray  # [n, 3] float64
    quats_wxyz: np.ndarray  # [n, 4] float64, rotation of the Gaussian's axes into the world
    scales_m: np.ndarray  # [n, 3] float64 sigma along (edge u, edge v, normal)
    colors_rgb: np.ndarray  # [n, 3] float32 in [0, 1]
    covered: np.ndarray  # [H, W] bool: pixels of accepted patches


def _tiles(x: np.ndarray, size_px: int) -> np.ndarray:
    """``x`` [H, W, ...] cropped to whole tiles and viewed as [ty, tx, size, size, ...]."""
    ty, tx = x.shape[0] // size_px, x.shape[1] // size_px
    x = x[: ty * size_px, : tx * size_px]
    x = x.reshape(ty, size_px, tx, size_px, *x.shape[2:])
    return np.moveaxis(x, 2, 1)


def plane_patches(
    depth_m: np.ndarray, usable: np.ndarray, image_rgb: np.ndarray, size_px: int
) -> PlanePatches:
    """Least-squares plane in inverse depth over every whole ``size_px`` tile of the image.

    ``depth_m`` [H, W] (> 0 where ``usable``), ``usable`` [H, W] bool, ``image_rgb`` [H, W, 3].
    On a complete tile the centred pixel offsets form a regular grid, so the fit decouples:
    ``a = sum(du w) / sum(du^2)``, ``b`` likewise, ``c = mean(w)`` with ``w = 1 / z``. Incomplete
    tiles get ``rel_rms`` inf."""
    P = int(size_px)
    ok = _tiles(usable, P).all(axis=(2, 3))
    w = _tiles(np.where(usable, 1.0 / np.where(usable, depth_m, 1.0), 0.0), P)
    off = np.arange(P, dtype=np.float64) - (P - 1) / 2.0
    du, dv = off[None, :], off[:, None]
    s2 = P * float((off**2).sum())
    a = (w * du).sum(axis=(2, 3)) / max(s2, 1e-12)
    b = (w * dv).sum(axis=(2, 3)) / max(s2, 1e-12)
    c = w.mean(axis=(2, 3))
    r = w - (a[..., None, None] * du + b[..., None, None] * dv + c[..., None, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.sqrt((r**2).mean(axis=(2, 3))) / c
    rel = np.where(ok & (c > 0) & np.isfinite(rel), rel, np.inf)
    rgb = _tiles(np.asarray(image_rgb, dtype=np.float64), P)
    grey_std = rgb.mean(-1).std(axis=(2, 3))
    ty, tx = ok.shape
    v0, u0 = np.meshgrid(np.arange(ty) * P, np.arange(tx) * P, indexing="ij")
    return PlanePatches(
        u0=u0.ravel(),
        v0=v0.ravel(),
        a=a.ravel(),
        b=b.ravel(),
        c=c.ravel(),
        rel_rms=rel.ravel(),
        color_std=grey_std.ravel(),
        mean_rgb=rgb.mean(axis=(2, 3)).reshape(-1, 3),
        complete=ok.ravel(),
    )


def _patch_axes(
    p: PlanePatches, size_px: int, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Centre [n, 3] and edge vectors e_u, e_v [n, 3] (camera frame, m) of each patch on its
    fitted plane, and whether the plane is in front of the camera over the whole patch [n]."""
    P = float(size_px)
    uc, vc = p.u0 + (P - 1) / 2.0, p.v0 + (P - 1) / 2.0

    def point(du: float, dv: float) -> tuple[np.ndarray, np.ndarray]:
        w = p.c + p.a * du + p.b * dv
        x, y = pixel_to_normalized(K, uc + du, vc + dv)
        z = 1.0 / np.where(w > 0, w, 1.0)
        return np.stack([x * z, y * z, z], -1), w > 0

    h = P / 2.0
    centre, ok = point(0.0, 0.0)
    (pu1, o1), (pu0, o2) = point(h, 0.0), point(-h, 0.0)
    (pv1, o3), (pv0, o4) = point(0.0, h), point(0.0, -h)
    return centre, pu1 - pu0, pv1 - pv0, ok & o1 & o2 & o3 & o4


def surface_patches(
    image_rgb: np.ndarray,
    depth_m: np.ndarray,
    mask: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    *,
    patch_px: int,
    min_patch_px: int,
    rel_tol: float,
    max_color_std: float,
    sigma_frac: float,
    thickness: float,
    max_footprint_rad: float,
) -> PatchGaussians:
    """One flat Gaussian per accepted patch of ``mask`` (module docstring), coarse to fine.

    ``image_rgb`` [H, W, 3] uint8, ``depth_m`` [H, W] (finite, > 0 where usable), ``mask`` [H, W]
    bool (pixels to insert), ``K`` [3, 3], ``T_world_cam`` [4, 4]. A patch is also refused when an
    in-plane axis is longer than ``max_footprint_rad`` times its distance (grazing planes: a long
    streak the mapper's size pruning would drop). ``max_color_std`` 0: no colour test."""
    H, W = mask.shape
    free = mask & np.isfinite(depth_m) & (depth_m > 0)
    covered = np.zeros((H, W), bool)
    parts: list[tuple[np.ndarray, ...]] = []
    size = int(patch_px)
    while size >= max(int(min_patch_px), 2):
        pp = plane_patches(depth_m, free & ~covered, image_rgb, size)
        keep = pp.complete & (pp.rel_rms < rel_tol)
        if max_color_std > 0:
            keep &= pp.color_std <= max_color_std
        centre, e_u, e_v, front = _patch_axes(pp, size, K)
        dist = np.linalg.norm(centre, axis=-1)
        longest = np.maximum(np.linalg.norm(e_u, axis=-1), np.linalg.norm(e_v, axis=-1))
        keep &= front & (sigma_frac * longest <= max_footprint_rad * dist)
        idx = np.flatnonzero(keep)
        if len(idx):
            parts.append((centre[idx], e_u[idx], e_v[idx], pp.mean_rgb[idx]))
            ty, tx = H // size, W // size
            grid = keep.reshape(ty, tx).repeat(size, 0).repeat(size, 1)
            covered[: ty * size, : tx * size] |= grid
        size //= 2
    if not parts:
        z3 = np.zeros((0, 3))
        return PatchGaussians(z3, np.zeros((0, 4)), z3, np.zeros((0, 3), np.float32), covered)
    centre, e_u, e_v, rgb = (np.concatenate(x) for x in zip(*parts))
    return _flat_gaussians(centre, e_u, e_v, rgb, T_world_cam, sigma_frac, thickness, covered)


def _flat_gaussians(
    centre: np.ndarray,
    e_u: np.ndarray,
    e_v: np.ndarray,
    rgb: np.ndarray,
    T_world_cam: np.ndarray,
    sigma_frac: float,
    thickness: float,
    covered: np.ndarray,
) -> PatchGaussians:
    """Gaussians with covariance ``sigma_frac^2 (e_u e_u^T + e_v e_v^T) + (thickness s)^2 n n^T``
    (``s`` the mean in-plane sigma, ``n`` the plane normal), in the world frame: the eigen-
    decomposition gives the rotation and the three sigmas (the edges need not be orthogonal)."""
    n = np.cross(e_u, e_v)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    cov = sigma_frac**2 * (e_u[:, :, None] * e_u[:, None, :] + e_v[:, :, None] * e_v[:, None, :])
    s_plane = sigma_frac * 0.5 * (np.linalg.norm(e_u, axis=-1) + np.linalg.norm(e_v, axis=-1))
    cov += (thickness * s_plane)[:, None, None] ** 2 * (n[:, :, None] * n[:, None, :])
    T_wc = np.asarray(T_world_cam, dtype=np.float64)
    R_wc = T_wc[:3, :3]
    cov_w = R_wc @ cov @ R_wc.T
    eigval, eigvec = np.linalg.eigh(cov_w)
    eigvec = eigvec * np.where(np.linalg.det(eigvec) < 0, -1.0, 1.0)[:, None, None]  # proper
    sigmas = np.sqrt(np.maximum(eigval, 1e-20))
    return PatchGaussians(
        means_world=transform_points(T_wc, centre),
        quats_wxyz=quat_wxyz_from_rotmat(eigvec),
        scales_m=sigmas,
        colors_rgb=(rgb / 255.0).astype(np.float32),
        covered=covered,
    )
