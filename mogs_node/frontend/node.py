"""Frontend node: ``/camera/image`` + ``/imu`` -> ``/frontend/odometry`` (every frame) and
``/frontend/keyframe`` (per keyframe). The shell only converts messages; the algorithm is
:class:`mogs_node.frontend.frontend.Frontend`.

Every handled image gets exactly one odometry message with its ``stamp_ns`` (the player's flow
control acknowledges frames by these stamps), also while initialising (status ``initializing``,
the last estimated pose or the identity before any) and after a reset (status ``reset``); an image
the frontend rejects (time going backwards) or drops (waited too long for its IMU) is acknowledged
with status ``rejected`` / ``dropped`` and the last pose.

The calibration (intrinsics, size, distortion, ``T_imu_cam``, camera height, IMU noise) comes from
the source's ``/camera/info`` (:class:`~mogs_node.msgs.CameraInfo`, docs/messages.md); a value
typed in the launch file overrides it. Until a calibration is known, IMU samples wait and images
are acknowledged with status ``no_calibration`` (counted; said once after
``no_calibration_warn_s``).

Images are best-effort (latest wins, drops counted by the shell); IMU samples are reliable (ordered,
bounded queue, gaps counted): the preintegration needs every sample. The frontend's own counters
(time going backwards, IMU gaps, resets) are merged into ``/diagnostics``.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np

from mogs_node import msgs
from mogs_node.frontend.backlog import BacklogParams, KeyframeBacklog
from mogs_node.frontend.frontend import FrameOutput, Frontend
from mogs_node.frontend.monocular import MonocularFrontend
from mogs_node.frontend.node_config import (
    CALIBRATION_FIELDS,
    FRONTEND_MODES,
    FrontendNodeParams,
    camera_from_info,
    keyframe_message,
)
from mogs_node.node import Node, parse_params

__all__ = [
    "CALIBRATION_FIELDS",
    "FRONTEND_MODES",
    "FrontendNode",
    "FrontendNodeParams",
    "camera_from_info",
]


class FrontendNode(Node):
    """Visual-inertial frontend process; its calibration from ``/camera/info`` (see the params)."""

    Params = FrontendNodeParams

    def setup(self) -> None:
        p: FrontendNodeParams = self.params
        self.frontend: Frontend | MonocularFrontend | None = None
        self.mode = ""  # the mode in use, chosen at the first image (see the params)
        self.camera_info: msgs.CameraInfo | None = None
        self._calibrated = False
        self._imu_waiting: deque[msgs.Imu] = deque(maxlen=100_000)  # IMU before the frontend
        self._imu_seen = False
        self._poses: dict[int, np.ndarray] = {}  # the user's poses by stamp (mode 'poses')
        self._first_uncalibrated: float | None = None
        self._last_T_world_cam = np.eye(4)  # best pose so far: acknowledges frames without one
        self._last_velocity = np.zeros(3)
        self._refined_sent: dict[int, np.ndarray] = {}  # keyframe stamp -> pose last published
        self.counters.update(frames_without_calibration=0, camera_info_ignored=0)
        if p.overrides_all():
            self._configure(None)  # the launch file gives everything: no need to wait
            if p.mode in ("vi", "camera_only"):
                self._start(0)
        self.subscribe(
            p.camera_info_topic, self.on_camera_info, reliable=True, msg_type=msgs.CameraInfo
        )
        self.subscribe(p.pose_topic, self.on_pose, reliable=True, msg_type=msgs.PoseStamped)
        self.subscribe(p.imu_topic, self.on_imu, reliable=True, msg_type=msgs.Imu)
        self.subscribe(p.image_topic, self.on_image, reliable=False, msg_type=msgs.Image)
        self.backlog = KeyframeBacklog(
            parse_params(BacklogParams, p.backlog, where=f"{self.name}.backlog")
        )
        self.counters["keyframes_shed"] = 0
        self._image_seen_s: dict[int, float] = {}  # stamp -> when its image came (latency)
        if self.backlog.params.enabled:  # the latest is enough: the chain works in order
            self.subscribe(self.backlog.params.done_topic, self.on_chain_done, reliable=False)
        # after a restart: replay every journaled calibration, image and IMU sample
        # (deterministic: the same keyframe ids); only missing outputs are published
        self.catch_up(
            (p.camera_info_topic, p.imu_topic, p.image_topic), (p.odometry_topic, p.keyframe_topic)
        )

    def _configure(self, info: msgs.CameraInfo | None) -> None:
        """Check and log the calibration (launch values over ``info``'s); ConfigError: stop."""
        p: FrontendNodeParams = self.params
        cal = p.calibration(self.name, info, imu=False)
        fp, cam, _ = p.build(self.name, info, imu=False)
        self._calibrated = True
        given = [k for k in CALIBRATION_FIELDS if getattr(p, k) is not None]
        pc = cam.pinhole
        self.log.info(
            "calibration %s%s: %dx%d fx %.3f fy %.3f cx %.3f cy %.3f, distortion %s, camera "
            "height %s, IMU noise %s",
            f"from {info.source or p.camera_info_topic}" if info else "from the launch file",
            f" (launch overrides: {', '.join(given)})" if info is not None and given else "",
            pc.width,
            pc.height,
            pc.fx_px,
            pc.fy_px,
            pc.cx_px,
            pc.cy_px,
            cam.model,
            f"{fp.ground.camera_height_m:.3f} m" if fp.ground.enabled else "not known",
            "from the source" if cal["imu_noise"] and not p.imu else "defaults/launch",
        )
        if cal["T_imu_cam_defect"] > 1e-12:
            self.log.info(
                "%s.T_imu_cam: rotation orthonormal only to %.2g, projected to the nearest rotation",
                self.name,
                cal["T_imu_cam_defect"],
            )

    def _start(self, stamp_ns: int) -> None:
        """Build the frontend at the first image, in the mode of the params (see ``mode``)."""
        p: FrontendNodeParams = self.params
        mode = p.mode
        if mode == "auto":
            height = p.build(self.name, self.camera_info, imu=False)[0].ground.enabled
            if stamp_ns in self._poses:
                mode = "poses"
            elif self._imu_seen or not height:
                mode = "vi"
            else:
                mode = "camera_only"
        if mode == "vi":
            fp, cam, T_imu_cam = p.build(self.name, self.camera_info)
            self.frontend = Frontend(fp, cam, T_imu_cam)
        else:
            self.frontend = p.build_monocular(
                self.name, self.camera_info, given_poses=mode == "poses"
            )
        self.mode = mode
        self.log.info(
            "mode %s%s",
            mode,
            {
                "vi": " (camera + IMU)",
                "camera_only": ": no IMU before the first image; metric scale from the road",
                "poses": ": the poses on " + p.pose_topic,
            }[mode],
        )
        while self._imu_waiting:
            self.on_imu(self._imu_waiting.popleft())

    def on_camera_info(self, msg: msgs.CameraInfo) -> None:
        if not self._calibrated:
            self._configure(msg)
            self.camera_info = msg
        elif self.camera_info is not None and not _same_calibration(self.camera_info, msg):
            self.counters["camera_info_ignored"] += 1
            if self.counters["camera_info_ignored"] == 1:
                self.log.warning(
                    "a different calibration on %s from %s is ignored: the frontend keeps the "
                    "first one (restart to change it)",
                    self.params.camera_info_topic,
                    msg.source,
                )

    def on_pose(self, msg: msgs.PoseStamped) -> None:
        self._poses[int(msg.stamp_ns)] = np.array(msg.T_world_cam, dtype=np.float64)
        while len(self._poses) > 10_000:  # images that never came: forget the oldest
            self._poses.pop(next(iter(self._poses)))

    def on_imu(self, msg: msgs.Imu) -> None:
        self._imu_seen = True
        if self.frontend is None:
            self._imu_waiting.append(msg)
            return
        outs = self.frontend.add_imu(msg.stamp_ns, msg.gyro_rad_s, msg.accel_m_s2)
        for out in outs:
            self._publish(out)
        if outs:
            self._publish_refined()

    def _no_calibration(self, msg: msgs.Image) -> None:
        """An image before any calibration: acknowledged, counted, said once after a while."""
        p: FrontendNodeParams = self.params
        self.counters["frames_without_calibration"] += 1
        self._acknowledge(msg.stamp_ns, "no_calibration")
        now = time.monotonic()
        if self._first_uncalibrated is None:
            self._first_uncalibrated = now
        elif now - self._first_uncalibrated >= p.no_calibration_warn_s >= 0:
            self._first_uncalibrated = float("inf")  # once
            missing = [k for k in CALIBRATION_FIELDS[:6] + ("T_imu_cam",) if getattr(p, k) is None]
            self.log.warning(
                "no calibration after %.0f s: nothing on %s, and the launch file lacks %s; "
                "the source must publish a CameraInfo (the player does) or set them with --set "
                "frontend.<name>=...",
                p.no_calibration_warn_s,
                p.camera_info_topic,
                ", ".join(missing),
            )

    def on_image(self, msg: msgs.Image) -> None:
        if not self._calibrated:
            self._no_calibration(msg)
            return
        if self.frontend is None:
            self._start(msg.stamp_ns)
        self._image_seen_s[int(msg.stamp_ns)] = time.monotonic()
        while len(self._image_seen_s) > 256:  # frames the frontend dropped: forget the oldest
            self._image_seen_s.pop(next(iter(self._image_seen_s)))
        img = msg.rgb_or_mono()
        fe = self.frontend
        assert fe is not None
        pending = fe.pending_stamps_ns
        rejected = fe.counters["image_time_backwards"] + fe.counters["image_wrong_size"]
        if isinstance(fe, MonocularFrontend):
            outs = fe.add_image(msg.stamp_ns, img, self._poses.pop(int(msg.stamp_ns), None))
        else:
            outs = fe.add_image(msg.stamp_ns, img)
        if fe.counters["image_time_backwards"] + fe.counters["image_wrong_size"] > rejected:
            self._acknowledge(msg.stamp_ns, "rejected")
        waiting = set(fe.pending_stamps_ns) | {o.stamp_ns for o in outs}
        for t in pending:  # frames dropped while waiting for their IMU
            if t not in waiting:
                self._acknowledge(t, "dropped")
        for out in outs:
            self._publish(out)
        if outs:
            self._publish_refined()

    def _publish_refined(self) -> None:
        """The window's keyframes whose pose its last solve moved, each as a ``PoseStamped``
        with the keyframe's stamp (the ROS bridges' path follows them)."""
        p: FrontendNodeParams = self.params
        window = getattr(self.frontend, "window_keyframe_poses", None)  # camera-only: none
        if not p.refined_pose_topic or window is None:
            return
        sent, self._refined_sent = self._refined_sent, {}
        for stamp_ns, T in window():
            self._refined_sent[stamp_ns] = T
            before = sent.get(stamp_ns)
            if before is None or not np.array_equal(before, T):
                self.publish(
                    p.refined_pose_topic,
                    msgs.PoseStamped(
                        stamp_ns=int(stamp_ns),
                        frame_id=p.frame_id,
                        T_world_cam=np.ascontiguousarray(T, dtype=np.float64),
                    ),
                )

    def _acknowledge(self, stamp_ns: int, status: str) -> None:
        self._send_odometry(stamp_ns, -1, self._last_T_world_cam, self._last_velocity, status)

    def _send_odometry(
        self,
        stamp_ns: int,
        frame_index: int,
        T_world_cam: np.ndarray,
        velocity: np.ndarray,
        status: str,
    ) -> None:
        p: FrontendNodeParams = self.params
        v = velocity
        self.publish(
            p.odometry_topic,
            msgs.Odometry(
                stamp_ns=int(stamp_ns),
                frame_id=p.frame_id,
                frame_index=int(frame_index),
                T_world_cam=np.ascontiguousarray(T_world_cam, dtype=np.float64),
                velocity_world_m_s=(float(v[0]), float(v[1]), float(v[2])),
                status=status,
            ),
        )

    def _publish(self, out: FrameOutput) -> None:
        p: FrontendNodeParams = self.params
        if out.T_world_cam is not None:
            self._last_T_world_cam = np.array(out.T_world_cam, dtype=np.float64)
            self._last_velocity = np.asarray(out.velocity_world_m_s, dtype=np.float64)
        # one odometry per handled frame, with the best pose available while initialising
        self._send_odometry(
            out.stamp_ns, out.frame_index, self._last_T_world_cam, self._last_velocity, out.status
        )
        image_s = self._image_seen_s.pop(int(out.stamp_ns), None)
        if out.keyframe is not None:
            shed = self.backlog.admit(out.keyframe.keyframe_id, time.monotonic(), image_s)
            if shed is None:
                self.publish(p.keyframe_topic, keyframe_message(out.keyframe, p.frame_id))
                self._refined_sent[out.keyframe.stamp_ns] = out.keyframe.T_world_cam
            else:
                self._shed(out.keyframe.keyframe_id, shed)

    def on_chain_done(self, msg: msgs.Message) -> None:
        self.backlog.done(int(msg.keyframe_id), time.monotonic())
        self.counters["chain_service_ms"] = round(1000.0 * self.backlog.service_s, 1)

    def _shed(self, keyframe_id: int, reason: str) -> None:
        """A keyframe not published: counted by reason, said at the 1st, 2nd, 4th, 8th, ..."""
        n = self.backlog.shed_total
        self.counters["keyframes_shed"] = n
        for why, count in self.backlog.shed.items():
            self.counters[f"keyframes_shed_{why}"] = count
        if n & (n - 1) == 0:
            self.log.info("keyframe %d shed (%s); %d shed so far", keyframe_id, reason, n)

    def diagnostics(self, status: str | None = None) -> msgs.Diagnostics:
        d = super().diagnostics(status)
        d.counters["frontend_camera_only"] = float(self.mode in ("camera_only", "poses"))
        if self.frontend is not None:
            d.counters.update(
                {f"frontend_{k}": float(v) for k, v in self.frontend.counters.items()}
            )
            figures = getattr(self.frontend, "figures", None)  # the VI frontend's estimates
            if figures is not None:
                d.counters.update({f"frontend_{k}": v for k, v in figures().items()})
        return d


def _same_calibration(a: msgs.CameraInfo, b: msgs.CameraInfo) -> bool:
    """Whether two CameraInfo messages carry the same calibration (stamps aside)."""
    return a == msgs.CameraInfo(**{**b.__dict__, "stamp_ns": a.stamp_ns})
