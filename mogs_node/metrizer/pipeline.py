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
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_kind import DepthKind
from mogs_node.geometry import pixel_to_normalized, up_in_camera
from mogs_node.metrizer import shapes
from mogs_node.metrizer.absorption import absorb_groups
from mogs_node.metrizer.alignment import (
    depth_from_space,
    fit_global_affine,
    metric_affine_earned,
    space_from_depth,
)
from mogs_node.metrizer.association import (
    associate_features,
    boundary_pairs,
    prepare_labels,
    region_adjacency,
)
from mogs_node.metrizer.cdr_rows import FeatureRows, SampleRows, geo_rows, local_anchor_target
from mogs_node.metrizer.compose import compose
from mogs_node.metrizer.consensus import fit_objects
from mogs_node.metrizer.dense_anchors import anchor_points
from mogs_node.metrizer.frame import (
    Frame,
    ShapeModels,
    StageTimer,
    far_and_norm,
    model_agrees,
    model_depth,
    object_map,
)
from mogs_node.metrizer.holdout import drop_unsupported_shapes
from mogs_node.metrizer.inputs import MetrizerInputs
from mogs_node.metrizer.mask_split import jump_band, split_masks
from mogs_node.metrizer.merging import merge_undersupported
from mogs_node.metrizer.params import MODES, MetrizedDepth, MetrizerParams
from mogs_node.metrizer.refinement import CdrProblem, solve_cdr

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
    p = params
    c = inputs.checked(mode, MODES)
    K, labels, image, prior_kind = c.K, c.labels, c.image_rgb, c.prior_kind
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

    ga = _align_global(p, prior, conf, z, w, fpix, prior_kind)
    conf = ga.conf
    stats: dict[str, Any] = {
        "mode": mode,
        "n_masks": int(n_obj - unmasked.sum()),
        "n_unmasked_regions": int(unmasked.sum()),
        "n_features": int(len(z)),
        "n_dense_anchors": int(len(z) - n_frontend),
        "n_features_global": int(ga.n_global),
        "global_affine": [float(ga.theta0[0]), float(ga.theta0[1])],
        "prior_unanchored": ga.unanchored,
    }
    tm.lap("global")

    ms = _merge_and_sample(p, mode, obj2d, n_obj, feat_obj, z, prior, conf, ga, prior_kind)
    x_sky = _sky_value(p, ms, prior, prior_kind, ga)
    if x_sky is not None:  # departure: docs/metrizer.md "The sky pins the shift"
        ga = _align_global(p, prior, conf, z, w, fpix, prior_kind, zero_at=(x_sky, p.sky_anchor))
        conf = ga.conf
        stats.update(global_affine=[float(ga.theta0[0]), float(ga.theta0[1])], sky_prior=x_sky)
        ms = _merge_and_sample(p, mode, obj2d, n_obj, feat_obj, z, prior, conf, ga, prior_kind)
    stats.update(n_objects=ms.G, merges=ms.n_merges, n_sky_objects=int(ms.sky.sum()))
    tm.lap("merge")

    fr = Frame(
        p=p,
        H=H,
        W=W,
        K=K,
        prior_kind=prior_kind,
        prior=prior,
        conf=conf,
        has_prior=conf > 0,
        all_prior=bool((conf > 0).all()),
        image=image,
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
    if mode == "no_msc_cdr":
        return compose(
            fr, tm, ShapeModels.none(ms.G), np.tile(ga.theta0, (ms.G, 1)), global_only=True
        )

    # ---- shape consensus, Algorithm 1 (III-B), then absorption
    models, Xf, counts = _fit_shapes(fr, uv, w, mode)
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
    models, gg_grid, n_absorbed = _absorb(fr, ms, models, Xf, mode)
    kind_g = models.kind
    stats.update(
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

    samples, snorm, d_glob = _propagate(fr, models, ms.grid, gg_grid, ms.norm_grid)
    tm.lap("propagate")

    # ---- cross-object depth refinement, eqs. (6)-(11) (III-C)
    features = FeatureRows(ga.fx, ga.fc * ga.f_consistent, ga.ft, w)
    theta, n_rows = _refine(fr, samples, features, models, ms.pairs, snorm, d_glob, ga.fd_glob)
    stats.update(n_rows)
    tm.lap("refine")
    return compose(fr, tm, models, theta, global_only=False)


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


@dataclass
class _GlobalFit:
    """Stage 3: the global affine alignment of the prior to all features."""

    theta0: F64  # [2] (a, b) of the prior's space
    n_global: int  # features with a prior that entered the fit (0: unanchored)
    fx: F64  # [N] prior value at each feature
    fc: F64  # [N] prior confidence at each feature (0 when unanchored)
    ft: F64  # [N] feature depth in the prior's space
    fd_glob: F64  # [N] globally aligned prior depth at each feature
    f_consistent: NDArray[np.bool_]  # [N] feature within feature_prior_gate of it
    conf: NDArray[np.float32]  # [HW] prior confidence (all 0 when unanchored)
    unanchored: bool  # a relative prior with 1-4 features: dropped


def _align_global(
    p: MetrizerParams,
    prior: NDArray,
    conf: NDArray,
    z: F64,
    w: F64,
    fpix: NDArray[np.intp],
    prior_kind: str,
    zero_at: tuple[float, float] | None = None,
) -> _GlobalFit:
    """One robust affine fit of the prior to every feature: the anchor of eq. (8) and the
    ``no_msc_cdr`` result. A relative prior that (almost) no metric point anchors has no metric
    meaning: its pixels get no depth (only the sparse evidence near features), not a guessed
    scale (the identity, or an affine through 1-4 points: AbsRel 0.3-0.9 on the demo)."""
    fx, fc = prior[fpix].astype(np.float64), conf[fpix].astype(np.float64)
    ft = space_from_depth(z, prior_kind)
    theta0, n_global = fit_global_affine(
        fx,
        ft,
        w * fc,
        prior_kind,
        p.global_huber,
        shift_prior=p.global_shift_prior,
        zero_at=zero_at,
    )
    if (
        p.metric_identity_test
        and prior_kind == DepthKind.METRIC
        and zero_at is None
        and not metric_affine_earned(fx, ft, w * fc, theta0)
    ):  # departure 23: a metric prior keeps its scale unless the features show otherwise
        theta0 = np.array([1.0, 0.0])
    unanchored = prior_kind != DepthKind.METRIC and 0 < n_global < p.min_anchor_features
    if prior_kind != DepthKind.METRIC and n_global < p.min_anchor_features:
        conf = np.zeros_like(conf)
        fc = np.zeros_like(fc)
        theta0, n_global = np.array([1.0, 0.0]), 0
    _, f_norm = far_and_norm(theta0[0] * fx + theta0[1], prior_kind, p)
    fd_glob = depth_from_space(f_norm, prior_kind, p.d_min_m, p.d_max_m)
    f_consistent = (fc > 0) & (np.abs(np.log(z / fd_glob)) <= np.log1p(p.feature_prior_gate))
    return _GlobalFit(
        theta0, int(n_global), fx, fc, ft, fd_glob, f_consistent, conf, bool(unanchored)
    )


def _sky_value(
    p: MetrizerParams, ms: _Merged, prior: NDArray, prior_kind: str, ga: _GlobalFit
) -> float | None:
    """The prior's value on the sky when it should pin the global shift (``sky_anchor`` > 0, a
    relative inverse-depth prior, sky found), else None: the lowest median prior of the sky
    groups with at least 5 sample pixels (a featureless far object counts as sky too; the sky
    itself is the farthest, its inverse depth the lowest). An affine-invariant inverse-depth
    model gives the sky its shift: inverse depth 0."""
    if not (p.sky_anchor > 0 and prior_kind == DepthKind.RELATIVE_INVERSE_DEPTH and ms.sky.any()):
        return None
    if ga.n_global < p.min_anchor_features:
        return None
    on_sky = ms.sky[ms.gg_grid]
    g, x = ms.gg_grid[on_sky], prior[ms.grid[on_sky]].astype(np.float64)
    n_g = np.bincount(g, minlength=ms.G)
    keep = n_g[g] >= 5
    if not keep.any():
        return None
    g, x = g[keep], x[keep]
    order = np.lexsort((x, g))
    g, x = g[order], x[order]
    start = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    cnt = np.diff(np.r_[start, len(g)])
    med = 0.5 * (x[start + (cnt - 1) // 2] + x[start + cnt // 2])
    return float(med.min())


@dataclass
class _Merged:
    """Stage 4: groups after multi-scale merging, the CDR sample grid and the sky groups."""

    group: NDArray[np.intp]  # [n_obj] object -> group
    obj_i: NDArray[np.intp]  # [HW] object of each pixel
    G: int  # number of groups
    n_merges: int
    pairs: Any  # boundary pixel pairs (None in mode no_msc_cdr)
    adjacency: tuple | None  # (adj_k, adj_l) region adjacency, mode full
    feat_g: NDArray[np.intp]  # [N] group of each feature
    n_feat_g: NDArray[np.int64]  # [G]
    grid: NDArray[np.intp]  # [S] CDR sample pixels (with a prior)
    gg_grid: NDArray[np.intp]  # [S] their group
    norm_grid: F64  # [S] globally aligned prior at them, normalised space
    sky: NDArray[np.bool_]  # [G]


def _merge_and_sample(
    p: MetrizerParams,
    mode: str,
    obj2d: NDArray,
    n_obj: int,
    feat_obj: NDArray[np.intp],
    z: F64,
    prior: NDArray,
    conf: NDArray,
    ga: _GlobalFit,
    prior_kind: str,
) -> _Merged:
    """Multi-scale merging (III-B, mode full), the CDR sample pixels (a strided grid plus every
    pixel of objects the grid misses) and sky: featureless groups whose prior is mostly far."""
    H, W = obj2d.shape
    pairs = boundary_pairs(obj2d) if mode != "no_msc_cdr" else None
    adjacency = None
    if mode == "full":
        adj_k, adj_l, _ = region_adjacency(obj2d, n_obj, pairs)
        adjacency = (adj_k, adj_l)
        group, n_merges = merge_undersupported(
            n_obj, adjacency, feat_obj, z, p.n_min, p.rho_contiguity
        )
    else:
        group, n_merges = np.arange(n_obj), 0
    G = int(group.max()) + 1 if n_obj else 0
    # intp indices: np.take with int32 indices is several times slower (index conversion); the
    # full-resolution object map is built once, after the last merge (absorption in mode full)
    obj_i = obj2d.ravel().astype(np.intp)
    group = group.astype(np.intp, copy=False)
    feat_g = group[feat_obj]
    n_feat_g = np.bincount(feat_g, minlength=G)
    s = p.sample_stride
    grid = (np.arange(0, H, s)[:, None] * W + np.arange(0, W, s)[None, :]).ravel()
    missing = np.bincount(group[obj_i[grid]], minlength=G) == 0
    if missing.any():
        grid = np.concatenate([grid, np.flatnonzero(np.take(missing[group], obj_i))])
    grid = grid[conf[grid] > 0]
    gg_grid = group[obj_i[grid]]
    theta0 = ga.theta0
    y_grid = theta0[0] * prior[grid].astype(np.float64) + theta0[1]
    far_grid, norm_grid = far_and_norm(y_grid, prior_kind, p)
    n_prior_g = np.bincount(gg_grid, minlength=G)
    n_far_g = np.bincount(gg_grid[far_grid], minlength=G)
    # sky needs the metric global alignment (no feature with a prior: "far" means nothing)
    sky = (n_feat_g == 0) & (n_prior_g > 0) & (n_far_g >= p.sky_far_fraction * n_prior_g)
    sky &= ga.n_global > 0
    return _Merged(
        group,
        obj_i,
        G,
        int(n_merges),
        pairs,
        adjacency,
        feat_g,
        n_feat_g,
        grid,
        gg_grid,
        norm_grid,
        sky,
    )


def _absorb(
    fr: Frame, ms: _Merged, models: ShapeModels, Xf: F64, mode: str
) -> tuple[ShapeModels, NDArray[np.intp], int]:
    """Stage 5b (mode full): groups without a shape join an adjacent shape that explains them;
    updates ``fr`` (groups, features, sky, object map). Returns the models, the samples' groups
    and the number of absorbed groups."""
    p = fr.p
    gg_grid, n_absorbed, obj_to_g = ms.gg_grid, 0, ms.group
    if mode == "full" and p.absorb and (models.kind > 0).any():
        remap = absorb_groups(
            fr,
            ms.group,
            ms.adjacency,
            (models.kind, models.A, models.b, models.c, models.zlo, models.zhi),
            Xf,
            (ms.grid, ms.gg_grid, ms.norm_grid),
        )
        if remap is not None:
            keep_ids, remap = remap
            n_absorbed = fr.G - len(keep_ids)
            obj_to_g = remap[ms.group]
            gg_grid, feat_g = remap[ms.gg_grid], remap[fr.feat_g]
            fr.G = len(keep_ids)
            fr.feat_g, fr.n_feat_g = feat_g, np.bincount(feat_g, minlength=fr.G)
            fr.sky, models = fr.sky[keep_ids], models.take(keep_ids)
    if fr.gobj is None:
        fr.gobj = object_map(obj_to_g, ms.obj_i)
    return models, gg_grid, n_absorbed


def _propagate(
    fr: Frame,
    models: ShapeModels,
    grid: NDArray[np.intp],
    gg_grid: NDArray[np.intp],
    norm_grid: F64,
) -> tuple[SampleRows, F64, F64]:
    """Stage 6: model depth by ray-shape intersection at the CDR samples (sky excluded) and
    whether it agrees with the globally aligned prior there."""
    p = fr.p
    keep = ~fr.sky[gg_grid]
    sidx, sg, snorm = grid[keep], gg_grid[keep], norm_grid[keep]
    sx, sc = fr.prior[sidx].astype(np.float64), fr.conf[sidx].astype(np.float64)
    mdepth = np.full(len(sidx), np.inf)
    mi = np.flatnonzero(models.kind[sg] > 0)
    if len(mi):
        mdepth[mi] = model_depth(
            sidx[mi], sg[mi], models.kind, models.A, models.b, models.c, fr.W, fr.K
        )
    d_glob = depth_from_space(snorm, fr.prior_kind, p.d_min_m, p.d_max_m)
    mok = model_agrees(mdepth, models.zlo[sg], models.zhi[sg], d_glob, p.model_prior_gate)
    return SampleRows(sidx, sg, sx, sc, mdepth, mok), snorm, d_glob


def _fit_shapes(
    fr: Frame, uv: F64, w: F64, mode: str
) -> tuple[ShapeModels, F64 | None, dict[str, int]]:
    """Stage 5, Algorithm 1 (III-B) for every object of ``fr`` (mode ``full`` only): plane,
    cylinder, ellipsoid by RANSAC with the residual of eq. (2), best by eq. (5), accepted with at
    least ``tau |F_k|`` inliers (consensus.py). Sets ``fr.t_abs_m``.

    Returns the accepted models, the features' 3D points ``[N, 3]`` (None when not fitted) and
    the counts ``tried`` / ``skipped`` (costly models skipped) / ``degenerate``.
    """
    p, z, G, K = fr.p, fr.z, fr.G, fr.K
    models = ShapeModels.none(G)
    counts = {"tried": 0, "skipped": 0, "degenerate": 0}
    # T_s(z) = t_abs + t_rel z: the absolute term (set for street scenes) shrinks with the scene:
    # at most t_abs_m * median feature depth / t_abs_ref_depth_m (departure 14)
    cons = p.consensus
    if len(z):
        t_abs = cons.t_abs_m * min(1.0, float(np.median(z)) / p.t_abs_ref_depth_m)
        if t_abs < cons.t_abs_m:
            cons = replace(cons, t_abs_m=t_abs)
    fr.t_abs_m = cons.t_abs_m
    if mode != "full" or not len(z):
        return models, None, counts
    rng = np.random.default_rng(p.seed)
    x_n, y_n = pixel_to_normalized(K, uv[:, 0], uv[:, 1])
    Xf = np.stack([x_n * z, y_n * z, z], 1)
    order = np.argsort(fr.feat_g, kind="stable")
    starts = np.concatenate([[0], np.cumsum(fr.n_feat_g)])
    fits = fit_objects(Xf, w, fr.feat_g, G, rng, cons)
    for g, fit in fits.items():
        counts["tried"] += 1
        counts["skipped"] += int(fit.skipped_costly)
        counts["degenerate"] += int(fit.degenerate)
        if fit.kind == shapes.KIND_NONE:
            continue
        models.kind[g], models.conf[g] = fit.kind, fit.confidence
        models.A[g], models.b[g], models.c[g] = fit.A, fit.b, fit.c
        zi = z[order[starts[g] : starts[g + 1]]][fit.inliers]
        models.zlo[g] = max(zi.min() / p.model_extrapolation, p.d_min_m)
        models.zhi[g] = min(zi.max() * p.model_extrapolation, p.d_max_m)
    return models, Xf, counts


def _refine(
    fr: Frame,
    samples: SampleRows,
    features: FeatureRows,
    models: ShapeModels,
    pairs: tuple[NDArray[np.intp], NDArray[np.intp]],
    snorm: F64,
    d_glob: F64,
    fd_glob: F64,
) -> tuple[F64, dict[str, int]]:
    """Stage 7, CDR (III-C): the per-object affine of eq. (6) minimising eq. (11) by IRLS.

    Rows of eq. (7) from :func:`geo_rows`; eq. (8) anchors each sample to ``snorm`` (the globally
    aligned prior there, ``d_glob`` in depth), or to the locally aligned prior
    (:func:`local_anchor_target`, departure 13; ``fd_glob``: the global depth at the features);
    eqs. (9)-(10) over the border pixel pairs ``pairs`` between different objects. Returns
    ``theta`` ``[G, 2]`` and the row counts.
    """
    p, G, gobj, sky, prior, theta0 = fr.p, fr.G, fr.gobj, fr.sky, fr.prior, fr.theta0
    prior_kind, image, has_prior = fr.prior_kind, fr.image, fr.has_prior
    sidx, sg, sx, sc = samples.idx, samples.obj, samples.x, samples.conf
    mok, mdepth = samples.model_ok, samples.model_depth_m
    geo = geo_rows(fr, samples, features, models.kind, models.conf)
    if p.local_anchor:
        snorm = local_anchor_target(fr, sidx, mok, mdepth, d_glob, fd_glob, snorm)
    nfc_w = sc / np.maximum(np.bincount(sg, sc, minlength=G), 1e-12)[sg]
    pp, qq = pairs
    gp, gq = gobj[pp], gobj[qq]
    keep = (gp != gq) & ~sky[gp] & ~sky[gq]
    if not fr.all_prior:
        keep &= has_prior[pp] & has_prior[qq]
    pp, qq, gp, gq = pp[keep], qq[keep], gp[keep], gq[keep]
    if image is not None:  # eq. (10)
        img = image.reshape(-1, 3)
        dc = img[pp].astype(np.float32) - img[qq].astype(np.float32)
        w_edge = np.exp(-np.einsum("ij,ij->i", dc, dc) / np.float32(2.0 * p.cdr.sigma_color**2))
    else:
        w_edge = np.ones(len(pp), np.float32)
    # eq. (9) as a per-object mean over its border pairs (see refinement.py)
    n_border = np.maximum(np.bincount(gp, minlength=G) + np.bincount(gq, minlength=G), 1.0)
    sm_w = w_edge / (0.5 * (n_border[gp] + n_border[gq]))
    xp, xq = prior[pp].astype(np.float64), prior[qq].astype(np.float64)
    _, norm_p = far_and_norm(theta0[0] * xp + theta0[1], prior_kind, p)
    _, norm_q = far_and_norm(theta0[0] * xq + theta0[1], prior_kind, p)
    prob = CdrProblem(
        n=G,
        theta0=np.tile(theta0, (G, 1)),
        geo_obj=geo[0],
        geo_x=geo[1],
        geo_t=geo[2],
        geo_w=geo[3],
        nfc_obj=sg,
        nfc_x=sx,
        nfc_t=snorm,
        nfc_w=nfc_w,
        sm_k=gp,
        sm_l=gq,
        sm_xk=xp,
        sm_xl=xq,
        sm_g=0.5 * (norm_p + norm_q),
        sm_w=sm_w.astype(np.float64),
    )
    # no feature with a prior: no metric evidence to calibrate with, every object keeps the global
    # affine (the identity then; shapes and the fill of pixels without prior still apply)
    n_global = fr.stats["n_features_global"]
    theta = solve_cdr(prob, p.cdr) if n_global > 0 else np.tile(theta0, (G, 1))
    # a non-finite or sign-flipping calibration (an inverted prior) falls back to the global one
    theta[~np.all(np.isfinite(theta), axis=1) | (theta[:, 0] <= 0)] = theta0
    n_rows = {"n_geo_rows": int(len(geo[0])), "n_nfc_rows": int(len(sg)), "n_sm_rows": int(len(gp))}
    return theta, n_rows
