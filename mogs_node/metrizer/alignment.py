"""Prior spaces and the global affine alignment of the prior (the ``no_msc_cdr`` baseline).

A prior is fitted in its own space (paper III-C, eq. 6): a relative *inverse* depth prior is
calibrated as ``1 / D = a x + b``, a relative depth (or metric) prior as ``D = a x + b``. Residuals
are relative, ``e = (a x + b) / t - 1`` with ``t`` the target in the same space, which to first
order is the relative depth error in either space.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_kind import DEPTH_KINDS, DepthKind

__all__ = [
    "PRIOR_KINDS",
    "depth_from_space",
    "fit_global_affine",
    "metric_affine_earned",
    "space_from_depth",
]

F64 = NDArray[np.float64]
PRIOR_KINDS = DEPTH_KINDS  # every kind can be a prior (mogs_node.depth_kind.DepthKind)


def space_from_depth(depth_m: F64, kind: str) -> F64:
    """Depth ``[...]`` (> 0) into the prior's fitting space (inverse depth or depth)."""
    return 1.0 / depth_m if kind == DepthKind.RELATIVE_INVERSE_DEPTH else depth_m


def depth_from_space(y: F64, kind: str, d_min_m: float, d_max_m: float) -> F64:
    """Calibrated values ``y`` back to depth, clipped to ``[d_min_m, d_max_m]``.

    A non-positive inverse depth is "beyond infinity" and maps to ``d_max_m``; a non-positive depth
    maps to ``d_min_m``. Non-finite values map to ``d_max_m``. The result is always finite.
    """
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if kind == DepthKind.RELATIVE_INVERSE_DEPTH:
            d = np.where(y > 0, 1.0 / np.where(y > 0, y, 1.0), d_max_m)
        else:
            d = y
    d = np.where(np.isfinite(d), d, d_max_m)
    return np.clip(d, d_min_m, d_max_m)


def fit_global_affine(
    x: F64,
    t: F64,
    w: F64,
    kind: str,
    huber: float = 0.05,
    iters: int = 10,
    shift_prior: float = 0.0,
    zero_at: tuple[float, float] | None = None,
) -> tuple[F64, int]:
    """Robust affine ``(a, b)`` with ``a x + b ~ t``, relative residuals.

    ``iters`` Huber IRLS iterations, then ``iters`` more in which residuals beyond four Huber
    widths get no weight (Huber alone keeps a bias from gross outliers).

    ``shift_prior`` > 0 adds a pseudo-observation ``b / median(t) = 0`` with that share of the
    total weight: a weak pull to the pure scale that decides only where the features' spread
    leaves the shift undetermined (a few points at one depth: the shift then sets where the
    far field ends; docs/metrizer.md, "Global affine shift prior").

    ``zero_at = (x0, share)`` adds a pseudo-observation ``(a x0 + b) / median(t) = 0`` with that
    share of the total weight: the prior value ``x0`` of the sky is at infinity (inverse depth 0;
    docs/metrizer.md "The sky pins the shift").

    ``x`` ``[N]`` prior values at the features, ``t`` ``[N]`` targets (> 0), ``w`` ``[N]`` weights.
    With fewer than two usable rows, or a degenerate / sign-flipping solution, falls back to a pure
    scale (median ratio); with none at all to the identity. Returns ``(theta [2], n_used)``.
    """
    ok = np.isfinite(x) & np.isfinite(t) & np.isfinite(w) & (t > 0) & (w > 0)
    x, t, w = x[ok], t[ok], w[ok]
    n = len(x)
    identity = np.array([1.0, 0.0])
    pos = x > 0
    scale = float(np.median(t[pos] / x[pos])) if pos.any() else np.nan
    scale_only = np.array([scale, 0.0]) if np.isfinite(scale) and scale > 0 else identity
    if n < 2 or np.ptp(x) <= 1e-9 * max(np.max(np.abs(x)), 1e-12):
        return scale_only, n
    theta = scale_only.copy()
    j1, j2 = x / t, 1.0 / t
    t_med = float(np.median(t))
    for it in range(2 * iters):
        e = j1 * theta[0] + j2 * theta[1] - 1.0
        ae = np.abs(e)
        ww = w * np.where(ae <= huber, 1.0, huber / np.maximum(ae, 1e-300))
        if it >= iters:  # second half: redescending, gross outliers (> 4 widths) drop out
            ww = np.where(ae <= 4.0 * huber, ww, 0.0)
            if np.count_nonzero(ww) < 2:
                break
        H = np.array([[ww @ (j1 * j1), ww @ (j1 * j2)], [ww @ (j1 * j2), ww @ (j2 * j2)]])
        g = np.array([ww @ j1, ww @ j2])
        H[1, 1] += 1e-9 * (H[0, 0] + H[1, 1])
        # a weak pull of the shift to 0 (the pure scale), relative to the median target: it
        # decides only where the features' spread leaves the shift undetermined
        H[1, 1] += shift_prior * ww.sum() / t_med**2
        if zero_at is not None:
            x0, share = zero_at
            H += share * ww.sum() / t_med**2 * np.array([[x0 * x0, x0], [x0, 1.0]])
        try:
            new = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(new)):
            break
        theta = new
    if not np.all(np.isfinite(theta)) or theta[0] <= 0:
        return scale_only, n
    return theta, n


def metric_affine_earned(x: F64, t: F64, w: F64, theta: F64) -> bool:
    """Whether the global affine ``theta`` of a **metric** prior explains the features better
    than the prior as it is (the identity), after correcting for its two fitted parameters
    (departure 23, docs/metrizer.md "MSC on real images, session 15").

    A metric prior (the weight-free flow prior: depth from the system's own metric poses) needs
    no calibration; the identity is its zero-parameter baseline, as the global affine is every
    object's (``compose.fallback_to_global``). The affine is kept only when
    ``L1_aff * n / (n - 2) < L1_id``, ``L1`` the weighted absolute log-depth error at the ``n``
    features with a prior (``x`` prior depth, ``t`` feature depth, ``w`` weight, all ``[N]``).
    """
    ok = np.isfinite(x) & np.isfinite(t) & np.isfinite(w) & (x > 0) & (t > 0) & (w > 0)
    n = int(ok.sum())
    if n <= 2:
        return False
    x, t, w = x[ok], t[ok], w[ok]
    with np.errstate(all="ignore"):
        e_aff = np.abs(np.log((theta[0] * x + theta[1]) / t))
        e_id = np.abs(np.log(x / t))
        l_aff, l_id = w @ e_aff, w @ e_id
    if not (np.isfinite(l_aff) and np.isfinite(l_id)):
        return False
    return bool(l_aff * n / (n - 2) < l_id)
