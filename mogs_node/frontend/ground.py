"""Metric translation from the road plane (beyond the paper: docs/frontend.md, "Round 5").

A car-mounted camera sees the road at a known height ``h`` (a vehicle calibration, like the
camera-IMU extrinsics). Between two frames the road maps by the plane homography
``H = K (R + tau u n^T) K^-1`` (``X_cur = R X_prev + t``, ``t = tau h u``, road ``n . X_prev = h``),
so aligning the road patch of the previous image onto the current one gives ``tau = |t| / h``, a
metric translation, from every road pixel at once. The rotation ``R`` and the direction ``u`` come
from the visual-inertial estimate, which knows them well; what it does not know on a cruising drive
is the scale (round 3). The road normal is kept perpendicular to the motion (a car moves along the
road); only its roll about the motion is estimated (the pitch and the scale trade off within one
frame pair). Pure: images and geometry in, one measurement out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.geometry import check_array

__all__ = [
    "GroundMeasurement",
    "GroundParams",
    "estimate_ground_translation",
    "road_height_of_points",
    "road_normal_from_mount",
    "road_scale_of_sfm",
]


@dataclass(frozen=True)
class GroundParams:
    """Parameters of the road-plane translation measurement."""

    camera_height_m: float = 0.0  # camera centre above the road; 0 turns the measurement off
    min_depth_m: float = 3.0  # road pixels used: between these distances (along the road normal
    max_depth_m: float = 25.0  # ray): far road has too little parallax, near road leaves the image
    lane_half_width_m: float = 2.0  # only road within this lateral distance of the camera: the
    # lane ahead (wider, parked cars and kerbs bias tau by +1.5 %; docs/frontend.md round 5)
    column_margin: float = 0.0  # share of the image width left out on each side
    min_change: float = 3.0  # use only road pixels that change by more than this (grey levels)
    # between the frames after the rotation alone: a vehicle ahead driving at our speed, and its
    # shadow, look static and would pull tau to 0 (real KITTI traffic, docs/frontend.md round 5)
    max_roll_deg: float = 1.0  # bound of the road normal's roll about the motion (from the guess)
    max_pixels: int = 6000  # road pixels per pyramid level (a regular subsample beyond this)
    levels: int = 3  # pyramid levels (coarse to fine)
    iterations: int = 4  # Gauss-Newton iterations per level
    search_span: float = 2.0  # coarse grid search over tau in [init / span, init * span]
    gate_rel: float = 0.15  # while tracking, reject a measurement whose ratio to the window's
    gate_window: int = 15  # distance is this far from the median ratio of the last gate_window
    max_ratio: float = 2.0  # while tracking, a measurement more than this factor from the
    # window's own (metric: IMU or road-initialised) distance is not road: a near object covering
    # the lane (the demo drive's start: 4-8x) moves like a much faster road; it is neither used nor
    # kept for the gate, whose median the first measurements would otherwise set (issue h16r)
    max_spread: float = 0.1  # initialisation: the SfM window's per-step scales must agree (MAD)
    relative_sigma: float = 0.03  # noise of one measurement relative to the distance (the robust
    # std measured on the sim: 1.4826 x 1.6 % MAD = 2.4 %; docs/frontend.md round 5)
    max_sigma_rel: float = 0.05  # reject when the alignment's own 1-sigma of tau exceeds this
    # (textureless or washed-out road: the Gauss-Newton step would leave the guess unchanged)
    max_residual: float = 12.0  # mean absolute photometric residual (grey levels) to accept
    min_pixels: int = 400  # valid road pixels at the finest level to accept
    sfm_search_span: float = 4.0  # initialisation (road_scale_of_sfm): search_span of each step
    sfm_min_share: float = 0.5  # ... and the share of the steps that must give a measurement

    def __post_init__(self) -> None:
        if not np.isfinite(self.camera_height_m) or self.camera_height_m < 0:
            raise ConfigError("ground.camera_height_m: must be finite and >= 0 (0: off)")
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError("ground: 0 < min_depth_m < max_depth_m")
        if not 0 <= self.column_margin < 0.5 or self.levels < 1 or self.iterations < 1:
            raise ConfigError("ground: 0 <= column_margin < 0.5, levels >= 1, iterations >= 1")
        if not self.lane_half_width_m > 0:
            raise ConfigError("ground.lane_half_width_m: must be > 0")
        if self.gate_rel <= 0 or self.gate_window < 1 or self.max_spread <= 0:
            raise ConfigError("ground: gate_rel > 0, gate_window >= 1, max_spread > 0")
        if not self.max_ratio > 1:
            raise ConfigError(f"ground.max_ratio: must be > 1, got {self.max_ratio}")
        if self.search_span < 1 or self.relative_sigma <= 0 or self.max_pixels < 100:
            raise ConfigError("ground: search_span >= 1, relative_sigma > 0, max_pixels >= 100")
        if self.sfm_search_span < 1 or not 0 < self.sfm_min_share <= 1:
            raise ConfigError("ground: sfm_search_span >= 1, 0 < sfm_min_share <= 1")

    @property
    def enabled(self) -> bool:
        return self.camera_height_m > 0


@dataclass(frozen=True)
class GroundMeasurement:
    """Translation between two frames measured on the road."""

    tau: float  # |t| / camera height
    distance_m: float  # |t|: distance between the two camera centres
    normal_cam: NDArray[np.float64]  # [3] road normal in the previous camera frame (towards it)
    residual: float  # mean absolute photometric residual at the solution (grey levels)
    sigma_rel: float  # the alignment's own 1-sigma of tau, relative
    n_pixels: int  # valid road pixels at the finest level


def road_normal_from_mount(T_imu_cam: NDArray) -> NDArray[np.float64]:
    """Road normal (pointing down to the road) in the camera frame for an IMU mounted level with
    the road, z up: the starting guess before the roll is estimated."""
    T = check_array("T_imu_cam", T_imu_cam, shape=(4, 4), finite=True)
    return T[:3, :3].T @ np.array([0.0, 0.0, -1.0])


def sample_at(img: NDArray[np.float32], qx: NDArray, qy: NDArray) -> NDArray[np.float32]:
    """Bilinear samples of ``img`` at float pixel coordinates; -1 outside the image."""
    return cv2.remap(
        img,
        np.asarray(qx, np.float32)[None],
        np.asarray(qy, np.float32)[None],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=-1.0,
    )[0]


def _pyramid(img: NDArray[np.float32], levels: int) -> list[NDArray[np.float32]]:
    out = [img]
    for _ in range(levels - 1):
        out.append(cv2.pyrDown(out[-1]))
    return out


def _level_K(K: NDArray, s: float) -> NDArray[np.float64]:
    Kl = K.astype(np.float64).copy()
    Kl[:2, :2] *= s
    Kl[:2, 2] = (K[:2, 2] + 0.5) * s - 0.5
    return Kl


def _road_pixels(
    shape: tuple[int, int], Kl: NDArray, n: NDArray, h: float, p: GroundParams
) -> NDArray[np.float64]:
    """Normalised rays [3, M] (z = 1) of the road pixels of the lane ahead between the depth
    bounds, on a regular grid coarse enough to keep about ``max_pixels``."""
    H, W = shape
    x0, x1 = int(p.column_margin * W), int(np.ceil((1 - p.column_margin) * W))
    step = max(1, int(np.sqrt((H - 4) * (x1 - x0) / (16.0 * p.max_pixels))))
    xn = (np.arange(x0, x1, step, dtype=np.float64) - Kl[0, 2]) / Kl[0, 0]
    yn = (np.arange(2, H - 2, step, dtype=np.float64) - Kl[1, 2]) / Kl[1, 1]
    nr = n[0] * xn[None, :] + n[1] * yn[:, None] + n[2]  # depth along the axis is h / (n . r)
    keep = (nr >= h / p.max_depth_m) & (nr <= h / p.min_depth_m)
    keep &= np.abs(xn)[None, :] * h <= p.lane_half_width_m * nr  # lateral offset h x / (n . r)
    iy, ix = np.nonzero(keep)
    if len(iy) > p.max_pixels:
        sel = slice(None, None, int(np.ceil(len(iy) / p.max_pixels)))
        iy, ix = iy[sel], ix[sel]
    return np.stack([xn[ix], yn[iy], np.ones(len(ix))])


Warp = Callable[[NDArray], tuple[NDArray, NDArray]]


def _search_log_tau(warp: Warp, I1: NDArray, ref: NDArray, p: NDArray, span: float) -> float:
    """The ``log tau`` of 25 on a grid over ``p[0] +- log(span)`` with the least photometric error."""
    best = (np.inf, p[0])
    for lt in p[0] + np.linspace(-np.log(span), np.log(span), 25):
        qx, qy = warp(np.array([lt, p[1]]))
        v = sample_at(I1, qx, qy)
        ok = v >= 0
        if ok.sum() > 0.3 * len(v):
            c = float(np.mean(np.abs(v[ok] - ref[ok])))
            if c < best[0]:
                best = (c, lt)
    return best[1]


def _align_level(
    warp: Warp, I1: NDArray, ref: NDArray, p: NDArray, iterations: int, max_roll: float
) -> tuple[NDArray, float, int, float] | None:
    """Robust (Huber) Gauss-Newton on ``(log tau, roll)`` at one pyramid level: the parameters,
    the mean absolute residual, the pixels used and the 1-sigma of ``log tau``; None with fewer
    than 50 pixels in view."""
    gx = cv2.Sobel(I1, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(I1, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    res_mean, n_valid, sigma_rel = np.inf, 0, np.inf
    for _ in range(iterations):
        qx, qy = warp(p)
        v = sample_at(I1, qx, qy)
        ok = (v >= 0) & (qx >= 0) & (qy >= 0)
        n_valid = int(ok.sum())
        if n_valid < 50:
            return None
        res = (v - ref)[ok]
        J = np.empty((n_valid, 2))
        gxs, gys = sample_at(gx, qx, qy)[ok], sample_at(gy, qx, qy)[ok]
        for k, eps in ((0, 1e-4), (1, 1e-4)):
            dp = np.zeros(2)
            dp[k] = eps
            ax, ay = warp(p + dp)
            J[:, k] = (gxs * (ax[ok] - qx[ok]) + gys * (ay[ok] - qy[ok])) / eps
        scale = 1.4826 * float(np.median(np.abs(res))) + 1e-3
        w = np.minimum(1.0, 1.345 * scale / np.maximum(np.abs(res), 1e-9))
        A = J.T @ (J * w[:, None]) + np.diag([1e-9, 1e-3 * n_valid])
        step = -np.linalg.solve(A, J.T @ (w * res))
        step[0] = np.clip(step[0], -0.3, 0.3)
        step[1] = np.clip(step[1], -0.02, 0.02)
        p = p + step
        p[1] = np.clip(p[1], -max_roll, max_roll)
        res_mean = float(np.mean(np.abs(res)))
        # 1-sigma of log(tau) from the robust residual scale and the information of tau
        sigma_rel = scale / np.sqrt(max(float(A[0, 0]), 1e-30))
        if np.max(np.abs(step)) < 1e-4:
            break
    return p, res_mean, n_valid, sigma_rel


def estimate_ground_translation(
    gray_prev: NDArray,
    gray_cur: NDArray,
    K: NDArray,
    R_cur_prev: NDArray,
    t_dir_cur_prev: NDArray,
    normal_prev: NDArray,
    tau_init: float,
    params: GroundParams,
    *,
    search: bool = False,
) -> GroundMeasurement | None:
    """Align the road of ``gray_prev`` onto ``gray_cur`` by the plane homography: ``tau`` and the
    roll of the road normal about the motion, robust Gauss-Newton coarse to fine.

    ``R_cur_prev``, ``t_dir_cur_prev``: rotation and translation direction taking previous-camera
    points into the current camera frame (from the VI estimate); ``normal_prev``: a guess of the
    road normal in the previous camera frame (pointing to the road); ``tau_init``: a guess of
    ``|t| / h``. ``search``: start with a grid over ``tau`` (when the guess may be far off, e.g. the
    initialisation's). None when the road is not usable (too few pixels, no convergence, large
    residual). Images are single-channel of the same size.
    """
    if not params.enabled:
        raise ConfigError("ground.camera_height_m: 0, the road measurement is off")
    g0 = np.asarray(gray_prev, np.float32)
    g1 = np.asarray(gray_cur, np.float32)
    if g0.ndim != 2 or g0.shape != g1.shape:
        raise ConfigError(
            f"gray images: need two 2-D images of one size, got {g0.shape} {g1.shape}"
        )
    R = check_array("R_cur_prev", R_cur_prev, shape=(3, 3), finite=True).astype(np.float64)
    u = check_array("t_dir_cur_prev", t_dir_cur_prev, shape=(3,), finite=True).astype(np.float64)
    n_in = check_array("normal_prev", normal_prev, shape=(3,), finite=True).astype(np.float64)
    if not (np.isfinite(tau_init) and tau_init > 0):
        return None
    nu = np.linalg.norm(u)
    if nu < 1e-9:
        return None
    u = u / nu
    d = -R.T @ u  # direction of the camera's displacement in the previous frame
    n0 = n_in - (n_in @ d) * d  # the road is parallel to the motion
    if np.linalg.norm(n0) < 0.5:  # motion along the normal: not a car on a road
        return None
    n0 /= np.linalg.norm(n0)
    e_roll = np.cross(d, n0)
    e_roll /= np.linalg.norm(e_roll)
    h = params.camera_height_m

    def normal(theta: float) -> NDArray[np.float64]:
        return np.cos(theta) * n0 + np.sin(theta) * e_roll

    p = np.array([np.log(tau_init), 0.0])
    max_roll = np.radians(params.max_roll_deg)
    pyr0, pyr1 = _pyramid(g0, params.levels), _pyramid(g1, params.levels)
    res_mean, n_valid, sigma_rel = np.inf, 0, np.inf
    for lev in range(params.levels - 1, -1, -1):
        I0, I1 = pyr0[lev], pyr1[lev]
        Kl = _level_K(np.asarray(K, np.float64), 0.5**lev)
        r = _road_pixels(I0.shape, Kl, n0, h, params)
        if r.shape[1] < 50:
            return None
        px0 = Kl @ r
        ref = cv2.remap(
            I0,
            px0[0].astype(np.float32)[None],
            px0[1].astype(np.float32)[None],
            cv2.INTER_LINEAR,
        )[0]
        q_rot = Kl @ (R @ r)
        static = sample_at(I1, q_rot[0] / q_rot[2], q_rot[1] / q_rot[2])
        moving = np.abs(static - ref) > params.min_change
        if moving.sum() < 50:
            return None
        r, ref = r[:, moving], ref[moving]

        def warp(pp: NDArray, _Kl=Kl, _r=r) -> tuple[NDArray, NDArray]:
            q = _Kl @ ((R + np.exp(pp[0]) * np.outer(u, normal(pp[1]))) @ _r)
            w = np.where(np.abs(q[2]) > 1e-9, q[2], 1e-9)
            return q[0] / w, q[1] / w

        if search and lev == params.levels - 1:
            p[0] = _search_log_tau(warp, I1, ref, p, params.search_span)
        fit = _align_level(warp, I1, ref, p, params.iterations, max_roll)
        if fit is None:
            return None
        p, res_mean, n_valid, sigma_rel = fit
    if (
        not np.all(np.isfinite(p))
        or n_valid < params.min_pixels
        or res_mean > params.max_residual
        or sigma_rel > params.max_sigma_rel
    ):
        return None
    tau = float(np.exp(p[0]))
    return GroundMeasurement(tau, tau * h, normal(float(p[1])), res_mean, sigma_rel, n_valid)


def road_scale_of_sfm(
    grays: list[NDArray],
    T_c0_ci: NDArray,
    K: NDArray,
    normal_cam: NDArray,
    params: GroundParams,
    step_guess_m: NDArray,
) -> float | None:
    """Metric scale of an up-to-scale visual SfM window (the dynamic initialisation's) from the
    road: the median over consecutive frames of measured / SfM step length.

    ``grays`` [F] images, ``T_c0_ci`` [F, 4, 4] SfM camera poses, ``normal_cam`` a road normal guess
    in the camera frame (fixed to the car, so the same in every frame), ``step_guess_m`` [F - 1] a guess of each metric step (searched
    within ``params.sfm_search_span`` either way). None when fewer than ``params.sfm_min_share``
    of the steps give a measurement."""
    T = check_array("T_c0_ci", T_c0_ci, shape=(len(grays), 4, 4), finite=True)
    steps = check_array("step_guess_m", step_guess_m, shape=(len(grays) - 1,))
    if len(grays) < 2:
        return None
    p = replace(params, search_span=params.sfm_search_span)
    ratios = []
    for k in range(len(grays) - 1):
        T_cur_prev = np.linalg.inv(T[k + 1]) @ T[k]
        t = T_cur_prev[:3, 3]
        sfm_step = float(np.linalg.norm(t))
        if sfm_step < 1e-9 or not (np.isfinite(steps[k]) and steps[k] > 0):
            continue
        m = estimate_ground_translation(
            grays[k],
            grays[k + 1],
            K,
            T_cur_prev[:3, :3],
            t,
            normal_cam,
            float(steps[k]) / params.camera_height_m,
            p,
            search=True,
        )
        if m is not None:
            ratios.append(m.distance_m / sfm_step)
    if len(ratios) < max(1, params.sfm_min_share * (len(grays) - 1)):
        return None
    med = float(np.median(ratios))
    if np.median(np.abs(np.asarray(ratios) / med - 1)) > params.max_spread:
        return None  # the steps disagree: something else than the road moved in the lane
    return med


def road_height_of_points(
    xyz_cam: NDArray,
    normal_cam: NDArray,
    *,
    lane: tuple[float, float] = (2.5, 18.0),
    window: float = 0.1,
    min_points: int = 5,
) -> tuple[float, int] | None:
    """Height of the road below the camera from triangulated points [N, 3] (camera frame) in their
    own units, and the number of points it rests on. The points below the camera in the lane
    ahead are selected scale-free (an up-to-scale reconstruction's units are unknown): lateral
    offset <= ``lane[0]`` x height (4 m at 1.65 m), ahead <= ``lane[1]`` x height (30 m).
    The road is their densest height: the median of the most populated interval of heights
    (along ``normal_cam``, pointing to the road) within ``+-window`` (relative), the higher one on
    a tie. Vehicles' and kerbs' points spread over heights above it; points of a vehicle moving
    ahead triangulate too far, i.e. below it (a high quantile took those: docs/frontend.md,
    round 12). The calibrated height over this one is the reconstruction's scale. None with
    fewer than ``min_points`` selected points."""
    X = check_array("xyz_cam", xyz_cam, shape=(None, 3)).astype(np.float64)
    n = check_array("normal_cam", normal_cam, shape=(3,), finite=True).astype(np.float64)
    max_lateral, max_ahead = lane
    if not 0 < window < 1 or min_points < 1 or max_lateral <= 0 or max_ahead <= 0:
        raise ConfigError("road points: 0 < window < 1, min_points >= 1, bounds > 0")
    nn = float(np.linalg.norm(n))
    if nn < 1e-9:
        raise ConfigError("road points: normal_cam must be non-zero")
    n = n / nn
    fwd = np.array([0.0, 0.0, 1.0]) - n * n[2]  # the view along the road
    if np.linalg.norm(fwd) < 1e-6:
        raise ConfigError(
            "road points: normal along the optical axis: the camera looks at the road"
        )
    fwd /= np.linalg.norm(fwd)
    X = X[np.all(np.isfinite(X), axis=1)]
    h, ahead, lateral = X @ n, X @ fwd, np.abs(X @ np.cross(n, fwd))
    keep = (h > 0) & (ahead > 0) & (lateral <= max_lateral * h) & (ahead <= max_ahead * h)
    if int(keep.sum()) < min_points:
        return None
    lh = np.sort(np.log(h[keep]))
    w = np.log1p(window)
    lo = np.searchsorted(lh, lh - w, side="left")
    hi = np.searchsorted(lh, lh + w, side="right")
    count = hi - lo
    best = int(np.flatnonzero(count == count.max())[-1])  # the highest of the densest
    return float(np.exp(np.median(lh[lo[best] : hi[best]]))), int(keep.sum())
