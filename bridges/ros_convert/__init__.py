"""Conversions between our messages and standard ROS messages, for ROS 1 and ROS 2 alike.

Pure functions over the ``rosbags`` typestore classes (ROS 1 Noetic or ROS 2 Humble, chosen by
:class:`Distro`): no ROS installation is needed, so they are tested without one, and the ROS 1
bridge (:mod:`bridges.ros1`), the ROS 2 mirror (:mod:`bridges.ros2`) and ``mogs record`` share them.
The bridges move the bytes (:func:`serialize` / :func:`deserialize`: ROS 1 wire format or CDR).

| ours | ROS |
| --- | --- |
| ``Image`` (mono8, rgb8, bgr8) | ``sensor_msgs/Image`` (same encoding; 8UC1 read as mono8) |
| ``Image`` | ``sensor_msgs/CompressedImage`` (jpeg or png, decoded with OpenCV) |
| :class:`CameraCalibration` | ``sensor_msgs/CameraInfo`` (K, D, size; plumb_bob / equidistant) |
| ``Imu`` | ``sensor_msgs/Imu`` (orientation unknown: ``orientation_covariance[0] = -1``) |
| ``Odometry`` | ``nav_msgs/Odometry``: pose ``T_world_cam``, twist in the child (camera) frame |
| keyframe poses ``[N, 4, 4]`` | ``nav_msgs/Path`` |
| ``PoseStamped`` | ``geometry_msgs/PoseStamped`` |
| Gaussian centres + colours | ``sensor_msgs/PointCloud2`` x, y, z float32 + rgb (packed, as RViz) |
| ``DepthMap`` (metric) | ``sensor_msgs/Image`` 32FC1 metres, NaN where there is no value (REP 118) |
| a pose | ``tf2_msgs/TFMessage`` with one ``TransformStamped`` |
| ``MapStats`` | ``diagnostic_msgs/DiagnosticArray`` with one status of key/value pairs |

Each ``*_from_ros`` raises one :class:`~mogs_node.errors.MessageError` naming the field when the
message is malformed; a bridge counts it and keeps running. Stamps are int nanoseconds; ROS 1 time
is unsigned 32-bit seconds, ROS 2 signed.
"""

from __future__ import annotations

from typing import Any

from bridges.ros_convert.base import (
    Distro,
    deserialize,
    header,
    msgdef_md5,
    ros_stamp_ns,
    rostype,
    serialize,
    typestore,
)
from bridges.ros_convert.images import (
    CameraCalibration,
    camera_info_from_ros,
    camera_info_to_ros,
    compressed_image_from_ros,
    compressed_image_to_ros,
    depth_from_ros,
    depth_to_ros,
    image_from_ros,
    image_to_ros,
)
from bridges.ros_convert.maps import (
    mapstats_from_ros,
    mapstats_to_ros,
    pointcloud_from_ros,
    pointcloud_to_ros,
)
from bridges.ros_convert.motion import (
    imu_from_ros,
    imu_to_ros,
    odometry_from_ros,
    odometry_to_ros,
    path_from_ros,
    path_to_ros,
    pose_from_ros,
    pose_to_ros,
    tf_from_pose,
    transforms_from_ros,
)
from mogs_node import msgs

__all__ = [
    "ROS_TYPES",
    "CameraCalibration",
    "Distro",
    "camera_info_from_ros",
    "camera_info_to_ros",
    "compressed_image_from_ros",
    "compressed_image_to_ros",
    "depth_from_ros",
    "depth_to_ros",
    "deserialize",
    "header",
    "image_from_ros",
    "image_to_ros",
    "imu_from_ros",
    "imu_to_ros",
    "mapstats_from_ros",
    "mapstats_to_ros",
    "msgdef_md5",
    "odometry_from_ros",
    "odometry_to_ros",
    "path_from_ros",
    "path_to_ros",
    "pointcloud_from_ros",
    "pointcloud_to_ros",
    "pose_from_ros",
    "pose_to_ros",
    "ros_stamp_ns",
    "rostype",
    "serialize",
    "tf_from_pose",
    "to_ros",
    "transforms_from_ros",
    "typestore",
]

# ------------------------------------------------------------------------------------ dispatch

#: our type -> the ROS type :func:`to_ros` produces for it
ROS_TYPES = {
    "Image": "sensor_msgs/msg/Image",
    "Imu": "sensor_msgs/msg/Imu",
    "Odometry": "nav_msgs/msg/Odometry",
    "PoseStamped": "geometry_msgs/msg/PoseStamped",
    "Keyframe": "geometry_msgs/msg/PoseStamped",
    "DepthMap": "sensor_msgs/msg/Image",
    "MapStats": "diagnostic_msgs/msg/DiagnosticArray",
}


def to_ros(msg: msgs.Message, *, distro: Distro = Distro.ROS2) -> tuple[str, Any] | None:
    """The standard ROS form of ``msg`` as ``(ros type name, message)``, or None if it has none.

    Keyframes become their pose; only metric depth maps convert.
    """
    if isinstance(msg, msgs.Image):
        return ROS_TYPES["Image"], image_to_ros(msg, distro=distro)
    if isinstance(msg, msgs.Imu):
        return ROS_TYPES["Imu"], imu_to_ros(msg, distro=distro)
    if isinstance(msg, msgs.Odometry):
        return ROS_TYPES["Odometry"], odometry_to_ros(msg, distro=distro)
    if isinstance(msg, msgs.PoseStamped | msgs.Keyframe):
        return ROS_TYPES["PoseStamped"], pose_to_ros(msg.stamp_ns, msg.T_world_cam, distro=distro)
    if isinstance(msg, msgs.DepthMap) and msg.kind == "metric":
        return ROS_TYPES["DepthMap"], depth_to_ros(msg, distro=distro)
    if isinstance(msg, msgs.MapStats):
        return ROS_TYPES["MapStats"], mapstats_to_ros(msg, distro=distro)
    return None
