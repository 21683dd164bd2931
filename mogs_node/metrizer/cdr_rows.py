"""The residual rows of CDR (paper III-C) that the pipeline builds from MSC's results: eq. (7)
geometric rows (model depth of accepted shapes, else the object's sparse features) and the
eq. (8) anchor target (the locally aligned prior, departure 13)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mogs_node.metrizer.alignment import space_from_depth
from mogs_node.metrizer.fill import smooth_field
from mogs_node.metrizer.frame import Frame

__all__ = ["geo_rows", "local_anchor_target"]

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


def geo_rows(
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
