"""ROS 2 bridge: the rclpy mirror of the bus, with the conversions of :mod:`bridges.ros_convert`.

The conversions (shared with the ROS 1 bridge and ``mogs record``) are pure functions over the
``rosbags`` typestore classes, tested without ROS; ``mogs ros2`` publishes their CDR bytes through
rclpy. Tests and tools call them from :mod:`bridges.ros_convert`; this module keeps the two
readers whose defaults name ROS 2. Stamps are ``builtin_interfaces/Time`` (sec, nanosec) of our
int ``stamp_ns``, in [0, 2^31 s).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

from bridges import ros_convert
from bridges.ros_convert import Distro, pose_to_ros
from bridges.ros_inputs import RosInputParams, RosInputs, calibration_line
from bridges.ros_outputs import RosOutputParams, RosOutputs
from bridges.ros_shell import RosBridgeShell
from mogs_node import msgs
from mogs_node.errors import MessageError, Ros2UnavailableError
from mogs_node.node import Node
from mogs_node.params import group_of

__all__ = [
    "Ros2Mirror",
    "Ros2MirrorParams",
    "Ros2UnavailableError",
    "depth_from_ros",
    "odometry_from_ros",
    "require_rclpy",
    "typestore",
]

log = logging.getLogger(__name__)


def typestore() -> Any:
    """The ROS 2 Humble typestore of ``rosbags`` (message classes and CDR codec)."""
    return ros_convert.typestore(Distro.ROS2)


def _header(stamp_ns: int, frame_id: str) -> Any:
    return ros_convert.header(stamp_ns, frame_id, Distro.ROS2)


def odometry_from_ros(ros: Any, *, frame_index: int = 0, status: str = "ros2") -> msgs.Odometry:
    """``nav_msgs/msg/Odometry`` -> ``Odometry`` (:func:`bridges.ros_convert.odometry_from_ros`)."""
    return ros_convert.odometry_from_ros(ros, frame_index=frame_index, status=status)


def depth_from_ros(
    ros: Any, *, keyframe_id: int = 0, source: str = "ros2", confidence: float = 1.0
) -> msgs.DepthMap:
    """32FC1 / 16UC1 image -> metric ``DepthMap`` (:func:`bridges.ros_convert.depth_from_ros`)."""
    return ros_convert.depth_from_ros(
        ros, keyframe_id=keyframe_id, source=source, confidence=confidence
    )


# ------------------------------------------------------------------------------ rclpy mirror


def require_rclpy() -> Any:
    """Import rclpy or raise :class:`Ros2UnavailableError` saying what to install."""
    try:
        import rclpy
    except ImportError as err:
        raise Ros2UnavailableError(
            "rclpy is not importable: `mogs ros2` needs a ROS 2 installation (e.g. Humble or "
            "Jazzy; `source /opt/ros/<distro>/setup.bash` first, with the same Python). "
            f"({err})"
        ) from err
    return rclpy


@dataclass(frozen=True)
class Ros2MirrorParams:
    """Parameters of the ROS 2 mirror node."""

    ros_image_topic: str = "/camera/image_raw"  # ROS 2 camera in -> /camera/image
    ros_image_compressed: bool = False  # the camera is sensor_msgs/CompressedImage (jpeg / png)
    ros_imu_topic: str = "/imu"  # ROS 2 sensor_msgs/Imu in -> /imu
    ros_camera_info_topic: str = ""  # sensor_msgs/CameraInfo -> the calibration on /camera/info
    # ("" = none: the frontend's launch values)
    ros_tf_static_topic: str = "/tf_static"  # T_imu_cam (the IMU's frame -> the camera's)
    T_imu_cam: tuple[float, ...] | None = None  # without /tf_static: the camera in the IMU frame
    # (16 numbers, row-major; None: the frontend's own launch value)
    tf_wait_s: float = 1.0  # after the first CameraInfo, wait this long for /tf_static
    camera_info_period_s: float = 2.0  # the calibration on the bus again this often
    mirror_in: bool = True  # bring the ROS 2 camera and IMU onto the bus
    mirror_out: bool = True  # publish odometry, path, map cloud, depth, map stats to ROS 2
    ros_prefix: str = "/mogs"  # ROS 2 names of the outputs: <prefix>/odometry, /path,
    # /map_cloud, /depth, /keyframe_pose, /map_stats, and tf (world -> camera)
    world_frame: str = "world"  # parent frame of poses, path, cloud and tf
    map_period_s: float = 2.0  # map cloud at most this often (0: after every mapped keyframe)
    tick_s: float = 0.005  # how often the rclpy executor is spun

    def __post_init__(self) -> None:
        self.inputs()  # checks T_imu_cam, tf_wait_s

    def inputs(self) -> RosInputParams:
        return group_of(
            RosInputParams,
            self,
            camera_info_topic=self.ros_camera_info_topic,
            tf_static_topic=self.ros_tf_static_topic,
            source="ros2",
        )


class Ros2Mirror(RosBridgeShell, Node):
    """Mirrors the bus to and from ROS 2 through rclpy, with the conversions of
    :mod:`bridges.ros_convert` and the outputs of :mod:`bridges.ros_outputs` (shared with the
    ROS 1 node).

    Messages cross as CDR bytes: rclpy publishers accept serialized messages and subscriptions
    created with ``raw=True`` deliver them, so the rosbags typestore does the (tested) encoding.
    """

    Params = Ros2MirrorParams
    bus_camera_info_topic = "/camera/info"

    def setup(self) -> None:
        rclpy = require_rclpy()
        p: Ros2MirrorParams = self.params
        if not rclpy.ok():
            rclpy.init()
        self.rnode = rclpy.create_node(self.name.replace("/", "_"))
        self._rclpy = rclpy
        self._out: dict[str, tuple[Any, str]] = {}
        if p.mirror_in:
            self._mirror_in()
        if p.mirror_out:
            self._mirror_out()
            self.every(max(0.1, min(1.0, p.map_period_s)), self.flush_map)
        self.every(p.tick_s, self.spin_ros)
        self.log.info("mirroring to ROS 2 as node %s", self.rnode.get_name())

    def _sub(self, rtype: str, topic: str, callback: Any, qos: Any = None) -> None:
        from rclpy.qos import qos_profile_sensor_data
        from rosidl_runtime_py.utilities import get_message

        self.rnode.create_subscription(
            get_message(rtype), topic, callback, qos or qos_profile_sensor_data, raw=True
        )

    def _mirror_in(self) -> None:
        """The camera, IMU, CameraInfo and /tf_static through :class:`RosInputs` (shared with the
        ROS 1 bridge): malformed messages are counted and logged, never fatal."""
        from rclpy.qos import DurabilityPolicy, QoSProfile

        p = self.params
        self.inputs = RosInputs(p.inputs(), Distro.ROS2)
        self.counters.update(ros_malformed=0, frames_published=0, imu_published=0)
        itype = "sensor_msgs/msg/" + ("CompressedImage" if p.ros_image_compressed else "Image")
        self._sub(itype, p.ros_image_topic, lambda raw: self._in_image(itype, raw))
        self._sub("sensor_msgs/msg/Imu", p.ros_imu_topic, self._in_imu)
        if p.ros_camera_info_topic:
            self._sub("sensor_msgs/msg/CameraInfo", p.ros_camera_info_topic, self._in_info)
            latched = QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self._sub("tf2_msgs/msg/TFMessage", p.ros_tf_static_topic, self._in_tf, latched)
            self.every(0.2, self._calibration_due)
            self.every(p.camera_info_period_s, self._republish_calibration)

    def _in_image(self, itype: str, raw: bytes) -> None:
        try:
            img = self.inputs.image(itype, raw)
        except MessageError as err:
            self._bad("image", err)
            return
        if self.params.mirror_out:
            self.outputs.input_frame = img.frame_id
        self.publish("/camera/image", img)
        self.counters["frames_published"] += 1

    def _in_imu(self, raw: bytes) -> None:
        try:
            imu = self.inputs.imu(raw)
        except MessageError as err:
            self._bad("IMU", err)
            return
        self.publish("/imu", imu)
        self.counters["imu_published"] += 1

    def _in_info(self, raw: bytes) -> None:
        try:
            cal = self.inputs.camera_info(raw, time.monotonic())
        except MessageError as err:
            self._bad("CameraInfo", err)
            return
        if cal is not None:
            self.log.info(*calibration_line(cal, self.params.ros_camera_info_topic))

    def _in_tf(self, raw: bytes) -> None:
        try:
            self.inputs.tf_static(raw)
        except MessageError as err:
            self._bad("tf_static", err)

    def _mirror_out(self) -> None:
        from rosidl_runtime_py.utilities import get_message

        p = self.params
        pre = p.ros_prefix.rstrip("/")
        self.outputs = RosOutputs(
            RosOutputParams(
                prefix=p.ros_prefix,
                world_frame=p.world_frame,
                map_period_s=p.map_period_s,
                diagnostics_topic=f"{pre}/map_stats",
            ),
            Distro.ROS2,
        )
        topics = self.outputs.params.publisher_types()  # map stats on <prefix>/map_stats
        topics[f"{pre}/keyframe_pose"] = "geometry_msgs/msg/PoseStamped"
        for name, rtype in topics.items():
            self._out[name] = (self.rnode.create_publisher(get_message(rtype), name, 10), rtype)
        self._subscribe_outputs()

    def _send(self, triples: list[tuple[str, str, Any]]) -> None:
        for name, rtype, rmsg in triples:
            pub, _ = self._out[name]
            pub.publish(ros_convert.serialize(rmsg, rtype, Distro.ROS2))

    def on_odometry(self, msg: msgs.Message) -> None:
        assert isinstance(msg, msgs.Odometry)
        self._send(self.outputs.on_odometry(msg))

    def on_keyframe(self, msg: msgs.Message) -> None:
        p = self.params
        assert isinstance(msg, msgs.Keyframe)
        pose = pose_to_ros(msg.stamp_ns, msg.T_world_cam, world_frame=p.world_frame)
        rtype = "geometry_msgs/msg/PoseStamped"
        self._send([(f"{p.ros_prefix.rstrip('/')}/keyframe_pose", rtype, pose)])
        self._send(self.outputs.on_keyframe(msg))

    def on_keyframe_pose(self, msg: msgs.Message) -> None:
        assert isinstance(msg, msgs.PoseStamped)
        self._send(self.outputs.on_keyframe_pose(msg))

    def on_depth(self, msg: msgs.Message) -> None:
        assert isinstance(msg, msgs.DepthMap)
        self._send(self.outputs.on_depth(msg))

    def on_gaussians(self, msg: msgs.Message) -> None:
        assert isinstance(msg, msgs.GaussianUpdate)
        self._send(self.outputs.on_gaussians(msg, time.monotonic()))

    def on_stats(self, msg: msgs.Message) -> None:
        assert isinstance(msg, msgs.MapStats)
        self._send(self.outputs.on_stats(msg))

    def flush_map(self) -> None:
        self._send(self.outputs.flush(time.monotonic()))

    def spin_ros(self) -> None:
        self._rclpy.spin_once(self.rnode, timeout_sec=0.0)

    def teardown(self) -> None:
        self.rnode.destroy_node()
        if self._rclpy.ok():
            self._rclpy.shutdown()
