"""The depth metrizer: MSC (paper III-B) + CDR (paper III-C), sparse metric points -> dense depth.

Stages (wall / CPU milliseconds in ``stats["ms"]`` / ``stats["cpu_ms"]``):

1. ``prepare``: compact labels, unmasked pixels -> connected components (association.py);
   sanitise inputs (non-finite prior -> no prior, features outside ``[d_min, d_max]`` dropped).
2. ``associate``: features -> masks with a border vote.
3. ``global``: one robust affine alignment of the prior to all features (the anchor of eq. 8 and
   the ``no_msc_cdr`` result).
4. ``merge``: under-supported masks merge into contiguous neighbours (merging.py), mode ``full``;
   CDR sample pixels; sky objects = featureless objects whose prior is mostly far.
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
   nearest such feature's depth (fill.py); output confidence.

Modes: ``full``; ``no_msc`` (no merging, no shapes: the geometric term of eq. 7 uses each mask's
sparse features); ``no_msc_cdr`` (the globally aligned prior). See docs/metrizer.md.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError, GeometryError
from mogs_node.geometry import check_array
from mogs_node.metrizer import shapes
from mogs_node.metrizer.alignment import (
    PRIOR_KINDS,
    depth_from_space,
    fit_global_affine,
    space_from_depth,
)
from mogs_node.metrizer.association import (
    associate_features,
    boundary_pairs,
    prepare_labels,
    region_adjacency,
)
from mogs_node.metrizer.consensus import ConsensusParams, fit_objects
from mogs_node.metrizer.fill import consistent_seeds, edge_aware_fill, smooth_field
from mogs_node.metrizer.merging import absorb_into_models, merge_undersupported
from mogs_node.metrizer.refinement import CdrParams, CdrProblem, solve_cdr

__all__ = ["MODES", "MetrizedDepth", "MetrizerParams", "metrize_depth"]

log = logging.getLogger(__name__)
MODES = ("full", "no_msc", "no_msc_cdr")
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class MetrizerParams:
    """Parameters of the metrizer (MSC + CDR); nested dataclasses hold the stage parameters."""

    d_min_m: float = 0.1  # smallest output depth [m]; features nearer are dropped
    d_max_m: float = 80.0  # largest output depth [m] (sky and far pixels); features beyond dropped
    n_min: int = 9  # III-B: a mask with fewer features is under-supported and merges
    rho_contiguity: float = 0.1  # III-B: merge only when |z_i - z_u| <= rho z_i (median depths)
    border_vote_radius: int = 1  # feature association: vote in a (2r+1)^2 window on mask borders
    sample_stride: int = 6  # CDR data terms use every stride-th pixel in x and y (+ tiny masks)
    model_extrapolation: float = 2.0  # model depth used within [z_min / f, z_max * f] of inliers
    hole_model_extrapolation: float = 1.25  # the same f for pixels without prior (no gate there)
    fallback_global: bool = True  # per object: the global affine where the object's own result
    # does not explain its features better (degrees-of-freedom corrected, see _fallback_to_global)
    fallback_featureless: bool = False  # ... and objects without features always
    fallback_min_features: int = 18  # ... objects without features also when the frame has fewer
    # features with a prior than this (their calibration follows thin neighbouring evidence)
    hole_model_radius: float = 0.05  # a pixel without prior takes its object's model depth only
    # within this fraction of the image width of one of the object's own features
    hole_fill_radius: float = 0.02  # ... the edge-aware fill of the features only within this
    t_abs_ref_depth_m: float = 10.0  # median feature depth for which consensus.t_abs_m is meant
    fill_method: str = "nearest"  # pixels without prior and shape: "nearest" consistent feature
    # of the same object, or "edge_aware" (FGS normalised convolution of the features)
    fill_seed_gate: float = 0.3  # a fill seed must be within this relative depth of the median
    # of its nearest features (of 8) within fill_seed_radius (x image width), and have >= 2 there
    fill_seed_radius: float = 0.1
    model_prior_gate: float = 0.3  # eq. (7) uses a model pixel only within this relative
    # distance of the globally aligned prior (the pixel is then plausibly on the model's surface)
    feature_prior_gate: float = 0.5  # eq. (7) feature rows: drop a feature whose depth is more than
    # (1 + gate) times off the globally aligned prior (occlusion-boundary / mismatched features)
    model_edge_gate: float = 0.5  # the same gate within prior_edge_radius px of a prior depth edge
    model_edge_min_conf: float = 0.9  # ... for shapes with eq.-(5) confidence at least this
    prior_edge_rel: float = 0.05  # a prior depth edge: relative gradient above this per pixel
    prior_edge_radius: int = (
        4  # [px] neighbourhood of prior depth edges (blurred by learned priors)
    )
    residual_field: bool = True  # departure: smooth multiplicative correction after CDR
    residual_sigma_frac: float = 0.05  # its Gaussian width, fraction of the image width
    residual_model_weight: float = 0.05  # weight of a model-output sample vs a feature (1)
    residual_shrink: float = 1.0  # the field decays to 1 (no correction) where it has less
    # evidence than this many features per Gaussian footprint (as anchor_shrink)
    absorb: bool = True  # departure: groups without a shape join a neighbour's shape that fits
    local_anchor: bool = True  # departure: eq. (8) anchors to the globally aligned prior times a
    # smooth field of the geometric evidence (model depth, features) relative to it
    anchor_shrink: float = 1.0  # that field decays to 0 where it has less evidence than this
    # many features per Gaussian footprint (pseudo-observation of "no correction")
    absorb_prior_gate: float = 0.15  # featureless groups: model vs globally aligned prior
    absorb_sample_below: int = 5  # groups with fewer features also use sample-pixel evidence
    model_output: bool = True  # departure: output the model depth where it agrees (below)
    model_output_gate: float = 0.1  # output the model depth where it is within this relative
    # distance of the calibrated prior (accepted shapes only); else the calibrated prior
    sky_depth_frac: float = 0.9  # a prior pixel is "far" beyond this fraction of d_max (globally)
    sky_far_fraction: float = 0.6  # a featureless object is sky when this share of it is far
    global_huber: float = 0.05  # Huber width (relative) of the global affine alignment
    fill_scale: float = 0.5  # resolution factor of the edge-aware fill
    fill_lambda: float = 50.0  # edge-aware fill: smoothing strength (FGS lambda)
    fill_sigma_color: float = 8.0  # edge-aware fill: colour edge scale (FGS sigma)
    seed: int = 0  # RANSAC random seed (results are deterministic per input)
    consensus: ConsensusParams = ConsensusParams()  # Algorithm 1 parameters
    cdr: CdrParams = CdrParams()  # eqs. (6)-(11) parameters

    def __post_init__(self) -> None:
        if not (0 < self.d_min_m < self.d_max_m and np.isfinite(self.d_max_m)):
            raise ConfigError("MetrizerParams: need 0 < d_min_m < d_max_m < inf")
        if not self.anchor_shrink >= 0:
            raise ConfigError(
                f"MetrizerParams: anchor_shrink >= 0 required, got {self.anchor_shrink}"
            )
        if self.n_min < 1 or self.sample_stride < 1 or self.rho_contiguity < 0:
            raise ConfigError("MetrizerParams: n_min >= 1, sample_stride >= 1, rho >= 0 required")


@dataclass
class MetrizedDepth:
    """Output of :func:`metrize_depth`."""

    depth_m: NDArray[np.float32]  # [H, W] metric z-depth, in (0, d_max]; 0 = no value
    confidence: NDArray[np.float32]  # [H, W] in [0, 1]; 0 where depth_m is 0
    object_labels: NDArray[np.int32]  # [H, W] object id after merging (every pixel has one)
    object_model: NDArray[np.int8]  # [M] 0 none, 1 plane, 2 cylinder, 3 ellipsoid
    object_affine: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))  # [M, 2]
    object_confidence: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))  # [M] eq. 5
    stats: dict[str, Any] = field(default_factory=dict)


# ------------------------------------------------------------------------------ input checks


def _check_inputs(K, labels, uv, z, w, prior, conf, kind, image, mode):
    if kind not in PRIOR_KINDS:
        raise ConfigError(f"prior_kind: expected one of {PRIOR_KINDS}, got {kind!r}")
    if mode not in MODES:
        raise ConfigError(f"mode: expected one of {MODES}, got {mode!r}")
    K = check_array("K", K, shape=(3, 3), dtype=np.number).astype(np.float64)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise GeometryError(f"K: invalid intrinsics {K.tolist()}")
    labels = check_array("labels", labels, shape=(None, None), dtype=np.integer)
    H, W = labels.shape
    if H == 0 or W == 0:
        raise GeometryError("labels: empty image")
    prior = check_array("prior", prior, shape=(H, W), dtype=np.number)
    conf = check_array("prior_confidence", conf, shape=(H, W), dtype=np.number)
    uv = check_array("feature_uv_px", uv, shape=(None, 2), dtype=np.number)
    n = len(uv)
    z = check_array("feature_depth_m", z, shape=(n,), dtype=np.number)
    w = check_array("feature_weight", w, shape=(n,), dtype=np.number)
    if image is not None:
        image = check_array("image_rgb", image, shape=(H, W, 3), dtype=np.uint8)
    return K, labels, uv, z, w, prior, conf, image


def _sanitise(uv, z, w, prior, conf, p: MetrizerParams, H: int, W: int, kind: str = ""):
    """Flat float32 prior / confidence (non-finite -> no prior) and the usable features.

    A depth-space prior (``relative_depth`` / ``metric``) has no value where it is not positive.
    """
    prior = np.ascontiguousarray(prior, dtype=np.float32).ravel()
    conf = np.ascontiguousarray(conf, dtype=np.float32).ravel()
    good_p, good_c = np.isfinite(prior).all(), np.isfinite(conf).all()
    if not (good_p and good_c) or conf.min(initial=0.0) < 0 or conf.max(initial=0.0) > 1:
        good = np.isfinite(prior) & np.isfinite(conf)
        conf = np.where(good, np.clip(conf, 0.0, 1.0), 0.0).astype(np.float32)
        prior = np.where(good & (conf > 0), prior, 0.0).astype(np.float32)
    if kind in ("relative_depth", "metric") and prior.min(initial=1.0) <= 0:
        conf = np.where(prior > 0, conf, 0.0).astype(np.float32)
    uv = uv.astype(np.float64)
    z = z.astype(np.float64)
    w = w.astype(np.float64)
    with np.errstate(invalid="ignore"):
        keep = (
            np.all(np.isfinite(uv), axis=1)
            & np.isfinite(z)
            & np.isfinite(w)
            & (z >= p.d_min_m)
            & (z <= p.d_max_m)
            & (uv[:, 0] > -0.5)
            & (uv[:, 0] < W - 0.5)
            & (uv[:, 1] > -0.5)
            & (uv[:, 1] < H - 0.5)
        )
    w = np.maximum(w[keep], 0.0) + 1e-6
    return uv[keep], z[keep], w, prior, conf


# ------------------------------------------------------------------------------ helpers


@dataclass
class _Frame:
    """Working set of one keyframe shared by the stages of :func:`metrize_depth` (flat arrays)."""

    p: MetrizerParams
    H: int
    W: int
    K: F64
    prior_kind: str
    prior: NDArray[np.float32]  # [HW] prior values (0 where no prior)
    conf: NDArray[np.float32]  # [HW] prior confidence
    has_prior: NDArray[np.bool_]  # [HW]
    all_prior: bool
    image: NDArray[np.uint8] | None  # [H, W, 3]
    z: F64  # [N] feature depths
    fpix: NDArray[np.intp]  # [N] flat pixel of each feature
    f_consistent: NDArray[np.bool_]  # [N] feature agrees with the globally aligned prior
    theta0: F64  # [2] global affine
    stats: dict[str, Any]
    G: int = 0  # objects after merging
    gobj: NDArray[np.intp] | None = None  # [HW] object per pixel
    feat_g: NDArray[np.intp] | None = None  # [N] object per feature
    n_feat_g: NDArray[np.int64] | None = None  # [G]
    sky: NDArray[np.bool_] | None = None  # [G]
    theta: F64 | None = None  # [G, 2] per-object affine (eq. 6)
    kind_g: NDArray[np.int8] | None = None  # [G] accepted model kind
    conf_g: F64 | None = None  # [G] eq. (5) confidence of the accepted model
    Am: F64 | None = None  # [G, 3, 3] quadric of the accepted model (camera frame)
    bm: F64 | None = None  # [G, 3]
    cm: F64 | None = None  # [G]
    zlo: F64 | None = None  # [G] model depth valid range
    zhi: F64 | None = None  # [G]
    run_label: NDArray[np.intp] | None = None  # [R] object of each raster run of gobj
    run_len: NDArray[np.intp] | None = None  # [R] its length in pixels
    edges: NDArray[np.uint8] | None = None  # quarter-resolution depth-edge band of the prior
    t_abs_m: float = 0.0  # absolute part of T_s(z) used (see the consensus stage)

    def in_edge_band(self, flat_idx: NDArray[np.intp]) -> NDArray[np.bool_]:
        """Whether flat pixels lie in the prior's depth-edge band (computed once, on demand)."""
        if self.edges is None:
            self.edges = _prior_edges(self.prior, self.conf, self.H, self.W, self.p)
        v, u = np.divmod(flat_idx, self.W)
        h4, w4 = self.edges.shape
        return (
            self.edges[np.minimum(v * h4 // self.H, h4 - 1), np.minimum(u * w4 // self.W, w4 - 1)]
            > 0
        )

    def per_pixel(self, table: NDArray) -> NDArray:
        """``table[gobj]`` ``[HW]`` for a per-object ``table`` ``[G]``: the object map is
        piecewise constant, so its raster runs are expanded (``np.repeat``), which is cheaper
        than a per-pixel gather."""
        if self.run_label is None:
            g = self.gobj
            starts = np.concatenate([[0], np.flatnonzero(g[1:] != g[:-1]) + 1])
            self.run_label = g[starts]
            self.run_len = np.diff(np.append(starts, len(g)))
        return np.repeat(table[self.run_label], self.run_len)


class _Timer:
    """Per-stage wall-clock (``ms``) and process CPU (``cpu_ms``) times in milliseconds."""

    def __init__(self) -> None:
        self.t0 = self.tic = time.perf_counter()
        self.c0 = self.ctic = time.process_time()
        self.ms: dict[str, float] = {}
        self.cpu_ms: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now, cnow = time.perf_counter(), time.process_time()
        self.ms[name] = (now - self.tic) * 1e3
        self.cpu_ms[name] = (cnow - self.ctic) * 1e3
        self.tic, self.ctic = now, cnow

    def total(self) -> dict[str, float]:
        self.ms["total"] = (time.perf_counter() - self.t0) * 1e3
        self.cpu_ms["total"] = (time.process_time() - self.c0) * 1e3
        return self.ms


def _far_and_norm(y: F64, kind: str, p: MetrizerParams) -> tuple[NDArray[np.bool_], F64]:
    """Globally aligned values ``y`` -> (far mask, positive normaliser in the same space)."""
    if kind == "relative_inverse_depth":
        return y <= 1.0 / (p.sky_depth_frac * p.d_max_m), np.clip(
            y, 1.0 / p.d_max_m, 1.0 / p.d_min_m
        )
    return y >= p.sky_depth_frac * p.d_max_m, np.clip(y, p.d_min_m, p.d_max_m)


def _object_map(table: NDArray[np.intp], obj_i: NDArray[np.intp]) -> NDArray[np.intp]:
    """Object id per pixel ``[HW]`` from the compact labels ``obj_i`` ``[HW]`` and a look-up table
    ``[n_obj]`` (``obj_i`` itself when the table is the identity)."""
    if np.array_equal(table, np.arange(len(table))):
        return obj_i
    return np.take(table, obj_i)


def _pixel_xy(flat_idx: NDArray[np.intp], W: int, K: F64) -> tuple[F64, F64]:
    """Normalised image coordinates (ray ``(x, y, 1)``) of flat pixel indices."""
    v, u = np.divmod(flat_idx, W)
    return (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]


def _model_depth(flat_idx, g, kind_g, Am, bm, cm, W, K) -> F64:
    """Ray-shape intersection depth (nearest positive root, ``inf`` on a miss) at flat pixels
    ``flat_idx`` of objects ``g``; planes in closed form, quadrics via :func:`shapes.ray_depth`."""
    x, y = _pixel_xy(flat_idx, W, K)
    out = np.full(len(flat_idx), np.inf)
    plane = kind_g[g] == shapes.KIND_PLANE
    if plane.any():
        gp = g[plane]
        b = bm[gp]
        qb = b[:, 0] * x[plane] + b[:, 1] * y[plane] + b[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -cm[gp] / qb
        out[plane] = np.where(np.isfinite(t) & (t > 0), t, np.inf)
    qi = np.flatnonzero(~plane)
    if len(qi):  # few curved objects: one model at a time, no per-pixel gather of A
        gq = g[qi]
        order = np.argsort(gq, kind="stable")
        qi, gq = qi[order], gq[order]
        cuts = np.flatnonzero(np.diff(gq)) + 1
        for part in np.split(np.arange(len(qi)), cuts):
            k = gq[part[0]]
            rays = np.stack([x[qi[part]], y[qi[part]], np.ones(len(part))], 1)
            out[qi[part]] = shapes.ray_depth(Am[k], bm[k], cm[k], rays)
    return out


def _prior_edges(
    prior: NDArray[np.float32], conf: NDArray[np.float32], H: int, W: int, p: MetrizerParams
) -> NDArray[np.uint8]:
    """Depth-edge neighbourhood of the prior (relative gradient), at quarter resolution."""
    x = prior if conf.min(initial=1.0) > 0 else np.where(conf > 0, prior, np.float32(0.0))
    x = x.reshape(H, W).astype(np.float32, copy=False)
    h4, w4 = max(1, H // 4), max(1, W // 4)
    xs = cv2.resize(x, (w4, h4), interpolation=cv2.INTER_AREA)
    gx = np.abs(cv2.Sobel(xs, cv2.CV_32F, 1, 0, ksize=3))
    gy = np.abs(cv2.Sobel(xs, cv2.CV_32F, 0, 1, ksize=3))
    rel = (gx + gy) / (32.0 * np.maximum(np.abs(xs), 1e-6))  # per full-resolution pixel
    r = max(1, round(p.prior_edge_radius / 4))
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return cv2.dilate((rel > p.prior_edge_rel).astype(np.uint8), k)


def _to_depth(y: NDArray, kind: str, p: MetrizerParams) -> NDArray:
    """In-place :func:`depth_from_space` for large float32 arrays (finite input)."""
    if kind == "relative_inverse_depth":
        np.maximum(y, np.float32(1.0 / p.d_max_m), out=y)
        np.reciprocal(y, out=y)
    np.clip(y, np.float32(p.d_min_m), _f32_below(p.d_max_m), out=y)
    return y


def _f32_below(v: float) -> np.float32:
    """Largest float32 not above ``v``."""
    f = np.float32(v)
    return f if float(f) <= v else np.nextafter(f, np.float32(-np.inf))


# ------------------------------------------------------------------------------ main entry


def metrize_depth(
    *,
    K: F64,
    labels: NDArray[np.integer],
    feature_uv_px: NDArray[np.floating],
    feature_depth_m: NDArray[np.floating],
    feature_weight: NDArray[np.floating],
    prior: NDArray[np.floating],
    prior_confidence: NDArray[np.floating],
    prior_kind: str = "relative_inverse_depth",
    image_rgb: NDArray[np.uint8] | None = None,
    params: MetrizerParams = MetrizerParams(),
    mode: str = "full",
) -> MetrizedDepth:
    """Metric dense depth of one keyframe from sparse metric points, masks and a dense prior.

    Args:
        K: ``[3, 3]`` float64 intrinsics.
        labels: ``[H, W]`` int instance masks, -1 = no mask.
        feature_uv_px: ``[N, 2]`` feature pixels; feature_depth_m: ``[N]`` metric z-depth;
            feature_weight: ``[N]`` omega (track quality).
        prior: ``[H, W]`` dense prior of kind ``prior_kind``; prior_confidence: ``[H, W]`` in
            ``[0, 1]``, 0 where there is no prior.
        image_rgb: ``[H, W, 3]`` uint8 for the edge-aware weights of eq. (10) and the fill.
        params: :class:`MetrizerParams`. mode: ``full`` | ``no_msc`` | ``no_msc_cdr``.

    Returns a :class:`MetrizedDepth`; depth is finite, in ``(0, d_max]`` or 0 (no value).
    Raises ShapeError / GeometryError / ConfigError for malformed arguments; any NaN / inf in the
    values is treated as missing data, never raised.
    """
    tm = _Timer()
    p = params
    K, labels, uv, z, w, prior, conf, image = _check_inputs(
        K,
        labels,
        feature_uv_px,
        feature_depth_m,
        feature_weight,
        prior,
        prior_confidence,
        prior_kind,
        image_rgb,
        mode,
    )
    H, W = labels.shape
    uv, z, w, prior, conf = _sanitise(uv, z, w, prior, conf, p, H, W, prior_kind)
    obj2d, n_obj, unmasked = prepare_labels(labels)
    obj = obj2d.ravel()
    has_prior = conf > 0
    all_prior = bool(has_prior.all())
    tm.lap("prepare")

    feat_obj = associate_features(obj2d, uv, p.border_vote_radius)
    fu = np.clip(np.round(uv[:, 0]).astype(np.intp), 0, W - 1)
    fv = np.clip(np.round(uv[:, 1]).astype(np.intp), 0, H - 1)
    fpix = fv * W + fu
    tm.lap("associate")

    # ---- global affine alignment: the anchor of eq. (8) and the no_msc_cdr result
    fx, fc = prior[fpix].astype(np.float64), conf[fpix].astype(np.float64)
    ft = space_from_depth(z, prior_kind)
    theta0, n_global = fit_global_affine(fx, ft, w * fc, prior_kind, p.global_huber)
    _, f_norm = _far_and_norm(theta0[0] * fx + theta0[1], prior_kind, p)
    fd_glob = depth_from_space(f_norm, prior_kind, p.d_min_m, p.d_max_m)
    f_consistent = (fc > 0) & (np.abs(np.log(z / fd_glob)) <= np.log1p(p.feature_prior_gate))
    stats: dict[str, Any] = {
        "mode": mode,
        "n_masks": int(n_obj - unmasked.sum()),
        "n_unmasked_regions": int(unmasked.sum()),
        "n_features": int(len(z)),
        "n_features_global": int(n_global),
        "global_affine": [float(theta0[0]), float(theta0[1])],
    }
    tm.lap("global")

    # ---- multi-scale merging (III-B)
    pairs = boundary_pairs(obj2d) if mode != "no_msc_cdr" else None
    if mode == "full":
        adj_k, adj_l, _ = region_adjacency(obj2d, n_obj, pairs)
        group, n_merges = merge_undersupported(
            n_obj, adj_k, adj_l, feat_obj, z, p.n_min, p.rho_contiguity
        )
    else:
        group, n_merges = np.arange(n_obj), 0
    G = int(group.max()) + 1 if n_obj else 0
    # intp indices: np.take with int32 indices is several times slower (index conversion); the
    # full-resolution object map is built once, after the last merge (absorption in mode full)
    obj_i = obj.astype(np.intp)
    group = group.astype(np.intp, copy=False)
    feat_g = group[feat_obj]
    n_feat_g = np.bincount(feat_g, minlength=G)
    # CDR sample pixels: a strided grid plus every pixel of objects the grid misses
    s = p.sample_stride
    grid = (np.arange(0, H, s)[:, None] * W + np.arange(0, W, s)[None, :]).ravel()
    missing = np.bincount(group[obj_i[grid]], minlength=G) == 0
    if missing.any():
        grid = np.concatenate([grid, np.flatnonzero(np.take(missing[group], obj_i))])
    grid = grid[has_prior[grid]]
    gg_grid = group[obj_i[grid]]
    y_grid = theta0[0] * prior[grid].astype(np.float64) + theta0[1]
    far_grid, norm_grid = _far_and_norm(y_grid, prior_kind, p)
    n_prior_g = np.bincount(gg_grid, minlength=G)
    n_far_g = np.bincount(gg_grid[far_grid], minlength=G)
    # sky needs the metric global alignment (no feature with a prior: "far" means nothing)
    sky = (n_feat_g == 0) & (n_prior_g > 0) & (n_far_g >= p.sky_far_fraction * n_prior_g)
    sky &= n_global > 0
    stats.update(n_objects=G, merges=int(n_merges), n_sky_objects=int(sky.sum()))
    tm.lap("merge")

    fr = _Frame(
        p=p,
        H=H,
        W=W,
        K=K,
        prior_kind=prior_kind,
        prior=prior,
        conf=conf,
        has_prior=has_prior,
        all_prior=all_prior,
        image=image,
        z=z,
        fpix=fpix,
        f_consistent=f_consistent,
        theta0=theta0,
        stats=stats,
        G=G,
        gobj=None if mode == "full" else _object_map(group, obj_i),
        feat_g=feat_g,
        n_feat_g=n_feat_g,
        sky=sky,
        theta=np.tile(theta0, (G, 1)),
        kind_g=np.zeros(G, np.int8),
        conf_g=np.zeros(G),
    )
    if mode == "no_msc_cdr":
        return _compose(fr, tm, global_only=True)

    # ---- shape consensus, Algorithm 1 (III-B)
    kind_g = np.zeros(G, np.int8)
    conf_g = np.zeros(G)
    Am, bm, cm = np.zeros((G, 3, 3)), np.zeros((G, 3)), np.zeros(G)
    zlo, zhi = np.zeros(G), np.zeros(G)
    n_skipped = n_tried = n_degenerate = 0
    # T_s(z) = t_abs + t_rel z: the absolute term (set for street scenes) shrinks with the scene:
    # at most t_abs_m * median feature depth / t_abs_ref_depth_m (departure 14)
    cons = p.consensus
    if len(z):
        t_abs = cons.t_abs_m * min(1.0, float(np.median(z)) / p.t_abs_ref_depth_m)
        if t_abs < cons.t_abs_m:
            cons = replace(cons, t_abs_m=t_abs)
    if mode == "full" and len(z):
        rng = np.random.default_rng(p.seed)
        Xf = np.stack(
            [(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], 1
        )
        order = np.argsort(feat_g, kind="stable")
        starts = np.concatenate([[0], np.cumsum(n_feat_g)])
        fits = fit_objects(Xf, w, feat_g, G, rng, cons)
        for g, fit in fits.items():
            n_tried += 1
            n_skipped += int(fit.skipped_costly)
            n_degenerate += int(fit.degenerate)
            if fit.kind == shapes.KIND_NONE:
                continue
            kind_g[g], conf_g[g] = fit.kind, fit.confidence
            Am[g], bm[g], cm[g] = fit.A, fit.b, fit.c
            zi = z[order[starts[g] : starts[g + 1]]][fit.inliers]
            zlo[g] = max(zi.min() / p.model_extrapolation, p.d_min_m)
            zhi[g] = min(zi.max() * p.model_extrapolation, p.d_max_m)
    fr.t_abs_m = cons.t_abs_m
    tm.lap("consensus")
    n_absorbed = 0
    obj_to_g = group  # [n_obj] object -> group (after absorption in mode full)
    if mode == "full" and p.absorb and (kind_g > 0).any():
        remap = _absorb(
            fr,
            group,
            (adj_k, adj_l),
            (kind_g, Am, bm, cm, zlo, zhi),
            Xf,
            (grid, gg_grid, norm_grid),
        )
        if remap is not None:
            keep_ids, remap = remap
            n_absorbed = G - len(keep_ids)
            G = len(keep_ids)
            obj_to_g = remap[group]
            gg_grid, feat_g = remap[gg_grid], remap[feat_g]
            n_feat_g = np.bincount(feat_g, minlength=G)
            sky, kind_g, conf_g = sky[keep_ids], kind_g[keep_ids], conf_g[keep_ids]
            Am, bm, cm, zlo, zhi = (
                Am[keep_ids],
                bm[keep_ids],
                cm[keep_ids],
                zlo[keep_ids],
                zhi[keep_ids],
            )
            fr.G, fr.feat_g, fr.n_feat_g, fr.sky = G, feat_g, n_feat_g, sky
    if fr.gobj is None:
        fr.gobj = _object_map(obj_to_g, obj_i)
    gobj = fr.gobj
    stats.update(
        n_objects=G,
        absorbed=n_absorbed,
        objects_tried=n_tried,
        skipped_costly=n_skipped,
        models={
            "plane": int((kind_g == 1).sum()),
            "cylinder": int((kind_g == 2).sum()),
            "ellipsoid": int((kind_g == 3).sum()),
        },
        rejected=int(n_tried - (kind_g > 0).sum()),
        rejected_degenerate=n_degenerate,
    )
    tm.lap("absorb")

    # ---- propagation: model depth by ray-shape intersection at the CDR samples
    keep = ~sky[gg_grid]
    sidx, sg, snorm = grid[keep], gg_grid[keep], norm_grid[keep]
    sx, sc = prior[sidx].astype(np.float64), conf[sidx].astype(np.float64)
    mdepth = np.full(len(sidx), np.inf)
    mi = np.flatnonzero(kind_g[sg] > 0)
    if len(mi):
        mdepth[mi] = _model_depth(sidx[mi], sg[mi], kind_g, Am, bm, cm, W, K)
    d_glob = depth_from_space(snorm, prior_kind, p.d_min_m, p.d_max_m)
    mok = _model_agrees(mdepth, zlo[sg], zhi[sg], d_glob, p.model_prior_gate)
    tm.lap("propagate")

    # ---- cross-object depth refinement, eqs. (6)-(11) (III-C)
    geo = _geo_rows(
        mok,
        sg,
        sx,
        sc,
        mdepth,
        conf_g,
        kind_g,
        feat_g,
        fx,
        fc * f_consistent,
        ft,
        w,
        n_feat_g,
        G,
        p,
        prior_kind,
        sky,
    )
    if p.local_anchor:
        snorm = _local_anchor(fr, sidx, mok, mdepth, d_glob, fd_glob, snorm)
    nfc_w = sc / np.maximum(np.bincount(sg, sc, minlength=G), 1e-12)[sg]
    pp, qq = pairs
    gp, gq = gobj[pp], gobj[qq]
    keep = (gp != gq) & ~sky[gp] & ~sky[gq]
    if not all_prior:
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
    _, norm_p = _far_and_norm(theta0[0] * xp + theta0[1], prior_kind, p)
    _, norm_q = _far_and_norm(theta0[0] * xq + theta0[1], prior_kind, p)
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
    theta = solve_cdr(prob, p.cdr) if n_global > 0 else np.tile(theta0, (G, 1))
    # a non-finite or sign-flipping calibration (an inverted prior) falls back to the global one
    theta[~np.all(np.isfinite(theta), axis=1) | (theta[:, 0] <= 0)] = theta0
    stats.update(n_geo_rows=int(len(geo[0])), n_nfc_rows=int(len(sg)), n_sm_rows=int(len(gp)))
    tm.lap("refine")
    fr.theta, fr.kind_g, fr.conf_g = theta, kind_g, conf_g
    fr.Am, fr.bm, fr.cm, fr.zlo, fr.zhi = Am, bm, cm, zlo, zhi
    return _compose(fr, tm, global_only=False)


def _model_agrees(dm: F64, lo: F64, hi: F64, d_ref: F64, gate: float) -> NDArray[np.bool_]:
    """Model depth ``dm`` hit, within the shape's valid range ``[lo, hi]`` and within ``gate``
    (relative) of the reference depth ``d_ref`` (the globally aligned prior)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.isfinite(dm) & (dm >= lo) & (dm <= hi) & (np.abs(dm / d_ref - 1.0) <= gate)


def _local_anchor(fr: _Frame, sidx, mok, mdepth, d_glob, fd_glob, snorm) -> F64:
    """Eq. (8) target at the CDR samples: the globally aligned prior times a smooth field.

    The field is the Gaussian normalised convolution of ``log(target / globally aligned prior)``
    over the geometric evidence of eq. (7): model depth at sample pixels outside the prior's
    depth-edge band (where the blurred prior makes the ratio an edge artefact, not a warp),
    weight ``residual_model_weight``, and consistent features, weight 1, with the width of the
    residual field; the factor ``exp(field)`` decays to 1 away from evidence (``anchor_shrink``). An object without
    geometry is then anchored to the prior as its neighbourhood's geometry aligns it, rather than
    to one affine for the whole frame (departure 13 in docs/metrizer.md). ``snorm`` (the global
    target) is returned unchanged when there is no evidence.
    """
    p = fr.p
    mk = mok.copy()
    mk[mok] = ~fr.in_edge_band(sidx[mok])
    fok = fr.f_consistent
    idx = np.concatenate([sidx[mk], fr.fpix[fok]])
    if len(idx) == 0:
        return snorm
    with np.errstate(divide="ignore", invalid="ignore"):
        val = np.concatenate([np.log(mdepth[mk] / d_glob[mk]), np.log(fr.z[fok] / fd_glob[fok])])
    wt = np.concatenate([np.full(int(mk.sum()), p.residual_model_weight), np.ones(int(fok.sum()))])
    good = np.isfinite(val)
    field = smooth_field(
        (fr.H, fr.W),
        idx[good],
        val[good],
        wt[good],
        p.residual_sigma_frac,
        shrink=p.anchor_shrink,
        at=sidx,
    )
    d = np.clip(d_glob * np.exp(field.astype(np.float64)), p.d_min_m, p.d_max_m)
    return space_from_depth(d, fr.prior_kind)


def _expand(item_group, n_groups, pair_groups):
    """Rows ``(item, pair)`` for every item (feature / sample) of each pair's group, vectorised."""
    order = np.argsort(item_group, kind="stable")
    counts = np.bincount(item_group, minlength=n_groups)
    starts = np.concatenate([[0], np.cumsum(counts)])
    lens = counts[pair_groups]
    row_pair = np.repeat(np.arange(len(pair_groups)), lens)
    offs = np.arange(len(row_pair)) - np.repeat(np.cumsum(lens) - lens, lens)
    return order[starts[pair_groups][row_pair] + offs], row_pair


def _absorb(fr: _Frame, group, adjacency, model, Xf, samples):
    """Second merging scale (departure, docs/metrizer.md): a group without an accepted shape joins
    an adjacent group whose shape explains it: at least ``tau`` of its features are inliers of that
    model (eq. 2 residual below ``T_s(z)``); a group with fewer than ``absorb_sample_below``
    features also counts its sample pixels, where the model depth must be within
    ``absorb_prior_gate`` of the globally aligned prior.
    ``adjacency`` = ``(adj_k, adj_l)`` object pairs, ``model`` = ``(kind, A, b, c, zlo, zhi)`` per
    group, ``samples`` = ``(grid, group of grid, globally aligned normaliser)`` of the CDR samples;
    features, groups, camera and parameters come from ``fr``.
    Returns ``(kept old ids [G'], old -> new id map [G])`` or None when nothing is absorbed."""
    adj_k, adj_l = adjacency
    kind_g, Am, bm, cm, zlo, zhi = model
    grid, gg_grid, norm_grid = samples
    p, G, W, K, prior_kind = fr.p, fr.G, fr.W, fr.K, fr.prior_kind
    z, feat_g, n_feat_g, sky = fr.z, fr.feat_g, fr.n_feat_g, fr.sky
    ga, gb = group[adj_k], group[adj_l]
    diff = ga != gb
    a = np.concatenate([ga[diff], gb[diff]])
    b = np.concatenate([gb[diff], ga[diff]])
    cand = (kind_g[a] == 0) & (kind_g[b] > 0) & ~sky[a]
    if not cand.any():
        return None
    key = np.unique(a[cand].astype(np.int64) * G + b[cand])
    pg, pu = (key // G).astype(np.intp), (key % G).astype(np.intp)
    # evidence 1: the features of g against u's model (eq. 2 residual below T_s)
    fi, frow = _expand(feat_g, G, pg)
    u = pu[frow]
    r = shapes.quadric_residual_rows(Am[u], bm[u], cm[u], Xf[fi])
    f_ok = r <= fr.t_abs_m + p.consensus.t_rel * z[fi]
    # evidence 2: g with few features: u's model depth at g's samples vs the global prior
    si, srow = _expand(gg_grid, G, pg)
    sel = n_feat_g[pg][srow] < p.absorb_sample_below
    si, srow = si[sel], srow[sel]
    us = pu[srow]
    dm = _model_depth(grid[si], us, kind_g, Am, bm, cm, W, K)
    d_glob = depth_from_space(norm_grid[si], prior_kind, p.d_min_m, p.d_max_m)
    s_ok = _model_agrees(dm, zlo[us], zhi[us], d_glob, p.absorb_prior_gate)
    target = absorb_into_models(
        pg, pu, np.concatenate([frow, srow]), np.concatenate([f_ok, s_ok]), G, p.consensus.tau
    )
    if np.array_equal(target, np.arange(G)):
        return None
    keep_ids, remap = np.unique(target, return_inverse=True)
    return keep_ids, remap.astype(np.intp)


def _geo_rows(
    mok, sg, sx, sc, mdepth, conf_g, kind_g, feat_g, fx, fc, ft, w, n_feat_g, G, p, prior_kind, sky
):
    """Rows of eq. (7): model pixels of accepted shapes, else the object's sparse features.

    Model pixels weigh ``C_k`` (eq. 5) times the prior confidence, features ``omega`` times the
    prior confidence times ``min(1, n_k / n_min)``; each object's weights are normalised to a mean.
    """
    mo, mx, mc = sg[mok], sx[mok], sc[mok]
    mt = space_from_depth(mdepth[mok], prior_kind)
    mw = mc / np.maximum(np.bincount(mo, mc, minlength=G), 1e-12)[mo] * conf_g[mo]
    use = (kind_g[feat_g] == 0) & (fc > 0) & ~sky[feat_g]
    fo, fxx, ftt, fw = feat_g[use], fx[use], ft[use], (w * fc)[use]
    support = np.minimum(1.0, n_feat_g / p.n_min)
    fw = fw / np.maximum(np.bincount(fo, fw, minlength=G), 1e-12)[fo] * support[fo]
    return (
        np.concatenate([mo, fo]).astype(np.intp),
        np.concatenate([mx, fxx]),
        np.concatenate([mt, ftt]),
        np.concatenate([mw, fw]),
    )


# ------------------------------------------------------------------------------ composition


def _model_output(fr: _Frame, depth: NDArray[np.float32], special) -> tuple:
    """Replace the calibrated prior by the model depth where they agree (gate), in place.

    Planes are evaluated on the full image at once: their inverse depth is affine in the
    normalised image coordinates, ``1 / t = alpha x + beta y + gamma`` with ``(alpha, beta, gamma)
    = -b / c``. Cylinders and ellipsoids use :func:`shapes.ray_depth` on their own pixels.
    Returns the mask ``[HW]`` of pixels that now hold model depth, and flat indices of every
    ``sample_stride^2``-th of them with ``log(model / calibrated)`` there (for the residual field).
    """
    p: MetrizerParams = fr.p
    H, W, G, K = fr.H, fr.W, fr.G, fr.K
    gobj, kind_g, conf_g = fr.gobj, fr.kind_g, fr.conf_g
    Am, bm, cm, zlo, zhi = fr.Am, fr.bm, fr.cm, fr.zlo, fr.zhi
    trusted = (conf_g >= p.model_edge_min_conf) & (kind_g > 0)
    # the prior's edge band is looked up only where the wide gate matters
    use_band = p.model_edge_gate > p.model_output_gate and bool(trusted.any())

    def in_band(flat_idx):
        return fr.in_edge_band(flat_idx) & trusted[gobj[flat_idx]]

    g1, g2 = 1.0 + p.model_output_gate, 1.0 + p.model_edge_gate
    out_idx, out_ratio = [np.zeros(0, np.intp)], [np.zeros(0)]
    used = np.zeros(H * W, bool)
    sub = max(1, p.sample_stride**2)
    plane = (kind_g == shapes.KIND_PLANE) & (np.abs(cm) > 1e-12)
    quad = (kind_g == shapes.KIND_CYLINDER) | (kind_g == shapes.KIND_ELLIPSOID)
    if plane.any():
        coef = np.zeros((G, 3))
        coef[plane] = -bm[plane] / cm[plane, None]
        lo = np.where(plane, 1.0 / zhi.clip(min=1e-12), np.inf).astype(np.float32)
        hi = np.where(plane, 1.0 / zlo.clip(min=1e-12), -np.inf).astype(np.float32)
        xg = ((np.arange(W) - K[0, 2]) / K[0, 0]).astype(np.float32)
        yg = ((np.arange(H) - K[1, 2]) / K[1, 1]).astype(np.float32)
        # full-resolution float32 passes; per-object values expanded from the raster runs
        c32 = coef.astype(np.float32)
        inv = fr.per_pixel(c32[:, 0]).reshape(H, W)
        inv *= xg[None, :]
        tmp = fr.per_pixel(c32[:, 1]).reshape(H, W)
        tmp *= yg[:, None]
        inv += tmp
        inv, tmp = inv.ravel(), tmp.ravel()
        inv += fr.per_pixel(c32[:, 2])
        ok = inv >= fr.per_pixel(lo)
        ok &= inv <= fr.per_pixel(hi)
        r = np.multiply(inv, depth, out=tmp)  # calibrated / model
        okg = r >= np.float32(1.0 / g1)
        if g1 < 2:
            okg &= r <= np.float32(1.0 / (2.0 - g1))
        if use_band:  # wider gate in the prior's edge band, for trusted shapes
            oke = r >= np.float32(1.0 / g2)
            if g2 < 2:
                oke &= r <= np.float32(1.0 / (2.0 - g2))
            oke &= ok
            oke &= ~okg
            cand = np.flatnonzero(oke)
            okg[cand[in_band(cand)]] = True
        ok &= okg
        if special is not None:
            ok &= ~special
        used |= ok
        idx = np.flatnonzero(ok)[::sub]  # residual samples only: no full gather / scatter
        out_idx.append(idx)
        out_ratio.append(-np.log(r[idx].astype(np.float64)))
        np.divide(np.float32(1.0), inv, out=depth, where=ok)
    if quad.any():
        qpix = np.flatnonzero(fr.per_pixel(quad))
        if special is not None:
            qpix = qpix[~special[qpix]]
        g = gobj[qpix]
        dm = _model_depth(qpix, g, kind_g, Am, bm, cm, W, K)
        dcal = depth[qpix].astype(np.float64)
        gate = np.full(len(qpix), p.model_output_gate)
        if use_band:
            gate[in_band(qpix)] = p.model_edge_gate
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = (
                np.isfinite(dm)
                & (dm >= zlo[g])
                & (dm <= zhi[g])
                & (np.abs(dm / dcal - 1.0) <= gate)
            )
        used[qpix[ok]] = True
        out_idx.append(qpix[ok][::sub])
        out_ratio.append(np.log(dm[ok] / dcal[ok])[::sub])
        depth[qpix[ok]] = dm[ok]
    return used, np.concatenate(out_idx), np.concatenate(out_ratio)


# parameters fitted per object beyond the frame's shared global affine: its affine (eq. 6) plus
# the accepted shape (plane 3, cylinder 5, ellipsoid 9)
_N_PARAMS = np.array([2, 5, 7, 11])


def _fallback_to_global(fr: _Frame, depth: NDArray[np.float32], *, featureless: bool) -> int:
    """Per-object fallback to the global affine (the ``no_msc_cdr`` result), in place.

    An object keeps its own result (calibrated prior, model output, residual field) only when it
    explains the object's own sparse features better than the global affine does, after
    correcting for what it fitted to them: ``L1_obj * n / (n - p) < L1_glob`` with ``L1`` the
    summed absolute log-depth error at the object's features with a prior, ``n`` their number and
    ``p`` the object's fitted parameters (2 for its affine of eq. 6, plus those of its shape).
    ``RSS / (n - p)`` is the unbiased residual variance of a fit with ``p`` parameters; the
    global affine's two parameters are shared by all features of the frame. An object with
    ``n <= p`` cannot show that it beats the baseline and falls back. With ``featureless``,
    objects without features fall back too (else they keep what CDR's anchor and smoothness
    gave them). Returns the number of objects that fell back.
    """
    G, theta0, kind = fr.G, fr.theta0, fr.prior_kind
    fpix, z = fr.fpix, fr.z
    ok = fr.has_prior[fpix] & ~fr.sky[fr.feat_g] & (depth[fpix] > 0)
    g = fr.feat_g[ok]
    x = fr.prior[fpix[ok]].astype(np.float64)
    d_glob = depth_from_space(theta0[0] * x + theta0[1], kind, fr.p.d_min_m, fr.p.d_max_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        e_obj = np.abs(np.log(z[ok] / depth[fpix[ok]].astype(np.float64)))
        e_glob = np.abs(np.log(z[ok] / d_glob))
    n = np.bincount(g, minlength=G).astype(np.float64)
    l_obj = np.bincount(g, e_obj, minlength=G)
    l_glob = np.bincount(g, e_glob, minlength=G)
    dof = n - _N_PARAMS[np.clip(fr.kind_g, 0, 3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        keep = (dof > 0) & (l_obj * n / np.where(dof > 0, dof, 1.0) < l_glob)
    fall = ~keep & ~fr.sky
    if not featureless:
        fall &= fr.n_feat_g > 0
    if not fall.any():
        return 0
    pix = fr.per_pixel(fall) & fr.has_prior
    y = (np.float32(theta0[0]) * fr.prior[pix] + np.float32(theta0[1])).astype(np.float32)
    depth[pix] = _to_depth(y, kind, fr.p)
    return int(fall.sum())


def _nearest_seed(
    fr: _Frame, seed_pix: NDArray[np.intp], flat_idx: NDArray[np.intp]
) -> tuple[F64, NDArray[np.intp]]:
    """Distance [px] from flat pixels to the nearest seed pixel, and that seed pixel.

    A distance transform over the seed pixels (``DIST_LABEL_PIXEL``: the label of a pixel is the
    raster rank of its nearest zero pixel); ``inf`` / -1 without seeds."""
    H, W = fr.H, fr.W
    if len(seed_pix) == 0:
        return np.full(len(flat_idx), np.inf), np.zeros(len(flat_idx), np.intp)
    seeds = np.ones(H * W, np.uint8)
    seeds[seed_pix] = 0
    dist, lab = cv2.distanceTransformWithLabels(
        seeds.reshape(H, W), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    ranked = np.flatnonzero(seeds == 0)  # raster order = label order
    near = ranked[np.clip(lab.ravel()[flat_idx] - 1, 0, len(ranked) - 1)]
    return dist.ravel()[flat_idx].astype(np.float64), near


def _fill_holes(
    fr: _Frame, holes: NDArray[np.bool_], depth: NDArray[np.float32], out_conf: NDArray[np.float32]
) -> tuple[int, int]:
    """Depth for pixels without prior (and not sky), in place; returns the pixel counts
    ``(model depth, edge-aware fill)``.

    Seeds are the features that agree with their image neighbours (:func:`consistent_seeds`: no
    prior checks a feature here, so a gross outlier would otherwise be copied into the fill).
    Only where sparse metric evidence is near: the pixel's nearest seed must lie in the same
    object and within ``hole_model_radius`` (accepted shape: the model depth by ray-shape
    intersection) or ``hole_fill_radius`` (otherwise: the edge-aware fill of the sparse points)
    times the image width. Elsewhere there is no value (0): extrapolating a shape or diffusing
    far points into a region without any evidence (a textureless car or pillar close to the
    camera) gave errors of several hundred percent (docs/metrizer.md, pixels without prior).
    """
    p, H, W, gobj, kind_g = fr.p, fr.H, fr.W, fr.gobj, fr.kind_g
    hole_idx = np.flatnonzero(holes)
    v, u = np.divmod(fr.fpix, W)
    good = consistent_seeds(
        np.stack([u, v], 1).astype(np.float64),
        fr.z,
        gate=p.fill_seed_gate,
        radius_px=p.fill_seed_radius * W,
    )
    dist, near = _nearest_seed(fr, fr.fpix[good], hole_idx)
    same = np.isfinite(dist) & (gobj[near] == gobj[hole_idx])
    n_model = n_fill = 0
    hi = hole_idx[same & (kind_g[gobj[hole_idx]] > 0) & (dist <= p.hole_model_radius * W)]
    if len(hi):  # no prior, accepted shape, own features near: the model depth
        g = gobj[hi]
        d = _model_depth(hi, g, kind_g, fr.Am, fr.bm, fr.cm, W, fr.K)
        # no prior to gate the model against: a tighter extrapolation range
        f = p.hole_model_extrapolation / p.model_extrapolation
        ok = np.isfinite(d) & (d >= fr.zlo[g] / f) & (d <= fr.zhi[g] * f)
        depth[hi[ok]] = d[ok]
        out_conf[hi[ok]] = 0.5 * fr.conf_g[g[ok]]
        n_model = int(ok.sum())
    sel = same & (dist <= p.hole_fill_radius * W)
    sel[sel] = depth[hole_idx[sel]] == 0
    rest = hole_idx[sel]
    if len(rest) and p.fill_method == "nearest":  # the nearest consistent feature's depth
        seed_d = np.zeros(H * W, np.float32)
        seed_d[fr.fpix[good]] = fr.z[good]
        depth[rest] = np.clip(seed_d[near[sel]], p.d_min_m, _f32_below(p.d_max_m))
        out_conf[rest] = 0.1
        n_fill = len(rest)
    elif len(rest):  # the edge-aware fill from the consistent features
        seed_d = np.zeros(H * W, np.float32)
        seed_w = np.zeros(H * W, np.float32)
        seed_d[fr.fpix[good]] = fr.z[good]
        seed_w[fr.fpix[good]] = 1.0
        filled = edge_aware_fill(
            seed_d.reshape(H, W),
            seed_w.reshape(H, W),
            fr.image,
            p.fill_scale,
            p.fill_lambda,
            p.fill_sigma_color,
            geometric=True,
        ).ravel()[rest]
        ok = filled > 0
        depth[rest[ok]] = np.clip(filled[ok], p.d_min_m, _f32_below(p.d_max_m))
        out_conf[rest[ok]] = 0.1
        n_fill = int(ok.sum())
    return n_model, n_fill


def _compose(fr: _Frame, tm: _Timer, global_only: bool) -> MetrizedDepth:
    """Full-resolution output: calibrated prior per object, model depth, sky, holes, confidence."""
    p: MetrizerParams = fr.p
    H, W, G = fr.H, fr.W, fr.G
    gobj, prior, conf, has_prior = fr.gobj, fr.prior, fr.conf, fr.has_prior
    kind, theta, theta0, sky = fr.prior_kind, fr.theta, fr.theta0, fr.sky
    kind_g, conf_g, n_feat_g, stats = fr.kind_g, fr.conf_g, fr.n_feat_g, fr.stats
    z, fpix = fr.z, fr.fpix

    if global_only:
        q_g = np.full(G, 0.3)
    else:
        q_g = np.where(
            kind_g > 0,
            0.5 + 0.5 * conf_g,
            np.where(n_feat_g > 0, 0.5 * np.minimum(1.0, n_feat_g / p.n_min), 0.25),
        )
    # calibrated prior, eq. (6), everywhere (float32, in place)
    depth = fr.per_pixel(theta[:, 0].astype(np.float32))
    depth *= prior
    depth += fr.per_pixel(theta[:, 1].astype(np.float32))
    _to_depth(depth, kind, p)
    out_conf = fr.per_pixel(q_g.astype(np.float32))
    out_conf *= conf
    n_model_px = n_model_fill = n_edge_fill = 0
    sky_pix = fr.per_pixel(sky) if sky.any() else None
    special = None if sky_pix is None else sky_pix.copy()
    if not fr.all_prior:
        special = ~has_prior if special is None else special | ~has_prior

    tm.lap("compose")
    used, used_idx, used_ratio = None, np.zeros(0, np.intp), np.zeros(0)
    if p.model_output and (kind_g > 0).any() and not global_only:
        used, used_idx, used_ratio = _model_output(fr, depth, special)
        n_model_px = int(np.count_nonzero(used))
    tm.lap("model_output")

    if p.residual_field and not global_only:
        # departure (docs/metrizer.md): smooth multiplicative correction of the calibrated prior
        # from its residuals at the model-output pixels and at the consistent features
        fok = fr.f_consistent & ~sky[fr.feat_g]
        if used is not None:
            fok &= ~used[fpix]
        idx = np.concatenate([used_idx, fpix[fok]])
        val = np.concatenate([used_ratio, np.log(z[fok] / depth[fpix[fok]])])
        wt = np.concatenate(
            [np.full(len(used_idx), p.residual_model_weight), np.ones(int(fok.sum()))]
        )
        if len(idx):
            field = smooth_field(
                (H, W),
                idx,
                val,
                wt,
                p.residual_sigma_frac,
                exponentiate=True,
                shrink=p.residual_shrink,
            ).ravel()
            if used is not None:
                field[used] = 1.0
            depth *= field
            np.clip(depth, np.float32(p.d_min_m), _f32_below(p.d_max_m), out=depth)
    n_fallback = 0
    if p.fallback_global and not global_only:
        thin = stats["n_features_global"] < p.fallback_min_features
        n_fallback = _fallback_to_global(fr, depth, featureless=p.fallback_featureless or thin)
    stats["n_fallback_objects"] = n_fallback
    tm.lap("residual")

    if special is not None:
        if sky_pix is not None:  # sky objects: far / prior-less pixels -> d_max, others global
            y0 = (theta0[0] * prior[sky_pix] + theta0[1]).astype(np.float64)
            far, _ = _far_and_norm(y0, kind, p)
            far |= ~has_prior[sky_pix]
            ds = depth_from_space(y0, kind, p.d_min_m, p.d_max_m)
            ds[far] = p.d_max_m
            cs = np.where(far, 0.5 * np.maximum(conf[sky_pix], 0.2), 0.25 * conf[sky_pix])
            depth[sky_pix] = ds
            out_conf[sky_pix] = cs
        holes = ~has_prior if sky_pix is None else ~has_prior & ~sky_pix
        depth[holes] = 0.0
        out_conf[holes] = 0.0
        if holes.any() and not global_only:
            n_model_fill, n_edge_fill = _fill_holes(fr, holes, depth, out_conf)
    stats.update(
        n_model_output_px=n_model_px, n_hole_px_model=n_model_fill, n_hole_px_fill=n_edge_fill
    )
    tm.lap("sky_holes")
    # final guarantees: finite, 0 or within (0, d_max], confidence in [0, 1] and 0 without depth
    bad = ~np.isfinite(depth)
    if bad.any():
        depth[bad] = 0.0
    np.clip(out_conf, 0.0, 1.0, out=out_conf)
    out_conf[depth <= 0] = 0.0
    stats["ms"] = tm.total()
    stats["cpu_ms"] = tm.cpu_ms
    stats["coverage"] = float(np.count_nonzero(depth) / depth.size)
    return MetrizedDepth(
        depth_m=depth.reshape(H, W),
        confidence=out_conf.reshape(H, W),
        object_labels=gobj.reshape(H, W).astype(np.int32, copy=False),
        object_model=np.where(sky, 0, kind_g).astype(np.int8),
        object_affine=theta,
        object_confidence=conf_g,
        stats=stats,
    )
