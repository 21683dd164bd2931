"""Visual-inertial initialisation: static (stillness + gravity from the accelerometer) and dynamic
(visual SfM over a short window + visual-inertial alignment, as VINS-Mono does).

Both return the metric state of the last frame of their window (IMU pose in a gravity-aligned world
frame with z up, velocity, gyroscope bias); the world frame's yaw and origin are arbitrary (the first
IMU pose of the window has zero yaw and sits at the origin). No ground truth is read.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from mogs_node.errors import ConfigError
from mogs_node.frontend.estimator import EstimatorDivergedError, EstimatorParams, VioEstimator
from mogs_node.frontend.ground import GroundParams, road_normal_from_mount, road_scale_of_sfm
from mogs_node.frontend.platform import PlatformProfile, motion_violation
from mogs_node.frontend.preintegration import ImuNoise, ImuSamples, make_params, preintegrate
from mogs_node.frontend.visual_sfm import visual_sfm
from mogs_node.geometry import PinholeCamera, check_array, make_T, se3_inverse, so3_log

__all__ = [
    "DynamicInitializer",
    "InitParams",
    "InitResult",
    "dynamic_init",
    "gravity_aligned_rotation",
    "is_still",
    "static_init",
    "visual_sfm",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InitParams:
    """Initialisation parameters: when the platform counts as still (static initialisation from
    the accelerometer's gravity), and the dynamic initialisation's window, SfM and scale search."""

    still_window_s: float = 1.0  # IMU span inspected for stillness / averaged by the static init
    still_gyro_std_rad_s: float = 0.1  # stillness: gyro standard deviation below this (vibration)
    still_accel_std_m_s2: float = 1.5  # stillness: accel standard deviation below this (rotors)
    still_flow_px: float = 0.5  # stillness: median image flow below this
    still_accel_dev_m_s2: float = 0.3  # stillness while tracking: gravity-compensated mean
    # acceleration below this (a car driving off has little image flow and IMU spread)
    still_accel_window_s: float = 0.3  # IMU span of that mean (short: drive-off is seen early)
    dyn_frames: int = 10  # frames in the dynamic-initialisation window
    road_speed_guess_m_s: float = 10.0  # road scale at the dynamic initialisation (ground on):
    # starting guess of the speed, searched within 4x either way (2.5-40 m/s)
    dyn_min_parallax_px: float = 15.0  # parallax of the SfM pair that fixes the scale
    dyn_min_features: int = 30  # common features required by SfM
    gravity_m_s2: float = 9.81  # gravity magnitude
    min_scale: float = 1e-3  # scale from the alignment must be positive and above this
    dyn_hypotheses: int = 8  # scale hypotheses scored by the VI window when the alignment is weak
    min_speed_m_s: float = 0.5  # their speed range
    dyn_select_frames: int = 20  # frames each hypothesis runs before the best one is kept
    dyn_vel_sigma_rel: float = 0.1  # velocity prior sigma of a hypothesis, relative to its speed
    # (tight: each hypothesis keeps its scale while it is scored; loose ones drift and score alike)
    dyn_tilt_sigma_rad: float = 0.05  # roll/pitch prior sigma of a hypothesis (its gravity is
    # solved at a fixed scale and absorbs part of the acceleration: it must stay free to move)
    max_speed_m_s: float = 40.0
    dyn_lm_iterations: int = 3  # LM iterations per frame of the hypothesis windows (their scores
    # need converged solves; the kept estimator then runs with EstimatorParams.lm_iterations)

    def __post_init__(self) -> None:
        if self.dyn_frames < 4 or self.still_window_s <= 0 or self.dyn_lm_iterations < 1:
            raise ConfigError("init: dyn_frames >= 4, still_window_s > 0, dyn_lm_iterations >= 1")


@dataclass
class InitResult:
    """Metric states of the initialisation window's frames (index -1 is the newest)."""

    T_world_imu: NDArray[np.float64]  # [F, 4, 4]
    velocity_world_m_s: NDArray[np.float64]  # [F, 3]
    gyro_bias_rad_s: NDArray[np.float64]  # [3]
    accel_bias_m_s2: NDArray[np.float64]  # [3] (zero: not observable this early)
    scale: float = 1.0  # metric / SfM scale (1 for the static init)
    gravity_imu0: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))  # g in IMU 0
    kind: str = "static"


def _window(imu: ImuSamples, t_ns: int, span_s: float) -> tuple[NDArray, NDArray]:
    m = (imu.stamps_ns <= t_ns) & (imu.stamps_ns >= t_ns - int(span_s * 1e9))
    return imu.gyro_rad_s[m], imu.accel_m_s2[m]


def is_still(params: InitParams, imu: ImuSamples, t_ns: int, median_flow_px: float) -> bool:
    """Stillness: low gyro and accel spread over the last ``still_window_s`` and no image flow."""
    g, a = _window(imu, t_ns, params.still_window_s)
    if len(g) < 10:
        return False
    return bool(
        np.max(np.std(g, axis=0)) < params.still_gyro_std_rad_s
        and np.max(np.std(a, axis=0)) < params.still_accel_std_m_s2
        and median_flow_px < params.still_flow_px
    )


def gravity_aligned_rotation(up_in_body: NDArray, yaw_ref: NDArray | None = None) -> NDArray:
    """``R_world_body`` [3, 3] that maps ``up_in_body`` [3] to world +z, with zero yaw of the body
    x axis (or of ``yaw_ref`` [3] given in the body frame)."""
    z = np.asarray(up_in_body, float) / np.linalg.norm(up_in_body)
    ref = np.array([1.0, 0, 0]) if yaw_ref is None else np.asarray(yaw_ref, float)
    x = ref - z * (z @ ref)
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0, 1.0, 0]) - z * z[1]
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])  # rows: world axes expressed in the body frame


def static_init(params: InitParams, imu: ImuSamples, t_ns: int) -> InitResult:
    """Static initialisation at ``t_ns``: attitude from the mean specific force (gravity), gyro bias
    from the mean angular rate, zero velocity, origin at the IMU."""
    g, a = _window(imu, t_ns, params.still_window_s)
    if len(g) < 10:
        raise ConfigError("imu: fewer than 10 samples in the stillness window")
    f = a.mean(axis=0)
    R = gravity_aligned_rotation(f)
    return InitResult(
        T_world_imu=make_T(R, np.zeros(3))[None],
        velocity_world_m_s=np.zeros((1, 3)),
        gyro_bias_rad_s=g.mean(axis=0),
        accel_bias_m_s2=np.zeros(3),
        gravity_imu0=-params.gravity_m_s2 * f / np.linalg.norm(f),
        kind="static",
    )


# ------------------------------------------------------------------------------------- dynamic


def _solve_gyro_bias(R_c: NDArray, pims: list, R_imu_cam: NDArray) -> NDArray:
    """Gyro bias minimising the rotation residuals between SfM and preintegration (VINS-Mono)."""
    R_b = R_c @ R_imu_cam.T  # R_c0_bi
    rel = [R_b[i].T @ R_b[i + 1] for i in range(len(pims))]
    nav0 = gtsam.NavState()

    def res(bg: NDArray) -> NDArray:
        bias = gtsam.imuBias.ConstantBias(np.zeros(3), bg)
        out = [
            so3_log(pim.predict(nav0, bias).pose().rotation().matrix().T @ r)
            for pim, r in zip(pims, rel, strict=True)
        ]
        return np.concatenate(out)

    return least_squares(res, np.zeros(3), method="lm").x


def _tangent_basis(g: NDArray) -> NDArray:
    a = g / np.linalg.norm(g)
    tmp = np.array([0, 0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0, 0])
    b1 = np.cross(a, tmp)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(a, b1)], 1)  # [3, 2]


def _align(
    pc: NDArray,
    R_c: NDArray,
    t_cb: NDArray,
    R_cb: NDArray,
    pims: list,
    dts: NDArray,
    G: float,
    g_fixed: NDArray | None,
    sigma_pos_m: float = 0.05,
    sigma_vel_m_s: float = 0.005,
    s_fixed: float | None = None,
) -> tuple[NDArray, NDArray, float]:
    """Linear VI alignment: velocities (c0 frame), gravity (c0) and scale. With ``g_fixed`` the
    gravity is ``|G| * g_fixed/|g_fixed| + B w`` with 2 tangent unknowns (gravity refinement)."""
    F = len(pc)
    ng = 3 if g_fixed is None else 2
    n = 3 * F + ng + 1
    rows, rhs = [], []
    if g_fixed is not None:
        g0 = G * g_fixed / np.linalg.norm(g_fixed)
        Bt = _tangent_basis(g_fixed)
    for i, (pim, dt) in enumerate(zip(pims, dts, strict=True)):
        j = i + 1
        Ri = R_c[i] @ R_cb
        dp, dv = np.asarray(pim.deltaPij()), np.asarray(pim.deltaVij())
        A = np.zeros((6, n))
        b = np.zeros(6)
        # s (pc_j - pc_i) - v_i dt - 0.5 g dt^2 = R_i dp - (Rc_j - Rc_i) t_cb
        A[0:3, 3 * i : 3 * i + 3] = -dt * np.eye(3)
        A[0:3, -1] = pc[j] - pc[i]
        b[0:3] = Ri @ dp - (R_c[j] - R_c[i]) @ t_cb
        # v_j - v_i - g dt = R_i dv
        A[3:6, 3 * i : 3 * i + 3] = -np.eye(3)
        A[3:6, 3 * j : 3 * j + 3] = np.eye(3)
        b[3:6] = Ri @ dv
        if g_fixed is None:
            A[0:3, 3 * F : 3 * F + 3] = -0.5 * dt**2 * np.eye(3)
            A[3:6, 3 * F : 3 * F + 3] = -dt * np.eye(3)
        else:
            A[0:3, 3 * F : 3 * F + 2] = -0.5 * dt**2 * Bt
            A[3:6, 3 * F : 3 * F + 2] = -dt * Bt
            b[0:3] += 0.5 * dt**2 * g0
            b[3:6] += dt * g0
        # Rows weighted by their expected noise: velocity rows carry only IMU noise, position rows
        # the (much larger) SfM position noise; unweighted, a near-zero scale fits almost as well.
        w = np.r_[[1.0 / sigma_pos_m] * 3, [1.0 / sigma_vel_m_s] * 3]
        rows.append(A * w[:, None])
        rhs.append(b * w)
    A, b = np.vstack(rows), np.concatenate(rhs)
    if s_fixed is not None:  # known scale: move its column to the right-hand side
        b = b - A[:, -1] * s_fixed
        A = A[:, :-1]
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    if s_fixed is not None:
        x = np.r_[x, s_fixed]
    v = x[: 3 * F].reshape(F, 3)
    g = x[3 * F : 3 * F + 3] if g_fixed is None else g0 + Bt @ x[3 * F : 3 * F + 2]
    return v, g, float(x[-1])


def dynamic_init(
    params: InitParams,
    frames: list[tuple[NDArray, NDArray]],
    stamps_ns: NDArray,
    imu: ImuSamples,
    camera: PinholeCamera,
    T_imu_cam: NDArray,
    pim_params: gtsam.PreintegrationCombinedParams,
    hypotheses: int = 0,
    speeds_m_s: list[float] | None = None,
    sfm_scale_fn: Callable[[NDArray], float | None] | None = None,
) -> list[InitResult]:
    """VINS-Mono dynamic initialisation over ``frames`` (ids, undistorted px) at ``stamps_ns`` [F]
    (IMU time): SfM, gyro bias from the rotations, linear alignment for velocities, gravity and
    scale with the gravity magnitude enforced on its tangent plane.

    Returns candidate initial states, best guess first: the linear alignment's (when its scale is
    positive), then ``hypotheses`` states whose scale puts the mean speed on a geometric grid
    between ``min_speed_m_s`` and ``max_speed_m_s`` (velocities and gravity re-solved for each);
    with ``speeds_m_s`` only those mean speeds are proposed. ``sfm_scale_fn`` (SfM camera poses
    ``T_c0_ci`` [F, 4, 4] -> metric scale or None) measures the scale directly, e.g. from the road
    (:func:`~mogs_node.frontend.ground.road_scale_of_sfm`); when it does, that scale is the only
    candidate.
    Under near-constant acceleration (a vehicle cruising) the scale is poorly observable in a short
    window, so the caller scores the candidates with the full visual-inertial window solve. Empty
    when the SfM fails (retry with the next frame).
    """
    stamps_ns = check_array("stamps_ns", stamps_ns, shape=(len(frames),), dtype=np.integer)
    T_imu_cam = check_array("T_imu_cam", T_imu_cam, shape=(4, 4), finite=True)
    Tc = visual_sfm(frames, camera, params.dyn_min_features, params.dyn_min_parallax_px)
    if Tc is None:
        return []
    R_c, pc = Tc[:, :3, :3], Tc[:, :3, 3]
    T_cb = se3_inverse(T_imu_cam)
    R_cb, t_cb = T_cb[:3, :3], T_cb[:3, 3]
    pims = [
        preintegrate(imu, int(stamps_ns[i]), int(stamps_ns[i + 1]), pim_params)
        for i in range(len(frames) - 1)
    ]
    bg = _solve_gyro_bias(R_c, pims, T_imu_cam[:3, :3])
    bias = gtsam.imuBias.ConstantBias(np.zeros(3), bg)
    pims = [
        preintegrate(imu, int(stamps_ns[i]), int(stamps_ns[i + 1]), pim_params, bias)
        for i in range(len(frames) - 1)
    ]
    dts = np.diff(stamps_ns) * 1e-9
    G = params.gravity_m_s2
    # Gravity starts from the mean specific force (minus the mean acceleration, which is small for
    # a vehicle) and keeps its magnitude throughout: the unconstrained solve of VINS-Mono has a
    # near-degenerate mirror solution (scale ~ 0, velocities flipped) under constant acceleration.
    g0 = -np.mean(
        [
            (R_c[i] @ R_cb) @ np.asarray(pim.deltaVij()) / dt
            for i, (pim, dt) in enumerate(zip(pims, dts, strict=True))
        ],
        axis=0,
    )
    g = g0
    for _ in range(6):
        v, g, s = _align(pc, R_c, t_cb, R_cb, pims, dts, G, g)
    sfm_speed = max(np.linalg.norm(pc[-1] - pc[0]) / (dts.sum()), 1e-9)
    measured = sfm_scale_fn(Tc) if sfm_scale_fn is not None and speeds_m_s is None else None
    if measured is not None and not (np.isfinite(measured) and measured > 0):
        measured = None
    scales = [s] if s > params.min_scale and speeds_m_s is None and measured is None else []
    if measured is not None:
        scales, hypotheses = [float(measured)], 0
    if hypotheses:
        scales += list(
            np.geomspace(params.min_speed_m_s, params.max_speed_m_s, hypotheses) / sfm_speed
        )
    if speeds_m_s:
        scales += [v / sfm_speed for v in speeds_m_s]
    out = []
    R_c0_b = R_c @ R_cb  # [F, 3, 3]
    for s_h in scales:
        g = g0
        for _ in range(4):
            v, g, _s = _align(pc, R_c, t_cb, R_cb, pims, dts, G, g, s_fixed=s_h)
        # c0 -> world: gravity to -z, zero yaw of the first IMU frame's x axis.
        p_c0_b = s_h * pc + np.einsum("fij,j->fi", R_c, t_cb)
        R_w_c0 = gravity_aligned_rotation(-g, yaw_ref=R_c0_b[0][:, 0])
        R_wb = R_w_c0 @ R_c0_b
        p_wb = (p_c0_b - p_c0_b[0]) @ R_w_c0.T
        out.append(
            InitResult(
                T_world_imu=make_T(R_wb, p_wb),
                velocity_world_m_s=v @ R_w_c0.T,
                gyro_bias_rad_s=bg,
                accel_bias_m_s2=np.zeros(3),
                scale=float(s_h),
                gravity_imu0=R_c0_b[0].T @ g,
                kind="dynamic",
            )
        )
    return out


class DynamicInitializer:
    """Dynamic initialisation as a stream: feed frames until it hands back a running estimator.

    Keeps the last ``dyn_frames`` frames; once full, :func:`dynamic_init` gives candidate states
    (the linear alignment's and a grid of scale hypotheses). Each candidate starts a window
    estimator replaying the buffered frames, then every candidate is fed the next
    ``dyn_select_frames`` frames; the one whose IMU factors fit best (smallest accumulated IMU
    factor error: the visual factors are blind to scale) is kept. In a cruising vehicle the scale is
    only observable through changes of acceleration, which this longer look-ahead collects.
    """

    def __init__(
        self,
        params: InitParams,
        estimator_params: EstimatorParams,
        camera: PinholeCamera,
        T_imu_cam: NDArray,
        noise: ImuNoise,
        ground: GroundParams | None = None,
        profile: PlatformProfile | None = None,
    ) -> None:
        self.params = params
        self.profile = profile  # a chosen hypothesis outside its bounds is rejected
        self.rejections: dict[str, int] = {}  # rejected chosen hypotheses by the bound broken
        self.last_rejection: str | None = None
        self.estimator_params = estimator_params
        self.camera = camera
        self.T_imu_cam = T_imu_cam
        self.noise = noise
        self.ground = ground if ground is not None and ground.enabled else None
        self._road_normal = road_normal_from_mount(T_imu_cam)
        self._pim_params = make_params(noise)
        self.reset()

    def reset(self) -> None:
        self._frames: list[tuple[int, NDArray, NDArray, NDArray]] = []
        self._grays: dict[int, NDArray] = {}  # stamp -> grey image (road scale only)
        self._history: list[tuple[int, NDArray, NDArray, NDArray]] = []  # since the window start
        self._cands: list[list] = []  # [estimator, accumulated IMU error, frames fed, speed]

    def add_frame(
        self,
        t_ns: int,
        ids: NDArray,
        uv_px: NDArray,
        track_len: NDArray,
        imu: ImuSamples,
        gray: NDArray | None = None,
    ) -> VioEstimator | None:
        """Add one frame (IMU time, tracks, undistorted pixels); the chosen estimator or None.
        ``gray``: the frame's grey image, for the road scale when ``ground`` is on."""
        p = self.params
        if self.ground is not None and gray is not None and not self._cands:
            self._grays[t_ns] = gray
        if self._cands:
            self._history.append((t_ns, ids, uv_px, track_len))
            return self._advance((t_ns, ids, uv_px, track_len), imu)
        self._frames.append((t_ns, ids, uv_px, track_len))
        self._frames = self._frames[-p.dyn_frames :]
        if len(self._frames) < p.dyn_frames:
            return None
        frames = self._frames
        stamps = np.array([f[0] for f in frames], np.int64)
        self._grays = {t: g for t, g in self._grays.items() if t >= stamps[0]}
        for res in dynamic_init(
            p,
            [(f[1], f[2]) for f in frames],
            stamps,
            imu,
            self.camera,
            self.T_imu_cam,
            self._pim_params,
            hypotheses=p.dyn_hypotheses,
            sfm_scale_fn=self._road_scale_fn(stamps),
        ):
            est = self._replay(frames, imu, res)
            if est is not None:
                speed = float(np.mean(np.linalg.norm(res.velocity_world_m_s, axis=1)))
                self._cands.append([est, 0.0, 0, speed])
        self._history = list(frames)
        if not self._cands:
            self._frames.pop(0)
            return None
        if len(self._cands) == 1 or p.dyn_select_frames == 0:
            return self._advance(None, imu)
        return None

    def _road_scale_fn(self, stamps: NDArray) -> Callable[[NDArray], float | None] | None:
        """The SfM window's metric scale from the road (every frame's grey image needed)."""
        if self.ground is None or any(int(t) not in self._grays for t in stamps):
            return None
        grays = [self._grays[int(t)] for t in stamps]
        # a guess of each step at a typical road speed; the road alignment searches 4x either way
        steps = self.params.road_speed_guess_m_s * np.diff(stamps) * 1e-9
        ground, K, n = self.ground, self.camera.K, self._road_normal

        def fn(T_c0_ci: NDArray) -> float | None:
            return road_scale_of_sfm(grays, T_c0_ci, K, n, ground, steps)

        return fn

    def _replay(self, frames: list, imu: ImuSamples, res: InitResult) -> VioEstimator | None:
        params = replace(self.estimator_params, lm_iterations=self.params.dyn_lm_iterations)
        est = VioEstimator(params, self.camera, self.T_imu_cam, self.noise)
        t0, ids, uv, tl = frames[0]
        speed = float(np.linalg.norm(res.velocity_world_m_s[0]))
        est.initialize(
            t0,
            res.T_world_imu[0],
            res.velocity_world_m_s[0],
            res.gyro_bias_rad_s,
            res.accel_bias_m_s2,
            ids,
            uv,
            tl,
            vel_sigma_m_s=self.params.dyn_vel_sigma_rel * max(speed, 1.0),
            tilt_sigma_rad=self.params.dyn_tilt_sigma_rad,
        )
        try:
            for t, ids_k, uv_k, tl_k in frames[1:]:
                est.add_frame(t, ids_k, uv_k, imu, is_keyframe=True, track_len=tl_k)
        except EstimatorDivergedError as err:
            log.debug("dynamic initialisation candidate diverged (%s)", err)
            return None
        return est

    def _advance(self, frame: tuple | None, imu: ImuSamples) -> VioEstimator | None:
        if frame is not None:
            t, ids, uv, tl = frame
            alive = []
            for cand in self._cands:
                try:
                    cand[0].add_frame(t, ids, uv, imu, is_keyframe=True, track_len=tl)
                except EstimatorDivergedError:
                    continue
                cand[1] += cand[0].last_imu_error
                cand[2] += 1
                alive.append(cand)
            self._cands = alive
            if not alive:
                self.reset()
                return None
            if alive[0][2] < self.params.dyn_select_frames and len(alive) > 1:
                return None
        for c in self._cands:
            log.debug(
                "init hypothesis: speed %.2f m/s, accumulated IMU error %.3f",
                float(np.linalg.norm(c[0].state().velocity_world_m_s)),
                c[1],
            )
        cands = sorted(self._cands, key=lambda c: c[3])
        b = min(range(len(cands)), key=lambda i: cands[i][1])
        best = cands[b][0]
        if 0 < b < len(cands) - 1:
            refined = self._refine(cands[b - 1 : b + 2], imu)
            if refined is not None:
                best = refined
        self.reset()
        reason = self._violation(best)
        if reason is not None:
            self._reject(reason)
            return None
        best.params = self.estimator_params
        return best

    def _violation(self, est: VioEstimator) -> str | None:
        """The profile bound the chosen hypothesis's window breaks (None: plausible)."""
        if self.profile is None:
            return None
        return motion_violation(self.profile, *est.window_states())

    def _reject(self, reason: str) -> None:
        """Count and log (once per bound) a rejected hypothesis; the next window starts afresh."""
        key = reason.split(":", 1)[0]
        n = self.rejections[key] = self.rejections.get(key, 0) + 1
        self.last_rejection = reason
        (log.warning if n == 1 else log.debug)(
            "initialisation rejected (%s, platform %s, %d so far): waiting for a better window",
            reason,
            self.profile.name if self.profile else "-",
            n,
        )

    def _refine(self, three: list[list], imu: ImuSamples) -> VioEstimator | None:
        """Vertex of the parabola through (log speed, error) of the best hypothesis and its two
        neighbours; a new estimator at that speed replayed over every frame seen so far."""
        x = np.log([c[3] for c in three])
        y = np.array([c[1] for c in three])
        a, bcoef, _ = np.polyfit(x, y, 2)
        if a <= 0:
            return None
        x_star = float(np.clip(-bcoef / (2 * a), x[0], x[2]))
        if abs(x_star - x[1]) < 0.05:
            return None
        hist = self._history
        n = self.params.dyn_frames
        stamps = np.array([f[0] for f in hist[:n]], np.int64)
        res = dynamic_init(
            self.params,
            [(f[1], f[2]) for f in hist[:n]],
            stamps,
            imu,
            self.camera,
            self.T_imu_cam,
            self._pim_params,
            speeds_m_s=[float(np.exp(x_star))],
        )
        if not res:
            return None
        est = self._replay(hist, imu, res[0])
        log.debug("init refined to %.2f m/s (from %.2f)", float(np.exp(x_star)), three[1][3])
        return est
