"""What a ROS bridge takes in: serialized ROS messages -> bus messages; pure state, no ROS, no bus.

:class:`RosInputs` decodes the camera (``sensor_msgs/Image`` mono8/rgb8/bgr8 or
``sensor_msgs/CompressedImage``), the IMU, the ``CameraInfo`` and ``/tf_static`` of ROS 1 or
ROS 2 (the wire bytes a rospy ``AnyMsg`` or an rclpy ``raw=True`` subscription delivers) with the
conversions of :mod:`bridges.ros_convert`, and assembles the bus's calibration
(:class:`~mogs_node.msgs.CameraInfo` on ``/camera/info``): intrinsics and distortion from the
CameraInfo, ``T_imu_cam`` from ``/tf_static`` (the IMU's frame -> the camera's frame) when it has
them, else the launch value, else unknown (the frontend's own launch value). The ROS 1 bridge
(:mod:`bridges.ros1`) and the ROS 2 mirror (:mod:`bridges.ros2`) share it; a test drives it
without either.

Every decode raises one :class:`~mogs_node.errors.MessageError` naming the field when the message
is malformed; the bridge counts it and goes on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bridges import ros_convert as rc
from bridges.ros_convert import Distro
from mogs_node import msgs
from mogs_node.errors import ConfigError, GeometryError, MessageError
from mogs_node.geometry import rigid_transform, tf_lookup

__all__ = ["IMAGE_TYPES", "RosInputParams", "RosInputs", "calibration_line"]

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


@dataclass(frozen=True)
class RosInputParams:
    """Where the calibration comes from."""

    camera_info_topic: str = "/camera/camera_info"  # named in the calibration's source
    tf_static_topic: str = "/tf_static"  # named in the calibration's source
    T_imu_cam: tuple[float, ...] | None = None  # without /tf_static: the camera in the IMU frame
    # (16 numbers, row-major; None: the frontend's own launch value)
    tf_wait_s: float = 1.0  # after the first CameraInfo, wait this long for /tf_static
    source: str = "ros"  # the calibration's source names this ("ros1", "ros2")

    def __post_init__(self) -> None:
        if self.tf_wait_s < 0:
            raise ConfigError(f"{self.source}.tf_wait_s: >= 0, got {self.tf_wait_s}")
        if self.T_imu_cam is not None:
            try:
                rigid_transform(self.T_imu_cam, f"{self.source}.T_imu_cam")
            except GeometryError as err:
                raise ConfigError(str(err)) from err


class RosInputs:
    """Serialized ROS inputs -> bus messages (see the module docstring); ``now_s`` is a monotonic
    time the caller passes (the wait for ``/tf_static``), so this stays pure and testable."""

    def __init__(self, params: RosInputParams, distro: Distro) -> None:
        self.params = params
        self.distro = distro
        self.calibration: rc.CameraCalibration | None = None  # the first valid CameraInfo
        self.calibration_msg: msgs.CameraInfo | None = None  # the bus's, once assembled
        self.tf_edges: dict[tuple[str, str], np.ndarray] = {}
        self.imu_frame = ""  # the IMU's frame id (the first sample's)
        self.image_frame = ""  # the camera images' frame id (the last image's)
        self._calibration_since_s: float | None = None
        self.malformed = 0  # malformed messages so far

    def count_malformed(self, what: str, err: Exception) -> str | None:
        """Counts a malformed ``what``; the line to log at the 1st, 2nd, 4th, ... (else None:
        a flood of bad input is not a log flood)."""
        self.malformed += 1
        n = self.malformed
        return f"malformed {what} from ROS ({n} so far): {err}" if n & (n - 1) == 0 else None

    def image(self, rtype: str, raw: bytes) -> msgs.Image:
        """A camera message of ROS type ``rtype`` (either spelling) -> ``Image``."""
        t = rc.rostype(rtype) if rtype else ""
        if t not in IMAGE_TYPES:
            raise MessageError(
                f"a camera topic carries {rtype!r}, expected one of {IMAGE_TYPES}", field="type"
            )
        ros = rc.deserialize(raw, t, self.distro)
        if t == "sensor_msgs/msg/CompressedImage":
            img = rc.compressed_image_from_ros(ros)
        else:
            img = rc.image_from_ros(ros)
        self.image_frame = img.frame_id
        return img

    def imu(self, raw: bytes) -> msgs.Imu:
        m = rc.imu_from_ros(rc.deserialize(raw, "sensor_msgs/msg/Imu", self.distro))
        self.imu_frame = self.imu_frame or m.frame_id
        return m

    def tf_static(self, raw: bytes) -> None:
        ros = rc.deserialize(raw, "tf2_msgs/msg/TFMessage", self.distro)
        self.tf_edges.update(rc.transforms_from_ros(ros))

    def camera_info(self, raw: bytes, now_s: float) -> rc.CameraCalibration | None:
        """The calibration of the first valid CameraInfo (returned once: the caller logs it);
        later ones None (the frontend keeps its first calibration)."""
        if self.calibration is not None:
            return None
        ros = rc.deserialize(raw, "sensor_msgs/msg/CameraInfo", self.distro)
        self.calibration = rc.camera_info_from_ros(ros)
        self._calibration_since_s = now_s
        return self.calibration

    def calibration_due(self, now_s: float) -> tuple[msgs.CameraInfo, str] | None:
        """The bus's calibration and where its ``T_imu_cam`` came from ("" = unknown), once:
        when ``T_imu_cam`` is found on ``/tf_static``, given in the launch file, or
        ``tf_wait_s`` after the CameraInfo (then unknown). None before or after that."""
        p, cal = self.params, self.calibration
        if cal is None or self.calibration_msg is not None:
            return None
        T, where = None, ""
        if self.tf_edges and self.imu_frame:
            imu, cam = self.imu_frame.lstrip("/"), cal.frame_id.lstrip("/")
            T = tf_lookup(self.tf_edges, imu, cam)
            where = f"{p.tf_static_topic} {imu} -> {cam}"
        if T is None and p.T_imu_cam is not None:
            T, where = rigid_transform(p.T_imu_cam, f"{p.source}.T_imu_cam")[0], "the launch file"
        assert self._calibration_since_s is not None
        if T is None and now_s - self._calibration_since_s < p.tf_wait_s:
            return None
        where = where if T is not None else ""
        source = f"{p.source}:{p.camera_info_topic}" + (f" + {where}" if where else "")
        self.calibration_msg = cal.message(T_imu_cam=T, source=source)
        return self.calibration_msg, where


def calibration_line(cal: rc.CameraCalibration, topic: str) -> tuple[Any, ...]:
    """The log line (format, args) of a received CameraInfo."""
    c = cal.camera
    return (
        "CameraInfo on %s: %dx%d fx %.3f fy %.3f cx %.3f cy %.3f, %s %s",
        topic,
        c.width,
        c.height,
        c.fx_px,
        c.fy_px,
        c.cx_px,
        c.cy_px,
        cal.distortion_model,
        list(cal.distortion_coeffs),
    )
