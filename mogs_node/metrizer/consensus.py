"""Shape consensus per object: Algorithm 1 of the paper (III-B).

For one object with metric feature points ``F_k``, fit a plane, a cylinder and an ellipsoid by
minimal-sample RANSAC (hypotheses generated and scored in batches), score each with the confidence
of eq. (5), ``C = gamma * exp(-sigma^2 / (beta T_s^2))`` (``gamma`` inlier ratio, ``sigma^2`` mean
squared eq.-(2) residual of the inliers), pick the argmax and accept it when the inliers number at
least ``tau |F_k|``.

Departures, documented in docs/metrizer.md:

- ``T_s`` scales with depth: a point at z-depth ``z`` is an inlier when its eq.-(2) residual is
  below ``T_s(z) = t_abs_m + t_rel * z`` (the depth error of triangulated points grows with depth).
  Residuals are divided by ``T_s(z)``, so eq. (5) is evaluated with ``T_s = 1`` in these units.
- A costlier model (cylinder, then ellipsoid) must beat the simpler one by ``model_margin`` in C:
  a plane is a cylinder of infinite radius, and ties must go to the simpler shape.
- "Skip what a scene doesn't need": when the plane alone reaches ``skip_confidence`` the cylinder
  and ellipsoid are not fitted at all; :class:`ObjectFit` records that it happened.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from mogs_node.metrizer import shapes

__all__ = ["ConsensusParams", "ObjectFit", "fit_object", "score_hypotheses"]

log = logging.getLogger(__name__)
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class ConsensusParams:
    """Parameters of the per-object shape consensus (Algorithm 1)."""

    t_rel: float = 0.03  # T_s(z) = t_abs_m + t_rel * z: relative part of the inlier threshold
    t_abs_m: float = 0.02  # absolute part of the inlier threshold [m]
    beta: float = 1.0  # eq. (5): width of the residual penalty in units of T_s^2
    tau: float = 0.8  # accept a model when inliers >= tau * |F_k|
    success_prob: float = 0.99  # adaptive RANSAC: probability of one all-inlier sample
    max_iters: int = 192  # RANSAC hypotheses per model at most
    batch: int = 64  # plane hypotheses generated and scored per numpy batch
    batch_quadric: int = 32  # cylinder / ellipsoid hypotheses per batch
    min_points_plane: int = 5  # fewer features: no plane is tried
    min_points_quadric: int = 12  # fewer features: no cylinder / ellipsoid is tried
    skip_confidence: float = 0.85  # plane C above this: skip the cylinder and ellipsoid
    model_margin: float = 0.1  # a costlier model must beat a simpler one by this much C
    max_size: float = 4.0  # largest ellipsoid semi-axis / cylinder radius, in robust spreads of F_k
    refit_rounds: int = 1  # least-squares refits on the inliers after RANSAC
    min_spread: float = 0.5  # inliers' RMS spread along their 2nd principal axis >= this * mean T_s


@dataclass
class ObjectFit:
    """Result of Algorithm 1 for one object; the model is in the camera frame."""

    kind: int = shapes.KIND_NONE  # accepted model (shapes.KIND_*), KIND_NONE when rejected
    A: F64 = field(default_factory=lambda: np.zeros((3, 3)))
    b: F64 = field(default_factory=lambda: np.zeros(3))
    c: float = 0.0
    confidence: float = 0.0  # eq. (5) of the accepted model, 0 when rejected
    n_points: int = 0
    n_inliers: int = 0
    inliers: NDArray[np.bool_] | None = None
    confidences: dict[int, float] = field(default_factory=dict)  # eq. (5) per tried kind
    skipped_costly: bool = False  # plane was good enough: cylinder/ellipsoid not fitted
    degenerate: bool = False  # rejected: the inliers are nearly collinear


def score_hypotheses(
    A: F64, b: F64, c: F64, valid: NDArray[np.bool_], Xn: F64, ts_n: F64, beta: float
) -> tuple[F64, NDArray[np.bool_]]:
    """Eq. (5) confidence per hypothesis ``[H]`` and the inlier mask ``[H, N]``.

    ``Xn`` ``[N, 3]`` normalised points, ``ts_n`` ``[N]`` their thresholds ``T_s(z)`` in the same
    units. Invalid hypotheses get confidence -1.
    """
    if not np.any(A):  # planes (unit normal b): the exact point-plane distance, cheaper
        u = np.abs(b @ Xn.T + c[:, None]) / ts_n[None, :]
    else:
        u = shapes.quadric_residual(A, b, c, Xn) / ts_n[None, :]
    inl = u < 1.0
    cnt = inl.sum(axis=1)
    gamma = cnt / max(Xn.shape[0], 1)
    sigma2 = np.where(inl, u * u, 0.0).sum(axis=1) / np.maximum(cnt, 1)
    conf = gamma * np.exp(-sigma2 / beta)
    return np.where(valid & (cnt > 0), conf, -1.0), inl


def _needed(ratio: float, s: int, success_prob: float, max_iters: int) -> int:
    """RANSAC hypotheses for one all-inlier ``s``-sample with probability ``success_prob``."""
    if ratio >= 1.0:
        return 0
    if ratio <= 0.0:
        return max_iters
    q = 1.0 - ratio**s
    if q <= 0.0:
        return 1
    return min(max_iters, math.ceil(math.log(1.0 - success_prob) / math.log(q)))


def _sample(rng: np.random.Generator, H: int, N: int, s: int) -> NDArray[np.intp]:
    """``H`` random ``s``-subsets of ``range(N)`` without repetition inside a subset."""
    return np.argpartition(rng.random((H, N)), s - 1, axis=1)[:, :s]


def _fit_batch(kind: int, P: F64, max_size: float, w: F64 | None = None):
    if kind == shapes.KIND_PLANE:
        if P.shape[1] == 3 and w is None:
            return shapes.fit_plane_minimal(P)
        A, n, d, ok = shapes.fit_plane(P[0], None if w is None else w[0])
        return A[None], n[None], np.array([d]), np.array([ok])
    if kind == shapes.KIND_CYLINDER:
        return shapes.fit_cylinder(P, w, max_radius=max_size)
    return shapes.fit_ellipsoid(P, w, max_axis=max_size)


def _ransac(
    kind: int, Xn: F64, w: F64, ts_n: F64, rng: np.random.Generator, p: ConsensusParams
) -> tuple[float, F64, F64, float, NDArray[np.bool_]] | None:
    """Adaptive batched RANSAC + least-squares refit for one model kind (normalised frame)."""
    N = len(Xn)
    s = 3 if kind == shapes.KIND_PLANE else 9
    if s > N:
        return None
    best = (-1.0, None, None, 0.0, None)
    # a model is only accepted with an inlier ratio >= tau: enough hypotheses to draw one
    # all-inlier sample of such a model bound the count (Algorithm 1 + adaptive RANSAC)
    cap = min(p.max_iters, _needed(p.tau, s, p.success_prob, p.max_iters))
    done, needed = 0, cap
    while done < min(needed, cap):
        H = min(p.batch if s == 3 else p.batch_quadric, p.max_iters - done)
        idx = _sample(rng, H, N, s)
        A, b, c, valid = _fit_batch(kind, Xn[idx], p.max_size)
        conf, inl = score_hypotheses(A, b, c, valid, Xn, ts_n, p.beta)
        h = int(np.argmax(conf))
        if conf[h] > best[0]:
            best = (float(conf[h]), A[h], b[h], float(c[h]), inl[h])
            needed = _needed(float(inl[h].mean()), s, p.success_prob, p.max_iters)
        done += H
    if best[1] is None:
        return None
    for _ in range(p.refit_rounds):
        inl = best[4]
        if inl.sum() < s:
            break
        A, b, c, valid = _fit_batch(kind, Xn[inl][None], p.max_size, w[inl][None])
        conf, inl2 = score_hypotheses(A, b, c, valid, Xn, ts_n, p.beta)
        if conf[0] < best[0]:
            break
        best = (float(conf[0]), A[0], b[0], float(c[0]), inl2[0])
    return best


def _spread_ok(X: F64, inl: NDArray[np.bool_], p: ConsensusParams, axis: int) -> bool:
    """RMS spread of the inliers along principal axis ``axis`` >= ``min_spread`` * mean T_s."""
    if inl.sum() < 3:
        return False
    Xi = X[inl] - X[inl].mean(axis=0)
    sv = np.linalg.svd(Xi, compute_uv=False)
    ts_mean = float(np.mean(p.t_abs_m + p.t_rel * np.abs(X[inl, 2])))
    return bool(sv[axis] / np.sqrt(len(Xi)) >= p.min_spread * ts_mean)


def fit_object(
    X: F64,
    w: F64,
    rng: np.random.Generator,
    params: ConsensusParams = ConsensusParams(),
    plane: tuple | None = None,
) -> ObjectFit:
    """Algorithm 1 on one object's camera-frame points ``X`` ``[N, 3]`` with weights ``w`` ``[N]``.

    Plane, cylinder and ellipsoid are tried in order of cost; the model with the largest eq.-(5)
    confidence (costlier ones needing ``model_margin`` more) is accepted when its inliers number at
    least ``tau * N``. The returned model is in the camera frame. ``plane`` optionally gives the
    plane RANSAC result ``(conf, A, b, c, inliers)`` in the normalised frame (from
    :func:`fit_objects`), which is then not recomputed.
    """
    p = params
    N = len(X)
    out = ObjectFit(n_points=N)
    if max(3, p.min_points_plane) > N:
        return out
    Xn, mu, s = shapes.normalise_points(X)
    ts_n = (p.t_abs_m + p.t_rel * np.abs(X[:, 2])) / s
    # robust spread (median distance to the coordinate-wise median) bounds the model size
    h = N // 2
    med = np.partition(X, h, axis=0)[h]
    spread = float(np.partition(np.linalg.norm(X - med, axis=1), h)[h]) / s
    p = replace(p, max_size=p.max_size * max(spread, 1e-3))
    w = np.where(np.isfinite(w) & (w > 0), w, 0.0) + 1e-6
    results = {}
    if plane is None:
        plane = _ransac(shapes.KIND_PLANE, Xn, w, ts_n, rng, p)
    if plane is not None:
        results[shapes.KIND_PLANE] = plane
    plane_conf = plane[0] if plane is not None else -1.0
    plane_ok = plane is not None and plane[4].sum() >= p.tau * N
    if plane_ok and plane_conf >= p.skip_confidence:
        out.skipped_costly = True
    elif p.min_points_quadric <= N:
        for kind in (shapes.KIND_CYLINDER, shapes.KIND_ELLIPSOID):
            r = _ransac(kind, Xn, w, ts_n, rng, p)
            if r is not None:
                results[kind] = r
    for kind in (shapes.KIND_CYLINDER, shapes.KIND_ELLIPSOID):
        # a curved model needs curvature above the noise: the inliers' 3rd principal RMS spread
        # must exceed min_spread * T_s, otherwise the data is planar within noise
        if kind in results and not _spread_ok(X, results[kind][4], p, axis=2):
            del results[kind]
    out.confidences = {k: max(r[0], 0.0) for k, r in results.items()}
    best_kind, best_conf = shapes.KIND_NONE, -1.0
    for kind in (shapes.KIND_PLANE, shapes.KIND_CYLINDER, shapes.KIND_ELLIPSOID):  # increasing cost
        if kind not in results:
            continue
        margin = p.model_margin if best_kind != shapes.KIND_NONE else 0.0
        if results[kind][0] > best_conf + margin:
            best_kind, best_conf = kind, results[kind][0]
    if best_kind == shapes.KIND_NONE:
        return out
    conf, A, b, c, inl = results[best_kind]
    out.n_inliers = int(inl.sum())
    out.inliers = inl
    if conf <= 0 or out.n_inliers < p.tau * N:
        return out
    # near-collinear support (e.g. features along a lane marking) leaves the surface's tilt free
    if not _spread_ok(X, inl, p, axis=1):
        out.degenerate = True
        return out
    A2, b2, c2 = shapes.denormalise_quadric(A[None], b[None], np.array([c]), mu, s)
    if not (np.all(np.isfinite(A2)) and np.all(np.isfinite(b2)) and np.isfinite(c2[0])):
        return out
    out.kind, out.A, out.b, out.c, out.confidence = best_kind, A2[0], b2[0], float(c2[0]), conf
    return out


def _plane_scores(nrm, d, valid, Pn, V, ts_n, n, beta):
    """Eq. (5) for plane hypotheses of many objects: ``nrm [M,H,3], d [M,H]`` -> conf, inliers."""
    u = np.abs(np.einsum("mhk,mnk->mhn", nrm, Pn) + d[..., None]) / ts_n[:, None, :]
    inl = (u < 1.0) & V[:, None, :]
    cnt = inl.sum(-1)
    sigma2 = np.where(inl, u * u, 0.0).sum(-1) / np.maximum(cnt, 1)
    conf = cnt / n[:, None] * np.exp(-sigma2 / beta)
    return np.where(valid & (cnt > 0), conf, -1.0), inl


def fit_objects(
    X: F64,
    w: F64,
    obj: NDArray[np.intp],
    n_obj: int,
    rng: np.random.Generator,
    params: ConsensusParams = ConsensusParams(),
) -> dict[int, ObjectFit]:
    """Algorithm 1 for every object at once: the fast kernel of :func:`fit_object`.

    ``X`` ``[N, 3]`` camera-frame points, ``w`` ``[N]`` weights, ``obj`` ``[N]`` object id per
    point. The plane RANSAC (hypotheses, eq.-(5) scores, adaptive iteration count, weighted least-
    squares refit and the spread test) runs for all objects in padded ``[M, N_max]`` batches; only
    objects the plane does not explain with ``skip_confidence`` go on, one by one, to the cylinder
    and ellipsoid (:func:`fit_object` with the plane result). Each object's points are taken in the
    order of a stable sort by ``obj``; ``ObjectFit.inliers`` follows that order.
    Returns ``{object id: ObjectFit}`` for the objects with at least ``min_points_plane`` points.
    """
    p = params
    counts = np.bincount(obj, minlength=n_obj)
    todo = np.flatnonzero(counts >= max(3, p.min_points_plane))
    if len(todo) == 0:
        return {}
    pad = _pad_objects(X, w, obj, counts, todo, p)
    best = _plane_ransac(pad, rng, p)
    _refit_planes(pad, best, p)
    return _collect_fits(X, w, pad, best, rng, p)


@dataclass
class _Padded:
    """The objects' points in padded ``[M, N_max]`` arrays (one row per object), normalised."""

    todo: NDArray[np.intp]  # [M] object id of each row
    order: NDArray[np.intp]  # [N] stable sort of the points by object
    starts: NDArray[np.int64]  # [n_obj + 1] first point of each object in ``order``
    n: F64  # [M] points per row
    P: F64  # [M, N_max, 3] points (camera frame, metres)
    V: NDArray[np.bool_]  # [M, N_max] valid entries
    Wt: F64  # [M, N_max] weights
    mu: F64  # [M, 3] centroid
    sc: F64  # [M] RMS radius (normalisation)
    Pn: F64  # [M, N_max, 3] normalised points
    ts_m: F64  # [M, N_max] T_s(z) in metres
    ts_n: F64  # [M, N_max] T_s in normalised units


@dataclass
class _BestPlanes:
    """Per row: the best plane so far (normalised frame) with its eq.-(5) score and inliers."""

    conf: F64  # [M]
    n: F64  # [M, 3]
    d: F64  # [M]
    inl: NDArray[np.bool_]  # [M, N_max]


def _pad_objects(
    X: F64, w: F64, obj: NDArray[np.intp], counts: NDArray, todo: NDArray, p: ConsensusParams
) -> _Padded:
    order = np.argsort(obj, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    M, Nmax = len(todo), int(counts[todo].max())
    row_of = np.full(len(counts), -1)
    row_of[todo] = np.arange(M)
    so = obj[order]
    rank = np.arange(len(order)) - starts[so]
    rows = row_of[so]
    keep = rows >= 0
    P = np.zeros((M, Nmax, 3))
    V = np.zeros((M, Nmax), bool)
    Wt = np.zeros((M, Nmax))
    P[rows[keep], rank[keep]] = X[order[keep]]
    V[rows[keep], rank[keep]] = True
    Wt[rows[keep], rank[keep]] = np.where(np.isfinite(w) & (w > 0), w, 0.0)[order[keep]] + 1e-6
    n = counts[todo].astype(np.float64)
    mu = P.sum(1) / n[:, None]
    D = (P - mu[:, None]) * V[..., None]
    sc = np.sqrt(np.einsum("mni,mni->m", D, D) / n)
    sc = np.where(np.isfinite(sc) & (sc > 1e-12), sc, 1.0)
    Pn = D / sc[:, None, None]
    ts_m = p.t_abs_m + p.t_rel * np.abs(P[..., 2])
    ts_n = np.where(V, ts_m / sc[:, None], 1.0)
    return _Padded(todo, order, starts, n, P, V, Wt, mu, sc, Pn, ts_m, ts_n)


def _plane_ransac(pad: _Padded, rng: np.random.Generator, p: ConsensusParams) -> _BestPlanes:
    """Batched plane RANSAC with the adaptive iteration count, all rows at once."""
    n, Pn, V, ts_n = pad.n, pad.Pn, pad.V, pad.ts_n
    M, Nmax = V.shape
    best = _BestPlanes(np.full(M, -1.0), np.zeros((M, 3)), np.zeros(M), np.zeros((M, Nmax), bool))
    cap = _needed(p.tau, 3, p.success_prob, p.max_iters)
    needed = np.full(M, cap)
    done = np.zeros(M, int)
    active = np.arange(M)
    while len(active):
        Hb = min(p.batch, p.max_iters)
        idx = (rng.random((len(active), Hb, 3)) * n[active, None, None]).astype(np.intp)
        pts = Pn[active[:, None, None], idx]  # [A, H, 3 points, 3]
        u, v = pts[:, :, 1] - pts[:, :, 0], pts[:, :, 2] - pts[:, :, 0]
        nrm = np.stack(
            [
                u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1],
                u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2],
                u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0],
            ],
            -1,
        )
        nn = np.sqrt(np.einsum("ahk,ahk->ah", nrm, nrm))
        scale = np.sqrt(np.einsum("ahk,ahk->ah", u, u) * np.einsum("ahk,ahk->ah", v, v))
        valid = nn > 1e-6 * np.maximum(scale, 1e-12)
        nrm = nrm / np.where(valid, nn, 1.0)[..., None]
        d = -np.einsum("ahk,ahk->ah", nrm, pts[:, :, 0])
        conf, inl = _plane_scores(
            nrm, d, valid, Pn[active], V[active], ts_n[active], n[active], p.beta
        )
        h = np.argmax(conf, axis=1)
        ai = np.arange(len(active))
        c = conf[ai, h]
        better = c > best.conf[active]
        upd = active[better]
        best.conf[upd] = c[better]
        best.n[upd] = nrm[ai[better], h[better]]
        best.d[upd] = d[ai[better], h[better]]
        best.inl[upd] = inl[ai[better], h[better]]
        ratio = best.inl[active].sum(1) / n[active]
        with np.errstate(divide="ignore", invalid="ignore"):
            need = np.ceil(np.log(1 - p.success_prob) / np.log(1 - ratio**3))
        need = np.where(ratio >= 1.0, 0, np.where(ratio > 0, need, cap))
        needed[active] = np.minimum(np.nan_to_num(need, nan=cap), cap)
        done[active] += Hb
        active = active[done[active] < needed[active]]
    return best


def _refit_planes(pad: _Padded, best: _BestPlanes, p: ConsensusParams) -> None:
    """Weighted least-squares plane on the inliers (batched), kept where it scores no worse."""
    Pn, V, ts_n, n = pad.Pn, pad.V, pad.ts_n, pad.n
    for _ in range(p.refit_rounds):
        Wi = pad.Wt * best.inl
        sw = Wi.sum(1)
        ok = best.inl.sum(1) >= 3
        mw = (Wi[..., None] * Pn).sum(1) / np.maximum(sw, 1e-300)[:, None]
        Dw = Pn - mw[:, None]
        C = np.einsum("mn,mni,mnj->mij", Wi, Dw, Dw)
        ev, evec = np.linalg.eigh(C)
        nrm = evec[:, :, 0]
        valid = ok & (ev[:, 1] > 1e-12 * np.maximum(ev[:, 2], 1e-300))
        d = -np.einsum("mk,mk->m", nrm, mw)
        conf, inl = _plane_scores(nrm[:, None], d[:, None], valid[:, None], Pn, V, ts_n, n, p.beta)
        take = valid & (conf[:, 0] >= best.conf)
        best.conf[take], best.n[take], best.d[take] = conf[take, 0], nrm[take], d[take]
        best.inl[take] = inl[take, 0]


def _collect_fits(
    X: F64,
    w: F64,
    pad: _Padded,
    best: _BestPlanes,
    rng: np.random.Generator,
    p: ConsensusParams,
) -> dict[int, ObjectFit]:
    """Planes confident enough to skip the costly models (with the spread test) become fits;
    the other objects go on to :func:`fit_object` with their plane result, in row order."""
    P, n, best_inl, best_conf = pad.P, pad.n, best.inl, best.conf
    # spread test (metric): RMS along the inliers' 2nd principal axis vs the mean T_s
    ci = best_inl.sum(1)
    mi = (best_inl[..., None] * P).sum(1) / np.maximum(ci, 1)[:, None]
    Di = (P - mi[:, None]) * best_inl[..., None]
    lam = np.linalg.eigvalsh(np.einsum("mni,mnj->mij", Di, Di) / np.maximum(ci, 1)[:, None, None])
    ts_mean = (pad.ts_m * best_inl).sum(1) / np.maximum(ci, 1)
    spread_ok = (ci >= 3) & (np.sqrt(np.maximum(lam[:, 1], 0.0)) >= p.min_spread * ts_mean)
    # camera-frame plane: n . (x - mu) / s + d = 0
    b_cam = best.n / pad.sc[:, None]
    c_cam = best.d - np.einsum("mk,mk->m", b_cam, pad.mu)
    accepted = (best_conf > 0) & (ci >= p.tau * n)
    skip = accepted & (best_conf >= p.skip_confidence)
    out: dict[int, ObjectFit] = {}
    for r in range(len(pad.todo)):
        k = int(pad.todo[r])
        N = int(n[r])
        inl = best_inl[r, :N].copy()
        if not skip[r]:
            pts_idx = pad.order[pad.starts[k] : pad.starts[k + 1]]
            plane = None
            if best_conf[r] > -1.0:
                plane = (
                    float(best_conf[r]),
                    np.zeros((3, 3)),
                    best.n[r].copy(),
                    float(best.d[r]),
                    inl,
                )
            out[k] = fit_object(X[pts_idx], w[pts_idx], rng, p, plane=plane)
            continue
        fit = ObjectFit(
            n_points=N,
            n_inliers=int(ci[r]),
            inliers=inl,
            skipped_costly=True,
            confidences={shapes.KIND_PLANE: float(best_conf[r])},
        )
        if not spread_ok[r]:
            fit.degenerate = True
        elif np.all(np.isfinite(b_cam[r])) and np.isfinite(c_cam[r]):
            fit.kind, fit.b, fit.c = shapes.KIND_PLANE, b_cam[r], float(c_cam[r])
            fit.confidence = float(best_conf[r])
        out[k] = fit
    return out
