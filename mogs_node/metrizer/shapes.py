"""Shape primitives of MSC (paper III-B): plane, cylinder, ellipsoid as quadrics.

Every model is stored as a quadric ``f(x) = x^T A x + b^T x + c`` (a plane has ``A = 0``), so one
residual (eq. 2, first-order geometric distance ``|f| / |grad f|``) and one ray intersection serve
all three. The functions are batched over a leading axis of hypotheses ``H`` so that RANSAC scores
many hypotheses in one numpy call (Algorithm 1).

Fits:

- plane: minimal 3 points (cross product); least squares by SVD of the centred points.
- ellipsoid: general quadric (10 coefficients, 9 DOF) from 9 points (null space of the 9x10 design
  matrix), kept only when ``A`` is positive definite after sign normalisation and the centre form
  ``(x - x0)^T A (x - x0) = k`` has ``k > 0`` (a real ellipsoid); least squares = smallest right
  singular vector of the design matrix of all inliers.
- cylinder: general quadric from 9 points, then projected onto the cylinder family: the axis is the
  eigenvector of ``A`` with the smallest ``|eigenvalue|``, centre and radius come from an algebraic
  (Kasa) circle fit of the points projected onto the plane normal to the axis. Exact for noiseless
  points. (The paper does not state its cylinder solver; without surface normals there is no closed
  form from fewer points.)

Points are expected in a normalised frame (centred, unit RMS radius; see :func:`normalise_points`)
for conditioning; :func:`denormalise_quadric` maps a model back to the camera frame.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ShapeError
from mogs_node.geometry import check_array

__all__ = [
    "KIND_CYLINDER",
    "KIND_ELLIPSOID",
    "KIND_NONE",
    "KIND_PLANE",
    "cylinder_quadric",
    "denormalise_quadric",
    "fit_cylinder",
    "fit_ellipsoid",
    "fit_plane",
    "fit_plane_minimal",
    "fit_quadric_coeffs",
    "normalise_points",
    "quadric_from_coeffs",
    "quadric_residual",
    "quadric_residual_reference",
    "quadric_residual_rows",
    "ray_depth",
    "ray_depth_reference",
]

KIND_NONE, KIND_PLANE, KIND_CYLINDER, KIND_ELLIPSOID = 0, 1, 2, 3

F64 = NDArray[np.float64]
_EPS = 1e-12


def normalise_points(X: F64) -> tuple[F64, F64, float]:
    """Centre ``X`` ``[N, 3]`` and scale it to unit RMS radius: returns ``(Xn, mu [3], s)``."""
    X = check_array("X", X, shape=(None, 3), dtype=np.floating)
    mu = X.mean(axis=0) if len(X) else np.zeros(3)
    s = float(np.sqrt(np.mean(np.sum((X - mu) ** 2, axis=1)))) if len(X) else 1.0
    s = s if np.isfinite(s) and s > _EPS else 1.0
    return (X - mu) / s, mu, s


def denormalise_quadric(A: F64, b: F64, c: F64, mu: F64, s: float) -> tuple[F64, F64, F64]:
    """Map quadrics fitted on ``x' = (x - mu) / s`` back to ``x``; batched ``[H,3,3],[H,3],[H]``."""
    A2 = A / s**2
    b2 = -2.0 * (A2 @ mu) + b / s
    c2 = np.einsum("i,...ij,j->...", mu, A2, mu) - (b @ mu) / s + c
    return A2, b2, c2


# ------------------------------------------------------------------------------ residual (eq. 2)


def quadric_residual(A: F64, b: F64, c: F64, X: F64) -> F64:
    """First-order geometric distance of eq. (2), ``|f(x)| / |grad f(x)|``.

    ``A`` ``[H, 3, 3]`` symmetric, ``b`` ``[H, 3]``, ``c`` ``[H]``, ``X`` ``[N, 3]`` -> ``[H, N]``.
    For a plane with unit normal this is the exact point-plane distance; for a cylinder it is
    ``|rho^2 - r^2| / (2 rho)``, i.e. ``|rho - r|`` to first order. Where the gradient vanishes the
    residual is ``inf`` (the point is not explained).
    """
    AX = np.einsum("hij,nj->hni", A, X)  # [H, N, 3]
    f = np.einsum("hni,ni->hn", AX, X) + b @ X.T + c[:, None]
    g = 2.0 * AX + b[:, None, :]
    gn = np.sqrt(np.einsum("hni,hni->hn", g, g))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.abs(f) / gn
    return np.where(np.isfinite(r) & (gn > _EPS), r, np.inf)


def quadric_residual_rows(A: F64, b: F64, c: F64, X: F64) -> F64:
    """Eq. (2) with one model per point: ``A [R,3,3], b [R,3], c [R], X [R,3]`` -> ``[R]``."""
    AX = np.einsum("rij,rj->ri", A, X)
    f = np.einsum("ri,ri->r", AX, X) + np.einsum("ri,ri->r", b, X) + c
    g = 2.0 * AX + b
    gn = np.sqrt(np.einsum("ri,ri->r", g, g))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.abs(f) / gn
    return np.where(np.isfinite(r) & (gn > _EPS), r, np.inf)


def quadric_residual_reference(A: F64, b: F64, c: F64, X: F64) -> F64:
    """Slow loop reference of :func:`quadric_residual` (tests only)."""
    out = np.empty((len(A), len(X)))
    for h in range(len(A)):
        for n in range(len(X)):
            x = X[n]
            f = x @ A[h] @ x + b[h] @ x + c[h]
            g = np.linalg.norm(2.0 * A[h] @ x + b[h])
            out[h, n] = abs(f) / g if g > _EPS else np.inf
    return out


# ------------------------------------------------------------------------------------- plane


def _cross(a: F64, b: F64) -> F64:
    """Row-wise cross product ``[H, 3] x [H, 3]`` (``np.cross`` has a large per-call overhead)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def fit_plane_minimal(P: F64) -> tuple[F64, F64, F64, NDArray[np.bool_]]:
    """Planes through point triples ``P`` ``[H, 3, 3]`` -> ``(A, b = unit normal, c, valid)``."""
    u, v = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    n = _cross(u, v)
    nn = np.sqrt(np.einsum("hi,hi->h", n, n))
    scale = np.maximum(np.sqrt(np.einsum("hi,hi->h", u, u) * np.einsum("hi,hi->h", v, v)), _EPS)
    valid = nn > 1e-6 * scale
    n = n / np.where(valid, nn, 1.0)[:, None]
    d = -np.einsum("hi,hi->h", n, P[:, 0])
    return np.zeros((len(P), 3, 3)), n, d, valid


def fit_plane(X: F64, w: F64 | None = None) -> tuple[F64, F64, float, bool]:
    """Weighted least-squares plane of ``X`` ``[N, 3]`` (weights ``w`` ``[N]``), by SVD."""
    if len(X) < 3:
        return np.zeros((3, 3)), np.array([0.0, 0.0, 1.0]), 0.0, False
    w = np.ones(len(X)) if w is None else w
    mu = (w[:, None] * X).sum(0) / max(w.sum(), _EPS)
    _, sv, vt = np.linalg.svd(np.sqrt(w)[:, None] * (X - mu), full_matrices=False)
    n = vt[-1]
    valid = bool(sv[1] > 1e-6 * max(sv[0], _EPS))
    return np.zeros((3, 3)), n, float(-n @ mu), valid


# ---------------------------------------------------------------------------- general quadric


def _design(X: F64) -> F64:
    """Quadric design rows ``[..., 10]``: x2 y2 z2 2xy 2xz 2yz x y z 1."""
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    one = np.ones_like(x)
    return np.stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, x, y, z, one], -1)


def quadric_from_coeffs(q: F64) -> tuple[F64, F64, F64]:
    """Coefficient vectors ``[H, 10]`` (see ``_design``) -> ``(A [H,3,3], b [H,3], c [H])``."""
    A = np.empty(q.shape[:-1] + (3, 3))
    A[..., 0, 0], A[..., 1, 1], A[..., 2, 2] = q[..., 0], q[..., 1], q[..., 2]
    A[..., 0, 1] = A[..., 1, 0] = q[..., 3]
    A[..., 0, 2] = A[..., 2, 0] = q[..., 4]
    A[..., 1, 2] = A[..., 2, 1] = q[..., 5]
    return A, q[..., 6:9].copy(), q[..., 9].copy()


def fit_quadric_coeffs(X: F64, w: F64 | None = None) -> tuple[F64, NDArray[np.bool_]]:
    """Quadric through each point set ``X`` ``[H, K, 3]`` (K >= 9): smallest right singular vector.

    Returns coefficients ``[H, 10]`` (unit norm) and ``valid [H]`` (False when the null space is not
    one-dimensional, e.g. coplanar or collinear points, or fewer than 9 distinct points).
    """
    D = _design(X)
    if w is not None:
        D = D * np.sqrt(w)[..., None]
    if D.shape[-2] == 9:  # minimal sample: the null vector is the last column of Q of D^T = QR
        Q, R = np.linalg.qr(np.swapaxes(D, -1, -2), mode="complete")
        q = Q[..., :, -1]
        diag = np.abs(np.diagonal(R, axis1=-2, axis2=-1))
        valid = diag.min(axis=-1) > 1e-7 * np.maximum(diag.max(axis=-1), _EPS)
        return q, valid
    if D.shape[-2] < 10:  # pad to a square system so that the null vector is the last row of V^T
        D = np.concatenate([D, np.zeros(D.shape[:-2] + (10 - D.shape[-2], 10))], axis=-2)
    _, sv, vt = np.linalg.svd(D, full_matrices=False)
    q = vt[..., -1, :]
    valid = sv[..., -2] > 1e-7 * np.maximum(sv[..., 0], _EPS)
    if X.shape[-2] > 9:  # over-determined: the best vector must also be clearly the best
        valid &= sv[..., -2] > 1e-3 * np.maximum(sv[..., 0], _EPS)
    return q, valid


def fit_ellipsoid(
    X: F64, w: F64 | None = None, max_axis: float = 10.0
) -> tuple[F64, F64, F64, NDArray[np.bool_]]:
    """Ellipsoids through point sets ``X`` ``[H, K, 3]`` (normalised frame).

    Valid only when ``A`` is positive definite (after flipping the overall sign), the centre form
    ``k = x0^T A x0 - c`` is positive, and every semi-axis is at most ``max_axis`` (normalised
    units; a larger "ellipsoid" is a plane in disguise). The quadric is rescaled so that ``k = 1``.
    """
    q, valid = fit_quadric_coeffs(X, w)
    A, b, c = quadric_from_coeffs(q)
    sign = np.where(np.trace(A, axis1=-2, axis2=-1) < 0, -1.0, 1.0)
    A, b, c = A * sign[:, None, None], b * sign[:, None], c * sign
    ev = np.linalg.eigvalsh(A)
    valid &= ev[:, 0] > 1e-9 * np.maximum(np.abs(ev[:, -1]), _EPS)
    Ainv = np.linalg.pinv(A)
    x0 = -0.5 * np.einsum("hij,hj->hi", Ainv, b)
    k = np.einsum("hi,hij,hj->h", x0, A, x0) - c
    valid &= k > 0
    ks = np.where(valid, k, 1.0)
    A, b, c = A / ks[:, None, None], b / ks[:, None], c / ks
    ev = ev / ks[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        semi = 1.0 / np.sqrt(np.where(valid, ev[:, 0], 1.0))
    valid &= np.isfinite(semi) & (semi <= max_axis)
    return A, b, c, valid


def cylinder_quadric(axis: F64, centre: F64, radius: F64) -> tuple[F64, F64, F64]:
    """Quadric of infinite cylinder(s) ``|(x - p0) x axis| = r``; batched ``[H,3],[H,3],[H]``."""
    a = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    Pm = np.eye(3) - a[..., :, None] * a[..., None, :]
    pc = np.einsum("hij,hj->hi", Pm, centre)
    return Pm, -2.0 * pc, np.einsum("hi,hi->h", pc, pc) - radius**2


def fit_cylinder(
    X: F64, w: F64 | None = None, max_radius: float = 10.0
) -> tuple[F64, F64, F64, NDArray[np.bool_]]:
    """Cylinders through point sets ``X`` ``[H, K, 3]`` (normalised frame), see module docstring.

    Valid when the general quadric is well defined, its smallest ``|eigenvalue|`` is clearly
    separated from the other two (a cylinder-like quadric), and the radius is at most
    ``max_radius`` (normalised units).
    """
    q, valid = fit_quadric_coeffs(X, w)
    A, _, _ = quadric_from_coeffs(q)
    ev, evec = np.linalg.eigh(A)
    order = np.argsort(np.abs(ev), axis=1)
    axis = np.take_along_axis(evec, order[:, None, :1], axis=2)[..., 0]  # [H, 3]
    ev_sorted = np.take_along_axis(ev, order, axis=1)
    big = np.abs(ev_sorted[:, 2])
    valid &= np.abs(ev_sorted[:, 0]) < 0.2 * np.maximum(np.abs(ev_sorted[:, 1]), _EPS)
    valid &= ev_sorted[:, 1] * ev_sorted[:, 2] > 0  # the two large eigenvalues share a sign
    valid &= big > _EPS
    # Kasa circle fit in the plane normal to the axis: u^2+v^2 + D u + E v + F = 0
    ref = np.where(np.abs(axis[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    e1 = _cross(axis, ref)
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), _EPS)
    e2 = _cross(axis, e1)
    u = np.einsum("hki,hi->hk", X, e1)
    v = np.einsum("hki,hi->hk", X, e2)
    M = np.stack([u, v, np.ones_like(u)], -1)  # [H, K, 3]
    rhs = -(u * u + v * v)
    if w is not None:
        sw = np.sqrt(w)
        M, rhs = M * sw[..., None], rhs * sw
    MtM = np.einsum("hki,hkj->hij", M, M) + 1e-12 * np.eye(3)
    Mtr = np.einsum("hki,hk->hi", M, rhs)
    sol = np.linalg.solve(MtM, Mtr[..., None])[..., 0]
    cu, cv = -0.5 * sol[:, 0], -0.5 * sol[:, 1]
    r2 = cu * cu + cv * cv - sol[:, 2]
    valid &= r2 > 0
    r = np.sqrt(np.where(r2 > 0, r2, 1.0))
    valid &= r <= max_radius
    centre = cu[:, None] * e1 + cv[:, None] * e2
    Ac, bc, cc = cylinder_quadric(axis, centre, r)
    return Ac, bc, cc, valid


# ---------------------------------------------------------------------------- ray intersection


def ray_depth(A: F64, b: F64, c: F64, rays: F64) -> F64:
    """z-depth where camera rays hit the quadric: nearest positive root; ``inf`` on a miss.

    One model per ray: ``A`` ``[P, 3, 3]``, ``b`` ``[P, 3]``, ``c`` ``[P]`` (or a single model
    broadcast: ``[3, 3], [3], []``), ``rays`` ``[P, 3]`` with ``z = 1`` and origin at the camera
    centre, so the ray parameter is the z-depth. Solves ``qa t^2 + qb t + c = 0`` with the
    cancellation-free formula; a plane (``qa = 0``) gives ``t = -c / qb``.
    """
    if A.ndim == 2:
        qa = np.einsum("pi,pi->p", rays @ A, rays)
        qb = rays @ b
        qc = np.broadcast_to(np.asarray(c, dtype=np.float64), qa.shape)
    else:
        qa = np.einsum("pi,pij,pj->p", rays, A, rays)
        qb = np.einsum("pi,pi->p", rays, b)
        qc = c
    scale = np.maximum(np.abs(qb), _EPS)
    lin = np.abs(qa) <= 1e-12 * scale
    disc = qb * qb - 4.0 * qa * qc
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        qq = -0.5 * (qb + np.copysign(sq, qb))
        t1 = np.where(lin, -qc / qb, qq / qa)
        t2 = np.where(lin, np.inf, qc / qq)
    t1 = np.where(np.isfinite(t1) & (t1 > 0), t1, np.inf)
    t2 = np.where(np.isfinite(t2) & (t2 > 0), t2, np.inf)
    return np.where(lin | (disc >= 0), np.minimum(t1, t2), np.inf)


def ray_depth_reference(A: F64, b: F64, c: float, rays: F64) -> F64:
    """Slow loop reference of :func:`ray_depth` for one model (tests only), via ``np.roots``."""
    out = np.full(len(rays), np.inf)
    for i, d in enumerate(rays):
        coeffs = [d @ A @ d, d @ b, c]
        while coeffs and abs(coeffs[0]) < 1e-14:
            coeffs = coeffs[1:]
        if len(coeffs) < 2:
            continue
        roots = np.roots(coeffs)
        real = [r.real for r in roots if abs(r.imag) < 1e-9 * max(1.0, abs(r)) and r.real > 0]
        if real:
            out[i] = min(real)
    return out


def check_model_arrays(A: F64, b: F64, c: F64) -> None:
    """Raise :class:`ShapeError` unless ``A [H,3,3], b [H,3], c [H]`` agree."""
    check_array("A", A, shape=(None, 3, 3))
    check_array("b", b, shape=(len(A), 3))
    check_array("c", c, shape=(len(A),))
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b)) and np.all(np.isfinite(c))):
        raise ShapeError("quadric: non-finite coefficients")
