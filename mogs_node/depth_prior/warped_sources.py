"""The warped sources of the dense prior: earlier keyframes' metrized depth (``warp``) and the
previous keyframe's own prior (``carry``), forward-warped into a new keyframe and checked against
its own DIS flow (:mod:`mogs_node.depth_prior.dense_prior` fuses them with the flow and the road).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_prior.flow_prior import FlowPrior, FlowPriorParams, _grey
from mogs_node.depth_prior.fusion import FusionParams, error_from_confidence
from mogs_node.depth_prior.road import project_depth
from mogs_node.depth_prior.warp import forward_warp_depth
from mogs_node.geometry import check_array, pixel_grid_xy, se3_inverse

__all__ = ["flow_check", "warp_earlier_in", "warped_candidates"]


def warp_earlier_in(
    grey_k: NDArray[np.uint8],
    Tk_inv: NDArray[np.float64],
    K: NDArray[np.float64],
    earlier: Sequence[tuple],
    max_depth_m: float,
    min_conf: float,
    params: FusionParams,
    name: str,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """``(depth, confidence, T_world_cam[, grey])`` of earlier keyframes warped into ``k``; per
    pixel the most confident one (most recent first on ties). Where the earlier keyframe's image
    is given, a warped pixel whose (blurred) grey level differs from ``k``'s by more than
    ``warp_max_grey_diff`` is dropped: it is seen through something the earlier depth lacked
    (a forward warp cannot know an occluder it was not given). Returns depth and confidence."""
    H, W = grey_k.shape
    depth = np.zeros((H, W), np.float32)
    conf = np.zeros((H, W), np.float32)
    gk = cv2.GaussianBlur(grey_k, (0, 0), 1.5).astype(np.float32)
    # the range of k's grey levels within one pixel: a warp that lands within a pixel of the
    # right place passes on texture too, a warp onto another surface does not
    box = np.ones((3, 3), np.uint8)
    gk_lo, gk_hi = cv2.erode(gk, box), cv2.dilate(gk, box)
    for i, item in enumerate(earlier):
        d_j, c_j, T_j = item[:3]
        T_j = check_array(f"{name}[{i}].T_world_cam", T_j, shape=(4, 4), finite=True)
        d_j = check_array(f"{name}[{i}].depth_m", d_j, shape=(H, W))
        c_j = check_array(f"{name}[{i}].confidence", c_j, shape=(H, W))
        with np.errstate(invalid="ignore"):
            keep = np.isfinite(c_j) & (c_j >= min_conf) & np.isfinite(d_j) & (d_j > 0)
            keep &= d_j <= max_depth_m
        vals = [np.where(keep, c_j, 0.0)]
        grey_j = item[3] if len(item) > 3 else None
        if grey_j is not None:
            g = _grey(grey_j, f"{name}[{i}].image")
            vals.append(cv2.GaussianBlur(g, (0, 0), 1.5).astype(np.float32))
        d_w, v_w = forward_warp_depth(np.where(keep, d_j, 0.0), np.stack(vals, -1), K, Tk_inv @ T_j)
        c_w = v_w[..., 0]
        if grey_j is not None:
            g_w = v_w[..., 1]
            diff = np.maximum(np.maximum(g_w - gk_hi, gk_lo - g_w), 0.0)
            c_w = np.where(diff <= params.warp_max_grey_diff, c_w, 0.0)
        take = (d_w > 0) & (d_w <= max_depth_m) & (c_w > conf)
        depth = np.where(take, d_w, depth)
        conf = np.where(take, c_w, conf)
    return depth, conf


def flow_check(
    d_c: NDArray[np.float32],
    e_c: NDArray[np.float32],
    flow: FlowPrior,
    K: NDArray[np.float64],
    T_r_k: Sequence[NDArray[np.float64]],
    params: FusionParams,
) -> tuple[NDArray[np.float32], float]:
    """Drop a warped candidate where this keyframe's own DIS flow contradicts it.

    A carried or warped depth is a hypothesis about where each pixel lands in a reference (as the
    road plane is, :mod:`mogs_node.depth_prior.road`). Where the flow to that reference is
    forward-backward consistent and the hypothesis is discriminative (it moves at least 1 px when
    the depth shrinks by 20 %), a flow end point farther than ``min(flow_check_px, disc / 2)``
    from the predicted one rejects it: typically background depth warped onto a near object that
    had no depth in the earlier keyframe (a forward warp cannot know an occluder it was not given),
    whose flow is many pixels larger. The flow pixels without a triangulated depth (low parallax,
    epipolar error) still carry this test. Returns the errors (inf where rejected) and the
    rejected share of the candidate's pixels.
    """
    has = (d_c > 0) & np.isfinite(e_c)
    if not params.flow_check or not has.any():
        return e_c, 0.0
    H, W = d_c.shape
    _, _, rays = pixel_grid_xy(K, H, W)
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    z = np.where(has, d_c, 1.0).astype(np.float32)
    bad = np.zeros((H, W), bool)
    for pair, T in zip(flow.pairs, T_r_k, strict=False):
        if pair.flow_px is None:
            continue
        u_p, v_p, ok = project_depth(z, rays, K, T)
        u_n, v_n, ok_n = project_depth(0.8 * z, rays, K, T)
        disc = np.hypot(u_n - u_p, v_n - v_p)
        res = np.hypot(u + pair.flow_px[..., 0] - u_p, v + pair.flow_px[..., 1] - v_p)
        test = has & ok & ok_n & (pair.fb_error_px < 1.0) & (disc >= 1.0)
        bad |= test & (res > np.minimum(np.float32(params.flow_check_px), 0.5 * disc))
    share = float(bad.sum() / max(1, has.sum()))
    return np.where(bad, np.float32(np.inf), e_c).astype(np.float32), share


def warped_candidates(
    grey: NDArray[np.uint8],
    Tk: NDArray[np.float64],
    K: NDArray[np.float64],
    earlier_depth: Sequence[tuple],
    previous_prior: tuple | None,
    flow_params: FlowPriorParams,
    params: FusionParams,
) -> list[tuple[str, NDArray[np.float32], NDArray[np.float32]]]:
    """The warp (metrized) and carry (previous prior) candidates: ``(name, depth, rel_err)``."""
    Tk_inv = se3_inverse(Tk)
    out = []
    if earlier_depth and params.warp_sources > 0:
        d_w, c_w = warp_earlier_in(
            grey,
            Tk_inv,
            K,
            earlier_depth[: params.warp_sources],
            flow_params.max_depth_m,
            params.warp_min_confidence,
            params,
            "earlier_depth",
        )
        e_w = np.where(c_w > 0, params.warp_rel_err / np.sqrt(np.maximum(c_w, 1e-6)), np.inf)
        out.append(("warp", d_w, e_w.astype(np.float32)))
    if previous_prior is not None and params.carry:
        d_c, c_c = warp_earlier_in(
            grey,
            Tk_inv,
            K,
            [previous_prior],
            flow_params.max_depth_m,
            max(params.carry_min_confidence, 1e-6),
            params,
            "previous_prior",
        )
        e_c = error_from_confidence(c_c, params.rel_err_ref) * np.float32(params.carry_growth)
        out.append(("carry", d_c, e_c))
    return out
