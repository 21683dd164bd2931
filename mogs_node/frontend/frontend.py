"""The frontend core: images and IMU samples in, odometry per frame and keyframes out (pure).

Wires :class:`~mogs_node.frontend.tracker.FeatureTracker`, the initialisers of
:mod:`~mogs_node.frontend.initialization`, :class:`~mogs_node.frontend.estimator.VioEstimator` and the
keyframe policy. It owns the sensor-stream checks (time going backwards, IMU gaps, frames that wait
for their IMU) and counts every rejection in :attr:`Frontend.counters`. No I/O, no bus.
"""

from __future__ import annotations

import logging
import time
from collections import deque

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.estimator import EstimatorDivergedError, VioEstimator
from mogs_node.frontend.frontend_types import FrameOutput, FrontendParams, KeyframeOutput
from mogs_node.frontend.initialization import DynamicInitializer, is_still, static_init
from mogs_node.frontend.keyframes import (
    StandstillKeyframes,
    is_keyframe,
    keeps_in_window,
    omega_weight,
)
from mogs_node.frontend.platform import PlatformChooser, motion_violation
from mogs_node.frontend.preintegration import ImuBuffer, ImuSamples, make_params
from mogs_node.frontend.reobserve import carry_forward, reobserved_points
from mogs_node.frontend.road_distance import RoadDistance
from mogs_node.frontend.time_offset import TimeOffsetEstimator, gyro_variation
from mogs_node.frontend.track_points import (
    KeyframePoints,
    TrackHistory,
    epipole_cell_caps,
    keyframe_points,
)
from mogs_node.frontend.tracker import FeatureTracker
from mogs_node.geometry import check_array, se3_inverse, so3_exp

__all__ = ["FrameOutput", "Frontend", "FrontendParams", "KeyframeOutput"]

log = logging.getLogger(__name__)


class Frontend:
    """Streaming VI frontend: :meth:`add_imu` for every IMU sample, :meth:`add_image` per frame.

    Both return the frames processed by the call (a frame is processed once the IMU covers it).
    """

    def __init__(self, params: FrontendParams, camera: CameraModel, T_imu_cam: NDArray) -> None:
        self.params = params
        self.camera = camera
        self.T_imu_cam = check_array("T_imu_cam", T_imu_cam, shape=(4, 4), finite=True).astype(
            float
        )
        self.tracker = FeatureTracker(params.tracker, camera)
        # the keyframes' sparse points come from their own, denser tracks: the estimator's
        # tracker and window stay exactly as they are (docs/frontend.md, round 6)
        self.point_tracker = (
            FeatureTracker(params.points.tracker(), camera) if params.points.enabled else None
        )
        self._history = TrackHistory(params.points.history_frames)
        self._last_points: tuple[NDArray, KeyframePoints] | None = None  # (T_world_cam, points)
        # the last keyframes' (T_world_cam, points, grey image): their points that a new
        # keyframe still sees join its own
        self._recent_points: deque[tuple[NDArray, KeyframePoints, NDArray]] = deque(
            maxlen=max(params.points.reproject_keyframes, 1)
        )
        self.platform = PlatformChooser(params.platform, params.bounds, params.platform_default)
        self.profile = self.platform.profile
        est_params = params.estimator_for(self.profile)
        self.estimator = VioEstimator(est_params, camera.pinhole, self.T_imu_cam, params.imu)
        self.time_offset_ns = int(params.time_offset_ns)  # the one in use (estimated or prior)
        self.clock = TimeOffsetEstimator(
            params.time_offset, params.time_offset_ns, camera.K, self.T_imu_cam[:3, :3]
        )
        self._first_stamp_ns: int | None = None
        self._init_offset_ns: int | None = None  # the offset a dynamic initialisation used
        self._reset_logged: set[str] = set()
        self._pim_params = make_params(params.imu)
        self.imu = ImuBuffer()
        self._pending: deque[tuple[int, NDArray]] = deque()
        self._last_image_ns: int | None = None
        self._last_frame_ns: int | None = None  # IMU time of the last processed frame
        self._frame_index = 0
        self._keyframe_id = 0
        self._dyn_init = DynamicInitializer(
            params.init,
            est_params,
            camera.pinhole,
            self.T_imu_cam,
            params.imu,
            params.ground,
            self.profile,
        )
        self._last_kf: tuple[int, NDArray, NDArray] | None = None
        self._standstill = StandstillKeyframes(params.keyframes)  # no keyframes while parked
        self._undistort_maps = camera.undistort_maps()
        self.counters: dict[str, int] = {
            "frames": 0,
            "keyframes": 0,
            "imu_samples": 0,
            "imu_time_backwards": 0,
            "image_time_backwards": 0,
            "imu_gap_resets": 0,
            "divergence_resets": 0,
            "frames_dropped_waiting_imu": 0,
            "bad_input": 0,
            "static_inits": 0,
            "dynamic_inits": 0,
            "image_wrong_size": 0,
            "ground_measurements": 0,
            "ground_rejected": 0,
            "ground_gated": 0,
            "ground_implausible": 0,
        }
        if params.ground.enabled and camera.model != "none":
            raise ConfigError(
                "ground.camera_height_m: the road measurement needs rectified images "
                f"(camera model 'none', got {camera.model!r})"
            )
        self._road = RoadDistance(params.ground, camera.K, self.T_imu_cam)
        self._keyframe_stamps: dict[int, int] = {}  # IMU time -> camera stamp of the keyframes

    @property
    def initialized(self) -> bool:
        return self.estimator.initialized

    @property
    def pending_stamps_ns(self) -> list[int]:
        """Camera stamps of the frames waiting for their IMU."""
        return [t for t, _ in self._pending]

    # ------------------------------------------------------------------------------------ input

    def add_imu(
        self, t_ns: int, gyro_rad_s: tuple | NDArray, accel_m_s2: tuple | NDArray
    ) -> list[FrameOutput]:
        """One IMU sample (IMU clock). Out-of-order or non-finite samples are rejected and counted."""
        g = np.asarray(gyro_rad_s, float).reshape(-1)
        a = np.asarray(accel_m_s2, float).reshape(-1)
        if (
            g.shape != (3,)
            or a.shape != (3,)
            or not (np.all(np.isfinite(g)) and np.all(np.isfinite(a)))
        ):
            self.counters["bad_input"] += 1
            return []
        last = self.imu.last_ns
        if last is not None and t_ns <= last:
            self.counters["imu_time_backwards"] += 1
            return []
        self.imu.append(int(t_ns), tuple(g), tuple(a))
        self.counters["imu_samples"] += 1
        return self._drain()

    def add_imu_batch(
        self, stamps_ns: NDArray, gyro_rad_s: NDArray, accel_m_s2: NDArray
    ) -> list[FrameOutput]:
        out: list[FrameOutput] = []
        for t, g, a in zip(
            np.asarray(stamps_ns).tolist(),
            np.asarray(gyro_rad_s),
            np.asarray(accel_m_s2),
            strict=True,
        ):
            out += self.add_imu(int(t), g, a)
        return out

    def add_image(self, stamp_ns: int, image: NDArray) -> list[FrameOutput]:
        """One camera frame (camera clock). Frames not after the previous one are rejected."""
        if self._last_image_ns is not None and stamp_ns <= self._last_image_ns:
            self.counters["image_time_backwards"] += 1
            return []
        pin = self.camera.pinhole
        if image.ndim not in (2, 3) or image.shape[:2] != (pin.height, pin.width):
            # a frame of another size would corrupt the KLT state: reject it, count it
            n = self.counters["image_wrong_size"] = self.counters["image_wrong_size"] + 1
            if n & (n - 1) == 0:  # 1st, 2nd, 4th, ...: a stream of bad frames is not a log flood
                log.warning(
                    "image %s rejected (%d so far): expected %dx%d (calibration)",
                    image.shape,
                    n,
                    pin.width,
                    pin.height,
                )
            return []
        self._last_image_ns = int(stamp_ns)
        self._pending.append((int(stamp_ns), image))
        while len(self._pending) > self.params.max_pending_frames:
            self._pending.popleft()
            self.counters["frames_dropped_waiting_imu"] += 1
        return self._drain()

    def _drain(self) -> list[FrameOutput]:
        out = []
        last = self.imu.last_ns
        while (
            self._pending and last is not None and self._pending[0][0] + self.time_offset_ns <= last
        ):
            stamp, img = self._pending.popleft()
            out.append(self._process(stamp, img))
        return out

    # ------------------------------------------------------------------------------------ core

    def _process(self, stamp_ns: int, image: NDArray) -> FrameOutput:
        p = self.params
        t_ns = stamp_ns + self.time_offset_ns
        t0 = time.perf_counter()
        ground_s = 0.0  # road measurement (with ground on), apart from the estimation
        R_pred = self._predicted_rotation(t_ns)
        tr = self.tracker.track(image, R_pred)
        self._update_time_offset(stamp_ns, tr.ids, tr.uv_px)
        self._update_platform(prev_t=self._last_frame_ns, t_ns=t_ns)
        t1 = time.perf_counter()
        if self.point_tracker is not None:
            dense = self.point_tracker.track(image, R_pred, self._dense_cell_caps())
            self._history.add(t_ns, dense.ids, dense.uv_px, self._undistorted_gray(image))
        points_s = time.perf_counter() - t1  # dense tracks and the keyframe's points
        self.counters["frames"] += 1
        idx = self._frame_index
        self._frame_index += 1
        status, kf = "initializing", None
        T_wc = v = None
        stats = {"features": float(len(tr.ids)), "tracked_ratio": tr.kept_ratio}
        flow = tr.stats.get("median_flow_px", 0.0)
        prev_t = self._last_frame_ns
        self._last_frame_ns = t_ns
        if (
            self.initialized
            and prev_t is not None
            and self.imu.max_gap_s(prev_t, t_ns) > p.max_imu_gap_s
        ):
            self.counters["imu_gap_resets"] += 1
            self._reset("imu_gap", f"IMU gap before frame {idx}")
            status = "reset"
        imu = self.imu.samples()
        if not self.initialized:
            if status != "reset":  # the frame after a reset starts the new initialisation
                self._try_init((t_ns, tr.ids, tr.uv_px, tr.track_len), imu, flow, image)
            if self.initialized:
                status = "tracking"
                st = self.estimator.state()
                T_wc, v = st.T_world_imu @ self.T_imu_cam, st.velocity_world_m_s
                if not self._standstill.holding:  # a static start waits for the first motion
                    kf = self._make_keyframe(stamp_ns, image, T_wc)
        else:
            dt_kf = (t_ns - self._last_kf[0]) * 1e-9
            make_kf, parallax = is_keyframe(
                p.keyframes, self._last_kf[1], self._last_kf[2], tr.ids, tr.uv_px, dt_kf
            )
            make_kf &= dt_kf >= self.profile.keyframe_min_interval_s  # the platform's rate cap
            still = (
                is_still(p.init, imu, t_ns, flow)
                and self._compensated_accel_m_s2(imu, t_ns) < p.init.still_accel_dev_m_s2
            )
            stats["parallax_px"] = parallax
            try:
                st = self.estimator.add_frame(
                    t_ns,
                    tr.ids,
                    tr.uv_px,
                    imu,
                    is_keyframe=make_kf or self._window_keeps(t_ns, tr.ids, tr.uv_px),
                    stationary=still,
                    track_len=tr.track_len,
                )
            except EstimatorDivergedError as err:
                self.counters["divergence_resets"] += 1
                self._reset(err.reason, f"frame {idx}: {err}")
                status = "reset"
            else:
                status = self._check_platform(idx, status)
            if status != "reset" and self.initialized:
                stats.update(st.stats)
                stats["landmarks"] = float(st.n_landmarks)
                T_wc, v = st.T_world_imu @ self.T_imu_cam, st.velocity_world_m_s
                self._history.set_pose(t_ns, T_wc)
                make_kf, skipped = self._standstill.decide(
                    make_kf, still, t_ns, T_wc[:3, 3], lambda: len(self._fresh_points())
                )
                if skipped:
                    key = f"keyframes_skipped_{skipped}"
                    self.counters[key] = self.counters.get(key, 0) + 1
                if make_kf:
                    self._last_kf = (t_ns, tr.ids, tr.uv_px)
                    tk = time.perf_counter()
                    kf = self._make_keyframe(stamp_ns, image, T_wc)
                    points_s += time.perf_counter() - tk
                if p.ground.enabled:
                    tg = time.perf_counter()
                    counter = self._road.measure(self.estimator, image)
                    if counter is not None:
                        self.counters[counter] += 1
                    ground_s = time.perf_counter() - tg
        if kf is not None:
            self._keyframe_stamps[t_ns] = stamp_ns
        if self.estimator.frames:
            self.imu.trim(self.estimator.frames[0].t_ns - int(1e9))
        else:
            self.imu.trim(t_ns - int(p.imu_history_s * 1e9))
        t2 = time.perf_counter()
        return FrameOutput(
            stamp_ns=stamp_ns,
            frame_index=idx,
            status=status,
            T_world_cam=T_wc,
            velocity_world_m_s=v,
            keyframe=kf,
            timings_ms={
                "tracking": 1e3 * (t1 - t0),
                "estimation": 1e3 * (t2 - t1 - ground_s - points_s),
                "ground": 1e3 * ground_s,
                "points": 1e3 * points_s,
            },
            stats=stats,
        )

    def _window_keeps(self, t_ns: int, ids: NDArray, uv_px: NDArray) -> bool:
        """Whether a frame that is no published keyframe stays in the window (after the next
        frame comes): every frame, or one per the window's interval or view change."""
        p = self.params
        if not p.window_every_frame:
            return False
        interval = p.window_interval_s
        if interval is None:
            interval = self.profile.window_interval_s
        kept = [f for f in self.estimator.frames if f.is_keyframe]
        if interval <= 0 or not kept:
            return True
        last = kept[-1]
        rule = (interval, p.window_parallax_px, p.window_tracked_ratio)
        return keeps_in_window(*rule, last.ids, last.uv_px, ids, uv_px, (t_ns - last.t_ns) * 1e-9)

    def window_keyframe_poses(self) -> list[tuple[int, NDArray[np.float64]]]:
        """``(camera stamp, T_world_cam [4, 4])`` of the published keyframes still in the
        estimator's window, as its latest solve left them: their earlier poses refined (VINS-Mono
        republishes its window's keyframe poses for its path the same way). Empty when none."""
        if not self.initialized or not self.estimator.frames:
            self._keyframe_stamps.clear()
            return []
        stamps, T_world_imu, _ = self.estimator.window_states()
        first = int(stamps[0])
        for t in [t for t in self._keyframe_stamps if t < first]:  # left the window
            del self._keyframe_stamps[t]
        return [
            (self._keyframe_stamps[int(t)], T @ self.T_imu_cam)
            for t, T in zip(stamps, T_world_imu)
            if int(t) in self._keyframe_stamps
        ]

    def _reset(self, reason: str, message: str) -> None:
        """Re-initialise, counted by ``reason`` (``resets_<reason>``), logged once per reason."""
        key = f"resets_{reason}"
        self.counters[key] = self.counters.get(key, 0) + 1
        (log.debug if reason in self._reset_logged else log.warning)(
            "%s; re-initialising (%d resets for %s)", message, self.counters[key], reason
        )
        self._reset_logged.add(reason)
        self.estimator.reset()
        self._dyn_init.reset()
        self._last_kf = None
        self._road.reset()
        self._history.reset()  # the next initialisation starts a new world frame
        self._last_points = None
        self._recent_points.clear()
        self._standstill.reset()

    def _check_platform(self, idx: int, status: str) -> str:
        """Reset when the newest window step leaves the platform's bounds; the frame's status."""
        stamps, T, v = self.estimator.window_states()
        reason = motion_violation(self.profile, stamps[-2:], T[-2:], v[-2:])
        if reason is None:
            return "tracking" if status != "reset" else status
        self.counters["divergence_resets"] += 1  # an implausible solution is a divergence
        self._reset(reason.split(":", 1)[0], f"frame {idx}: {reason} ({self.profile.name})")
        return "reset"

    def _update_platform(self, prev_t: int | None, t_ns: int) -> None:
        """``platform: auto``: the IMU up to this frame goes to the chooser; a walk switches the
        bounds and the keyframe cap from the next check on."""
        if not self.platform.auto or self.platform.detection is not None:
            return
        imu = self.imu.samples()
        new = (imu.stamps_ns <= t_ns) & (imu.stamps_ns > (prev_t if prev_t is not None else -1))
        if self.platform.add_imu(imu.stamps_ns[new], imu.accel_m_s2[new]):
            self.profile = self._dyn_init.profile = self.platform.profile
            est = self._dyn_init.estimator_params = self.params.estimator_for(self.profile)
            self.estimator.params = est

    def _update_time_offset(self, stamp_ns: int, ids: NDArray, uv_px: NDArray) -> None:
        """Feed the time-offset estimate; a new value is used from the next frame on (an
        initialisation under way restarts: its frames carry the old IMU times)."""
        if self._first_stamp_ns is None:
            self._first_stamp_ns = stamp_ns
        if not self.params.time_offset.enabled:
            return
        first = self.clock.estimate is None
        est = self.clock.add_frame(stamp_ns, ids, uv_px, self.imu.samples())
        if est is None or est.offset_ns == self.time_offset_ns:
            return
        big = abs(est.offset_ns - self.time_offset_ns) > 2e6 * self.params.time_offset.max_sigma_ms
        if (first or big) and not self.initialized:
            self._dyn_init.reset()
        if (
            self.initialized
            and self._init_offset_ns is not None
            and abs(est.offset_ns - self._init_offset_ns) > 1e6 * self.params.time_offset.reinit_ms
        ):  # initialised with a wrong offset (it was not known yet): once more with this one
            self._reset("time_offset", f"time offset {est.offset_ns / 1e6:.1f} ms")
        if first or big:
            log.info(
                "camera-IMU time offset %.1f ms (+-%.1f)", est.offset_ns / 1e6, est.sigma_ns / 1e6
            )
        self.time_offset_ns = est.offset_ns

    def figures(self) -> dict[str, float]:
        """Run figures for the diagnostics: the time offset in use, keyframes per second."""
        span_s = 0.0
        if self._first_stamp_ns is not None and self._last_image_ns is not None:
            span_s = (self._last_image_ns - self._first_stamp_ns) * 1e-9
        e = self.clock.estimate
        return {
            "time_offset_ms": self.time_offset_ns / 1e6,
            "time_offset_sigma_ms": e.sigma_ns / 1e6 if e is not None else float("nan"),
            "time_offset_pairs": float(self.clock.pairs),
            "keyframes_per_s": self.counters["keyframes"] / span_s if span_s > 0 else 0.0,
            "platform_walk_detected": float(self.platform.detection is not None),
            **{f"init_rejected_{k}": float(v) for k, v in self._dyn_init.rejections.items()},
        }

    def _compensated_accel_m_s2(self, imu: ImuSamples, t_ns: int) -> float:
        """Norm of the mean acceleration over the last ``still_accel_window_s`` with gravity and the
        estimated accelerometer bias removed, at the newest estimated attitude. A vehicle driving
        off smoothly shows almost no image flow and no IMU spread, but this is well above zero."""
        span_ns = int(self.params.init.still_accel_window_s * 1e9)
        m = (imu.stamps_ns <= t_ns) & (imu.stamps_ns >= t_ns - span_ns)
        if not np.any(m):
            return np.inf
        st = self.estimator.state()
        f = imu.accel_m_s2[m].mean(axis=0) - st.accel_bias_m_s2
        a_world = st.T_world_imu[:3, :3] @ f - np.array([0.0, 0.0, self.params.imu.gravity_m_s2])
        return float(np.linalg.norm(a_world))

    def _predicted_rotation(self, t_ns: int) -> NDArray | None:
        """Camera rotation since the previous frame from the gyro (bias-corrected when known)."""
        if self._last_frame_ns is None or self.imu.last_ns is None:
            return None
        imu = self.imu.samples()
        m = (imu.stamps_ns > self._last_frame_ns) & (imu.stamps_ns <= t_ns)
        if not np.any(m):
            return None
        bg = self.estimator.gyro_bias()
        w = (imu.gyro_rad_s[m].mean(axis=0) - bg) * (t_ns - self._last_frame_ns) * 1e-9
        R_imu = so3_exp(w)  # R_prev_cur in the IMU frame
        R_ic = self.T_imu_cam[:3, :3]
        R_prev_cur_cam = R_ic.T @ R_imu @ R_ic
        return R_prev_cur_cam.T

    def _try_init(self, frame: tuple, imu: ImuSamples, flow: float, image: NDArray) -> None:
        p = self.params
        t_ns = frame[0]
        if (
            p.init_mode in ("auto", "static")
            and len(imu.stamps_ns)
            and (imu.stamps_ns[0] <= t_ns - int(p.init.still_window_s * 1e9))
            and is_still(p.init, imu, t_ns, flow)
        ):
            res = static_init(p.init, imu, t_ns)
            self._dyn_init.reset()
            _, ids, uv, tl = frame
            self.estimator.initialize(
                t_ns,
                res.T_world_imu[-1],
                res.velocity_world_m_s[-1],
                res.gyro_bias_rad_s,
                res.accel_bias_m_s2,
                ids,
                uv,
                tl,
            )
            self.counters["static_inits"] += 1
            self._standstill.parked(t_ns, (res.T_world_imu[-1] @ self.T_imu_cam)[:3, 3])
            self._init_offset_ns = None  # a static start does not depend on the offset
            self._last_kf = (t_ns, ids, uv)
            log.info("static initialisation at %.3f s", t_ns * 1e-9)
            return
        if p.init_mode == "static":
            return
        if (  # a dynamic initialisation needs the camera and IMU times to agree
            p.time_offset.enabled
            and self.clock.estimate is None
            and (t_ns - self.time_offset_ns - self._first_stamp_ns) * 1e-9
            < p.time_offset.init_wait_s
            and gyro_variation(imu, t_ns) > p.time_offset.init_wait_gyro_std_rad_s
        ):
            self.counters["init_waiting_time_offset"] = (
                self.counters.get("init_waiting_time_offset", 0) + 1
            )
            return
        gray = None
        if p.ground.enabled:
            gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        est = self._dyn_init.add_frame(*frame, imu, gray)
        if est is not None:
            self.estimator = est
            f = est.frames[-1]
            self._last_kf = (f.t_ns, f.ids, f.uv_px)
            self.counters["dynamic_inits"] += 1
            self._init_offset_ns = self.time_offset_ns
            log.info(
                "dynamic initialisation at %.3f s (speed %.2f m/s)",
                f.t_ns * 1e-9,
                float(np.linalg.norm(est.state().velocity_world_m_s)),
            )

    def _dense_cell_caps(self) -> NDArray | None:
        """The dense tracker's per-cell caps around the focus of expansion (the latest velocity
        in the camera frame; :func:`epipole_cell_caps`); None before the initialisation."""
        if self.params.points.epipole_radius_deg <= 0 or not self.initialized:
            return None
        st = self.estimator.state()
        R_world_cam = st.T_world_imu[:3, :3] @ self.T_imu_cam[:3, :3]
        v_cam = R_world_cam.T @ st.velocity_world_m_s
        return epipole_cell_caps(self.camera.pinhole, v_cam, self.params.points)

    def _undistorted_gray(self, image: NDArray) -> NDArray[np.uint8]:
        """Grey image in the undistorted pinhole camera (the dense tracks' photometric check)."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        if self._undistort_maps is not None:
            gray = cv2.remap(gray, *self._undistort_maps, cv2.INTER_LINEAR)
        return gray

    def _fresh_points(self) -> KeyframePoints:
        """The newest frame's well-triangulated dense tracks (with the window's latest poses)."""
        if self.point_tracker is None:  # the estimator window's landmarks, as before round 6
            lm = self.estimator.newest_landmarks()
            w = omega_weight(lm.track_len, lm.reproj_err_px, self.params.keyframes)
            return KeyframePoints(lm.track_ids, lm.uv_px, lm.xyz_cam_m, lm.cov_cam_m2, w)
        for f in self.estimator.frames:
            self._history.set_pose(f.t_ns, self.estimator.pose(f.seq) @ self.T_imu_cam)
        return keyframe_points(self._history, self.camera.pinhole, self.params.points)

    def _keyframe_points(self, T_world_cam: NDArray) -> KeyframePoints:
        """The keyframe's sparse points: every well-triangulated dense track (with the window's
        latest poses), or at standstill, when too few are fresh, the previous keyframe's points
        moved over."""
        pts = self._fresh_points()
        if self.point_tracker is None:
            return pts
        pp = self.params.points
        image = self._history.newest_image()
        if image is not None:
            pts = reobserved_points(
                pts, self._recent_points, T_world_cam, self.camera.pinhole, image, pp
            )
        if len(pts) < pp.carry_min_points and self._last_points is not None:
            T_world_prev, prev = self._last_points
            T_cur_prev = se3_inverse(T_world_cam) @ T_world_prev
            if np.linalg.norm(T_cur_prev[:3, 3]) < pp.carry_max_motion_m:  # standstill
                moved = carry_forward(prev, T_cur_prev, self.camera.pinhole)
                if len(moved) > len(pts):
                    pts = moved
        self._last_points = (T_world_cam.copy(), pts)
        if image is not None and pp.reproject_keyframes > 0:
            self._recent_points.append((T_world_cam.copy(), pts, image))
        return pts

    def _make_keyframe(self, stamp_ns: int, image: NDArray, T_world_cam: NDArray) -> KeyframeOutput:
        pts = self._keyframe_points(T_world_cam)
        img = np.asarray(image)
        if self._undistort_maps is not None:
            img = cv2.remap(img, *self._undistort_maps, cv2.INTER_LINEAR)
        kf = KeyframeOutput(
            keyframe_id=self._keyframe_id,
            stamp_ns=stamp_ns,
            image=img,
            K=self.camera.K.copy(),
            T_world_cam=T_world_cam.copy(),
            feature_ids=pts.ids,
            feature_uv_px=pts.uv_px,
            feature_xyz_cam_m=pts.xyz_cam_m,
            feature_cov_cam_m2=pts.cov_cam_m2,
            feature_weight=pts.weight,
        )
        self._keyframe_id += 1
        self.counters["keyframes"] += 1
        return kf
