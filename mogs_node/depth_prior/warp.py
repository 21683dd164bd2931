"""Forward warp of an earlier keyframe's depth into a new keyframe, with a z-buffer.

Each source pixel with a depth is lifted to 3D (``X_j = d K^-1 [u, v, 1]``), moved into the new
camera (``X_k = T_k_j X_j``) and splatted onto the target pixel nearest its projection; where
several points land on a pixel the nearest point wins (z-buffer), so a foreground object hides what
lies behind it. A second pass splats onto the 2x2 pixels around each projection, into pixels the
first left empty only (closing the cracks of a forward motion magnifying the scene up to 2x). Remaining one-pixel cracks inside a surface (all valid 4-neighbours within ``crack_rel`` of
each other) are filled with their mean. Pixels the source never saw (disocclusions, outside its
view) stay empty. Vectorised: one ``np.minimum.at`` over the splats, no Python loop over pixels.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ShapeError
from mogs_node.geometry import check_array

__all__ = ["forward_warp_depth"]


def forward_warp_depth(
    depth_j_m: NDArray[np.floating],
    value_j: NDArray[np.floating] | None,
    K: NDArray[np.float64],
    T_k_j: NDArray[np.float64],
    *,
    out_hw: tuple[int, int] | None = None,
    min_depth_m: float = 1e-3,
    crack_rel: float = 0.05,
    occlusion_rel: float = 0.1,
    max_footprint: int = 9,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Warp z-depth ``depth_j_m`` ``[H, W]`` (0 / non-finite = none) of camera ``j`` into ``k``.

    Args:
        depth_j_m: source z-depth; value_j: optional ``[H, W]`` or ``[H, W, C]`` per-pixel
            values carried along (e.g. a confidence, an intensity; those of the winning, nearest
            point).
        K: ``[3, 3]`` intrinsics of both cameras; T_k_j: ``[4, 4]`` pose of ``j`` in ``k``.
        out_hw: target size (default the source's).
        occlusion_rel, max_footprint: a point magnified by the motion covers a square of up to
            ``max_footprint`` pixels, over pixels farther than ``1 + occlusion_rel`` times it
            (:func:`_magnified_splats`; ``occlusion_rel = inf`` turns this off).

    Returns:
        ``(depth_k_m, value_k)``, ``[H', W']`` float32, 0 where nothing landed.
    """
    d = np.asarray(depth_j_m, np.float32)
    if d.ndim != 2:
        raise ShapeError(f"depth_j_m: expected [H, W], got shape {list(d.shape)}")
    H, W = d.shape
    val = np.ones((H, W), np.float32) if value_j is None else np.asarray(value_j, np.float32)
    if val.shape[:2] != (H, W) or val.ndim not in (2, 3):
        raise ShapeError(
            f"value_j: expected shape {[H, W]} or {[H, W, 'C']}, got {list(val.shape)}"
        )
    C = 1 if val.ndim == 2 else val.shape[2]
    val2 = val.reshape(H * W, C)
    K = check_array("K", K, shape=(3, 3), finite=True)
    T = check_array("T_k_j", T_k_j, shape=(4, 4), finite=True)
    Ho, Wo = (H, W) if out_hw is None else out_hw
    depth_k = np.zeros((Ho, Wo), np.float32)
    value_k = np.zeros((Ho, Wo) + val.shape[2:], np.float32)
    with np.errstate(invalid="ignore"):
        src = np.flatnonzero(
            np.isfinite(d).ravel() & (d > min_depth_m).ravel() & np.isfinite(val2).all(1)
        )
    if src.size == 0:
        return depth_k, value_k
    v_j, u_j = np.divmod(src, W)
    Kinv = np.linalg.inv(K)
    z = d.ravel()[src].astype(np.float64)
    x = (Kinv[0, 0] * u_j + Kinv[0, 1] * v_j + Kinv[0, 2]) * z
    y = (Kinv[1, 1] * v_j + Kinv[1, 2]) * z
    P = T[:3, :3] @ np.stack([x, y, z]) + T[:3, 3:4]
    front = P[2] > min_depth_m
    P, vals = P[:, front], val2[src][front]
    u = K[0, 0] * P[0] / P[2] + K[0, 1] * P[1] / P[2] + K[0, 2]
    v = K[1, 1] * P[1] / P[2] + K[1, 2]
    zbuf = np.full(Ho * Wo, np.inf)
    vbuf = np.zeros((Ho * Wo, C), np.float32)
    # pass 1: the nearest pixel (exact where the motion does not magnify); pass 2: the 2x2
    # footprint around the projection, only into pixels pass 1 left empty (cracks)
    nearest = [(np.rint(u).astype(np.int64), np.rint(v).astype(np.int64))]
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    footprint = [(u0 + du, v0 + dv) for du in (0, 1) for dv in (0, 1)]
    for splats in (nearest, footprint):
        idx, zs, vs = [], [], []
        for uu, vv in splats:  # at most four vectorised passes, not a loop over points
            ok = (uu >= 0) & (uu < Wo) & (vv >= 0) & (vv < Ho)
            idx.append(vv[ok] * Wo + uu[ok])
            zs.append(P[2][ok])
            vs.append(vals[ok])
        idx_a, z_a, v_a = np.concatenate(idx), np.concatenate(zs), np.concatenate(vs)
        free = ~np.isfinite(zbuf[idx_a])
        idx_a, z_a, v_a = idx_a[free], z_a[free], v_a[free]
        if idx_a.size == 0:
            continue
        z_new = np.full(Ho * Wo, np.inf)
        np.minimum.at(z_new, idx_a, z_a)
        win = z_a == z_new[idx_a]
        vbuf[idx_a[win]] = v_a[win]
        zbuf = np.minimum(zbuf, z_new)
    # pass 3: magnified points cover their footprint, over empty pixels and over pixels
    # farther than 1 + occlusion_rel times them (background seen through the gaps)
    if np.isfinite(occlusion_rel):
        splats = _magnified_splats(u, v, z[front] / np.maximum(P[2], 1e-9), max_footprint)
        if splats:
            pi = np.concatenate([p for p, _, _ in splats])
            uu = np.concatenate([a for _, a, _ in splats])
            vv = np.concatenate([b for _, _, b in splats])
            ok = (uu >= 0) & (uu < Wo) & (vv >= 0) & (vv < Ho)
            pi, idx_a = pi[ok], vv[ok] * Wo + uu[ok]
            z_a = P[2][pi]
            z_new = np.full(Ho * Wo, np.inf)
            np.minimum.at(z_new, idx_a, z_a)
            take = z_new * (1.0 + occlusion_rel) < zbuf
            win = (z_a == z_new[idx_a]) & take[idx_a]
            vbuf[idx_a[win]] = vals[pi[win]]
            zbuf = np.where(take, z_new, zbuf)
    hit = np.isfinite(zbuf)
    depth_k.ravel()[hit] = zbuf[hit]
    vbuf[~hit] = 0.0
    vk = vbuf.reshape(Ho, Wo, C)
    _fill_cracks(depth_k, vk, crack_rel)
    value_k[...] = vk if val.ndim == 3 else vk[..., 0]
    return depth_k, value_k


def _magnified_splats(
    u: NDArray[np.float64], v: NDArray[np.float64], mag: NDArray[np.float64], max_footprint: int
) -> list[tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]]:
    """Footprint splats of magnified points: ``(point index, u, v)`` per offset.

    Approaching a near object magnifies it by about ``mag = z_j / z_k``: its points land that many
    pixels apart, and what lies behind it would show through the gaps a 2x2 splat cannot close
    (background depth on a pole one metre ahead: a relative error of 10 or more). A point
    magnified more than 1.5x covers a ``k x k`` square around its projection, ``k`` the odd size
    at or above its magnification (at most ``max_footprint``).
    """
    size = np.clip(2 * np.ceil(0.5 * (mag - 1)).astype(np.int64) + 1, 1, max_footprint)
    big = np.flatnonzero((mag > 1.5) & (size >= 3))
    out = []
    if big.size == 0:
        return out
    r_pt = size[big] // 2
    uc, vc = np.rint(u[big]).astype(np.int64), np.rint(v[big]).astype(np.int64)
    r_max = int(r_pt.max())
    for du in range(-r_max, r_max + 1):  # at most max_footprint^2 vectorised passes
        for dv in range(-r_max, r_max + 1):
            sel = (np.abs(du) <= r_pt) & (np.abs(dv) <= r_pt)
            out.append((big[sel], uc[sel] + du, vc[sel] + dv))
    return out


def _fill_cracks(depth: NDArray[np.float32], value: NDArray[np.float32], rel: float) -> None:
    """Fill empty pixels whose 4 neighbours all hold depths within ``rel`` of each other
    (``value`` ``[H, W, C]``: the neighbours' minimum, a conservative confidence)."""
    p = np.pad(depth, 1)
    pv = np.pad(value, ((1, 1), (1, 1), (0, 0)))
    nb = np.stack([p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]])
    nv = np.stack([pv[:-2, 1:-1], pv[2:, 1:-1], pv[1:-1, :-2], pv[1:-1, 2:]])
    lo, hi = nb.min(0), nb.max(0)
    crack = (depth == 0) & (lo > 0) & (hi <= lo * (1 + rel))
    depth[crack] = nb.mean(0)[crack]
    value[crack] = nv.min(0)[crack]
