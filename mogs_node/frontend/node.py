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
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from mogs_node import msgs
from mogs_node.errors import ConfigError, GeometryError
from mogs_node.frontend.backlog import BacklogParams, KeyframeBacklog
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.estimator import EstimatorParams
from mogs_node.frontend.frontend import FrameOutput, Frontend, FrontendParams, KeyframeOutput
from mogs_node.frontend.ground import GroundParams
from mogs_node.frontend.initialization import InitParams
from mogs_node.frontend.keyframes import KeyframeParams
from mogs_node.frontend.monocular import MonocularFrontend, MonocularParams
from mogs_node.frontend.platform import PlatformBounds
from mogs_node.frontend.preintegration import ImuNoise
from mogs_node.frontend.time_offset import TimeOffsetParams
from mogs_node.frontend.track_points import TrackPointsParams
from mogs_node.frontend.tracker import TrackerParams
from mogs_node.geometry import PinholeCamera, rigid_transform
from mogs_node.node import Node, parse_params

__all__ = [
    "CALIBRATION_FIELDS",
    "FRONTEND_MODES",
    "FrontendNode",
    "FrontendNodeParams",
    "camera_from_info",
]

FRONTEND_MODES = ("auto", "vi", "camera_only", "poses")

#: the calibration values a launch file may override; the rest come from ``/camera/info``
CALIBRATION_FIELDS = (
    "fx_px",
    "fy_px",
    "cx_px",
    "cy_px",
    "width",
    "height",
    "distortion_model",
    "distortion_coeffs",
    "T_imu_cam",
)


@dataclass(frozen=True)
class FrontendNodeParams:
    """Parameters of the frontend node: calibration overrides, the algorithm's groups, topics.

    The calibration comes from the source's ``/camera/info`` (:class:`mogs_node.msgs.CameraInfo`);
    every calibration value set here (not None) overrides the message's, e.g. a re-calibrated
    ``T_imu_cam``. With all of intrinsics, size and ``T_imu_cam`` set here the frontend starts
    without waiting for the message.
    """

    fx_px: float | None = None  # pinhole intrinsics of the published images (None: /camera/info)
    fy_px: float | None = None
    cx_px: float | None = None
    cy_px: float | None = None
    width: int | None = None  # image size (px)
    height: int | None = None
    distortion_model: str | None = None  # 'none', 'radtan' (k1 k2 p1 p2) or 'equidistant' (k1..k4)
    distortion_coeffs: tuple[float, ...] | None = None  # coefficients of the distortion model
    T_imu_cam: tuple[float, ...] | None = None  # camera pose in the IMU frame, row-major 4x4; a
    # rotation orthonormal to 1e-4 is projected to the nearest rotation (noted), worse is an error
    imu_noise_inflation: float = 2.0  # the source's IMU noise densities (datasheet, Kalibr) times
    # this: the usual inflation that absorbs vibration and integration error (ImuNoise defaults)
    time_offset_ns: int = 0  # t_imu = t_cam + time_offset_ns
    mode: str = "auto"  # 'vi' (camera + IMU), 'camera_only' (scale from the road at the camera
    # height), 'poses' (the user's poses on pose_topic) or 'auto': at the first image, 'poses' if
    # a pose came for it, 'vi' if IMU came before it, else 'camera_only' if the camera height is
    # known, else 'vi' (waiting for IMU)
    camera_only: dict[str, Any] = field(default_factory=dict)  # MonocularParams fields
    init_mode: str = "auto"  # 'auto', 'static' or 'dynamic'
    platform: str = "car"  # 'car', 'handheld' or 'drone' (motion bounds, keyframe rate cap);
    # 'auto': platform_default until the IMU shows a walk (step cadence), then 'handheld'
    platform_default: str = "car"
    bounds: dict[str, Any] = field(default_factory=dict)  # PlatformBounds fields (overrides)
    time_offset: dict[str, Any] = field(default_factory=dict)  # TimeOffsetParams fields
    tracker: dict[str, Any] = field(default_factory=dict)  # TrackerParams fields
    estimator: dict[str, Any] = field(default_factory=dict)  # EstimatorParams fields
    keyframes: dict[str, Any] = field(default_factory=dict)  # KeyframeParams fields
    backlog: dict[str, Any] = field(default_factory=dict)  # BacklogParams fields: shed whole
    # keyframes while max_backlog are in the chain or their depth would come later than
    # max_latency_s after their image (real-time sources; frontend/backlog.py)
    points: dict[str, Any] = field(default_factory=dict)  # TrackPointsParams fields: the
    # keyframes' sparse points from the dense tracks (docs/frontend.md, round 6)
    init: dict[str, Any] = field(default_factory=dict)  # InitParams fields
    imu: dict[str, Any] = field(default_factory=dict)  # ImuNoise fields (override the source's)
    ground: dict[str, Any] = field(default_factory=dict)  # GroundParams fields: camera_height_m
    # (> 0 on a car with rectified images; default: the source's) adds the road-plane translation
    image_topic: str = "/camera/image"
    imu_topic: str = "/imu"
    camera_info_topic: str = "/camera/info"
    pose_topic: str = "/camera/pose"  # poses the user has (player.poses), mode 'poses'
    odometry_topic: str = "/frontend/odometry"
    keyframe_topic: str = "/frontend/keyframe"
    refined_pose_topic: str = "/frontend/refined_pose"  # a published keyframe's pose each time
    # the window's solve moves it (PoseStamped with the keyframe's stamp; "" = not published)
    frame_id: str = "world"
    no_calibration_warn_s: float = 10.0  # images this long without a calibration: say so once

    def __post_init__(self) -> None:
        if self.T_imu_cam is not None and len(self.T_imu_cam) != 16:
            raise ConfigError(f"frontend.T_imu_cam: need 16 numbers, got {len(self.T_imu_cam)}")
        if self.mode not in FRONTEND_MODES:
            raise ConfigError(f"frontend.mode: {self.mode!r} not in {FRONTEND_MODES}")
        if not (np.isfinite(self.imu_noise_inflation) and self.imu_noise_inflation > 0):
            raise ConfigError(f"frontend.imu_noise_inflation: > 0, got {self.imu_noise_inflation}")

    def overrides_all(self) -> bool:
        """Whether the launch file gives the whole calibration (no need to wait for a message)."""
        need = ("fx_px", "fy_px", "cx_px", "cy_px", "width", "height", "T_imu_cam")
        return all(getattr(self, k) is not None for k in need)

    def build(
        self, where: str = "frontend", info: msgs.CameraInfo | None = None, *, imu: bool = True
    ) -> tuple[FrontendParams, CameraModel, np.ndarray]:
        """The algorithm's parameters, camera model and ``T_imu_cam`` [4, 4]: each calibration
        value from this launch file when set, else from ``info``; a value in neither is a
        :class:`ConfigError` naming it (``imu`` False: ``T_imu_cam`` may be unknown, None)."""
        cal = self.calibration(where, info, imu=imu)
        noise = dict(cal.pop("imu_noise"))
        noise.update(self.imu)  # the launch file's values win
        ground = dict(self.ground)
        if "camera_height_m" not in ground and cal["camera_height_m"] == cal["camera_height_m"]:
            ground["camera_height_m"] = cal["camera_height_m"]
        groups = {
            "tracker": parse_params(TrackerParams, self.tracker, where=f"{where}.tracker"),
            "estimator": parse_params(EstimatorParams, self.estimator, where=f"{where}.estimator"),
            "keyframes": parse_params(KeyframeParams, self.keyframes, where=f"{where}.keyframes"),
            "points": parse_params(TrackPointsParams, self.points, where=f"{where}.points"),
            "init": parse_params(InitParams, self.init, where=f"{where}.init"),
            "imu": parse_params(ImuNoise, noise, where=f"{where}.imu"),
            "ground": parse_params(GroundParams, ground, where=f"{where}.ground"),
            "bounds": parse_params(PlatformBounds, self.bounds, where=f"{where}.bounds"),
            "time_offset": parse_params(
                TimeOffsetParams, self.time_offset, where=f"{where}.time_offset"
            ),
        }
        params = FrontendParams(
            init_mode=self.init_mode,
            time_offset_ns=self.time_offset_ns,
            platform=self.platform,
            platform_default=self.platform_default,
            **groups,
        )
        cam = CameraModel(
            PinholeCamera(
                cal["fx_px"], cal["fy_px"], cal["cx_px"], cal["cy_px"], cal["width"], cal["height"]
            ),
            cal["distortion_model"],
            tuple(cal["distortion_coeffs"]),
        )
        return params, cam, cal["T_imu_cam"]

    def build_monocular(
        self, where: str, info: msgs.CameraInfo | None, *, given_poses: bool
    ) -> MonocularFrontend:
        """The camera-only (or given-pose) frontend: the calibration as :meth:`build`, the road
        measurement's and points' groups shared with the visual-inertial frontend's."""
        fp, cam, T = self.build(where, info, imu=False)
        mono = dict(self.camera_only)
        points = {"max_reproj_px": 1.5, **self.points, **mono.pop("points", {})}
        for k in ("ground", "keyframes"):
            if k in mono:
                raise ConfigError(f"{where}.camera_only.{k}: set it in {where}.{k}")
        params = replace(
            parse_params(MonocularParams, mono, where=f"{where}.camera_only"),
            points=parse_params(TrackPointsParams, points, where=f"{where}.points"),
            ground=fp.ground,
            keyframes=fp.keyframes,
        )
        return MonocularFrontend(params, cam, T, given_poses=given_poses)

    def calibration(
        self, where: str, info: msgs.CameraInfo | None, *, imu: bool = True
    ) -> dict[str, Any]:
        """The merged calibration (launch values over ``info``'s) as plain values (``imu`` False:
        ``T_imu_cam`` may be unknown, None)."""
        base = camera_from_info(info, self.imu_noise_inflation) if info is not None else {}
        out: dict[str, Any] = {}
        for k in CALIBRATION_FIELDS:
            v = getattr(self, k)
            if v is None:
                v = base.get(k)
            if v is None and k in ("distortion_model", "distortion_coeffs"):
                v = "none" if k == "distortion_model" else ()
            if v is None and k == "T_imu_cam" and not imu:
                out[k] = None
                continue
            if v is None:
                raise ConfigError(
                    f"{where}.{k}: not in the launch file and "
                    + ("no /camera/info received" if info is None else f"unknown to {info.source}")
                )
            out[k] = v
        defect = 0.0
        if out["T_imu_cam"] is not None:
            try:
                out["T_imu_cam"], defect = rigid_transform(out["T_imu_cam"], f"{where}.T_imu_cam")
            except GeometryError as err:
                raise ConfigError(str(err)) from err
        out["T_imu_cam_defect"] = defect
        out["camera_height_m"] = base.get("camera_height_m", float("nan"))
        out["imu_noise"] = base.get("imu_noise", {})
        return out


def camera_from_info(info: msgs.CameraInfo, imu_noise_inflation: float = 1.0) -> dict[str, Any]:
    """A :class:`~mogs_node.msgs.CameraInfo` as the frontend's calibration values (the names of
    :data:`CALIBRATION_FIELDS`, plus ``camera_height_m`` and ``imu_noise`` (ImuNoise fields, the
    source's densities times ``imu_noise_inflation``); ``T_imu_cam`` None when not known)."""
    K = info.K
    return {
        "fx_px": float(K[0, 0]),
        "fy_px": float(K[1, 1]),
        "cx_px": float(K[0, 2]),
        "cy_px": float(K[1, 2]),
        "width": int(info.width),
        "height": int(info.height),
        "distortion_model": info.distortion_model,
        "distortion_coeffs": tuple(float(c) for c in info.distortion_coeffs),
        "T_imu_cam": None if info.T_imu_cam is None else np.asarray(info.T_imu_cam, np.float64),
        "camera_height_m": float(info.camera_height_m),
        "imu_noise": {
            k: float(v) * (imu_noise_inflation if k in _NOISE_DENSITIES else 1.0)
            for k, v in info.imu_noise.items()
        },
    }


_NOISE_DENSITIES = (
    "gyro_noise_rad_s_rthz",
    "accel_noise_m_s2_rthz",
    "gyro_walk_rad_s2_rthz",
    "accel_walk_m_s3_rthz",
)


def keyframe_message(kf: KeyframeOutput, frame_id: str) -> msgs.Keyframe:
    """The ``/frontend/keyframe`` message of a keyframe (wire dtypes)."""
    return msgs.Keyframe(
        stamp_ns=kf.stamp_ns,
        frame_id=frame_id,
        keyframe_id=kf.keyframe_id,
        image=np.ascontiguousarray(kf.image),
        K=kf.K.astype(np.float64),
        T_world_cam=kf.T_world_cam.astype(np.float64),
        feature_ids=kf.feature_ids.astype(np.int64),
        feature_uv_px=kf.feature_uv_px.astype(np.float32),
        feature_xyz_cam_m=kf.feature_xyz_cam_m.astype(np.float32),
        feature_weight=kf.feature_weight.astype(np.float32),
    )


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
        img = msg.data
        if msg.encoding == "bgr8":
            img = np.ascontiguousarray(img[..., ::-1])
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
