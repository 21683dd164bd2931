"""A shape must also explain its object's prior pixels (departure 22, docs/metrizer.md "MSC on
real images, session 15").

Algorithm 1 accepts a shape on the features it was fitted to (at least ``tau`` of them inliers).
Those features are corners: on real images they sit on a truck's frame rails, on a wheel next to
the road, on lane markings, and a shape through them can be a good fit to them and the wrong
surface for the rest of the object. The object's prior pixels were not used by the fit: they are
held-out evidence of the object's surface. Calibrated locally by the object's own features (the
median log ratio of feature depth to the globally aligned prior at them, one scale parameter that
the features, not the shape, decide), at least ``tau`` of the object's prior samples, weighted by
prior confidence, must agree with the shape within ``model_output_gate``: the same acceptance
rule (``tau``) as Algorithm 1 and the same gate as the model output that the shape would then
replace them with (departure 7). A shape that fails is dropped; its object is calibrated from its
features like an object without a shape.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_kind import DepthKind
from mogs_node.group_stats import group_medians
from mogs_node.metrizer.alignment import depth_from_space
from mogs_node.metrizer.frame import Frame, ShapeModels, model_depth

__all__ = ["drop_unsupported_shapes", "shapes_explain_prior"]

F64 = NDArray[np.float64]


def shapes_explain_prior(
    models: ShapeModels,
    samples: tuple[NDArray[np.intp], NDArray[np.intp], F64, F64],
    features: tuple[NDArray[np.intp], F64, F64],
    W: int,
    K: F64,
    tau: float,
    gate: float,
    min_samples: int = 5,
) -> NDArray[np.bool_]:
    """Which accepted shapes fail the held-out test of the module docstring: ``[G]`` bool.

    ``samples`` = ``(pixel [S], group [S], globally aligned prior depth [S], prior confidence
    [S])`` at the CDR sample pixels with a prior; ``features`` = ``(group [N], depth [N],
    globally aligned prior depth at them [N])`` of the features consistent with the prior.
    A shape is tested where the model depth hits within its valid range ``[zlo, zhi]`` at at
    least ``min_samples`` samples and its object has a feature to calibrate with; otherwise it is
    kept (nothing to test it on).
    """
    G = len(models.kind)
    fail = np.zeros(G, bool)
    has = models.kind > 0
    if not has.any():
        return fail
    sidx, sg, sd, sc = samples
    fg, fz, fd = features
    with np.errstate(divide="ignore", invalid="ignore"):
        lf = np.log(fz / fd)
    okf = np.isfinite(lf) & has[fg]
    _, offset = group_medians(fg[okf], lf[okf], G)  # the features' local scale of the prior
    pick = np.flatnonzero(has[sg] & np.isfinite(offset[sg]) & (sc > 0))
    if not len(pick):
        return fail
    g = sg[pick]
    dm = model_depth(sidx[pick], g, models.kind, models.A, models.b, models.c, W, K)
    with np.errstate(divide="ignore", invalid="ignore"):
        hit = np.isfinite(dm) & (dm >= models.zlo[g]) & (dm <= models.zhi[g])
        r = np.abs(np.log(dm / sd[pick]) - offset[g])
    agree = hit & (r <= np.log1p(gate))
    w = sc[pick]
    n_hit = np.bincount(g[hit], minlength=G)
    w_hit = np.bincount(g[hit], w[hit], minlength=G)
    w_agree = np.bincount(g[agree], w[agree], minlength=G)
    tested = has & (n_hit >= min_samples)
    fail[tested] = w_agree[tested] < tau * w_hit[tested]
    return fail


def drop_unsupported_shapes(
    fr: Frame,
    models: ShapeModels,
    grid: tuple[NDArray[np.intp], NDArray[np.intp], F64],
    features: tuple[NDArray[np.intp], F64, F64],
) -> int:
    """Stage 5 of ``fr`` (after Algorithm 1, before absorption): drop, in place, the accepted
    shapes that their object's prior samples do not support (:func:`shapes_explain_prior`).
    Returns the number dropped.

    ``grid`` = the CDR sample pixels with a prior, their group and the globally aligned prior
    there in its normalised space; ``features`` as in :func:`shapes_explain_prior`. Only for a
    metric prior: a relative prior's depth at a pixel has no metric meaning before the object's
    own affine (eq. 6), which CDR takes from the shape itself, so it cannot hold the shape out.
    """
    p = fr.p
    if not p.shape_prior_check or fr.prior_kind != DepthKind.METRIC or not (models.kind > 0).any():
        return 0
    pix, grp, norm = grid
    keep = ~fr.sky[grp]
    d_ref = depth_from_space(norm[keep], fr.prior_kind, p.d_min_m, p.d_max_m)
    conf = fr.conf[pix[keep]].astype(np.float64)
    fail = shapes_explain_prior(
        models,
        (pix[keep], grp[keep], d_ref, conf),
        features,
        fr.W,
        fr.K,
        tau=p.consensus.tau,
        gate=p.model_output_gate,
    )
    models.kind[fail] = 0
    models.conf[fail] = 0.0
    return int(fail.sum())
