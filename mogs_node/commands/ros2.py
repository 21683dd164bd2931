"""``mogs ros2``: mirror the bus to and from ROS 2 (needs rclpy, i.e. a ROS 2 installation).

In: ROS 2 ``sensor_msgs/Image`` or ``CompressedImage`` (``--image-topic``, ``--compressed``) and
``sensor_msgs/Imu`` (``--imu-topic``) become ``/camera/image`` and ``/imu``; a ``CameraInfo``
(``--camera-info-topic``) with ``T_imu_cam`` from ``/tf_static`` becomes the calibration on
``/camera/info``. Out: ``/frontend/odometry`` (``nav_msgs/Odometry`` + ``/tf``), the keyframe path
(``nav_msgs/Path``, following the window's refinements) and poses, the map cloud
(``sensor_msgs/PointCloud2``), ``/metrizer/depth`` (32FC1 image) and ``/mapper/stats``
(``diagnostic_msgs/DiagnosticArray``) under ``--prefix`` (default ``/mogs``).
Without rclpy the command exits with code 1 and says so.
"""

from __future__ import annotations

import argparse

from mogs_node.commands.broker import bus_from_args
from mogs_node.commands.play import _endpoint_args

HELP = "mirror bus topics to and from ROS 2 (needs rclpy)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--image-topic", default="/camera/image_raw", help="ROS 2 image input")
    parser.add_argument("--imu-topic", default="/imu", help="ROS 2 IMU input")
    parser.add_argument(
        "--compressed", action="store_true", help="the camera is sensor_msgs/CompressedImage"
    )
    parser.add_argument(
        "--camera-info-topic",
        default="",
        help="ROS 2 CameraInfo: the calibration on /camera/info (T_imu_cam from /tf_static)",
    )
    parser.add_argument("--prefix", default="/mogs", help="ROS 2 namespace of the outputs")
    parser.add_argument("--no-in", action="store_true", help="do not bring ROS 2 sensors in")
    parser.add_argument("--no-out", action="store_true", help="do not publish results to ROS 2")
    _endpoint_args(parser)


def command(args: argparse.Namespace) -> int:
    from bridges.ros2 import Ros2Mirror, require_rclpy

    require_rclpy()  # before touching the bus: a clear message when ROS 2 is missing
    params = {
        "ros_image_topic": args.image_topic,
        "ros_imu_topic": args.imu_topic,
        "ros_image_compressed": args.compressed,
        "ros_camera_info_topic": args.camera_info_topic,
        "ros_prefix": args.prefix,
        "mirror_in": not args.no_in,
        "mirror_out": not args.no_out,
    }
    return Ros2Mirror("ros2_mirror", params, bus_from_args(args)).run()
