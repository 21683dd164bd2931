"""The residual rows of CDR (paper III-C) that the pipeline builds from MSC's results: eq. (7)
geometric rows (model depth of accepted shapes, else the object's sparse features), the
eq. (8) anchor target (the locally aligned prior, departure 13) and, stage 7, the border rows of
eqs. (9)-(10) with the solve (:func:`refine_objects`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mogs_node.metrizer.alignment import space_from_depth
from mogs_node.metrizer.fill import smooth_field
from mogs_node.metrizer.frame import Frame, ShapeModels, far_and_norm
from mogs_node.metrizer.refinement import CdrProblem, solve_cdr

__all__ = ["FeatureRows", "SampleRows", "geo_rows", "local_anchor_target", "refine_objects"]

F64 = NDArray[np.float64]


def local_anchor_target(fr: Frame, sidx, mok, mdepth, d_glob, fd_glob, snorm) -> F64:
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


@dataclass(frozen=True)
class SampleRows:
    """The CDR sample pixels outside sky objects ``[P]`` and MSC's model depth there."""

    idx: NDArray[np.intp]  # flat pixel
    obj: NDArray[np.intp]  # object (after merging and absorption)
    x: F64  # prior value
    conf: F64  # prior confidence
    model_depth_m: F64  # ray-shape intersection of the object's accepted shape (inf: none)
    model_ok: NDArray[np.bool_]  # the model depth passes the eq.-(7) gate


@dataclass(frozen=True)
class FeatureRows:
    """The sparse features ``[N]`` in the prior's space (eq. 7 targets)."""

    x: F64  # prior value at the feature
    conf: F64  # prior confidence there, 0 for a feature inconsistent with the global alignment
    t: F64  # the feature's depth in the prior's space (inverse depth or depth)
    w: F64  # omega


def geo_rows(
    fr: Frame,
    samples: SampleRows,
    features: FeatureRows,
    kind_g: NDArray[np.int8],
    conf_g: F64,
) -> tuple[NDArray[np.intp], F64, F64, F64]:
    """Rows of eq. (7) ``(object, prior value, target, weight)``: model pixels of accepted shapes
    (``kind_g > 0``), else the object's sparse features (objects, sky and parameters from
    ``fr``).

    Model pixels weigh ``C_k`` (eq. 5, ``conf_g``) times the prior confidence, features
    ``omega`` times the prior confidence times ``min(1, n_k / n_min)``; each object's weights
    are normalised to a mean.
    """
    G, feat_g, sky = fr.G, fr.feat_g, fr.sky
    mok = samples.model_ok
    mo, mx, mc = samples.obj[mok], samples.x[mok], samples.conf[mok]
    mt = space_from_depth(samples.model_depth_m[mok], fr.prior_kind)
    mw = mc / np.maximum(np.bincount(mo, mc, minlength=G), 1e-12)[mo] * conf_g[mo]
    fc = features.conf
    use = (kind_g[feat_g] == 0) & (fc > 0) & ~sky[feat_g]
    fo, fxx, ftt = feat_g[use], features.x[use], features.t[use]
    fw = (features.w * fc)[use]
    support = np.minimum(1.0, fr.n_feat_g / fr.p.n_min)
    fw = fw / np.maximum(np.bincount(fo, fw, minlength=G), 1e-12)[fo] * support[fo]
    return (
        np.concatenate([mo, fo]).astype(np.intp),
        np.concatenate([mx, fxx]),
        np.concatenate([mt, ftt]),
        np.concatenate([mw, fw]),
    )


def refine_objects(
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
