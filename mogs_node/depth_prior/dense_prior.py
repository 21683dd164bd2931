"""Dense weight-free depth prior: flow, road plane and warped earlier depth, fused by confidence.

The default prior backend (DESIGN.md section 3; paper III-A's LFM slot). Three sources, each with a
*predicted relative depth error* ``e`` per pixel:

1. ``flow``: two-view DIS depth against one or more earlier keyframes
   (:func:`mogs_node.depth_prior.flow_prior.compute_flow_prior`); ``e = sigma / parallax_px``
   (match error over parallax), recovered from its confidence.
2. ``road``: the road plane at the calibrated camera height, verified against the nearest
   reference's flow and image (:mod:`mogs_node.depth_prior.road`); ``e`` grows as
   ``sigma_n / sin(angle below the horizon)``.
3. ``warp``: earlier keyframes' metrized depth (``/metrizer/depth``) forward-warped with the
   frontend's poses and a z-buffer (:mod:`mogs_node.depth_prior.warp`);
   ``e = warp_rel_err / sqrt(c_m)`` (``c_m`` the metrizer's confidence, floored at
   ``warp_min_confidence``). This carries depth through standstill, where there is no baseline.

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

The prior is metric (``DepthMap.kind = "metric"``) because all three sources are: the frontend's
poses are metric (VI or road-scaled), the plane height is metric, the metrizer's depth is metric.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_prior.contour_fill import ContourFillParams, outline_fill
from mogs_node.depth_prior.edge_stereo import EdgeStereoParams
from mogs_node.depth_prior.flow_prior import (
    FlowPrior,
    FlowPriorParams,
    _grey,
    compute_flow_prior,
    ground_depth_bound,
)
from mogs_node.depth_prior.ground_height import (
    fit_ground_height,
    ground_height_m,
    refine_ground_height,
)
from mogs_node.depth_prior.road import RoadPriorParams, project_depth, road_prior, up_in_camera
from mogs_node.depth_prior.warp import forward_warp_depth
from mogs_node.errors import ConfigError
from mogs_node.geometry import check_array, pixel_grid_xy, se3_inverse

EDGE_PARAMS = EdgeStereoParams(enabled=True)  # FusionParams.contour_fill: the edge search's
CONTOUR_PARAMS = ContourFillParams()  # FusionParams.contour_fill: the fill's defaults
AUTO_HEIGHT_MEASUREMENTS = 10  # road.auto_height: keyframes measured before the height is settled

__all__ = [
    "SOURCES",
    "DensePrior",
    "FusionParams",
    "PriorHistory",
    "compute_dense_prior",
    "confidence_from_error",
    "depth_edge_range",
    "error_from_confidence",
    "fuse_candidates",
]

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
_DepthErr = tuple[F32, F32]  # a source's (depth in m, predicted relative error), [H, W] each

#: source codes of :attr:`DensePrior.source` (0 = none)
SOURCES = {"flow": 1, "road": 2, "warp": 3, "carry": 4, "contour": 5}


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


@dataclass(frozen=True)
class PriorHistory:
    """What earlier keyframes give a new keyframe's prior (:func:`compute_dense_prior`; the
    node's :class:`~mogs_node.depth_prior.sequence.PriorSequence` assembles it).

    Attributes:
        references: ``(image, T_world_cam)`` of earlier keyframes for the flow (nearest first,
            see :func:`~mogs_node.depth_prior.flow_prior.choose_references`); may be empty.
        earlier_depth: ``(depth_m, confidence, T_world_cam[, image])`` metrized depths of
            earlier keyframes, most recent first (at most ``FusionParams.warp_sources`` used),
            with their image for the photometric check; may be empty.
        previous_prior: ``(depth_m, confidence, T_world_cam[, image])`` of the previous
            keyframe's own prior (carried when ``FusionParams.carry``), or None.
        road_references: ``(image, T_world_cam)`` of further earlier keyframes the road plane
            is verified against (photometrically), besides ``references``.
        ground_heights_m: earlier keyframes' measurements of the camera height
            (``road.auto_height`` with no ``flow.camera_height_m`` given).
        far_field_reference: ``(image, T_world_cam)`` of a reference farther back for the pixels
            below the nearest pair's parallax gate
            (:func:`~mogs_node.depth_prior.flow_prior.choose_far_field_reference`), or None.
    """

    references: Sequence[tuple[NDArray[np.uint8], NDArray[np.float64]]] = ()
    earlier_depth: Sequence[tuple] = ()
    previous_prior: tuple | None = None
    road_references: Sequence[tuple[NDArray[np.uint8], NDArray[np.float64]]] = ()
    ground_heights_m: Sequence[float] = ()
    far_field_reference: tuple[NDArray[np.uint8], NDArray[np.float64]] | None = None


@dataclass
class DensePrior:
    """The dense prior of one keyframe (all ``[H, W]``)."""

    depth_m: NDArray[np.float32]  # metric z-depth, 0 where none
    confidence: NDArray[np.float32]  # in [0, 1], 0 where none
    rel_err: NDArray[np.float32]  # predicted relative error, inf where none
    source: NDArray[np.int8]  # leading source (SOURCES), 0 where none
    sky: NDArray[np.bool_]
    stats: dict[str, float] = field(default_factory=dict)
    # the confidence a later keyframe carries (without this keyframe's depth-edge term, which
    # the later keyframe applies afresh to its own depth); None: ``confidence``
    carry_confidence: NDArray[np.float32] | None = None


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


def _warp_in(
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


def _verify(cand: _DepthErr, meas: _DepthErr, params: FusionParams) -> tuple[F32, float]:
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


def _flow_check(
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


def _road(
    grey: NDArray[np.uint8],
    K: NDArray[np.float64],
    Tk: NDArray[np.float64],
    references: Sequence[tuple[NDArray[np.uint8], NDArray[np.float64]]],
    road_references: Sequence[tuple[NDArray[np.uint8], NDArray[np.float64]]],
    flow: FlowPrior,
    height_m: float,
    up: NDArray[np.float64],
    road_params: RoadPriorParams,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The road plane ``height_m`` below the camera (``up``: camera frame) verified against each
    reference (the flow ones with their DIS flow, the extra ``road_references`` photometrically
    only): road where any reference verifies it (a reference may have seen the road hidden
    behind something that has since been passed)."""
    H, W = grey.shape
    _, _, rays = pixel_grid_xy(K, H, W)
    refs: list = []
    for i, (img, T_r) in enumerate(list(references) + list(road_references)):
        T_r = check_array(f"references[{i}].T_world_cam", T_r, shape=(4, 4), finite=True)
        pair = flow.pairs[i] if i < len(flow.pairs) else None
        refs.append(
            (
                _grey(img, f"references[{i}].image"),
                se3_inverse(T_r) @ Tk,
                None if pair is None else pair.flow_px,
                None if pair is None else pair.fb_error_px,
            )
        )
    depth = np.zeros((H, W), np.float32)
    err = np.full((H, W), np.inf, np.float32)
    for ref in refs or [None]:
        road = road_prior(grey, K, rays, up, height_m, road_params, ref)
        better = road.rel_err < err
        depth = np.where(better, road.depth_m, depth)
        err = np.where(better, road.rel_err, err)
    return depth, err


def _measured_height(
    grey: NDArray[np.uint8],
    K: NDArray[np.float64],
    Tk: NDArray[np.float64],
    references: Sequence[tuple[NDArray[np.uint8], NDArray[np.float64]]],
    flow: FlowPrior,
    up: NDArray[np.float64],
    road_params: RoadPriorParams,
    earlier_m: Sequence[float],
) -> tuple[float, float]:
    """The camera height measured on this keyframe (NaN: none) and the height to use (0: none
    yet): around the earlier measurements' median, or the flow depth's ground band for the first,
    refined by the road plane's tests against the nearest reference (ground_height.py). After
    ``AUTO_HEIGHT_MEASUREMENTS`` measurements the height is settled and costs nothing more."""
    H, W = grey.shape
    rays = pixel_grid_xy(K, H, W)[2]
    centre = ground_height_m(earlier_m)
    if len(earlier_m) >= AUTO_HEIGHT_MEASUREMENTS or not references or not flow.pairs:
        return float("nan"), centre
    if centre <= 0:
        fit = fit_ground_height(
            flow.depth_m, flow.confidence, rays, up, road_params.auto_height_range_m
        )
        if fit is None:
            return float("nan"), 0.0
        centre = fit[0]
    img_r, T_r = references[0]
    pair = flow.pairs[0]
    ref = (
        _grey(img_r, "references[0].image"),
        se3_inverse(T_r) @ Tk,
        pair.flow_px,
        pair.fb_error_px,
    )
    lo, hi = road_params.auto_height_range_m
    meas = refine_ground_height(
        centre,
        lambda h: (
            int(road_prior(grey, K, rays, up, h, road_params, ref).verified.sum())
            if lo <= h <= hi
            else 0
        ),
    )
    if meas is None:
        return float("nan"), ground_height_m(earlier_m)
    return meas[0], ground_height_m([*earlier_m, meas[0]])


def _warped(
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
        d_w, c_w = _warp_in(
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
        d_c, c_c = _warp_in(
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


def compute_dense_prior(
    image_k: NDArray[np.uint8],
    K: NDArray[np.float64],
    T_world_cam_k: NDArray[np.float64],
    past: PriorHistory = PriorHistory(),
    *,
    flow_params: FlowPriorParams | None = None,
    road_params: RoadPriorParams | None = None,
    params: FusionParams | None = None,
) -> DensePrior:
    """Dense prior of keyframe ``k`` (module docstring).

    Args:
        image_k: ``[H, W, 3]`` RGB or ``[H, W]`` uint8 keyframe; K: ``[3, 3]`` intrinsics.
        T_world_cam_k: ``[4, 4]`` pose of the keyframe (frontend, metric).
        past: flow and road references, earlier metrized depths, the previous prior and height
            measurements (:class:`PriorHistory`; default: none). This keyframe's own height
            measurement is in the stats (``ground_height_fit_m``, NaN: none), the height used
            in ``ground_height_m``.
        flow_params, road_params, params: the sources' and the fusion's parameters (None:
            defaults).
    """
    references = past.references
    flow_params = flow_params or FlowPriorParams()
    road_params = road_params or RoadPriorParams()
    params = params or FusionParams()
    grey = _grey(image_k, "image_k")
    H, W = grey.shape
    K = check_array("K", K, shape=(3, 3), finite=True)
    Tk = check_array("T_world_cam_k", T_world_cam_k, shape=(4, 4), finite=True)
    flow = compute_flow_prior(
        grey, K, Tk, references, flow_params, far_field=past.far_field_reference
    )
    stats: dict[str, float] = {}
    height_m = flow_params.camera_height_m
    if road_params.enabled:
        up = up_in_camera(Tk, road_params.up_world, flow_params.ground_up_cam)
    if road_params.enabled and road_params.auto_height and height_m <= 0:
        fit_m, height_m = _measured_height(
            grey, K, Tk, references, flow, up, road_params, past.ground_heights_m
        )
        stats.update(ground_height_fit_m=fit_m, ground_height_m=height_m)
        if height_m > 0:  # the flow depth's bound at the ground, as a given height sets it
            bound = ground_depth_bound(K, H, W, replace(flow_params, camera_height_m=height_m))
            beyond = flow.depth_m > bound
            flow = replace(
                flow,
                depth_m=np.where(beyond, 0.0, flow.depth_m).astype(np.float32),
                confidence=np.where(beyond, 0.0, flow.confidence).astype(np.float32),
            )
    cands_d = [flow.depth_m]
    cands_e = [error_from_confidence(flow.confidence, flow_params.rel_err_ref)]
    names = ["flow"]
    if road_params.enabled and height_m > 0:
        road_d, road_e = _road(
            grey, K, Tk, references, past.road_references, flow, height_m, up, road_params
        )
        # the plane checked against the flow depth as the warped sources are (a wrong up direction
        # or a poor pose moves the whole plane): the local disagreement raises its error
        road_e, r_road = _verify((road_d, road_e), (cands_d[0], cands_e[0]), params)
        cands_d.append(road_d)
        cands_e.append(road_e)
        names.append("road")
    if len(names) > 1:
        stats["road_disagreement"] = r_road
    d_meas, e_meas, _ = fuse_candidates(np.stack(cands_d), np.stack(cands_e), params)
    warped = _warped(grey, Tk, K, past.earlier_depth, past.previous_prior, flow_params, params)
    T_r_k = [se3_inverse(np.asarray(T, np.float64)) @ Tk for _, T in references]
    for name, d_w, e_w in warped:
        e_w, stats[f"{name}_flow_rejected"] = _flow_check(d_w, e_w, flow, K, T_r_k, params)
        e_w, r = _verify((d_w, e_w), (d_meas, e_meas), params)
        stats[f"{name}_disagreement"] = r
        cands_d.append(d_w)
        cands_e.append(e_w)
        names.append(name)
    depth, err, lead = fuse_candidates(np.stack(cands_d), np.stack(cands_e), params)
    depth[flow.sky] = 0.0
    err[flow.sky] = np.inf
    if params.contour_fill and references:  # untextured regions from their outline
        conf0 = confidence_from_error(err, params.rel_err_ref)
        fd, fe, st = outline_fill(
            grey, K, Tk, references, depth, conf0, flow.sky, EDGE_PARAMS, CONTOUR_PARAMS
        )
        put = fd > 0
        depth[put] = fd[put]
        err[put] = fe[put]
        lead[put] = len(names)
        names.append("contour")
        stats.update(st)
    carry_conf = None
    if params.edge_window_px > 0 and not params.edge_carried:
        carry_conf = confidence_from_error(err, params.rel_err_ref)
    if params.edge_window_px > 0:
        r = depth_edge_range(depth, params.edge_window_px, params.edge_far_only)
        jump = np.maximum(r - params.edge_free, 0.0)
        err = np.sqrt(err * err + (params.edge_gain * jump) ** 2).astype(np.float32)
    conf = confidence_from_error(err, params.rel_err_ref)
    refused = conf < params.min_confidence
    depth[refused] = 0.0
    err[refused] = np.inf
    conf[refused] = 0.0
    if carry_conf is not None:
        carry_conf[refused] = 0.0
    source = np.zeros((H, W), np.int8)
    for i, n in enumerate(names):
        source[(lead == i) & (conf > 0)] = SOURCES[n]
    stats.update(flow.stats)
    stats["flow_coverage"] = stats.pop("coverage")
    stats["coverage"] = float(np.mean(conf > 0))
    for n, code in SOURCES.items():
        stats[f"share_{n}"] = float(np.mean(source == code))
    log.debug("dense prior: %s", stats)
    return DensePrior(depth, conf, err, source, flow.sky, stats, carry_conf)
