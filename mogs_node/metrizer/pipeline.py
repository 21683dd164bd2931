"""The depth metrizer: MSC (paper III-B) + CDR (paper III-C), sparse metric points -> dense depth.

Stages (wall / CPU milliseconds in ``stats["ms"]`` / ``stats["cpu_ms"]``):

1. ``prepare``: compact labels, unmasked pixels -> connected components (association.py);
   sanitise inputs (non-finite prior -> no prior, features outside ``[d_min, d_max]`` dropped);
   with a metric anchor map (``MetrizerInputs.anchor_*``), its grid samples away from the
   features join them as lower-weighted points (dense_anchors.py); with ``mask_split`` the masks
   are cut along the prior's depth jumps (mask_split.py; in every mode, so that the ablations
   see the same objects).
2. ``associate``: features -> masks with a border vote.
3. ``global``: one robust affine alignment of the prior to all features (the anchor of eq. 8 and
   the ``no_msc_cdr`` result).
4. ``merge``: under-supported masks merge into contiguous neighbours (merging.py), mode ``full``;
   CDR sample pixels; sky objects = featureless objects whose prior is mostly far; with
   ``sky_anchor`` and a relative inverse-depth prior, the sky's prior value pins the global
   affine's shift (inverse depth 0) and stages 3-4 are redone once.
5. ``consensus``: Algorithm 1 for all objects (consensus.py), then groups without a shape join an
   adjacent shape that explains them (absorption), mode ``full``.
6. ``propagate``: model depth by ray-shape intersection at the CDR sample pixels.
7. ``refine``: CDR, eqs. (6)-(11) by IRLS (refinement.py); eq. (8) anchors to a locally aligned
   prior (the global one times a smooth field of the geometric evidence, ``local_anchor``).
8. ``compose`` / ``model_output`` / ``residual`` / ``sky_holes``: calibrated prior per object;
   model depth where it agrees; the smooth residual correction; per object, the global affine
   where the object's own result does not explain its features better (never worse than the
   baseline, docs/metrizer.md); sky -> ``d_max``; pixels without prior get, only near
   neighbour-confirmed features of their own object, the model depth (accepted shape) or the
   nearest such feature's depth (fill.py); with the camera's height above the road and the
   keyframe's pose, road objects' empty pixels get the road plane (ground.py); output confidence.

Modes: ``full``; ``no_msc`` (no merging, no shapes: the geometric term of eq. 7 uses each mask's
sparse features); ``no_msc_cdr`` (the globally aligned prior). See docs/metrizer.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mogs_node.geometry import up_in_camera
from mogs_node.metrizer.association import associate_features, prepare_labels
from mogs_node.metrizer.cdr_rows import FeatureRows, refine_objects
from mogs_node.metrizer.compose import compose
from mogs_node.metrizer.dense_anchors import anchor_points
from mogs_node.metrizer.frame import Frame, ShapeModels, StageTimer, object_map
from mogs_node.metrizer.global_fit import GlobalFit, align_global
from mogs_node.metrizer.grouping import Merged, merge_and_sample, sky_value
from mogs_node.metrizer.holdout import drop_unsupported_shapes
from mogs_node.metrizer.inputs import MetrizerInputs
from mogs_node.metrizer.mask_split import jump_band, split_masks
from mogs_node.metrizer.msc import absorb, fit_shapes, propagate
from mogs_node.metrizer.params import MODES, MetrizedDepth, MetrizerParams

__all__ = [
    "MODES",
    "MetrizedDepth",
    "MetrizerInputs",
    "MetrizerParams",
    "metrize",
    "metrize_depth",
]

log = logging.getLogger(__name__)
F64 = NDArray[np.float64]
_Frame = Frame  # the working set's former private name (tests)
DEFAULT_PARAMS = MetrizerParams()


def metrize_depth(
    *, params: MetrizerParams = DEFAULT_PARAMS, mode: str = "full", **fields: Any
) -> MetrizedDepth:
    """Keyword form of :func:`metrize`: the fields of :class:`MetrizerInputs` as arguments
    (``metrize_depth(**inputs, params=..., mode=...)``); an unknown or missing field is the
    dataclass's own TypeError naming it."""
    return metrize(MetrizerInputs(**fields), params, mode)


def metrize(
    inputs: MetrizerInputs, params: MetrizerParams = DEFAULT_PARAMS, mode: str = "full"
) -> MetrizedDepth:
    """Metric dense depth of one keyframe from sparse metric points, masks and a dense prior.

    ``inputs``: :class:`MetrizerInputs` (intrinsics, masks, sparse points with omega, the prior
    and its confidence, the image for eq. (10)); ``params``: :class:`MetrizerParams`; ``mode``:
    ``full`` | ``no_msc`` | ``no_msc_cdr`` (paper Table IV ablations).

    Returns a :class:`MetrizedDepth`; depth is finite, in ``(0, d_max]`` or 0 (no value).
    Raises ShapeError / GeometryError / ConfigError for malformed arguments; any NaN / inf in the
    values is treated as missing data, never raised.
    """
    tm = StageTimer()
    c = inputs.checked(mode, MODES)
    pts = _prepare(params, c, tm)
    fr, ga, ms = _global_and_groups(params, mode, c, pts, tm)
    if mode == "no_msc_cdr":
        return compose(
            fr, tm, ShapeModels.none(ms.G), np.tile(ga.theta0, (ms.G, 1)), global_only=True
        )

    # ---- shape consensus, Algorithm 1 (III-B), then absorption
    models, gg_grid = _shape_consensus(fr, ms, ga, pts, mode, tm)
    samples, snorm, d_glob = propagate(fr, models, ms.grid, gg_grid, ms.norm_grid)
    tm.lap("propagate")

    # ---- cross-object depth refinement, eqs. (6)-(11) (III-C)
    features = FeatureRows(ga.fx, ga.fc * ga.f_consistent, ga.ft, pts.w)
    theta, n_rows = refine_objects(
        fr, samples, features, models, ms.pairs, snorm, d_glob, ga.fd_glob
    )
    fr.stats.update(n_rows)
    tm.lap("refine")
    return compose(fr, tm, models, theta, global_only=False)


@dataclass
class _Points:
    """Stages 1-2: the sanitised points and prior, the objects and the features' objects."""

    uv: F64  # [N, 2] feature pixels (frontend points, then dense anchors)
    z: F64  # [N] their metric depth
    w: F64  # [N] their weight
    n_frontend: int  # the first n_frontend points are the frontend's
    prior: NDArray  # [HW] the prior (non-finite -> no prior)
    conf: NDArray  # [HW] its confidence
    obj2d: NDArray  # [H, W] compact object ids (unmasked components included)
    n_obj: int
    unmasked: NDArray[np.bool_]  # [n_obj] the object is an unmasked component
    feat_obj: NDArray[np.intp]  # [N] object of each feature
    fpix: NDArray[np.intp]  # [N] flat pixel of each feature


def _prepare(p: MetrizerParams, c: MetrizerInputs, tm: StageTimer) -> _Points:
    """Stages 1-2: sanitise, add dense anchors, split masks, compact labels; associate."""
    labels, prior_kind = c.labels, c.prior_kind
    H, W = labels.shape
    uv, z, w, prior, conf = c.sanitised(p.d_min_m, p.d_max_m)
    n_frontend = len(z)
    if c.anchor_depth_m is not None:  # dense metric anchors as extra points (dense_anchors.py)
        uv, z, w = _with_anchors(p, c, uv, z, w)
    if p.mask_split:  # departure: docs/metrizer.md "Masks split"
        labels = _split_labels(p, labels, prior, conf, prior_kind)
    obj2d, n_obj, unmasked = prepare_labels(labels)
    tm.lap("prepare")

    feat_obj = associate_features(obj2d, uv, p.border_vote_radius)
    fu = np.clip(np.round(uv[:, 0]).astype(np.intp), 0, W - 1)
    fv = np.clip(np.round(uv[:, 1]).astype(np.intp), 0, H - 1)
    fpix = fv * W + fu
    tm.lap("associate")
    return _Points(uv, z, w, n_frontend, prior, conf, obj2d, n_obj, unmasked, feat_obj, fpix)


def _global_and_groups(
    p: MetrizerParams, mode: str, c: MetrizerInputs, pts: _Points, tm: StageTimer
) -> tuple[Frame, GlobalFit, Merged]:
    """Stages 3-4: the global affine, the merged groups with their CDR samples (both redone once
    when the sky pins the shift), and the frame the later stages share."""
    prior, z, w, fpix, prior_kind = pts.prior, pts.z, pts.w, pts.fpix, c.prior_kind
    ga = align_global(p, prior, pts.conf, z, w, fpix, prior_kind)
    conf = ga.conf
    stats: dict[str, Any] = {
        "mode": mode,
        "n_masks": int(pts.n_obj - pts.unmasked.sum()),
        "n_unmasked_regions": int(pts.unmasked.sum()),
        "n_features": int(len(z)),
        "n_dense_anchors": int(len(z) - pts.n_frontend),
        "n_features_global": int(ga.n_global),
        "global_affine": [float(ga.theta0[0]), float(ga.theta0[1])],
        "prior_unanchored": ga.unanchored,
    }
    tm.lap("global")

    objects = (pts.obj2d, pts.n_obj, pts.feat_obj)
    ms = merge_and_sample(p, mode, *objects, z, prior, conf, ga, prior_kind)
    x_sky = sky_value(p, ms, prior, prior_kind, ga)
    if x_sky is not None:  # departure: docs/metrizer.md "The sky pins the shift"
        ga = align_global(p, prior, conf, z, w, fpix, prior_kind, zero_at=(x_sky, p.sky_anchor))
        conf = ga.conf
        stats.update(global_affine=[float(ga.theta0[0]), float(ga.theta0[1])], sky_prior=x_sky)
        ms = merge_and_sample(p, mode, *objects, z, prior, conf, ga, prior_kind)
    stats.update(n_objects=ms.G, merges=ms.n_merges, n_sky_objects=int(ms.sky.sum()))
    tm.lap("merge")

    H, W = pts.obj2d.shape
    fr = Frame(
        p=p,
        H=H,
        W=W,
        K=c.K,
        prior_kind=prior_kind,
        prior=prior,
        conf=conf,
        has_prior=conf > 0,
        all_prior=bool((conf > 0).all()),
        image=c.image_rgb,
        z=z,
        fpix=fpix,
        f_consistent=ga.f_consistent,
        theta0=ga.theta0,
        stats=stats,
        G=ms.G,
        gobj=None if mode == "full" else object_map(ms.group, ms.obj_i),
        feat_g=ms.feat_g,
        n_feat_g=ms.n_feat_g,
        sky=ms.sky,
        up_cam=_road_up(p, c.T_world_cam),
    )
    return fr, ga, ms


def _shape_consensus(
    fr: Frame, ms: Merged, ga: GlobalFit, pts: _Points, mode: str, tm: StageTimer
) -> tuple[ShapeModels, NDArray[np.intp]]:
    """Stage 5: Algorithm 1 for every group, the held-out check and the absorption; returns the
    accepted models and the CDR samples' groups after absorption."""
    models, Xf, counts = fit_shapes(fr, pts.uv, pts.w, mode)
    n_held_out = 0
    if mode == "full":  # departure 22 (holdout.py): the shape must explain its prior pixels
        fok = ga.f_consistent
        n_held_out = drop_unsupported_shapes(
            fr,
            models,
            (ms.grid, ms.gg_grid, ms.norm_grid),
            (ms.feat_g[fok], fr.z[fok], ga.fd_glob[fok]),
        )
    tm.lap("consensus")
    models, gg_grid, n_absorbed = absorb(fr, ms, models, Xf, mode)
    kind_g = models.kind
    fr.stats.update(
        n_objects=fr.G,
        absorbed=n_absorbed,
        objects_tried=counts["tried"],
        skipped_costly=counts["skipped"],
        models={
            "plane": int((kind_g == 1).sum()),
            "cylinder": int((kind_g == 2).sum()),
            "ellipsoid": int((kind_g == 3).sum()),
        },
        rejected=int(counts["tried"] - (kind_g > 0).sum()),
        rejected_degenerate=counts["degenerate"],
        rejected_held_out=n_held_out,
    )
    tm.lap("absorb")
    return models, gg_grid


def _with_anchors(
    p: MetrizerParams, c: MetrizerInputs, uv: F64, z: F64, w: F64
) -> tuple[F64, F64, F64]:
    """The features plus the metric anchor map's grid samples away from them (dense_anchors.py),
    as lower-weighted points."""
    uv_a, z_a, w_a = anchor_points(
        c.anchor_depth_m,
        c.anchor_confidence,
        uv,
        stride=p.dense_anchor_stride,
        min_confidence=p.dense_anchor_min_conf,
        gap_px=p.dense_anchor_gap * c.labels.shape[1],
        weight=p.dense_anchor_weight,
        depth_range_m=(p.d_min_m, p.d_max_m),
    )
    keep = w_a > 0
    uv, z = np.concatenate([uv, uv_a[keep]]), np.concatenate([z, z_a[keep]])
    return uv, z, np.concatenate([w, w_a[keep] + 1e-6])


def _split_labels(
    p: MetrizerParams, labels: NDArray, prior: NDArray, conf: NDArray, prior_kind: str
) -> NDArray[np.int32]:
    """The masks cut along the prior's depth jumps (mask_split.py, ``mask_split_*``)."""
    H, W = labels.shape
    band = jump_band(
        prior.reshape(H, W), conf.reshape(H, W), prior_kind, p.mask_split_rel, p.mask_split_radius
    )
    reach = 2 * p.mask_split_radius + 4  # the band's width and then some
    return split_masks(labels, band, round(p.mask_split_min_frac * H * W), reach)


def _road_up(p: MetrizerParams, T_world_cam: F64 | None) -> F64 | None:
    """Unit "up" in the camera frame for the road plane (``road_*`` parameters), or None when
    the road plane is off (no camera height) or its "up" needs a pose the inputs lack."""
    if not p.road_camera_height_m > 0 or (p.road_up_world is not None and T_world_cam is None):
        return None
    T = np.eye(4) if T_world_cam is None else T_world_cam
    return up_in_camera(T, p.road_up_world, p.road_up_cam)
