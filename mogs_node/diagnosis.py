"""Why a run makes no keyframe, or a keyframe no depth, and what to do (issue 18).

A run on a user's data that produces nothing must say why. :class:`RunDoctor` is fed what
crossed the bus (node counters from ``/diagnostics``, odometry statuses and positions, IMU
samples, keyframes, prior and metrized depth coverage) and returns, once per cause, a line that
names the cause and the remedy:

- no keyframe for ``no_keyframe_s`` of data (odometry stamps: the frames the frontend handled;
  a pipeline slowed down by back-pressure is not a stall), or of wall time after the first image
  when the frontend handles none: no IMU, images waiting for IMU samples
  that never come (clocks disagree), the frontend receiving no image, no motion (the IMU or the
  odometry says the sensor stands still), still initialising (the calibration does not fit), or
  tracking lost (resets);
- a keyframe whose metrized depth is empty: the prior was empty (little motion between keyframes,
  no texture) or the metrizer had nothing to scale it with (too few sparse points).

Pure: messages or numbers in, strings out, no bus and no I/O; the launcher
(:mod:`mogs_node.launch`) subscribes and prints.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mogs_node import msgs
from mogs_node.errors import ShapeError

__all__ = ["DIAGNOSED_TOPICS", "DoctorParams", "RunDoctor", "depth_coverage", "imu_is_still"]

#: topics a :class:`RunDoctor` is fed from, besides ``/diagnostics``
DIAGNOSED_TOPICS = (
    "/imu",
    "/frontend/odometry",
    "/frontend/keyframe",
    "/prior/depth",
    "/metrizer/depth",
)


@dataclass(frozen=True)
class DoctorParams:
    """Thresholds of the diagnosis."""

    no_keyframe_s: float = 10.0  # say why after this long of data without a keyframe
    still_gyro_std_rad_s: float = 0.1  # the frontend's stillness test (frontend/initialization.py)
    still_accel_std_m_s2: float = 1.5
    still_travel_m: float = 0.2  # odometry moved less than this since the last keyframe: no motion
    min_sparse_points: int = 10  # fewer sparse points than this cannot scale a prior
    imu_window: int = 400  # IMU samples kept for the stillness test


def depth_coverage(depth_m: NDArray, confidence: NDArray | None = None) -> float:
    """Fraction of pixels with a finite depth > 0 (and confidence > 0): ``[H, W]`` arrays."""
    d = np.asarray(depth_m)
    if d.ndim != 2 or d.size == 0:
        raise ShapeError(f"depth_m: expected a non-empty [H, W] array, got shape {d.shape}")
    ok = np.isfinite(d) & (d > 0)
    if confidence is not None:
        c = np.asarray(confidence)
        if c.shape != d.shape:
            raise ShapeError(f"confidence: shape {c.shape} differs from depth_m {d.shape}")
        ok &= np.isfinite(c) & (c > 0)
    return float(np.count_nonzero(ok)) / d.size


def imu_is_still(
    gyro_rad_s: NDArray, accel_m_s2: NDArray, *, gyro_std: float, accel_std: float
) -> bool:
    """Whether IMU samples ``[N, 3]`` (N >= 2) show a sensor standing still: the per-axis standard
    deviation of gyro and accel below the thresholds (the frontend's own stillness test)."""
    g, a = np.asarray(gyro_rad_s, np.float64), np.asarray(accel_m_s2, np.float64)
    if g.ndim != 2 or g.shape[1] != 3 or a.shape != g.shape or len(g) < 2:
        raise ShapeError(
            f"gyro_rad_s, accel_m_s2: expected two [N>=2, 3], got {g.shape}, {a.shape}"
        )
    if not (np.isfinite(g).all() and np.isfinite(a).all()):
        return False
    return bool(np.std(g, axis=0).max() < gyro_std and np.std(a, axis=0).max() < accel_std)


@dataclass
class _State:
    images: int = 0  # published by the source (largest count any node reports)
    imu: int = 0
    frontend: dict[str, float] = field(default_factory=dict)  # frontend_* counters
    keyframes: int = 0
    last_keyframe_at: float | None = None
    first_image_at: float | None = None  # when images were first seen (wall clock)
    odometry: int = 0  # frames the frontend acknowledged, in all
    span_from_ns: int | None = None  # data time of the last keyframe (or first odometry)
    span_to_ns: int | None = None  # data time of the latest odometry
    statuses: Counter[str] = field(default_factory=Counter)  # odometry since the last keyframe
    positions: list[NDArray] = field(default_factory=list)  # odometry since the last keyframe
    prior_coverage: dict[int, float] = field(default_factory=dict)
    sparse_points: dict[int, int] = field(default_factory=dict)


class RunDoctor:
    """Diagnoses a run from its observations; every ``on_*`` / :meth:`check` returns the lines to
    print now (each cause once, until it changes)."""

    def __init__(self, params: DoctorParams | None = None) -> None:
        self.p = params or DoctorParams()
        self.s = _State()
        self._said: set[str] = set()
        self._gyro: deque[NDArray] = deque(maxlen=self.p.imu_window)
        self._accel: deque[NDArray] = deque(maxlen=self.p.imu_window)

    # ------------------------------------------------------------------ observations

    def observe(self, topic: str, msg: msgs.Message, now: float) -> list[str]:
        """Feed one bus message (of ``/diagnostics`` or :data:`DIAGNOSED_TOPICS`); the lines to
        say now."""
        if isinstance(msg, msgs.Diagnostics):
            self.on_diagnostics(msg.node, msg.counters, msg.topics, now)
        elif isinstance(msg, msgs.Imu):
            self.on_imu(msg.gyro_rad_s, msg.accel_m_s2)
        elif isinstance(msg, msgs.Odometry):
            self.on_odometry(msg.status, np.asarray(msg.T_world_cam)[:3, 3], msg.stamp_ns)
        elif isinstance(msg, msgs.Keyframe):
            self.on_keyframe(msg.keyframe_id, len(msg.feature_ids), msg.stamp_ns, now)
        elif isinstance(msg, msgs.DepthMap) and topic == "/prior/depth":
            self.on_prior(msg.keyframe_id, depth_coverage(msg.depth, msg.confidence))
        elif isinstance(msg, msgs.DepthMap) and topic == "/metrizer/depth":
            return self.on_depth(msg.keyframe_id, depth_coverage(msg.depth, msg.confidence))
        return []

    def on_diagnostics(
        self, node: str, counters: dict[str, float], topics: dict[str, dict], now: float
    ) -> None:
        """A node's heartbeat: its counters and per-topic statistics."""
        s = self.s
        images = int(topics.get("/camera/image", {}).get("published", 0))
        imu = int(topics.get("/imu", {}).get("published", 0))
        if images > s.images:
            s.images = images
            if s.first_image_at is None:
                s.first_image_at = now
        s.imu = max(s.imu, imu)
        if any(k.startswith("frontend_") for k in counters):
            s.frontend = {k: float(v) for k, v in counters.items() if k.startswith("frontend_")}

    def on_imu(self, gyro_rad_s: tuple[float, ...], accel_m_s2: tuple[float, ...]) -> None:
        self._gyro.append(np.asarray(gyro_rad_s, np.float64))
        self._accel.append(np.asarray(accel_m_s2, np.float64))

    def on_odometry(self, status: str, position_m: NDArray, stamp_ns: int) -> None:
        """One frame's odometry: status, camera position in the world ``[3]`` and stamp."""
        s = self.s
        s.odometry += 1
        if s.span_from_ns is None:
            s.span_from_ns = int(stamp_ns)
        s.span_to_ns = max(int(stamp_ns), s.span_to_ns or int(stamp_ns))
        self.s.statuses[status] += 1
        if status == "tracking":
            self.s.positions.append(np.asarray(position_m, np.float64)[:3])

    def on_keyframe(
        self, keyframe_id: int, n_sparse_points: int, stamp_ns: int, now: float
    ) -> None:
        s = self.s
        s.keyframes += 1
        s.last_keyframe_at = now
        s.span_from_ns = s.span_to_ns = int(stamp_ns)
        s.statuses.clear()
        s.positions.clear()
        s.sparse_points[keyframe_id] = int(n_sparse_points)
        self._said = {k for k in self._said if k.startswith("depth:")}

    def on_prior(self, keyframe_id: int, coverage: float) -> None:
        self.s.prior_coverage[keyframe_id] = float(coverage)

    def on_depth(self, keyframe_id: int, coverage: float) -> list[str]:
        """A keyframe's metrized depth; a line when it is empty."""
        if coverage > 0:
            return []
        prior = self.s.prior_coverage.pop(keyframe_id, None)
        sparse = self.s.sparse_points.pop(keyframe_id, None)
        if prior is not None and prior == 0:
            return self._once(
                "depth:prior_empty",
                f"keyframe {keyframe_id} got no depth: its depth prior is empty. The weight-free "
                "flow prior needs the camera to move between keyframes over static, textured "
                "structure within ~20 m, with the frontend's poses. What to do: use a drive "
                "with more motion between keyframes (a larger frontend.keyframes.min_parallax_px), "
                "or a learned prior (prior.backend: onnx with a Depth-Anything-style model file).",
            )
        if sparse is not None and sparse < self.p.min_sparse_points:
            return self._once(
                "depth:few_points",
                f"keyframe {keyframe_id} got no depth: only {sparse} sparse metric points came "
                "with it, too few to scale the prior. What to do: check the frontend's "
                "calibration (intrinsics, T_imu_cam) and that the images are sharp and textured.",
            )
        return self._once(
            "depth:empty",
            f"keyframe {keyframe_id} got no depth (prior coverage "
            f"{'unknown' if prior is None else f'{prior:.0%}'}, "
            f"{'unknown' if sparse is None else sparse} sparse points). What to do: see the "
            "metrizer's warnings above; run with -v for its per-keyframe statistics.",
        )

    # ------------------------------------------------------------------ the rules

    def check(self, now: float) -> list[str]:
        """Lines to print now: why no keyframe was made for ``no_keyframe_s`` while images came."""
        s = self.s
        if s.first_image_at is None:
            return []
        if s.odometry:  # data time: a back-pressured pipeline is slow, not stalled
            waited = (s.span_to_ns - s.span_from_ns) / 1e9  # type: ignore[operator]
        elif s.keyframes == 0:  # the frontend handles no frame at all: wall time
            waited = now - s.first_image_at
        else:
            return []
        if waited < self.p.no_keyframe_s:
            return []
        head = (
            f"no keyframe for {waited:.0f} s of data"
            if s.keyframes
            else f"no keyframe yet after {s.images} images"
        )
        cause, text = self._cause()
        return self._once(f"kf:{cause}", f"{head}: {text}")

    def at_end(self) -> list[str]:
        """At the end of a run: why it made no keyframe at all, if images came (unless said)."""
        s = self.s
        if s.keyframes or s.images == 0:
            return []
        cause, text = self._cause()
        return self._once(f"kf:{cause}", f"the run made no keyframe from {s.images} images: {text}")

    def _cause(self) -> tuple[str, str]:
        s, fe = self.s, self.s.frontend
        if s.imu == 0 and fe.get("frontend_imu_samples", 0) == 0:
            return "no_imu", (
                f"no IMU: {s.images} images and 0 IMU samples on /imu. The frontend is "
                "visual-inertial and cannot initialise without an IMU. What to do: play a "
                "source with an IMU (KITTI raw with its oxts/ folder, EuRoC mav0/imu0, a bag "
                "with sensor_msgs/Imu), or check the IMU topic's name."
            )
        if fe and fe.get("frontend_frames", 0) == 0:
            dropped = int(fe.get("frontend_frames_dropped_waiting_imu", 0))
            if dropped:
                return "imu_clock", (
                    f"the frontend dropped {dropped} images waiting for IMU samples up to "
                    "their stamps: camera and IMU stamps do not overlap. What to do: put both "
                    "on one clock (check the time stamps of both streams)."
                )
            return "no_images", (
                "the frontend has handled no image. What to do: check that the source's image "
                "topic is the frontend's (image_topic) and the image size its width/height."
            )
        resets = int(fe.get("frontend_imu_gap_resets", 0) + fe.get("frontend_divergence_resets", 0))
        if s.statuses.get("reset", 0) or (resets and s.statuses.get("tracking", 0) == 0):
            return "lost", (
                f"tracking lost: the frontend reset {resets} times "
                f"({int(fe.get('frontend_imu_gap_resets', 0))} IMU gaps, "
                f"{int(fe.get('frontend_divergence_resets', 0))} divergences). What to do: "
                "check the IMU rate and gaps, the IMU noise parameters and T_imu_cam."
            )
        if self._still():
            return "no_motion", (
                "no motion: the sensor stands still (IMU and odometry), so there is no parallax "
                "for a keyframe. What to do: nothing if it will move; else start the playback "
                "where it moves (player.start_s)."
            )
        if s.statuses.get("tracking", 0) == 0:
            return "initializing", (
                f"the frontend is still initialising ({int(fe.get('frontend_frames', 0))} frames, "
                f"{s.imu} IMU samples). What to do: check the calibration (frontend.fx_px, "
                "fy_px, cx_px, cy_px, T_imu_cam) against the camera, and that the sensor "
                "moves with some rotation and acceleration."
            )
        return "tracking_no_kf", (
            "the frontend tracks but makes no keyframe. What to do: lower "
            "frontend.keyframes.min_parallax_px or max_interval_s."
        )

    def _still(self) -> bool:
        s = self.s
        if len(s.positions) >= 2:
            travel = float(np.linalg.norm(s.positions[-1] - s.positions[0]))
            return travel < self.p.still_travel_m
        if len(self._gyro) >= 20:
            return imu_is_still(
                np.stack(self._gyro),
                np.stack(self._accel),
                gyro_std=self.p.still_gyro_std_rad_s,
                accel_std=self.p.still_accel_std_m_s2,
            )
        return False

    def _once(self, key: str, line: str) -> list[str]:
        if key in self._said:
            return []
        self._said.add(key)
        return [line]
