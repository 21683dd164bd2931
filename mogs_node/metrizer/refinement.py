"""Cross-object depth refinement (CDR), paper III-C: per-object affine calibration by IRLS.

Every object ``k`` gets an affine map of the prior ``x`` (eq. 6), ``y = a_k x + b_k``, in the
prior's own space (``y`` = inverse depth for a relative-inverse-depth prior, depth otherwise). The
parameters minimise eq. (11), ``E = lambda_geo E_geo + lambda_nfc E_nfc + lambda_sm E_sm``:

- eq. (7) ``E_geo``: confidence-weighted Huber residuals between the calibrated prior and the
  object's geometric target (the model depth of III-B where a shape was accepted, else the object's
  sparse metric features), ``e = (a x + b) / t - 1`` (relative: near and far objects weigh alike);
- eq. (8) ``E_nfc``: Huber residuals anchoring the calibrated prior to a target ``g`` given per
  row by the caller (the pipeline uses the globally aligned prior, one robust affine fit of the
  whole prior to all sparse features, times a smooth field of the geometric evidence: a locally
  aligned prior), ``e = (a x + b) / g - 1``; it regularises objects with weak geometry and, its
  gradient being bounded (``lambda_nfc * huber_nfc``), moves objects with strong geometric
  evidence by at most about ``lambda_nfc huber_nfc / lambda_geo`` (3.5% with the defaults);
- eqs. (9)-(10) ``E_sm``: edge-aware smoothness across object borders, over 4-neighbour pixel pairs
  ``(p in k, q in l)``: ``w_pq ((a_k x_p + b_k) - (a_l x_q + b_l))^2 / g_pq^2`` with
  ``w_pq = exp(-|I_p - I_q|^2 / (2 sigma_c^2))`` (eq. 10).

Each term is a per-object mean (``E_geo`` and ``E_nfc`` weights sum to one per object; a border
pair is divided by the mean border-pair count of its two objects), so 30 features weigh as much as
30 000 model pixels; the caller builds those weights (see :mod:`mogs_node.metrizer.pipeline`). A
tiny ridge towards the global affine keeps objects with a constant prior well posed.

IRLS: the Huber weights are re-evaluated from the current estimate, the 2x2 per-object blocks of the
normal equations are accumulated with ``bincount`` (eq.-(7) and eq.-(8) rows together, their fixed
Jacobians computed once), the (fixed, quadratic) smoothness couplings are pre-aggregated once, and
the ``2M x 2M`` system is solved exactly each iteration: densely (LAPACK) up to ``2M = 256``, where
that is cheaper than assembling and factorising a sparse matrix, else with SuperLU.
:func:`solve_cdr_reference` is the slow dense reference used by the tests.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

__all__ = ["CdrProblem", "CdrParams", "huber_weight", "solve_cdr", "solve_cdr_reference"]

log = logging.getLogger(__name__)
F64 = NDArray[np.float64]
IDX = NDArray[np.intp]
_DENSE_MAX = 256  # 2n at most: solve the normal equations densely (LAPACK), else SuperLU


@dataclass(frozen=True)
class CdrParams:
    """Parameters of the cross-object refinement (eqs. 6-11)."""

    lambda_geo: float = 1.0  # eq. (11) weight of the geometric term (eq. 7)
    lambda_nfc: float = 0.7  # eq. (11) weight of the prior-anchoring term (eq. 8)
    lambda_sm: float = 0.1  # eq. (11) weight of the edge-aware smoothness (eq. 9)
    huber_geo: float = 0.05  # Huber width of eq. (7), relative depth error
    huber_nfc: float = 0.05  # Huber width of eq. (8), relative depth error (as eq. 7)
    sigma_color: float = 12.0  # eq. (10): colour difference scale (0-255 units)
    irls_iters: int = 3  # IRLS iterations (at most)
    ridge: float = 1e-4  # relative Tikhonov weight towards the global affine (well-posedness)
    tol: float = 1e-3  # IRLS stops when no parameter moves by more than this (relative)
    anchor_free_start: bool = True  # start IRLS from the solve without eq. (8) (faster moves)


@dataclass
class CdrProblem:
    """Residual rows of eqs. (7)-(9); weights already include the per-object normalisation.

    ``n`` objects; ``theta0`` ``[n, 2]`` the global affine ``(a0, b0)`` (start and ridge target).
    Data rows (``geo_*`` ``[G]``, ``nfc_*`` ``[P]``): object id, prior value ``x``, target ``t>0``,
    weight ``>= 0``. Smoothness rows ``[B]``: objects ``k, l``, prior values ``xk, xl``, normaliser
    ``g > 0`` and edge weight.
    """

    n: int
    theta0: F64
    geo_obj: IDX
    geo_x: F64
    geo_t: F64
    geo_w: F64
    nfc_obj: IDX
    nfc_x: F64
    nfc_t: F64
    nfc_w: F64
    sm_k: IDX
    sm_l: IDX
    sm_xk: F64
    sm_xl: F64
    sm_g: F64
    sm_w: F64


def huber_weight(e: F64, delta: float | F64) -> F64:
    """IRLS weight of the Huber loss: 1 inside ``|e| <= delta``, ``delta / |e|`` outside."""
    ae = np.abs(e)
    return np.where(ae <= delta, 1.0, delta / np.maximum(ae, 1e-300))


def _ridge(prob: CdrProblem, ridge: float) -> tuple[F64, F64]:
    """Ridge weights ``[n]`` for a and b, scaled like the anchor Jacobian of each object."""
    n = prob.n
    cnt = np.bincount(prob.nfc_obj, minlength=n).astype(np.float64)
    sa = np.bincount(prob.nfc_obj, (prob.nfc_x / prob.nfc_t) ** 2, minlength=n)
    sb = np.bincount(prob.nfc_obj, (1.0 / prob.nfc_t) ** 2, minlength=n)
    safe = np.maximum(cnt, 1.0)
    ra = np.where(cnt > 0, sa / safe, 1.0) * ridge
    rb = np.where(cnt > 0, sb / safe, 1.0) * ridge
    ra = np.where(ra > 0, ra, ridge)
    rb = np.where(rb > 0, rb, ridge)
    return ra, rb


def _smooth_entries(prob: CdrProblem, lam: float) -> tuple[NDArray[np.intp], NDArray[np.intp], F64]:
    """Normal-equation contribution of eq. (9) as COO ``(rows, cols, vals)`` of the ``2n x 2n``
    matrix (duplicates to be summed), aggregated per object pair with ``bincount``."""
    n = prob.n
    if len(prob.sm_k) == 0 or n == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0)
    w = lam * prob.sm_w / prob.sm_g**2
    k, l, xk, xl = prob.sm_k, prob.sm_l, prob.sm_xk, prob.sm_xl
    key = k.astype(np.int64) * n + l
    if n * n <= 4_000_000:

        def agg(vals):
            return np.bincount(key, vals, minlength=n * n)

        used = np.flatnonzero(np.bincount(key, minlength=n * n))
    else:
        used, inv = np.unique(key, return_inverse=True)

        def agg(vals):
            return np.bincount(inv, vals, minlength=len(used))

    s = {
        name: agg(v)
        for name, v in (
            ("kk", w * xk * xk),
            ("k", w * xk),
            ("1", w),
            ("ll", w * xl * xl),
            ("l", w * xl),
            ("kl", w * xk * xl),
        )
    }
    if n * n <= 4_000_000:
        s = {name: v[used] for name, v in s.items()}
    pk, pl = used // n, used % n
    # residual e = u . theta_k + v . theta_l with u = (xk, 1), v = -(xl, 1)
    blocks = (
        (pk, pk, ((s["kk"], s["k"]), (s["k"], s["1"]))),
        (pl, pl, ((s["ll"], s["l"]), (s["l"], s["1"]))),
        (pk, pl, ((-s["kl"], -s["k"]), (-s["l"], -s["1"]))),
        (pl, pk, ((-s["kl"], -s["l"]), (-s["k"], -s["1"]))),
    )
    rows, cols, vals = [], [], []
    for oi, oj, m in blocks:
        for i in range(2):
            for j in range(2):
                rows.append(2 * oi + i)
                cols.append(2 * oj + j)
                vals.append(m[i][j])
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)


def solve_cdr(prob: CdrProblem, params: CdrParams = CdrParams()) -> F64:
    """Minimise eq. (11) by IRLS; returns ``theta`` ``[n, 2]`` = ``(a_k, b_k)`` per object."""
    n = prob.n
    theta = prob.theta0.astype(np.float64).copy()
    if n == 0:
        return theta
    s_rows, s_cols, s_vals = _smooth_entries(prob, params.lambda_sm)
    m = 2 * n
    dense = m <= _DENSE_MAX
    if dense:  # small systems: LAPACK on the dense matrix beats building + factorising CSC
        S = np.bincount(s_rows * m + s_cols, s_vals, minlength=m * m).reshape(m, m)
        S = S.astype(np.float64, copy=False)  # bincount of nothing is int64
    else:
        S = sp.csr_matrix((s_vals, (s_rows, s_cols)), shape=(m, m))
    ra, rb = _ridge(prob, params.ridge)
    k = np.arange(n)
    rows = np.concatenate([2 * k, 2 * k, 2 * k + 1, 2 * k + 1])
    cols = np.concatenate([2 * k, 2 * k + 1, 2 * k, 2 * k + 1])
    # eq. (7) and eq. (8) rows together; their Jacobians (x / t, 1 / t) and products are fixed
    obj = np.concatenate([prob.geo_obj, prob.nfc_obj]).astype(np.intp, copy=False)
    j1 = np.concatenate([prob.geo_x / prob.geo_t, prob.nfc_x / prob.nfc_t])
    j2 = np.concatenate([1.0 / prob.geo_t, 1.0 / prob.nfc_t])
    j11, j12, j22 = j1 * j1, j1 * j2, j2 * j2
    n_geo = len(prob.geo_obj)
    delta = np.concatenate(
        [np.full(n_geo, params.huber_geo), np.full(len(prob.nfc_obj), params.huber_nfc)]
    )
    w_geo = params.lambda_geo * prob.geo_w
    n_it = max(1, params.irls_iters) + int(params.anchor_free_start)
    for it in range(n_it):
        anchor = 0.0 if (params.anchor_free_start and it == 0) else params.lambda_nfc
        lw = np.concatenate([w_geo, anchor * prob.nfc_w])
        e = j1 * theta[obj, 0] + j2 * theta[obj, 1] - 1.0
        ww = lw * huber_weight(e, delta)
        h11 = np.bincount(obj, ww * j11, minlength=n) + ra
        h12 = np.bincount(obj, ww * j12, minlength=n)
        h22 = np.bincount(obj, ww * j22, minlength=n) + rb
        g1 = np.bincount(obj, ww * j1, minlength=n) + ra * prob.theta0[:, 0]
        g2 = np.bincount(obj, ww * j2, minlength=n) + rb * prob.theta0[:, 1]
        dvals = np.concatenate([h11, h12, h12, h22])
        rhs = np.stack([g1, g2], 1).ravel()
        if dense:
            Mx = S.copy()
            Mx[rows, cols] += dvals  # (rows, cols) pairs are distinct
            try:
                sol = np.linalg.solve(Mx, rhs)
            except np.linalg.LinAlgError:
                sol = np.full(m, np.nan)
        else:
            D = sp.csr_matrix((dvals, (rows, cols)), shape=(m, m))
            sol = spla.spsolve((D + S).tocsc(), rhs)
        if not np.all(np.isfinite(sol)):
            log.warning("CDR: singular system, keeping the previous estimate")
            break
        theta, done = _irls_update(theta, sol, params.tol, it)
        if done:
            break
    return theta


def _irls_update(theta: F64, sol: F64, tol: float, it: int) -> tuple[F64, bool]:
    """The new ``[n, 2]`` estimate from a solve and whether the iteration has converged (the
    largest relative change of a parameter below ``tol``, from the second iteration on)."""
    new = sol.reshape(theta.shape)
    step = np.max(np.abs(new - theta) / (np.abs(theta) + 1e-12))
    return new, bool(step < tol and it > 0)


def solve_cdr_reference(prob: CdrProblem, params: CdrParams = CdrParams()) -> F64:
    """Slow dense reference of :func:`solve_cdr` (explicit rows, ``lstsq``); tests only."""
    n = prob.n
    theta = prob.theta0.astype(np.float64).copy()
    if n == 0:
        return theta
    ra, rb = _ridge(prob, params.ridge)
    n_it = max(1, params.irls_iters) + int(params.anchor_free_start)
    for it in range(n_it):
        anchor = 0.0 if (params.anchor_free_start and it == 0) else params.lambda_nfc
        J, r, w = [], [], []
        for obj, xs, ts, ws, delta, lam in (
            (prob.geo_obj, prob.geo_x, prob.geo_t, prob.geo_w, params.huber_geo, params.lambda_geo),
            (prob.nfc_obj, prob.nfc_x, prob.nfc_t, prob.nfc_w, params.huber_nfc, anchor),
        ):
            for o, x, t, wt in zip(obj, xs, ts, ws, strict=False):
                row = np.zeros(2 * n)
                row[2 * o], row[2 * o + 1] = x / t, 1.0 / t
                e = row @ theta.ravel() - 1.0
                J.append(row)
                r.append(1.0)
                w.append(lam * wt * (1.0 if abs(e) <= delta else delta / abs(e)))
        for kk, ll, xk, xl, g, wt in zip(
            prob.sm_k, prob.sm_l, prob.sm_xk, prob.sm_xl, prob.sm_g, prob.sm_w, strict=False
        ):
            row = np.zeros(2 * n)
            row[2 * kk] += xk / g
            row[2 * kk + 1] += 1.0 / g
            row[2 * ll] -= xl / g
            row[2 * ll + 1] -= 1.0 / g
            J.append(row)
            r.append(0.0)
            w.append(params.lambda_sm * wt)
        for o in range(n):
            for i, (rw, tgt) in enumerate(((ra[o], prob.theta0[o, 0]), (rb[o], prob.theta0[o, 1]))):
                row = np.zeros(2 * n)
                row[2 * o + i] = 1.0
                J.append(row)
                r.append(tgt)
                w.append(rw)
        sw = np.sqrt(np.asarray(w))
        sol = np.linalg.lstsq(np.asarray(J) * sw[:, None], np.asarray(r) * sw, rcond=None)[0]
        theta, done = _irls_update(theta, sol, params.tol, it)
        if done:
            break
    return theta
