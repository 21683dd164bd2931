"""Depth at image edges by an epipolar line search: where textureless objects still have depth.

DIS flow fails on textureless near objects (the demo's grey pillars, a parked car's bonnet): its
forward-backward check has nothing to hold on inside them, and at their outline it smooths the
background's motion over the edge (docs/depth_prior.md, "What the prior cannot reach"). Their
outline and their creases are strong intensity edges, though, and an edge whose gradient is not
perpendicular to the epipolar line can be matched along that line, as LSD-SLAM's semi-dense depth
does (Engel et al., ICCV 2013, section 2.1: a 5-sample patch along the epipolar line, SSD, the
error from the disparity's derivative). Per edge pixel of the keyframe the reference image is
sampled along the pixel's epipolar line from the point at infinity outward in 1-px steps; the
mean-free SSD of the 5 samples is minimised, refined to sub-pixel by a parabola and accepted
when unique (best < ``ratio`` x the best outside +-3 steps). With two references the two depths
must agree within ``agree_rel``; their mean is kept, with the mean of their predicted errors. The predicted relative error is the depth
change of a ``sigma_px`` shift along the line (geometric: a short or foreshortened baseline gives
a large one), floored at ``min_rel_err``.

Pure: arrays in, arrays out (no bus). Vectorised over edge pixels and search steps.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.geometry import check_array, se3_inverse

__all__ = ["EdgeStereoParams", "edge_stereo_depth", "match_edges"]

F32 = NDArray[np.float32]


@dataclass(frozen=True)
class EdgeStereoParams:
    """Parameters of :func:`edge_stereo_depth` (``prior.edge`` in a launch file)."""

    enabled: bool = False
    min_gradient: float = 6.0  # grey levels per pixel (after a 0.7-px blur): an edge
    min_cos: float = 0.5  # |cos| of the gradient against the epipolar line (aperture problem)
    max_disparity_px: float = 120.0  # the search along the line from the point at infinity
    ratio: float = 0.6  # best SSD < ratio x the best outside +-3 steps: a unique match
    sigma_px: float = 0.5  # match error along the line that sets the predicted error
    min_rel_err: float = 0.02
    agree_rel: float = 0.05  # two references' depths must agree within this (relative)
    min_depth_m: float = 0.3
    max_depth_m: float = 300.0
    min_baseline_m: float = 0.05  # references nearer than this give nothing
    references: int = 2  # at most this many of the flow references are searched

    def __post_init__(self) -> None:
        if min(self.min_gradient, self.max_disparity_px, self.sigma_px, self.min_rel_err) <= 0:
            raise ConfigError(
                "edge: min_gradient, max_disparity_px, sigma_px, min_rel_err must be > 0"
            )
        if not 0 <= self.min_cos < 1 or not 0 < self.ratio <= 1 or self.agree_rel <= 0:
            raise ConfigError("edge: need 0 <= min_cos < 1, 0 < ratio <= 1, agree_rel > 0")
        if not 0 < self.min_depth_m < self.max_depth_m or self.references < 1:
            raise ConfigError("edge: need 0 < min_depth_m < max_depth_m and references >= 1")


def _blurred(grey: NDArray[np.uint8]) -> F32:
    return cv2.GaussianBlur(np.asarray(grey, np.float32), (0, 0), 0.7)


def _edge_mask(g: F32, params: EdgeStereoParams) -> NDArray[np.bool_]:
    edge = g > params.min_gradient
    edge[:3], edge[-3:], edge[:, :3], edge[:, -3:] = False, False, False, False
    return edge


def _edge_pixels(
    grey: NDArray[np.uint8], params: EdgeStereoParams, where: NDArray[np.bool_]
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    I = _blurred(grey)
    g = np.hypot(cv2.Sobel(I, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(I, cv2.CV_32F, 0, 1, ksize=3))
    return np.nonzero(_edge_mask(g / 8.0, params) & where)


def match_edges(
    grey_k: NDArray[np.uint8],
    grey_r: NDArray[np.uint8],
    K: NDArray[np.float64],
    T_r_k: NDArray[np.float64],
    params: EdgeStereoParams,
    pixels: tuple[NDArray[np.intp], NDArray[np.intp]] | None = None,
) -> tuple[NDArray[np.intp], NDArray[np.intp], F32, F32]:
    """Edge pixels of ``grey_k`` matched along their epipolar lines in ``grey_r``.

    ``T_r_k`` ``[4, 4]`` maps keyframe camera coordinates into the reference's. ``pixels``:
    ``(v, u)`` to try (default: every edge pixel of the keyframe). Returns ``(v, u, depth_m,
    rel_err)`` of the accepted matches (1-D, float32 depth and predicted relative error).
    """
    Ik, Ir = _blurred(grey_k), _blurred(grey_r)
    H, W = Ik.shape
    empty = (np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0, np.float32))
    R, t = T_r_k[:3, :3], T_r_k[:3, 3]
    if np.linalg.norm(t) < params.min_baseline_m:
        return (*empty, np.zeros(0, np.float32))
    gx = cv2.Sobel(Ik, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(Ik, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    g = np.hypot(gx, gy)
    if pixels is None:
        vs, us = np.nonzero(_edge_mask(g, params))
    else:
        vs, us = (np.asarray(a, np.intp) for a in pixels)
    # x_r(rho) ~ A + B rho (rho = 1 / depth): the reference projection of the pixel's ray
    rays = np.linalg.inv(K) @ np.stack([us, vs, np.ones_like(us)]).astype(np.float64)
    A = (K @ R @ rays).T
    B = K @ t
    ok = A[:, 2] > 1e-9  # the ray's point at infinity lies in front of the reference
    # keyframe epipolar direction at p: through p and the epipole (the reference's centre)
    c_k = K @ (-R.T @ t)
    if abs(c_k[2]) > 1e-9:
        e_k = np.stack([us - c_k[0] / c_k[2], vs - c_k[1] / c_k[2]], 1)
    else:
        e_k = np.tile(c_k[:2], (len(us), 1))
    e_k /= np.linalg.norm(e_k, axis=1, keepdims=True) + 1e-12
    gn = np.maximum(g[vs, us], 1e-6)
    ok &= np.abs(gx[vs, us] * e_k[:, 0] + gy[vs, us] * e_k[:, 1]) / gn >= params.min_cos
    vs, us, A, e_k = vs[ok], us[ok], A[ok], e_k[ok]
    P = len(us)
    if P == 0:
        return (*empty, np.zeros(0, np.float32))
    x0 = A[:, :2] / A[:, 2:3]
    rs = 1e-3
    x1 = (A[:, :2] + B[:2] * rs) / (A[:, 2:3] + B[2] * rs)
    e_r = x1 - x0
    e_r /= np.linalg.norm(e_r, axis=1, keepdims=True) + 1e-12
    # orient the keyframe's patch as the reference's: a small step along e_k maps (at infinity,
    # the rotation alone) onto the same side of the reference line
    Hinf = K @ R @ np.linalg.inv(K)
    p1 = np.stack([us + e_k[:, 0], vs + e_k[:, 1], np.ones(P)]) if P else np.zeros((3, 0))
    q1 = Hinf @ p1
    q1 = (q1[:2] / np.where(np.abs(q1[2]) > 1e-12, q1[2], 1e-12)).T
    sign = np.where(((q1 - x0) * e_r).sum(1) >= 0, 1.0, -1.0)
    ks = np.arange(-2, 3, dtype=np.float64)
    pk = np.stack(
        [
            us[:, None] + ks * e_k[:, :1] * sign[:, None],
            vs[:, None] + ks * e_k[:, 1:] * sign[:, None],
        ],
        -1,
    ).astype(np.float32)
    vk = cv2.remap(Ik, pk[..., 0], pk[..., 1], cv2.INTER_LINEAR)  # [P, 5]
    n = int(params.max_disparity_px) + 1
    # the line sampled once at 1-px steps from 2 px before the point at infinity; the 5-sample
    # patches at each step are windows of it (they overlap)
    m = np.arange(-2, n + 2, dtype=np.float32)
    x0f, erf = x0.astype(np.float32), e_r.astype(np.float32)
    mx = x0f[:, :1] + m * erf[:, :1]
    my = x0f[:, 1:] + m * erf[:, 1:]
    line = cv2.remap(Ir, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1e4)
    vr = np.lib.stride_tricks.sliding_window_view(line, 5, axis=1)  # [P, n, 5], no copy
    a = vk - vk.mean(1, keepdims=True)
    b = vr - vr.mean(2, keepdims=True)
    cost = ((a[:, None, :] - b) ** 2).sum(2)
    cost[(vr < -1e3).any(2)] = np.inf
    rows = np.arange(P)
    j = np.argmin(cost, 1)
    cb = cost[rows, j]
    masked = cost.copy()
    for o in range(-3, 4):
        masked[rows, np.clip(j + o, 0, n - 1)] = np.inf
    second = masked.min(1)
    energy = (a * a).sum(1)
    acc = np.isfinite(cb) & (cb < params.ratio * second) & (j > 0) & (j < n - 1)
    acc &= cb < 0.25 * energy + 10.0  # the patch matched, not just the least bad
    cm, cp = cost[rows, np.clip(j - 1, 0, n - 1)], cost[rows, np.clip(j + 1, 0, n - 1)]
    den = cm - 2 * cb + cp
    with np.errstate(invalid="ignore", divide="ignore"):
        off = np.where(np.isfinite(den) & (den > 0), 0.5 * (cm - cp) / den, 0.0)
    sp = j + np.clip(np.nan_to_num(off), -1.0, 1.0)

    def rho_at(sv: NDArray) -> NDArray:
        xr = x0 + sv[:, None] * e_r
        ax = (np.abs(e_r[:, 0]) < np.abs(e_r[:, 1])).astype(np.intp)
        xa, Aa, Ba = xr[rows, ax], A[rows, ax], B[ax]
        with np.errstate(invalid="ignore", divide="ignore"):
            return (Aa - xa * A[:, 2]) / (xa * B[2] - Ba)

    rho = rho_at(sp)
    lo, hi = rho_at(sp - params.sigma_px), rho_at(sp + params.sigma_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.abs(hi - lo) / (2.0 * np.abs(rho))
        depth = 1.0 / rho
    acc &= np.isfinite(depth) & (depth >= params.min_depth_m) & (depth <= params.max_depth_m)
    acc &= np.isfinite(rel)
    rel = np.maximum(rel, params.min_rel_err)
    return vs[acc], us[acc], depth[acc].astype(np.float32), rel[acc].astype(np.float32)


def edge_stereo_depth(
    grey_k: NDArray[np.uint8],
    K: NDArray[np.float64],
    T_world_cam_k: NDArray[np.float64],
    references: Sequence[tuple[NDArray[np.uint8], NDArray[np.float64]]],
    params: EdgeStereoParams,
    where: NDArray[np.bool_] | None = None,
) -> tuple[F32, F32]:
    """Edge depth of keyframe ``k`` ``(depth_m, rel_err)`` ``[H, W]`` (0 / inf where none).

    ``where`` ``[H, W]``: only these pixels are searched (default: all; the dense prior passes
    the pixels its flow did not measure well, which keeps the cost down).

    ``references``: ``(grey or RGB image, T_world_cam)``, nearest first; the first
    ``params.references`` with a baseline are searched. With two or more, a pixel needs the
    first two to agree (module docstring); with one, its matches are taken as they are.
    """
    grey_k = np.asarray(grey_k)
    H, W = grey_k.shape[:2]
    depth = np.zeros((H, W), np.float32)
    err = np.full((H, W), np.inf, np.float32)
    K = check_array("K", K, shape=(3, 3), finite=True)
    Tk = check_array("T_world_cam_k", T_world_cam_k, shape=(4, 4), finite=True)
    found = []
    for img, T in references[: params.references]:
        g = (
            img
            if np.ndim(img) == 2
            else cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
        )
        if g.shape != (H, W):
            continue
        T_r_k = se3_inverse(np.asarray(T, np.float64)) @ Tk
        if found:
            px = (found[0][0], found[0][1])
        elif where is not None:
            px = _edge_pixels(grey_k, params, np.asarray(where, bool))
        else:
            px = None
        m = match_edges(grey_k, g, K, T_r_k, params, pixels=px)
        if len(m[0]):
            found.append(m)
    if not found:
        return depth, err
    v, u, d, e = found[0]
    if len(found) > 1:
        flat = np.full(H * W, np.nan)
        v2, u2, d2, e2 = found[1]
        flat[v2 * W + u2] = d2
        other = flat[v * W + u]
        ok = np.isfinite(other) & (np.abs(other - d) <= params.agree_rel * d)
        e2_at = np.full(H * W, np.inf)
        e2_at[v2 * W + u2] = e2
        e = 0.5 * (e + e2_at[v * W + u])  # the mean's error: the two are not independent
        v, u, d, e = v[ok], u[ok], 0.5 * (d[ok] + other[ok]), e[ok]
    depth[v, u] = d
    err[v, u] = e
    return depth, err
