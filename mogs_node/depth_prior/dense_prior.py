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

Fusion per pixel and the depth-edge term: :mod:`mogs_node.depth_prior.fusion`; the warped sources
and their checks against this keyframe's flow: :mod:`mogs_node.depth_prior.warped_sources`.

The prior is metric (``DepthMap.kind = "metric"``) because all three sources are: the frontend's
poses are metric (VI or road-scaled), the plane height is metric, the metrizer's depth is metric.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

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
from mogs_node.depth_prior.fusion import (
    FusionParams,
    confidence_from_error,
    depth_edge_range,
    error_from_confidence,
    fuse_candidates,
    verify_candidate,
)
from mogs_node.depth_prior.ground_height import (
    fit_ground_height,
    ground_height_m,
    refine_ground_height,
)
from mogs_node.depth_prior.road import RoadPriorParams, road_prior, up_in_camera
from mogs_node.depth_prior.warped_sources import flow_check, warped_candidates
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

#: source codes of :attr:`DensePrior.source` (0 = none)
SOURCES = {"flow": 1, "road": 2, "warp": 3, "carry": 4, "contour": 5}


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
        road_e, r_road = verify_candidate((road_d, road_e), (cands_d[0], cands_e[0]), params)
        cands_d.append(road_d)
        cands_e.append(road_e)
        names.append("road")
    if len(names) > 1:
        stats["road_disagreement"] = r_road
    d_meas, e_meas, _ = fuse_candidates(np.stack(cands_d), np.stack(cands_e), params)
    warped = warped_candidates(
        grey, Tk, K, past.earlier_depth, past.previous_prior, flow_params, params
    )
    T_r_k = [se3_inverse(np.asarray(T, np.float64)) @ Tk for _, T in references]
    for name, d_w, e_w in warped:
        e_w, stats[f"{name}_flow_rejected"] = flow_check(d_w, e_w, flow, K, T_r_k, params)
        e_w, r = verify_candidate((d_w, e_w), (d_meas, e_meas), params)
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
