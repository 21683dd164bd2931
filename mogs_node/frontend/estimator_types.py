"""Value types and variable keys of the sliding-window estimator (:mod:`.estimator`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError, MogsError

__all__ = [
    "B",
    "EstimatorDivergedError",
    "EstimatorParams",
    "EstimatorState",
    "L",
    "LandmarkView",
    "V",
    "WindowFrame",
    "X",
    "depth_in_range",
    "lookup",
    "outlier_gate_px",
    "sorted_map",
]


def X(k: int) -> int:
    return gtsam.symbol("x", k)


def V(k: int) -> int:
    return gtsam.symbol("v", k)


def B(k: int) -> int:
    return gtsam.symbol("b", k)


def L(i: int) -> int:
    return gtsam.symbol("l", i)


def sorted_map(d: dict[int, int]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    k = np.fromiter(d.keys(), np.int64, len(d))
    v = np.fromiter(d.values(), np.int64, len(d))
    o = np.argsort(k)
    return k[o], v[o]


def lookup(keys: NDArray, vals: NDArray, q: NDArray, default: int) -> NDArray[np.int64]:
    """``vals`` at ``q`` in the sorted ``keys`` (``default`` where absent), vectorised."""
    if len(keys) == 0:
        return np.full(len(q), default, np.int64)
    i = np.minimum(np.searchsorted(keys, q), len(keys) - 1)
    return np.where(keys[i] == q, vals[i], default)


def depth_in_range(T_world_cam: NDArray, pts: NDArray, lo_m: float, hi_m: float) -> NDArray:
    """Whether each point ``pts`` [N, 3] (NaN read as 0) has a depth in (``lo_m``, ``hi_m``) in
    the camera ``T_world_cam`` ([1, 4, 4] for all points, or [N, 4, 4], one per point)."""
    Rt = np.swapaxes(T_world_cam[..., :3, :3], -1, -2)
    z = np.einsum(
        "nij,nj->ni",
        np.broadcast_to(Rt, (len(pts), 3, 3)),
        np.nan_to_num(pts) - np.broadcast_to(T_world_cam[..., :3, 3], pts.shape),
    )[:, 2]
    return (z > lo_m) & (z < hi_m)


class EstimatorDivergedError(MogsError, RuntimeError):
    """The window solve failed or left physical bounds (bias, speed); the caller must re-initialise.
    ``reason`` names the cause in one word (``solve_failed``, ``speed``, ``gyro_bias``, ...)."""

    def __init__(self, message: str, reason: str = "diverged") -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class EstimatorParams:
    """Parameters of :class:`VioEstimator`."""

    window_size: int = 8  # keyframes kept in the window (the newest frame comes on top)
    lm_iterations: int = 2  # Levenberg-Marquardt iterations per update (warm-started; 3 costs
    # ~20 % more estimation time for the same accuracy, docs/frontend.md)
    lm_lambda_initial: float = 1e-5  # LM's first damping (GTSAM's default). Below ~0.1 the
    # window's damped normal equations are near-indeterminate (low-parallax landmarks) in ~96 % of
    # tracking solves: 0.1 skips those failed eliminations (estimator CPU -25 %) but changes the
    # estimate (10 s test drive: scale error 2.4 %); docs/frontend.md, "Window solve speed"
    pixel_sigma_px: float = 4.0  # reprojection noise (undistorted px); KLT on rendered or real
    # images has heavy-tailed errors: 1 px lets vision override the IMU (jittery attitude)
    huber_k: float = 1.345  # Huber threshold in sigmas
    min_parallax_deg: float = 1.0  # triangulate only with at least this ray angle
    min_depth_m: float = 0.5  # landmark depth bounds at triangulation
    max_depth_m: float = 150.0
    outlier_reproj_px: float = 5.0  # a landmark with a larger reprojection error is removed
    outlier_reproj_rel: float | None = None  # > 0: the gate is at most this many times the
    # window's median reprojection error (never below outlier_reproj_min_px): drifting KLT tracks
    # bias the walk's scale low long before they reach a fixed gate; 0: the fixed gate. None: the
    # platform profile's (handheld 4, car and drone 0; docs/frontend.md round 11)
    outlier_reproj_min_px: float = 1.0
    marginalize_landmarks: bool = False  # Schur-complement the oldest keyframe's landmarks too
    # (True: restarts every landmark it saw; False: they stay variables, see keep_visual_prior)
    keep_visual_prior: bool | None = None  # the oldest keyframe's observations go into the
    # marginalisation prior with their landmarks kept as variables (exact Schur complement; a
    # landmark is marginalised out of the prior when it leaves the window). False: they are dropped
    # and the window's scale drifts (docs/frontend.md, "Investigation"). None: the platform
    # profile's (handheld on, car and drone off; docs/frontend.md round 10)
    visual_prior_sigma: float = 1.0  # their pixel sigma there, times pixel_sigma_px (> 1: a
    # weaker visual prior that lets the window's scale follow the IMU; docs/frontend.md round 9)
    visual_prior_min_obs: int = 4  # only landmarks seen by at least this many window frames go
    # into the prior (a fresh two-view landmark is linearised far from its converged position)
    zero_motion_sigma_m: float = 2e-3  # translation sigma of a zero-motion factor
    zero_motion_sigma_rad: float = 2e-3  # rotation sigma of a zero-motion factor
    init_rot_sigma_rad: float = 0.01  # prior on the first state (roll/pitch from gravity)
    init_pos_sigma_m: float = 0.01
    init_vel_sigma_m_s: float = 0.1
    init_gyro_bias_sigma_rad_s: float = 5e-3
    init_accel_bias_sigma_m_s2: float = 0.1
    max_gyro_bias_rad_s: float = 0.3  # failure bounds
    max_accel_bias_m_s2: float = 2.0
    max_speed_m_s: float = 80.0

    def __post_init__(self) -> None:
        if (
            self.window_size < 2
            or self.lm_iterations < 1
            or not self.lm_lambda_initial > 0
            or min(self.pixel_sigma_px, self.visual_prior_sigma) <= 0
            or (self.outlier_reproj_rel or 0.0) < 0
            or not 0 < self.outlier_reproj_min_px <= self.outlier_reproj_px
        ):
            raise ConfigError(
                "estimator: window_size >= 2, lm_iterations >= 1, lm_lambda_initial > 0, "
                "pixel_sigma_px and visual_prior_sigma > 0, outlier_reproj_rel >= 0, "
                "0 < outlier_reproj_min_px <= outlier_reproj_px"
            )


def outlier_gate_px(err_px: NDArray, params: EstimatorParams) -> float:
    """The reprojection error above which a track is an outlier: ``outlier_reproj_px``, or with
    ``outlier_reproj_rel`` that many times the median of the window's errors ``err_px`` [N] when
    smaller, never below ``outlier_reproj_min_px``. A gate that follows the tracker's accuracy: a
    drifting track stands out against the window's typical error long before a fixed gate."""
    p = params
    k = p.outlier_reproj_rel or 0.0  # None (no platform said): the fixed gate
    fin = err_px[np.isfinite(err_px)]
    if k <= 0 or len(fin) < 20:
        return p.outlier_reproj_px
    rel = k * float(np.median(fin))
    return min(p.outlier_reproj_px, max(p.outlier_reproj_min_px, rel))


@dataclass
class WindowFrame:
    """One frame of the window: its tracks' pixels and whether it is kept as a keyframe."""

    seq: int
    t_ns: int
    ids: NDArray[np.int64]
    uv_px: NDArray[np.float64]
    track_len: NDArray[np.int32]
    is_keyframe: bool
    stationary: bool


@dataclass
class EstimatorState:
    """Estimate at the newest frame."""

    t_ns: int
    T_world_imu: NDArray[np.float64]  # [4, 4]
    velocity_world_m_s: NDArray[np.float64]  # [3]
    gyro_bias_rad_s: NDArray[np.float64]  # [3]
    accel_bias_m_s2: NDArray[np.float64]  # [3]
    n_landmarks: int
    stats: dict[str, float] = field(default_factory=dict)


@dataclass
class LandmarkView:
    """Landmarks seen in one frame, in that frame's camera. Arrays share length ``N``."""

    track_ids: NDArray[np.int64]  # [N]
    uv_px: NDArray[np.float32]  # [N, 2] undistorted pixel of the observation
    xyz_cam_m: NDArray[np.float32]  # [N, 3] metric point in the camera frame
    cov_cam_m2: NDArray[np.float32]  # [N, 3, 3] its covariance (poses fixed)
    reproj_err_px: NDArray[np.float32]  # [N] worst reprojection error over the window
    track_len: NDArray[np.int32]  # [N]
