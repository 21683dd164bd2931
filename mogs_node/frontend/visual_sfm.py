"""Up-to-scale structure from motion over a short window (VINS-Mono's initial SfM): the
visual half of dynamic initialisation (:mod:`.initialization`)."""

from __future__ import annotations

import logging

import cv2
import gtsam
import numpy as np
from numpy.typing import NDArray

from mogs_node.geometry import PinholeCamera, make_T, se3_inverse

__all__ = ["visual_sfm"]

log = logging.getLogger(__name__)


def _common(
    frames: list[tuple[NDArray, NDArray]], i: int, j: int
) -> tuple[NDArray, NDArray, NDArray]:
    ids_i, uv_i = frames[i]
    ids_j, uv_j = frames[j]
    common, a, b = np.intersect1d(ids_i, ids_j, assume_unique=True, return_indices=True)
    return common, uv_i[a], uv_j[b]


def _triangulate(
    K: NDArray, T_c0_a: NDArray, T_c0_b: NDArray, ua: NDArray, ub: NDArray, min_angle_deg: float
) -> tuple[NDArray, NDArray]:
    """Points [N, 3] (c0 frame) from two posed views and a validity mask [N]."""
    Pa = K @ se3_inverse(T_c0_a)[:3]
    Pb = K @ se3_inverse(T_c0_b)[:3]
    Xh = cv2.triangulatePoints(Pa, Pb, ua.T.astype(float), ub.T.astype(float))
    with np.errstate(divide="ignore", invalid="ignore"):
        pts = (Xh[:3] / Xh[3]).T
    ok = np.all(np.isfinite(pts), axis=1)
    pts = np.where(ok[:, None], pts, 0.0)
    ra, rb = pts - T_c0_a[:3, 3], pts - T_c0_b[:3, 3]
    za = ra @ T_c0_a[:3, 2]
    zb = rb @ T_c0_b[:3, 2]
    cos = np.einsum("ij,ij->i", ra, rb) / np.maximum(
        np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12
    )
    ok &= (za > 0) & (zb > 0) & (np.degrees(np.arccos(np.clip(cos, -1, 1))) >= min_angle_deg)
    return pts, ok


def visual_sfm(
    frames: list[tuple[NDArray, NDArray]],
    camera: PinholeCamera,
    min_features: int = 30,
    min_parallax_px: float = 15.0,
) -> NDArray[np.float64] | None:
    """Up-to-scale camera poses ``T_c0_ci`` [F, 4, 4] of a short window of frames (VINS-Mono's
    initial SfM, incremental because tracks are short in forward driving).

    ``frames``: per frame (track ids [N] int64, undistorted pixels [N, 2]). The first frame ``j``
    with enough parallax to frame 0 fixes the scale (unit baseline) through the 5-point essential
    matrix (RANSAC); every other frame is registered by PnP on the points triangulated so far, and
    new points are triangulated against the previous frame. None when the geometry is degenerate.
    """
    K = camera.K
    F = len(frames)
    j = None
    for k in range(1, F):
        common, u0, uk = _common(frames, 0, k)
        if len(common) < min_features:
            break
        if np.mean(np.linalg.norm(u0 - uk, axis=1)) >= min_parallax_px:
            j = k
            break
    if j is None:
        return None
    common, u0, u1 = _common(frames, 0, j)
    E, inl = cv2.findEssentialMat(u0, u1, K, cv2.RANSAC, 0.999, 1.0)
    if E is None or E.shape != (3, 3):
        return None
    n, R, t, inl = cv2.recoverPose(E, u0, u1, K, mask=inl)
    if n < min_features // 2:
        return None
    T = np.full((F, 4, 4), np.nan)
    T[0] = np.eye(4)
    T[j] = se3_inverse(make_T(R, t.ravel()))
    good = inl.ravel() > 0
    pts, ok = _triangulate(K, T[0], T[j], u0[good], u1[good], 0.5)
    map_ids, map_pts = common[good][ok], pts[ok]
    if len(map_ids) < min_features // 2:
        return None
    for k in [*range(1, j), *range(j + 1, F)]:
        ids_k, uv_k = frames[k]
        _, a, b = np.intersect1d(map_ids, ids_k, assume_unique=True, return_indices=True)
        if len(a) < 10:
            return None
        ok_p, rvec, tvec, inl_p = cv2.solvePnPRansac(
            map_pts[a],
            uv_k[b].astype(float),
            K,
            None,
            reprojectionError=2.0,
            iterationsCount=100,
            flags=cv2.SOLVEPNP_EPNP,
        )
        if not ok_p or inl_p is None or len(inl_p) < 8:
            return None
        inl_p = inl_p.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(
            map_pts[a][inl_p], uv_k[b][inl_p].astype(float), K, None, rvec, tvec
        )
        Rc, _ = cv2.Rodrigues(rvec)
        T[k] = se3_inverse(make_T(Rc, tvec.ravel()))
        if k > j:  # grow the map with tracks new since the scale-fixing pair
            common, up, uk = _common(frames, k - 1, k)
            new = ~np.isin(common, map_ids)
            if np.any(new):
                pts, ok = _triangulate(K, T[k - 1], T[k], up[new], uk[new], 0.5)
                map_ids = np.concatenate([map_ids, common[new][ok]])
                map_pts = np.concatenate([map_pts, pts[ok]])
                order = np.argsort(map_ids)
                map_ids, map_pts = map_ids[order], map_pts[order]
    return _bundle_adjust(frames, K, T, map_ids, map_pts, j)


def _bundle_adjust(
    frames: list[tuple[NDArray, NDArray]],
    K: NDArray,
    T: NDArray,
    map_ids: NDArray,
    map_pts: NDArray,
    j: int,
    iterations: int = 20,
) -> NDArray:
    """Refine the SfM poses [F, 4, 4] and points by bundle adjustment (Huber loss, GTSAM). The
    gauge is fixed by the first pose and a soft prior on the position of frame ``j`` (unit
    baseline; a hard one would freeze the essential matrix's translation error)."""
    cal = gtsam.Cal3_S2(K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2])
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.345), gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    )
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, Tk in enumerate(T):
        values.insert(gtsam.symbol("x", k), gtsam.Pose3(Tk))
    for n, p in enumerate(map_pts):
        values.insert(gtsam.symbol("l", n), gtsam.Point3(*p))
    for k, (ids_k, uv_k) in enumerate(frames):
        _, a, b = np.intersect1d(map_ids, ids_k, assume_unique=True, return_indices=True)
        for n, m in zip(a.tolist(), uv_k[b], strict=True):
            graph.add(
                gtsam.GenericProjectionFactorCal3_S2(
                    m, noise, gtsam.symbol("x", k), gtsam.symbol("l", n), cal
                )
            )
    graph.add(
        gtsam.PriorFactorPose3(
            gtsam.symbol("x", 0), gtsam.Pose3(T[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
        )
    )
    graph.add(
        gtsam.PriorFactorPose3(
            gtsam.symbol("x", j),
            gtsam.Pose3(T[j]),
            gtsam.noiseModel.Diagonal.Sigmas(np.r_[[10.0] * 3, [0.05] * 3]),
        )
    )
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(iterations)
    try:
        out = gtsam.LevenbergMarquardtOptimizer(graph, values, lm).optimize()
    except RuntimeError as err:
        log.debug("SfM bundle adjustment failed: %s", err)
        return T
    return np.stack([out.atPose3(gtsam.symbol("x", k)).matrix() for k in range(len(T))])
