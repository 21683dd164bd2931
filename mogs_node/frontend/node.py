"""Frontend node: ``/camera/image`` + ``/imu`` -> ``/frontend/odometry`` (every frame) and
``/frontend/keyframe`` (per keyframe). The shell only converts messages; the algorithm is
:class:`mogs_node.frontend.frontend.Frontend`.

Every handled image gets exactly one odometry message with its ``stamp_ns`` (the player's flow
control acknowledges frames by these stamps), also while initialising (status ``initializing``,
the last estimated pose or the identity before any) and after a reset (status ``reset``); an image
the frontend rejects (time going backwards) or drops (waited too long for its IMU) is acknowledged
with status ``rejected`` / ``dropped`` and the last pose.

Images are best-effort (latest wins, drops counted by the shell); IMU samples are reliable (ordered,
bounded queue, gaps counted): the preintegration needs every sample. The frontend's own counters
(time going backwards, IMU gaps, resets) are merged into ``/diagnostics``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mogs_node import msgs
from mogs_node.errors import ConfigError
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.estimator import EstimatorParams
from mogs_node.frontend.frontend import FrameOutput, Frontend, FrontendParams, KeyframeOutput
from mogs_node.frontend.ground import GroundParams
from mogs_node.frontend.initialization import InitParams
from mogs_node.frontend.keyframes import KeyframeParams
from mogs_node.frontend.platform import PlatformBounds
from mogs_node.frontend.preintegration import ImuNoise
from mogs_node.frontend.time_offset import TimeOffsetParams
from mogs_node.frontend.track_points import TrackPointsParams
from mogs_node.frontend.tracker import TrackerParams
from mogs_node.geometry import PinholeCamera
from mogs_node.node import Node, parse_params

__all__ = ["FrontendNode", "FrontendNodeParams"]

_KITTI_T_IMU_CAM = (
    0.0,
    0.0,
    1.0,
    0.81,
    -1.0,
    0.0,
    0.0,
    -0.32,
    0.0,
    -1.0,
    0.0,
    0.72,
    0.0,
    0.0,
    0.0,
    1.0,
)


@dataclass(frozen=True)
class FrontendNodeParams:
    """Parameters of the frontend node: the camera, the camera-IMU calibration, the groups."""

    fx_px: float = 360.77  # pinhole intrinsics of the raw image (default: KITTI at 621x188)
    fy_px: float = 361.73
    cx_px: float = 304.53
    cy_px: float = 86.41
    width: int = 621  # image size (px)
    height: int = 188
    distortion_model: str = "none"  # 'none', 'radtan' (k1 k2 p1 p2) or 'equidistant' (k1..k4)
    distortion_coeffs: tuple[float, ...] = ()  # coefficients of the distortion model
    T_imu_cam: tuple[float, ...] = _KITTI_T_IMU_CAM  # camera pose in the IMU frame, row-major 4x4
    time_offset_ns: int = 0  # t_imu = t_cam + time_offset_ns
    init_mode: str = "auto"  # 'auto', 'static' or 'dynamic'
    platform: str = "car"  # 'car', 'handheld' or 'drone' (motion bounds, keyframe rate cap)
    bounds: dict[str, Any] = field(default_factory=dict)  # PlatformBounds fields (overrides)
    time_offset: dict[str, Any] = field(default_factory=dict)  # TimeOffsetParams fields
    tracker: dict[str, Any] = field(default_factory=dict)  # TrackerParams fields
    estimator: dict[str, Any] = field(default_factory=dict)  # EstimatorParams fields
    keyframes: dict[str, Any] = field(default_factory=dict)  # KeyframeParams fields
    points: dict[str, Any] = field(default_factory=dict)  # TrackPointsParams fields: the
    # keyframes' sparse points from the dense tracks (docs/frontend.md, round 6)
    init: dict[str, Any] = field(default_factory=dict)  # InitParams fields
    imu: dict[str, Any] = field(default_factory=dict)  # ImuNoise fields
    ground: dict[str, Any] = field(default_factory=dict)  # GroundParams fields: camera_height_m
    # (> 0 on a car with rectified images) adds the road-plane translation (docs/frontend.md)
    image_topic: str = "/camera/image"
    imu_topic: str = "/imu"
    odometry_topic: str = "/frontend/odometry"
    keyframe_topic: str = "/frontend/keyframe"
    frame_id: str = "world"

    def __post_init__(self) -> None:
        if len(self.T_imu_cam) != 16:
            raise ConfigError(f"frontend.T_imu_cam: need 16 numbers, got {len(self.T_imu_cam)}")

    def build(self, where: str = "frontend") -> tuple[FrontendParams, CameraModel, np.ndarray]:
        """The algorithm's parameters, camera model and ``T_imu_cam`` [4, 4]."""
        groups = {
            "tracker": parse_params(TrackerParams, self.tracker, where=f"{where}.tracker"),
            "estimator": parse_params(EstimatorParams, self.estimator, where=f"{where}.estimator"),
            "keyframes": parse_params(KeyframeParams, self.keyframes, where=f"{where}.keyframes"),
            "points": parse_params(TrackPointsParams, self.points, where=f"{where}.points"),
            "init": parse_params(InitParams, self.init, where=f"{where}.init"),
            "imu": parse_params(ImuNoise, self.imu, where=f"{where}.imu"),
            "ground": parse_params(GroundParams, self.ground, where=f"{where}.ground"),
            "bounds": parse_params(PlatformBounds, self.bounds, where=f"{where}.bounds"),
            "time_offset": parse_params(
                TimeOffsetParams, self.time_offset, where=f"{where}.time_offset"
            ),
        }
        params = FrontendParams(
            init_mode=self.init_mode,
            time_offset_ns=self.time_offset_ns,
            platform=self.platform,
            **groups,
        )
        cam = CameraModel(
            PinholeCamera(self.fx_px, self.fy_px, self.cx_px, self.cy_px, self.width, self.height),
            self.distortion_model,
            tuple(self.distortion_coeffs),
        )
        T = np.asarray(self.T_imu_cam, dtype=np.float64).reshape(4, 4)
        if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-5) or not np.allclose(
            T[3], [0, 0, 0, 1]
        ):
            raise ConfigError(f"{where}.T_imu_cam: not a rigid transform")
        return params, cam, T


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
    """Visual-inertial frontend process."""

    Params = FrontendNodeParams

    def setup(self) -> None:
        p: FrontendNodeParams = self.params
        fp, cam, T_imu_cam = p.build(self.name)
        self.frontend = Frontend(fp, cam, T_imu_cam)
        self._last_T_world_cam = np.eye(4)  # best pose so far: acknowledges frames without one
        self._last_velocity = np.zeros(3)
        self.subscribe(p.imu_topic, self.on_imu, reliable=True, msg_type=msgs.Imu)
        self.subscribe(p.image_topic, self.on_image, reliable=False, msg_type=msgs.Image)
        # after a restart: replay every journaled image + IMU sample (deterministic: the same
        # keyframe ids); only odometry and keyframes the journal lacks are published
        self.catch_up((p.imu_topic, p.image_topic), (p.odometry_topic, p.keyframe_topic))

    def on_imu(self, msg: msgs.Imu) -> None:
        for out in self.frontend.add_imu(msg.stamp_ns, msg.gyro_rad_s, msg.accel_m_s2):
            self._publish(out)

    def on_image(self, msg: msgs.Image) -> None:
        img = msg.data
        if msg.encoding == "bgr8":
            img = np.ascontiguousarray(img[..., ::-1])
        fe = self.frontend
        pending = fe.pending_stamps_ns
        rejected = fe.counters["image_time_backwards"] + fe.counters["image_wrong_size"]
        outs = fe.add_image(msg.stamp_ns, img)
        if fe.counters["image_time_backwards"] + fe.counters["image_wrong_size"] > rejected:
            self._acknowledge(msg.stamp_ns, "rejected")
        waiting = set(fe.pending_stamps_ns) | {o.stamp_ns for o in outs}
        for t in pending:  # frames dropped while waiting for their IMU
            if t not in waiting:
                self._acknowledge(t, "dropped")
        for out in outs:
            self._publish(out)

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
        if out.keyframe is not None:
            self.publish(p.keyframe_topic, keyframe_message(out.keyframe, p.frame_id))

    def diagnostics(self, status: str | None = None) -> msgs.Diagnostics:
        d = super().diagnostics(status)
        d.counters.update({f"frontend_{k}": float(v) for k, v in self.frontend.counters.items()})
        d.counters.update({f"frontend_{k}": v for k, v in self.frontend.figures().items()})
        return d
