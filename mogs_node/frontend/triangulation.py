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

__all__ = ["RefineParams", "RefinedPoints", "refine_points", "triangulate_dlt"]


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
    err = np.linalg.norm(r.reshape(N, n_f, 2), axis=2)  # [N, F]
    n_views = valid.sum(axis=1)
    rms = np.sqrt((err**2).sum(axis=1) / np.maximum(n_views, 1))
    H = np.swapaxes(J, 1, 2) @ J
    H += np.eye(3) * (1e-12 + 1e-9 * np.trace(H, axis1=1, axis2=2))[:, None, None]
    s = np.maximum(params.pixel_sigma_px, rms)
    cov_theta = np.linalg.inv(H) * (s**2)[:, None, None]
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
    cosang = (rays @ xyz[:, :, None])[..., 0] / np.maximum(
        np.linalg.norm(rays, axis=2) * np.linalg.norm(xyz, axis=1)[:, None], 1e-300
    )
    parallax = np.degrees(np.arccos(np.clip(np.where(valid, cosang, 1.0), -1.0, 1.0))).max(axis=1)
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
