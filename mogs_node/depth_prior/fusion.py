"""How the dense prior's candidate sources are fused, checked and turned into confidence.

The candidates are the flow, the road plane and the earlier keyframes' depths warped in
(:mod:`mogs_node.depth_prior.dense_prior`, which runs the fusion).

Fusion per pixel: the candidate with the smallest ``e`` leads; candidates that agree with it within
``agree_sigmas * (e_i + e_lead)`` (relative) are averaged with inverse-variance weights, and the
error stays the leader's (the sources are not independent: the metrized and the carried depth
descend from earlier priors, so shrinking the error as for independent ones would compound
over keyframes into overconfidence); a disagreeing candidate whose own error is within ``conflict_ratio``
of the leader's raises the error to the relative disagreement (two credible sources that differ
tell how wrong one is). Sky gets nothing. The published confidence is
``c = 1 / (1 + (e / rel_err_ref)^2)``: ``c = 0.5`` means a predicted 5 % error (default), the same
mapping as the flow prior's, so confidence is comparable across sources and calibrated against
the truth in docs/depth_prior.md (error against confidence bins).

Depth edges (``FusionParams.edge_window_px``; issue 16): a depth near a jump of the fused depth
is often on the wrong side of it (a carried edge a few pixels off, the road under an object's
foot, DIS smoothing across an occlusion), mostly on the far side. How far a pixel lies behind the
nearest depth of a small window (``edge_far_only``; else the window's whole log-depth range),
``r``, adds ``edge_gain * max(r - edge_free, 0)`` to the predicted error in quadrature
(docs/depth_prior.md, "Depth edges").
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError

__all__ = [
    "FusionParams",
    "confidence_from_error",
    "depth_edge_range",
    "error_from_confidence",
    "fuse_candidates",
    "verify_candidate",
]

F32 = NDArray[np.float32]
_DepthErr = tuple[F32, F32]  # a source's (depth in m, predicted relative error), [H, W] each


@dataclass(frozen=True)
class FusionParams:
    """Parameters of the fusion of the dense prior's sources."""

    rel_err_ref: float = 0.05  # predicted relative error at which the confidence is 0.5
    warp_rel_err: float = 0.10  # predicted relative error of warped depth at metrizer conf. 1
    warp_min_confidence: float = 0.05  # metrizer confidences below this are not carried
    # at most this many earlier metrized depths are warped in (3 with the edge term: demo
    # 0.1122 / 0.748 -> 0.1147 / 0.756 at 2 -> 3, docs/depth_prior.md "Depth edges")
    warp_sources: int = 3
    carry: bool = True  # the previous keyframe's own prior, warped in, is a source too
    carry_growth: float = 1.25  # ... with its predicted error times this (pose error, aging)
    carry_min_confidence: float = 0.0  # previous-prior confidences below this are not carried
    warp_max_grey_diff: float = 3  # warped grey level vs the keyframe's: larger -> dropped
    verify_warp: bool = True  # warped sources checked against this keyframe's measurements
    verify_max_err: float = 0.05  # measurements (flow / road) predicted better than this
    verify_min_pixels: int = 200  # fewer overlapping measurements: no check
    verify_window_px: int = 41  # window of the local disagreement
    flow_check: bool = True  # warped sources contradicted by this keyframe's DIS flow are dropped
    flow_check_px: float = 1.5  # ... when the flow (fb-consistent) ends farther than this
    agree_sigmas: float = 2.0  # agreement: |d_i - d_lead| <= this * (e_i + e_lead) * d_lead
    min_confidence: float = 0.0  # fused pixels less confident than this get no prior
    conflict_ratio: float = 2.0  # a disagreeing candidate with e_i <= this * e_lead is a conflict
    # depth edges (issue 16): the fused depth's log range over an edge_window_px square raises the
    # error by edge_gain per unit above edge_free (0: off); a source's depth near a jump is often
    # on the wrong side of it (a carried edge a few pixels off, a road under an object's foot)
    edge_window_px: int = 5
    edge_gain: float = 0.5
    edge_free: float = 0.0
    edge_carried: bool = True  # the carried prior keeps the edge term (it compounds over hops)
    # only how far a pixel lies behind its window's nearest depth (the background side of a jump,
    # where the wrong depths are: AbsRel 0.40-0.82 against 0.28-0.31 on the near side, demo)
    edge_far_only: bool = True
    # untextured regions filled from their outline's edge-stereo depth (contour_fill.py; issue 16,
    # session 15; docs/depth_prior.md "Outlines of textureless objects")
    contour_fill: bool = False

    def __post_init__(self) -> None:
        if min(self.rel_err_ref, self.warp_rel_err, self.agree_sigmas) <= 0:
            raise ConfigError("fusion: rel_err_ref, warp_rel_err and agree_sigmas must be > 0")
        if not 0 < self.warp_min_confidence <= 1 or self.warp_sources < 0:
            raise ConfigError("fusion: need 0 < warp_min_confidence <= 1 and warp_sources >= 0")
        if not 0 <= self.carry_min_confidence <= 1:
            raise ConfigError("fusion: need 0 <= carry_min_confidence <= 1")
        if self.conflict_ratio < 1 or self.carry_growth < 1:
            raise ConfigError("fusion: conflict_ratio and carry_growth must be >= 1")
        if self.verify_max_err <= 0 or self.verify_min_pixels < 1 or self.verify_window_px < 1:
            raise ConfigError("fusion: need verify_max_err > 0 and verify_min_pixels >= 1")
        if self.edge_window_px < 0 or self.edge_gain < 0 or self.edge_free < 0:
            raise ConfigError("fusion: need edge_window_px, edge_gain and edge_free >= 0")


def confidence_from_error(rel_err: NDArray, rel_err_ref: float) -> NDArray[np.float32]:
    """``1 / (1 + (e / e_ref)^2)``; 0 for infinite or NaN errors."""
    e = np.asarray(rel_err, np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        c = 1.0 / (1.0 + (e / np.float32(rel_err_ref)) ** 2)
    return np.where(np.isfinite(e) & (e >= 0), c, 0.0).astype(np.float32)


def error_from_confidence(conf: NDArray, rel_err_ref: float) -> NDArray[np.float32]:
    """Inverse of :func:`confidence_from_error`: ``e_ref sqrt(1/c - 1)``; inf where ``c <= 0``."""
    c = np.asarray(conf, np.float32)
    ok = np.isfinite(c) & (c > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.float32(rel_err_ref) * np.sqrt(np.maximum(1.0 / np.where(ok, c, 1.0) - 1.0, 0.0))
    return np.where(ok, e, np.inf).astype(np.float32)


def fuse_candidates(
    depth_m: NDArray[np.float32], rel_err: NDArray[np.float32], params: FusionParams
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int64]]:
    """Fuse ``S`` candidates ``[S, H, W]`` (depth 0 / error inf = none); see module docstring.

    Returns ``(depth, rel_err, lead)`` ``[H, W]``: fused depth (0 where none), its predicted error
    (inf where none) and the index of the leading candidate (-1 where none).
    """
    d = np.asarray(depth_m, np.float32)
    e = np.asarray(rel_err, np.float32)
    if d.ndim != 3 or d.shape != e.shape:
        raise ConfigError(f"fuse_candidates: need [S, H, W] arrays, got {d.shape} / {e.shape}")
    valid = np.isfinite(d) & (d > 0) & np.isfinite(e) & (e >= 0)
    e = np.where(valid, np.maximum(e, 1e-4), np.inf).astype(np.float32)
    d = np.where(valid, d, 0.0).astype(np.float32)
    if d.shape[0] == 0:
        z = np.zeros(d.shape[1:], np.float32)
        return z, np.full(d.shape[1:], np.inf, np.float32), np.full(d.shape[1:], -1, np.int64)
    lead = np.argmin(e, axis=0)
    d_lead = np.take_along_axis(d, lead[None], 0)[0]
    e_lead = np.take_along_axis(e, lead[None], 0)[0]
    any_valid = valid.any(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        gap = np.abs(d - d_lead) / np.where(d_lead > 0, d_lead, 1.0)
        agree = valid & (gap <= params.agree_sigmas * (e + e_lead))
        w = np.where(agree, 1.0 / (e * e), 0.0)
        wsum = w.sum(0)
        fused = (w * d).sum(0) / np.where(wsum > 0, wsum, 1.0)
        conflict = valid & ~agree & (e <= params.conflict_ratio * e_lead)
        e_conf = np.where(conflict, gap, 0.0).max(0)
    e_out = np.where(any_valid, np.maximum(e_lead, e_conf), np.inf).astype(np.float32)
    d_out = np.where(any_valid, fused, 0.0).astype(np.float32)
    return d_out, e_out, np.where(any_valid, lead, -1)


def depth_edge_range(
    depth_m: NDArray[np.floating], window_px: int, far_only: bool = False
) -> NDArray[np.float32]:
    """Range of ``log(depth)`` over the valid pixels of a ``window_px`` square around each pixel
    (0 where the pixel has no depth or is alone): how far the depth jumps near it. ``far_only``:
    only how far the pixel lies behind the nearest depth of its window."""
    d = np.asarray(depth_m, np.float32)
    ok = np.isfinite(d) & (d > 0)
    if window_px < 2 or not ok.any():
        return np.zeros(d.shape, np.float32)
    ld = np.log(np.where(ok, d, 1.0)).astype(np.float32)
    box = np.ones((window_px, window_px), np.uint8)
    hi = cv2.dilate(np.where(ok, ld, np.float32(-1e4)), box, borderType=cv2.BORDER_REPLICATE)
    lo = cv2.erode(np.where(ok, ld, np.float32(1e4)), box, borderType=cv2.BORDER_REPLICATE)
    return np.where(ok, (ld if far_only else hi) - lo, 0.0).astype(np.float32)


def verify_candidate(cand: _DepthErr, meas: _DepthErr, params: FusionParams) -> tuple[F32, float]:
    """Raise a warped source's error to what this keyframe's measurements say of it.

    ``cand``: the warped source's ``(depth, error)``; ``meas``: the fresh measurements'.

    Where fresh measurements (flow / road, predicted error below ``verify_max_err``) overlap the
    warped depth, their relative disagreement measures how wrong the carried depth is (a bad
    metrized depth, pose drift). Its mean over a ``verify_window_px`` window (where the window
    holds at least ``verify_min_pixels / 16`` overlapping pixels), else its median over the
    image, is ``r``; every warped pixel's error becomes ``sqrt(e^2 + r^2)``. Returns the new
    errors and the image median (NaN when the overlap is too small to tell).
    """
    (d_w, e_w), (d_meas, e_meas) = cand, meas
    both = (d_w > 0) & np.isfinite(e_w) & (d_meas > 0) & (e_meas < params.verify_max_err)
    if not params.verify_warp or int(both.sum()) < params.verify_min_pixels:
        return e_w, float("nan")
    with np.errstate(divide="ignore", invalid="ignore"):
        gap = np.where(both, np.abs(d_w - d_meas) / d_meas, 0.0).astype(np.float32)
    r_img = float(np.median(gap[both]))
    k = params.verify_window_px
    n = cv2.blur(both.astype(np.float32), (k, k), borderType=cv2.BORDER_CONSTANT) * (k * k)
    g = cv2.blur(gap, (k, k), borderType=cv2.BORDER_CONSTANT) * (k * k)
    local = n >= max(1.0, params.verify_min_pixels / 16)
    r = np.where(local, g / np.maximum(n, 1.0), np.float32(r_img)).astype(np.float32)
    return np.sqrt(e_w * e_w + r * r).astype(np.float32), r_img
