"""Multi-view triangulation of feature tracks (paper section IV-A: the linear (SVD) method, then
nonlinear least squares), vectorised over points; used by :mod:`mogs_node.frontend.track_points`.

1. :func:`triangulate_dlt`: the homogeneous linear system of all views (DLT), solved by SVD.
2. :func:`refine_points`: Gauss-Newton on the reprojection error, in the reference camera frame,
   parametrised by inverse depth along the reference ray (well conditioned for far points). It
   returns the covariance from the Jacobian (poses held fixed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mogs_node.geometry import PinholeCamera, check_array, se3_inverse

__all__ = [
    "RefineParams",
    "RefinedPoints",
    "refine_points",
    "triangulate_dlt",
    "triangulate_on_ray",
]


@dataclass(frozen=True)
class RefineParams:
    """Settings of :func:`refine_points`."""

    iterations: int = 4  # Gauss-Newton steps (from the DLT start one is often enough)
    pixel_sigma_px: float = 0.5  # floor of the residual scale behind the covariance


@dataclass
class RefinedPoints:
    """Result of :func:`refine_points`; arrays share length ``N``."""

    xyz_ref_m: NDArray[np.float64]  # [N, 3] point in the reference (keyframe) camera frame
    cov_ref_m2: NDArray[np.float64]  # [N, 3, 3] its covariance (poses fixed)
    depth_sigma_m: NDArray[np.float64]  # [N] 1-sigma of the depth z
    reproj_max_px: NDArray[np.float64]  # [N] largest reprojection error over the views
    reproj_rms_px: NDArray[np.float64]  # [N]
    parallax_deg: NDArray[np.float64]  # [N] largest angle between the reference ray and another
    n_views: NDArray[np.int64]  # [N] observations used
    in_front: NDArray[np.bool_]  # [N] in front of every camera that saw it


def _check_views(uv_px: NDArray, T_ref_cams: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    uv = check_array("uv_px", uv_px, shape=(None, None, 2), dtype=np.number).astype(np.float64)
    T = check_array("T_ref_cams", T_ref_cams, shape=(uv.shape[1], 4, 4), finite=True)
    valid = np.all(np.isfinite(uv), axis=2)  # [N, F]
    return uv, se3_inverse(T.astype(np.float64)), valid


def triangulate_dlt(
    uv_px: NDArray, T_ref_cams: NDArray, camera: PinholeCamera
) -> NDArray[np.float64]:
    """Linear multi-view triangulation (DLT, solved by SVD; paper IV-A), vectorised over points.

    ``uv_px`` [N, F, 2]: undistorted pixels of N tracks in F views, NaN where a view did not see
    the track; ``T_ref_cams`` [F, 4, 4]: each view's camera pose in the reference frame. Returns the
    points [N, 3] in the reference frame; NaN for tracks with fewer than 2 views or at infinity.
    """
    uv, T_cam_ref, valid = _check_views(uv_px, T_ref_cams)
    N, F = valid.shape
    x = (np.nan_to_num(uv[..., 0]) - camera.cx_px) / camera.fx_px  # [N, F]
    y = (np.nan_to_num(uv[..., 1]) - camera.cy_px) / camera.fy_px
    P = T_cam_ref[:, :3, :]  # [F, 3, 4]
    rows = np.stack(
        [
            x[..., None] * P[None, :, 2] - P[None, :, 0],
            y[..., None] * P[None, :, 2] - P[None, :, 1],
        ],
        axis=2,
    )  # [N, F, 2, 4]
    rows *= valid[..., None, None]
    norms = np.linalg.norm(rows, axis=-1, keepdims=True)
    rows = rows / np.where(norms > 0, norms, 1.0)
    A = rows.reshape(N, 2 * F, 4)
    out = np.full((N, 3), np.nan)
    ok = valid.sum(axis=1) >= 2
    if not np.any(ok):
        return out
    # the right singular vector of A's smallest singular value = the eigenvector of A^T A [4, 4]
    # with the smallest eigenvalue (an order of magnitude faster than a batched SVD of [2F, 4])
    Ao = A[ok]
    AtA = np.swapaxes(Ao, 1, 2) @ Ao  # [M, 4, 4] (a stacked matmul: ~4x einsum's speed)
    _, V = np.linalg.eigh(AtA)
    Xh = V[:, :, 0]  # [M, 4]
    w = Xh[:, 3]
    finite = np.abs(w) > 1e-9 * np.linalg.norm(Xh, axis=1)
    pts = np.full((len(Xh), 3), np.nan)
    pts[finite] = Xh[finite, :3] / w[finite, None]
    out[ok] = pts
    return out


def triangulate_on_ray(
    uv_px: NDArray, T_ref_cams: NDArray, camera: PinholeCamera, *, ref_view: int = -1
) -> NDArray[np.float64]:
    """Linear multi-view triangulation along the reference view's ray, vectorised over points.

    The DLT (:func:`triangulate_dlt`) with two of its three unknowns taken from the reference
    observation: the point is ``(a, b, 1) / rho`` with ``(a, b)`` the reference pixel's normalised
    coordinates, and each other view ``f`` gives the linear equations
    ``rho (x_f t_z - t_x) = m_x - x_f m_z`` (and the same in ``y``) with ``m = R (a, b, 1)``,
    ``(R, t)`` the view's ``T_cam_ref``. Their least-squares ``rho`` is closed form: no batched
    eigen-decomposition (~10x cheaper than the DLT's), and it is the start
    :func:`refine_points` parametrises anyway (docs/frontend.md, round 13).

    ``uv_px`` [N, F, 2] (NaN: unseen) and ``T_ref_cams`` [F, 4, 4] as in :func:`triangulate_dlt`;
    the reference view ``ref_view`` is the reference camera itself (identity pose). Returns the
    points [N, 3]; NaN where the reference view or every other view is missing, the baseline
    is along the ray, or the point is at or beyond infinity (``rho <= 0``).
    """
    uv, T_cam_ref, valid = _check_views(uv_px, T_ref_cams)
    N, n_f = valid.shape
    ref = ref_view % n_f if n_f else 0
    if n_f == 0 or not np.allclose(T_cam_ref[ref], np.eye(4), atol=1e-9):
        raise ValueError("triangulate_on_ray: the reference view's pose must be the identity")
    x = (uv[..., 0] - camera.cx_px) / camera.fx_px  # [N, F] (NaN where unseen)
    y = (uv[..., 1] - camera.cy_px) / camera.fy_px
    a, b = x[:, ref], y[:, ref]
    R, t = T_cam_ref[:, :3, :3], T_cam_ref[:, :3, 3]  # [F, 3, 3], [F, 3]
    m = a[:, None, None] * R[None, :, :, 0] + b[:, None, None] * R[None, :, :, 1] + R[None, :, :, 2]
    use = valid.copy()
    use[:, ref] = False
    cx = np.where(use, x * t[None, :, 2] - t[None, :, 0], 0.0)
    cy = np.where(use, y * t[None, :, 2] - t[None, :, 1], 0.0)
    dx = np.where(use, m[..., 0] - x * m[..., 2], 0.0)
    dy = np.where(use, m[..., 1] - y * m[..., 2], 0.0)
    den = (cx * cx + cy * cy).sum(axis=1)
    num = (cx * dx + cy * dy).sum(axis=1)
    scale = np.abs(t).max() if len(t) else 0.0  # a baseline along the ray gives den ~ 0
    ok = valid[:, ref] & use.any(axis=1) & (den > 1e-18 * max(scale, 1e-12) ** 2)
    rho = np.where(ok, num / np.where(ok, den, 1.0), np.nan)
    ok &= rho > 0
    rs = np.where(ok, rho, 1.0)
    out = np.stack([a / rs, b / rs, 1.0 / rs], axis=1)
    out[~ok] = np.nan
    return out


def refine_points(
    uv_px: NDArray,
    T_ref_cams: NDArray,
    camera: PinholeCamera,
    xyz_ref_init_m: NDArray,
    params: RefineParams = RefineParams(),
) -> RefinedPoints:
    """Gauss-Newton refinement of the reprojection error (paper IV-A), vectorised over points.

    Parameters per point: ``(a, b, rho)`` with the point ``(a, b, 1) / rho`` in the reference
    frame (inverse depth along a ray), so that a view's projection is that of
    ``R_cam_ref (a, b, 1) + t_cam_ref rho``: finite as ``rho -> 0``. ``uv_px`` [N, F, 2] (NaN:
    unseen) and ``T_ref_cams`` [F, 4, 4] as in :func:`triangulate_dlt`; ``xyz_ref_init_m`` [N, 3]
    the start (NaN or ``z <= 0``: the point comes back NaN). The covariance is
    ``s^2 (J^T J)^-1`` with ``s = max(params.pixel_sigma_px, RMS residual)``, mapped to ``xyz``.
    """
    uv, T_cam_ref, valid = _check_views(uv_px, T_ref_cams)
    X0 = check_array("xyz_ref_init_m", xyz_ref_init_m, shape=(len(uv), 3)).astype(np.float64)
    N, n_f = uv.shape[:2]
    usable = np.all(np.isfinite(X0), axis=1) & (X0[:, 2] > 0) & (valid.sum(axis=1) >= 2)
    z0 = np.where(usable, X0[:, 2], 1.0)
    theta = np.stack([X0[:, 0] / z0, X0[:, 1] / z0, 1.0 / z0], axis=1)  # [N, 3]
    theta[~usable] = (0.0, 0.0, 1.0)
    R, t = T_cam_ref[:, :3, :3], T_cam_ref[:, :3, 3]  # [F, 3, 3], [F, 3]
    obs = np.where(valid[..., None], uv, 0.0)
    f = np.array([camera.fx_px, camera.fy_px])
    c = np.array([camera.cx_px, camera.cy_px])
    W = valid.astype(np.float64)

    M = np.concatenate([R[:, :, :2], t[:, :, None]], axis=2)  # [F, 3, 3]: dq / d(a, b, rho)
    q0 = R[:, :, 2][None]  # [1, F, 3]

    def linearise(th: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        q = np.tensordot(th, M, axes=([1], [2])) + q0  # [N, F, 3] (one BLAS product)
        qz = np.where(np.abs(q[..., 2]) > 1e-12, q[..., 2], 1e-12)
        xy = q[..., :2] / qz[..., None]  # [N, F, 2]
        r = (f * xy + c - obs) * W[..., None]  # [N, F, 2]
        J = (f[:, None] * (W / qz)[..., None, None]) * (
            M[None, :, :2, :] - xy[..., None] * M[None, :, 2:3, :]
        )  # [N, F, 2, 3]
        return r.reshape(N, 2 * n_f), J.reshape(N, 2 * n_f, 3), q[..., 2]

    for _ in range(params.iterations):
        r, J, _ = linearise(theta)
        Jt = np.swapaxes(J, 1, 2)
        H = Jt @ J
        g = (Jt @ r[..., None])[..., 0]
        H += np.eye(3) * (1e-9 + 1e-6 * np.trace(H, axis1=1, axis2=2))[:, None, None]
        step = -np.linalg.solve(H, g[..., None])[..., 0]
        theta = theta + np.where(np.all(np.isfinite(step), axis=1, keepdims=True), step, 0.0)
    r, J, qz = linearise(theta)
    r2 = r.reshape(N, n_f, 2)
    err = np.sqrt(r2[..., 0] ** 2 + r2[..., 1] ** 2)  # [N, F]
    n_views = valid.sum(axis=1)
    rms = np.sqrt((err**2).sum(axis=1) / np.maximum(n_views, 1))
    H = np.swapaxes(J, 1, 2) @ J
    H += np.eye(3) * (1e-12 + 1e-9 * np.trace(H, axis1=1, axis2=2))[:, None, None]
    s = np.maximum(params.pixel_sigma_px, rms)
    cov_theta = _inv3(H) * (s**2)[:, None, None]
    a, b, rho = theta.T
    rho_ok = rho > 1e-12
    rs = np.where(rho_ok, rho, 1.0)
    xyz = np.stack([a / rs, b / rs, 1.0 / rs], axis=1)
    D = np.zeros((N, 3, 3))  # d xyz / d (a, b, rho)
    D[:, 0, 0] = D[:, 1, 1] = 1.0 / rs
    D[:, :, 2] = -xyz / rs[:, None]
    cov = D @ cov_theta @ np.swapaxes(D, 1, 2)
    centres = se3_inverse(T_cam_ref)[:, :3, 3]  # [F, 3] view centres in the reference frame
    rays = xyz[:, None, :] - centres[None]  # [N, F, 3]
    ray_len = np.sqrt((rays * rays).sum(axis=2))  # [N, F]
    cosang = (rays @ xyz[:, :, None])[..., 0] / np.maximum(
        ray_len * np.sqrt((xyz * xyz).sum(axis=1))[:, None], 1e-300
    )
    # the largest angle is the smallest cosine: one arccos per point, not per view
    min_cos = np.where(valid, cosang, 1.0).min(axis=1) if n_f else np.ones(N)
    parallax = np.degrees(np.arccos(np.clip(min_cos, -1.0, 1.0)))
    in_front = np.all((qz > 0) | ~valid, axis=1) & rho_ok
    bad = ~usable | ~np.all(np.isfinite(xyz), axis=1)
    xyz[bad] = np.nan
    cov[bad] = np.nan
    return RefinedPoints(
        xyz_ref_m=xyz,
        cov_ref_m2=cov,
        depth_sigma_m=np.sqrt(np.maximum(cov[:, 2, 2], 0.0)),
        reproj_max_px=np.where(bad, np.inf, np.where(valid, err, 0.0).max(axis=1)),
        reproj_rms_px=np.where(bad, np.inf, rms),
        parallax_deg=np.where(bad, 0.0, parallax),
        n_views=n_views.astype(np.int64),
        in_front=in_front & ~bad,
    )


def _inv3(A: NDArray) -> NDArray[np.float64]:
    """Inverses of a stack of 3x3 matrices [N, 3, 3] by the adjugate (a batched LAPACK inverse
    costs ~6x more at N ~ 1000); a singular matrix gives inf / NaN entries."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    C = np.empty_like(A, dtype=np.float64)
    C[:, 0, 0], C[:, 0, 1], C[:, 0, 2] = e * i - f * h, c * h - b * i, b * f - c * e
    C[:, 1, 0], C[:, 1, 1], C[:, 1, 2] = f * g - d * i, a * i - c * g, c * d - a * f
    C[:, 2, 0], C[:, 2, 1], C[:, 2, 2] = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * C[:, 0, 0] + b * C[:, 1, 0] + c * C[:, 2, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return C / det[:, None, None]
