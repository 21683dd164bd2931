"""Stage 3 of the metrizer: one robust affine alignment of the prior to every feature (the
anchor of eq. (8), the ``no_msc_cdr`` result, the sky test and the feature gates)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_kind import DepthKind
from mogs_node.metrizer.alignment import (
    depth_from_space,
    fit_global_affine,
    metric_affine_earned,
    space_from_depth,
)
from mogs_node.metrizer.frame import far_and_norm
from mogs_node.metrizer.params import MetrizerParams

__all__ = ["GlobalFit", "align_global"]

F64 = NDArray[np.float64]


@dataclass
class GlobalFit:
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


def align_global(
    p: MetrizerParams,
    prior: NDArray,
    conf: NDArray,
    z: F64,
    w: F64,
    fpix: NDArray[np.intp],
    prior_kind: str,
    zero_at: tuple[float, float] | None = None,
) -> GlobalFit:
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
    return GlobalFit(
        theta0, int(n_global), fx, fc, ft, fd_glob, f_consistent, conf, bool(unanchored)
    )
