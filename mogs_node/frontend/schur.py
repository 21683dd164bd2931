"""Schur complement of window variables into linear priors (the estimator's marginalisation).

Eliminating a set of variables from the linearised factors that touch them leaves a Gaussian
prior on their neighbours (VINS-Mono's marginalisation, done with GTSAM's partial elimination);
it stays in the nonlinear graph as ``LinearContainerFactor``s linearised at ``values``.
"""

from __future__ import annotations

from collections.abc import Iterable

import gtsam
import numpy as np

__all__ = ["regularize_points", "schur_complement"]


def regularize_points(lin: gtsam.GaussianFactorGraph, point_keys: Iterable[int]) -> None:
    """Add a weak (sigma 100 m) zero prior on each 3-D point, so eliminating a point seen by one
    frame only stays determinate."""
    for key in point_keys:
        lin.add(
            gtsam.JacobianFactor(
                key, np.eye(3) * 1e-2, np.zeros(3), gtsam.noiseModel.Unit.Create(3)
            )
        )


def schur_complement(
    lin: gtsam.GaussianFactorGraph, elim_keys: Iterable[int], values: gtsam.Values
) -> list[gtsam.LinearContainerFactor]:
    """Eliminate ``elim_keys`` (in the given order) from ``lin``; the factors left on the other
    variables, as nonlinear containers at ``values``. Raises ``RuntimeError`` when the elimination
    is indeterminate (GTSAM's own error)."""
    order = gtsam.Ordering()
    for key in elim_keys:
        order.push_back(key)
    _, remaining = lin.eliminatePartialMultifrontal(order)
    return [
        gtsam.LinearContainerFactor(remaining.at(i), values)
        for i in range(remaining.size())
        if remaining.at(i) is not None
    ]
