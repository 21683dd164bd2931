"""The frontend node's configuration: its parameters (calibration overrides, algorithm groups)
and the adapters between its messages and the core types: ``/camera/info`` -> calibration
values, a keyframe -> ``/frontend/keyframe``. Pure (no bus), shared by the node shell
(:mod:`mogs_node.frontend.node`) and the in-process evaluation (:mod:`mogs_node.eval`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from mogs_node import msgs
from mogs_node.errors import ConfigError, GeometryError
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.estimator import EstimatorParams
from mogs_node.frontend.frontend import FrontendParams, KeyframeOutput
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
from mogs_node.params import parse_params

__all__ = [
    "CALIBRATION_FIELDS",
    "FRONTEND_MODES",
    "FrontendNodeParams",
    "camera_from_info",
    "keyframe_message",
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
