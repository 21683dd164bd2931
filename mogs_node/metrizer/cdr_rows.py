"""The residual rows of CDR (paper III-C) that the pipeline builds from MSC's results: eq. (7)
geometric rows (model depth of accepted shapes, else the object's sparse features) and the
eq. (8) anchor target (the locally aligned prior, departure 13)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mogs_node.metrizer.alignment import space_from_depth
from mogs_node.metrizer.fill import smooth_field
from mogs_node.metrizer.frame import Frame

__all__ = ["FeatureRows", "SampleRows", "geo_rows", "local_anchor_target"]

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
