"""Full-resolution output of the metrizer (stage 8): the calibrated prior of eq. (6) per object,
the model depth where it agrees (departure 7), the residual field (departure 8), the per-object
fallback to the global affine (never worse than the baseline, departure 15), sky, pixels
without prior and the output confidence (docs/metrizer.md)."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.geometry import pixel_grid_xy, pixel_to_normalized, road_plane_depth
from mogs_node.metrizer import shapes
from mogs_node.metrizer.alignment import depth_from_space
from mogs_node.metrizer.edge_snap import near_object_boundary, prior_edge_band, snap_edges
from mogs_node.metrizer.fill import (
    PlaneSelect,
    complete_planar_masks,
    consistent_seeds,
    edge_aware_fill,
    smooth_field,
)
from mogs_node.metrizer.frame import (
    Frame,
    ShapeModels,
    StageTimer,
    f32_below,
    far_and_norm,
    model_depth,
    to_depth_inplace,
)
from mogs_node.metrizer.ground import (
    GroundParams,
    fill_ground_contact,
    fill_road_objects,
    snap_road_objects,
)
from mogs_node.metrizer.params import MetrizedDepth, MetrizerParams

__all__ = ["compose", "fallback_to_global", "fill_holes", "model_output", "nearest_seed"]

F64 = NDArray[np.float64]


def model_output(fr: Frame, models: ShapeModels, depth: NDArray[np.float32], special) -> tuple:
    """Replace the calibrated prior by the model depth where they agree (gate), in place.

    Planes are evaluated on the full image at once: their inverse depth is affine in the
    normalised image coordinates, ``1 / t = alpha x + beta y + gamma`` with ``(alpha, beta, gamma)
    = -b / c``. Cylinders and ellipsoids use :func:`shapes.ray_depth` on their own pixels.
    Returns the mask ``[HW]`` of pixels that now hold model depth, and flat indices of every
    ``sample_stride^2``-th of them with ``log(model / calibrated)`` there (for the residual field).
    """
    p: MetrizerParams = fr.p
    H, W, G, K = fr.H, fr.W, fr.G, fr.K
    gobj, kind_g, conf_g = fr.gobj, models.kind, models.conf
    Am, bm, cm, zlo, zhi = models.A, models.b, models.c, models.zlo, models.zhi
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
        xg, yg = pixel_to_normalized(K, np.arange(W), np.arange(H))
        xg, yg = xg.astype(np.float32), yg.astype(np.float32)
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
        dm = model_depth(qpix, g, kind_g, Am, bm, cm, W, K)
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
N_PARAMS = np.array([2, 5, 7, 11])


def fallback_to_global(
    fr: Frame, models: ShapeModels, depth: NDArray[np.float32], *, untestable: bool, thin: bool
) -> int:
    """Per-object fallback to the global affine (the ``no_msc_cdr`` result), in place.

    An object keeps its own result (calibrated prior, model output, residual field) only when it
    explains the object's own sparse features better than the global affine does, after
    correcting for what it fitted to them: ``L1_obj * n / (n - p) < L1_glob`` with ``L1`` the
    summed absolute log-depth error at the object's features with a prior, ``n`` their number and
    ``p`` the object's fitted parameters (2 for its affine of eq. 6, plus those of its shape).
    ``RSS / (n - p)`` is the unbiased residual variance of a fit with ``p`` parameters; the
    global affine's two parameters are shared by all features of the frame. An object with
    ``n <= p`` (no feature at all included) cannot be tested: it keeps what CDR's anchor and
    smoothness gave it, unless ``untestable``, or more than ``fallback_failed_share`` of the
    tested objects failed (then it falls back too). With ``thin`` (the frame has fewer than
    ``fallback_min_features`` features with a prior) every object falls back: an in-sample test
    on a handful of features, one of them perhaps an outlier, validates nothing. Returns the
    number of objects that fell back.
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
    dof = n - N_PARAMS[np.clip(models.kind, 0, 3)]
    testable = dof > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        better = l_obj * n / np.where(testable, dof, 1.0) < l_glob
    fall = testable & ~better
    # many tested objects failing: the frame's calibration is unreliable (CDR couples objects by
    # eq. 9, so the untested neighbours of failed objects were pulled by them too)
    if untestable or fall.sum() > fr.p.fallback_failed_share * max(int(testable.sum()), 1):
        fall |= ~testable
    if thin:  # too few features in the frame to validate any object's departure from it
        fall[:] = True
    fall &= ~fr.sky
    if not fall.any():
        return 0
    pix = fr.per_pixel(fall) & fr.has_prior
    y = (np.float32(theta0[0]) * fr.prior[pix] + np.float32(theta0[1])).astype(np.float32)
    depth[pix] = to_depth_inplace(y, kind, fr.p)
    return int(fall.sum())


def nearest_seed(
    fr: Frame, seed_pix: NDArray[np.intp], flat_idx: NDArray[np.intp]
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


def fill_holes(
    fr: Frame,
    models: ShapeModels,
    holes: NDArray[np.bool_],
    depth: NDArray[np.float32],
    out_conf: NDArray[np.float32],
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
    p, H, W, gobj, kind_g = fr.p, fr.H, fr.W, fr.gobj, models.kind
    hole_idx = np.flatnonzero(holes)
    v, u = np.divmod(fr.fpix, W)
    good = consistent_seeds(
        np.stack([u, v], 1).astype(np.float64),
        fr.z,
        gate=p.fill_seed_gate,
        radius_px=p.fill_seed_radius * W,
    )
    dist, near = nearest_seed(fr, fr.fpix[good], hole_idx)
    same = np.isfinite(dist) & (gobj[near] == gobj[hole_idx])
    n_model = n_fill = 0
    hi = hole_idx[same & (kind_g[gobj[hole_idx]] > 0) & (dist <= p.hole_model_radius * W)]
    if len(hi):  # no prior, accepted shape, own features near: the model depth
        g = gobj[hi]
        d = model_depth(hi, g, kind_g, models.A, models.b, models.c, W, fr.K)
        # no prior to gate the model against: a tighter extrapolation range
        f = p.hole_model_extrapolation / p.model_extrapolation
        ok = np.isfinite(d) & (d >= models.zlo[g] / f) & (d <= models.zhi[g] * f)
        depth[hi[ok]] = d[ok]
        out_conf[hi[ok]] = 0.5 * models.conf[g[ok]]
        n_model = int(ok.sum())
    sel = same & (dist <= p.hole_fill_radius * W)
    sel[sel] = depth[hole_idx[sel]] == 0
    rest = hole_idx[sel]
    if len(rest) and p.fill_method == "nearest":  # the nearest consistent feature's depth
        seed_d = np.zeros(H * W, np.float32)
        seed_d[fr.fpix[good]] = fr.z[good]
        depth[rest] = np.clip(seed_d[near[sel]], p.d_min_m, f32_below(p.d_max_m))
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
        depth[rest[ok]] = np.clip(filled[ok], p.d_min_m, f32_below(p.d_max_m))
        out_conf[rest[ok]] = 0.1
        n_fill = int(ok.sum())
    return n_model, n_fill


def apply_residual_field(
    fr: Frame, depth: NDArray, used: NDArray | None, used_idx: NDArray, used_ratio: NDArray
) -> None:
    """Departure (docs/metrizer.md): a smooth multiplicative correction of the calibrated prior
    ``depth`` (flat, in place) from its residuals at the model-output pixels (``used``) and at the
    consistent features."""
    p: MetrizerParams = fr.p
    z, fpix = fr.z, fr.fpix
    fok = fr.f_consistent & ~fr.sky[fr.feat_g]
    if used is not None:
        fok &= ~used[fpix]
    idx = np.concatenate([used_idx, fpix[fok]])
    val = np.concatenate([used_ratio, np.log(z[fok] / depth[fpix[fok]])])
    wt = np.concatenate([np.full(len(used_idx), p.residual_model_weight), np.ones(int(fok.sum()))])
    if not len(idx):
        return
    field = smooth_field(
        (fr.H, fr.W),
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
    np.clip(depth, np.float32(p.d_min_m), f32_below(p.d_max_m), out=depth)


def _plane_pass(
    fr: Frame,
    depth: NDArray[np.float32],
    out_conf: NDArray[np.float32],
    confident: bool,
    support: NDArray[np.bool_] | None = None,
) -> int:
    """One :func:`~mogs_node.metrizer.fill.complete_planar_masks` pass over the merged objects
    (``depth`` / ``out_conf`` flat, changed in place): the confident-pixel pass
    (``confident_plane_*``) or the whole-mask pass (``mask_plane_*``). Returns the pixels it
    gave a depth. ``support`` (flat bool): the pixels the whole-mask pass may fit and reach
    from (:class:`~mogs_node.metrizer.fill.PlaneSelect`)."""
    p: MetrizerParams = fr.p
    H, W = fr.H, fr.W
    if confident:
        share, inl, min_depth, min_px = (
            p.confident_plane_min_share,
            p.confident_plane_inlier_rel,
            0.0,
            p.confident_plane_min_pixels,
        )
        gap = p.confident_plane_max_gap * W
        select = PlaneSelect(
            fr.conf.reshape(H, W),
            p.confident_plane_fit_conf,
            p.confident_plane_replace_below,
            gap,
            colour_gap_px=p.confident_plane_colour_gap * W,
            colour_share=p.confident_plane_colour_share,
            image_rgb=fr.image,
        )
    else:
        share, inl, min_depth, min_px = (
            p.mask_plane_min_share,
            p.mask_plane_inlier_rel,
            p.mask_plane_min_depth_m,
            30,
        )
        select = PlaneSelect(
            max_gap_px=p.mask_plane_max_gap * W,
            colour_gap_px=p.mask_plane_colour_gap * W,
            colour_share=p.confident_plane_colour_share,
            image_rgb=fr.image,
            support=None if support is None else support.reshape(H, W),
        )
    return complete_planar_masks(
        depth.reshape(H, W),
        out_conf.reshape(H, W),
        fr.gobj.reshape(H, W),
        fr.G,
        min_share=share,
        inlier_rel=inl,
        min_depth_m=min_depth,
        max_depth_m=p.sky_depth_frac * p.d_max_m,
        min_pixels=min_px,
        min_out_m=p.d_min_m,
        select=select,
    )


def _mask_plane_support(
    p: MetrizerParams,
    has_prior: NDArray[np.bool_],
    point_fills: NDArray[np.intp],
    point_fill_m: NDArray[np.float32],
    depth: NDArray[np.float32],
) -> NDArray[np.bool_] | None:
    """The pixels (flat bool, or None: all) the whole-mask pass fits, counts and reaches from
    (``MetrizerParams.mask_plane_support``; docs/metrizer.md "Planes from measured support
    only"). ``point_fills`` / ``point_fill_m``: fill_holes' pixels and the depth it gave them;
    one a plane pass has replaced since holds that plane's depth and is support again."""
    if p.mask_plane_support == "measured":
        return has_prior
    if p.mask_plane_support == "no_point_fills":
        support = np.ones(len(depth), bool)
        support[point_fills[depth[point_fills] == point_fill_m]] = False
        return support
    return None


def _road_passes(fr: Frame, depth: NDArray[np.float32], out_conf: NDArray[np.float32]) -> tuple:
    """The road plane's passes (ground.py, departure: docs/metrizer.md "The road plane"): road
    objects, then objects standing on the road (``depth`` / ``out_conf`` flat, in place).
    Returns the pixels each gave a depth."""
    p: MetrizerParams = fr.p
    H, W = fr.H, fr.W
    gp = GroundParams(
        agree_rel=p.road_agree_rel,
        max_depth_m=min(p.road_max_depth_m, p.d_max_m),
        contact_check_rel=p.ground_contact_check_rel,
    )
    h = p.road_camera_height_m
    snap = p.road_snap_rel > 0
    if not (p.road_objects or p.ground_contact or snap) or (
        depth.min(initial=1.0) > 0 and not snap
    ):
        return 0, 0  # nothing to fill (a fully covered frame costs nothing)
    z_road = road_plane_depth(pixel_grid_xy(fr.K, H, W)[2], fr.up_cam, h)[0].ravel()
    n_road = n_contact = 0
    if snap:  # departure: docs/metrizer.md "The road plane over a learned prior's road"
        n_road += snap_road_objects(depth, fr.gobj, fr.G, z_road, gp, p.road_snap_rel)
    if p.road_objects:
        n_road += fill_road_objects(depth, out_conf, fr.gobj, fr.G, z_road, gp)
    if p.ground_contact:
        u, v = np.meshgrid(np.arange(W), np.arange(H))
        x, y = pixel_to_normalized(fr.K, u.ravel(), v.ravel())
        n_contact = fill_ground_contact(
            depth, out_conf, fr.conf, fr.gobj, fr.G, (x, y), z_road, fr.up_cam, h, gp, (H, W)
        )
    return n_road, n_contact


def compose(
    fr: Frame, tm: StageTimer, models: ShapeModels, theta: F64, global_only: bool
) -> MetrizedDepth:
    """Full-resolution output from the stage results: the per-object affine ``theta`` ``[G, 2]``
    of eq. (6) (CDR, or the global one) and the accepted shapes ``models`` (Algorithm 1):
    calibrated prior per object, model depth, sky, holes, confidence."""
    p: MetrizerParams = fr.p
    H, W, G = fr.H, fr.W, fr.G
    gobj, prior, conf, has_prior = fr.gobj, fr.prior, fr.conf, fr.has_prior
    kind, theta0, sky = fr.prior_kind, fr.theta0, fr.sky
    kind_g, conf_g, n_feat_g, stats = models.kind, models.conf, fr.n_feat_g, fr.stats

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
    to_depth_inplace(depth, kind, p)
    out_conf = fr.per_pixel(q_g.astype(np.float32))
    out_conf *= conf
    n_model_px = n_model_fill = n_edge_fill = 0
    point_fills = np.zeros(0, np.intp)  # fill_holes' pixels (flat)
    sky_pix = fr.per_pixel(sky) if sky.any() else None
    special = None if sky_pix is None else sky_pix.copy()
    if not fr.all_prior:
        special = ~has_prior if special is None else special | ~has_prior

    tm.lap("compose")
    used, used_idx, used_ratio = None, np.zeros(0, np.intp), np.zeros(0)
    if p.model_output and (kind_g > 0).any() and not global_only:
        used, used_idx, used_ratio = model_output(fr, models, depth, special)
        n_model_px = int(np.count_nonzero(used))
    tm.lap("model_output")

    if p.residual_field and not global_only:
        apply_residual_field(fr, depth, used, used_idx, used_ratio)
    n_fallback = 0
    if p.fallback_global and not global_only:
        thin = stats["n_features_global"] < p.fallback_min_features
        n_fallback = fallback_to_global(
            fr, models, depth, untestable=p.fallback_untestable, thin=thin
        )
    stats["n_fallback_objects"] = n_fallback
    tm.lap("residual")

    if special is not None:
        if sky_pix is not None:  # sky objects: far / prior-less pixels -> d_max, others global
            y0 = (theta0[0] * prior[sky_pix] + theta0[1]).astype(np.float64)
            far, _ = far_and_norm(y0, kind, p)
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
            n_model_fill, n_edge_fill = fill_holes(fr, models, holes, depth, out_conf)
            point_fills = np.flatnonzero(holes & (depth > 0))
    point_fill_m = depth[point_fills]  # a copy: the plane passes may replace them
    n_conf_plane = n_plane_fill = n_road = n_contact = 0
    if not global_only:  # departures: docs/metrizer.md, "Whole objects from the confident
        # pixels" (weak pixels and holes), then "Whole masks" (holes)
        if p.confident_planes:
            n_conf_plane = _plane_pass(fr, depth, out_conf, confident=True)
        if fr.up_cam is not None:
            n_road, n_contact = _road_passes(fr, depth, out_conf)
        if p.mask_plane_fill and special is not None:
            support = _mask_plane_support(p, has_prior, point_fills, point_fill_m, depth)
            n_plane_fill = _plane_pass(fr, depth, out_conf, confident=False, support=support)
    n_snap = 0
    if p.edge_snap and not global_only:  # departure: docs/metrizer.md "Depth edges snapped"
        objects = gobj.reshape(H, W)
        band = prior_edge_band(
            prior.reshape(H, W), conf.reshape(H, W), p.edge_snap_rel, p.edge_snap_radius
        )
        band &= near_object_boundary(objects, p.edge_snap_boundary_px)
        n_snap = snap_edges(depth.reshape(H, W), out_conf.reshape(H, W), objects, band)
    stats.update(
        n_px_edge_snap=n_snap,
        n_model_output_px=n_model_px,
        n_hole_px_model=n_model_fill,
        n_hole_px_fill=n_edge_fill,
        n_hole_px_plane=n_plane_fill,
        n_px_confident_plane=n_conf_plane,
        n_px_road=n_road,
        n_px_ground_contact=n_contact,
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
