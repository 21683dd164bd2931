"""ROS 2 bridge: conversions between our messages and standard ROS 2 messages, and the rclpy mirror.

The conversions are pure functions over the ``rosbags`` typestore classes of ROS 2 Humble (no ROS
installation needed), so they are tested here and shared by ``mogs record`` (standard types in the
MCAP file) and ``mogs ros2`` (which publishes their CDR bytes through rclpy):

| ours | ROS 2 |
| --- | --- |
| ``Image`` (mono8, rgb8, bgr8) | ``sensor_msgs/msg/Image`` (same encoding) |
| ``Imu`` | ``sensor_msgs/msg/Imu`` (orientation unknown: ``orientation_covariance[0] = -1``) |
| ``Odometry`` | ``nav_msgs/msg/Odometry``: pose = ``T_world_cam``, twist in the child (camera) frame |
| ``PoseStamped``, keyframe poses | ``geometry_msgs/msg/PoseStamped`` |
| a pose | ``tf2_msgs/msg/TFMessage`` with one ``TransformStamped`` (parent ``world``) |
| ``DepthMap`` | ``sensor_msgs/msg/Image`` 32FC1 metres, NaN where there is no value (REP 118) |
| ``MapStats`` | ``diagnostic_msgs/msg/DiagnosticArray`` with one status of key/value pairs |

Stamps are ``builtin_interfaces/Time`` (sec, nanosec) of our int ``stamp_ns``, in [0, 2^31 s).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from mogs_node import msgs
from mogs_node.errors import MessageError, Ros2UnavailableError
from mogs_node.geometry import make_T, quat_wxyz_from_rotmat, quat_wxyz_to_rotmat
from mogs_node.node import Node

__all__ = [
    "ROS_TYPES",
    "Ros2Mirror",
    "Ros2MirrorParams",
    "Ros2UnavailableError",
    "depth_from_ros",
    "depth_to_ros",
    "image_from_ros",
    "image_to_ros",
    "imu_from_ros",
    "imu_to_ros",
    "mapstats_from_ros",
    "mapstats_to_ros",
    "odometry_from_ros",
    "odometry_to_ros",
    "pose_from_ros",
    "pose_to_ros",
    "require_rclpy",
    "ros_stamp_ns",
    "tf_from_pose",
    "to_ros",
    "typestore",
]

log = logging.getLogger(__name__)

#: our type -> the ROS 2 type :func:`to_ros` produces for it
ROS_TYPES = {
    "Image": "sensor_msgs/msg/Image",
    "Imu": "sensor_msgs/msg/Imu",
    "Odometry": "nav_msgs/msg/Odometry",
    "PoseStamped": "geometry_msgs/msg/PoseStamped",
    "Keyframe": "geometry_msgs/msg/PoseStamped",
    "DepthMap": "sensor_msgs/msg/Image",
    "MapStats": "diagnostic_msgs/msg/DiagnosticArray",
}


@lru_cache(maxsize=1)
def typestore() -> Any:
    """The ROS 2 Humble typestore of ``rosbags`` (message classes and CDR codec)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _T(name: str) -> Any:
    return typestore().types[name]


_MAX_NS = (1 << 31) * 1_000_000_000  # builtin_interfaces/Time.sec is int32


def _header(stamp_ns: int, frame_id: str) -> Any:
    if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int) or not 0 <= stamp_ns < _MAX_NS:
        raise MessageError(
            f"ROS 2 time (int32 seconds) needs an int in [0, 2^31 s), got {stamp_ns!r}",
            field="stamp_ns",
        )
    t = _T("builtin_interfaces/msg/Time")(
        sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)
    )
    return _T("std_msgs/msg/Header")(stamp=t, frame_id=frame_id)


def ros_stamp_ns(header: Any) -> int:
    """``header.stamp`` as int nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _pose(T_world_x: np.ndarray) -> Any:
    T = np.asarray(T_world_x, dtype=np.float64)
    q = quat_wxyz_from_rotmat(T[:3, :3])
    t = T[:3, 3]
    return _T("geometry_msgs/msg/Pose")(
        position=_T("geometry_msgs/msg/Point")(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=_T("geometry_msgs/msg/Quaternion")(
            x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])
        ),
    )


def _pose_T(pose: Any) -> np.ndarray:
    q, p = pose.orientation, pose.position
    R = quat_wxyz_to_rotmat(np.array([q.w, q.x, q.y, q.z], dtype=np.float64))
    return make_T(R, np.array([p.x, p.y, p.z], dtype=np.float64))


def _vec3(v: Any) -> Any:
    return _T("geometry_msgs/msg/Vector3")(x=float(v[0]), y=float(v[1]), z=float(v[2]))


# ------------------------------------------------------------------------------------- images


def image_to_ros(msg: msgs.Image) -> Any:
    """``Image`` -> ``sensor_msgs/msg/Image`` with the same encoding and dense rows."""
    msg.validate()
    data = np.ascontiguousarray(msg.data)
    h, w = data.shape[:2]
    return _T("sensor_msgs/msg/Image")(
        header=_header(msg.stamp_ns, msg.frame_id),
        height=h,
        width=w,
        encoding=msg.encoding,
        is_bigendian=0,
        step=w * (3 if data.ndim == 3 else 1),
        data=data.reshape(-1),
    )


def _rows(ros: Any, channels: int, dtype: np.dtype, where: str) -> np.ndarray:
    h, w, step = int(ros.height), int(ros.width), int(ros.step)
    item = np.dtype(dtype).itemsize
    data = np.asarray(ros.data, dtype=np.uint8).reshape(-1)
    if step < w * channels * item or data.size < h * step:
        raise MessageError(
            f"{data.size} bytes do not hold {w}x{h} {ros.encoding} with step {step}", field=where
        )
    rows = np.ascontiguousarray(data[: h * step].reshape(h, step)[:, : w * channels * item])
    order = ">" if ros.is_bigendian else "<"
    arr = rows.view(np.dtype(dtype).newbyteorder(order)).astype(dtype)
    return arr.reshape(h, w, channels) if channels > 1 else arr.reshape(h, w)


def image_from_ros(ros: Any) -> msgs.Image:
    """``sensor_msgs/msg/Image`` mono8 / 8UC1 / rgb8 / bgr8 -> ``Image`` (encoding kept)."""
    enc = {"8UC1": "mono8"}.get(ros.encoding, ros.encoding)
    if enc not in msgs.Image.ENCODINGS:
        raise MessageError(
            f"unsupported encoding {ros.encoding!r} (mono8, 8UC1, rgb8, bgr8)", field="encoding"
        )
    data = _rows(ros, 1 if enc == "mono8" else 3, np.uint8, "data")
    out = msgs.Image(
        stamp_ns=ros_stamp_ns(ros.header), frame_id=ros.header.frame_id, encoding=enc, data=data
    )
    out.validate()
    return out


def depth_to_ros(msg: msgs.DepthMap) -> Any:
    """``DepthMap`` (metric) -> 32FC1 ``sensor_msgs/msg/Image``, NaN where depth is 0."""
    msg.validate()
    if msg.kind != "metric":
        raise MessageError(f"only metric depth maps become 32FC1, got {msg.kind!r}", field="kind")
    d = np.where(msg.depth > 0, msg.depth, np.nan).astype("<f4")
    h, w = d.shape
    return _T("sensor_msgs/msg/Image")(
        header=_header(msg.stamp_ns, msg.frame_id),
        height=h,
        width=w,
        encoding="32FC1",
        is_bigendian=0,
        step=w * 4,
        data=d.reshape(-1).view(np.uint8),
    )


def depth_from_ros(
    ros: Any, *, keyframe_id: int = 0, source: str = "ros2", confidence: float = 1.0
) -> msgs.DepthMap:
    """32FC1 (metres) or 16UC1 (millimetres) image -> metric ``DepthMap`` (non-finite / <= 0 -> 0,
    ``confidence`` where there is a value, 0 elsewhere)."""
    if ros.encoding == "32FC1":
        d = _rows(ros, 1, np.float32, "data")
    elif ros.encoding == "16UC1":
        d = _rows(ros, 1, np.uint16, "data").astype(np.float32) / 1000.0
    else:
        raise MessageError(f"depth needs 32FC1 or 16UC1, got {ros.encoding!r}", field="encoding")
    valid = np.isfinite(d) & (d > 0)
    depth = np.where(valid, d, 0.0).astype(np.float32)
    out = msgs.DepthMap(
        stamp_ns=ros_stamp_ns(ros.header),
        frame_id=ros.header.frame_id,
        keyframe_id=keyframe_id,
        kind="metric",
        depth=depth,
        confidence=np.where(valid, np.float32(confidence), np.float32(0)).astype(np.float32),
        source=source,
    )
    out.validate()
    return out


# ---------------------------------------------------------------------------------------- imu


def imu_to_ros(msg: msgs.Imu) -> Any:
    """``Imu`` -> ``sensor_msgs/msg/Imu`` (orientation unknown, covariances zero = unknown)."""
    msg.validate()
    ocov = np.zeros(9)
    ocov[0] = -1.0
    return _T("sensor_msgs/msg/Imu")(
        header=_header(msg.stamp_ns, msg.frame_id),
        orientation=_T("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=ocov,
        angular_velocity=_vec3(msg.gyro_rad_s),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=_vec3(msg.accel_m_s2),
        linear_acceleration_covariance=np.zeros(9),
    )


def imu_from_ros(ros: Any) -> msgs.Imu:
    g, a = ros.angular_velocity, ros.linear_acceleration
    out = msgs.Imu(
        stamp_ns=ros_stamp_ns(ros.header),
        frame_id=ros.header.frame_id,
        gyro_rad_s=(float(g.x), float(g.y), float(g.z)),
        accel_m_s2=(float(a.x), float(a.y), float(a.z)),
    )
    out.validate()
    return out


# -------------------------------------------------------------------------------------- poses


def odometry_to_ros(
    msg: msgs.Odometry, *, world_frame: str = "world", child_frame: str | None = None
) -> Any:
    """``Odometry`` -> ``nav_msgs/msg/Odometry``: pose ``T_world_cam`` in ``world_frame``; the
    twist's linear velocity in the child (camera) frame, ``R_world_cam^T v_world`` (REP 103)."""
    msg.validate()
    R = msg.T_world_cam[:3, :3]
    v_cam = R.T @ np.asarray(msg.velocity_world_m_s, dtype=np.float64)
    T = typestore().types
    return T["nav_msgs/msg/Odometry"](
        header=_header(msg.stamp_ns, world_frame),
        child_frame_id=child_frame or msg.frame_id,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose(msg.T_world_cam), covariance=np.zeros(36)
        ),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=_vec3(v_cam), angular=_vec3((0.0, 0.0, 0.0))),
            covariance=np.zeros(36),
        ),
    )


def odometry_from_ros(ros: Any, *, frame_index: int = 0, status: str = "ros2") -> msgs.Odometry:
    """``nav_msgs/msg/Odometry`` -> ``Odometry`` (frame id = child frame; world-frame velocity)."""
    T = _pose_T(ros.pose.pose)
    lin = ros.twist.twist.linear
    v_world = T[:3, :3] @ np.array([lin.x, lin.y, lin.z], dtype=np.float64)
    out = msgs.Odometry(
        stamp_ns=ros_stamp_ns(ros.header),
        frame_id=ros.child_frame_id,
        frame_index=frame_index,
        T_world_cam=T,
        velocity_world_m_s=(float(v_world[0]), float(v_world[1]), float(v_world[2])),
        status=status,
    )
    out.validate()
    return out


def pose_to_ros(stamp_ns: int, T_world_cam: np.ndarray, *, world_frame: str = "world") -> Any:
    """A pose ``T_world_cam`` [4, 4] -> ``geometry_msgs/msg/PoseStamped`` in ``world_frame``."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise MessageError(f"expected a finite [4, 4] pose, got {T.shape}", field="T_world_cam")
    return _T("geometry_msgs/msg/PoseStamped")(header=_header(stamp_ns, world_frame), pose=_pose(T))


def pose_from_ros(ros: Any, *, frame_id: str = "camera") -> msgs.PoseStamped:
    out = msgs.PoseStamped(
        stamp_ns=ros_stamp_ns(ros.header), frame_id=frame_id, T_world_cam=_pose_T(ros.pose)
    )
    out.validate()
    return out


def tf_from_pose(
    stamp_ns: int, T_parent_child: np.ndarray, *, parent: str = "world", child: str = "camera"
) -> Any:
    """One transform ``T_parent_child`` [4, 4] as a ``tf2_msgs/msg/TFMessage``."""
    T = np.asarray(T_parent_child, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise MessageError(f"expected a finite [4, 4] pose, got {T.shape}", field="T_parent_child")
    p = _pose(T)
    tfm = _T("geometry_msgs/msg/Transform")(
        translation=_vec3((p.position.x, p.position.y, p.position.z)), rotation=p.orientation
    )
    ts = _T("geometry_msgs/msg/TransformStamped")(
        header=_header(stamp_ns, parent), child_frame_id=child, transform=tfm
    )
    return _T("tf2_msgs/msg/TFMessage")(transforms=[ts])


# --------------------------------------------------------------------------------- map stats

_STATS_FIELDS = ("keyframe_id", "n_gaussians", "n_keyframes", "iterations", "loss", "psnr_db")


def mapstats_to_ros(msg: msgs.MapStats, *, name: str = "mogs/mapper") -> Any:
    """``MapStats`` -> ``diagnostic_msgs/msg/DiagnosticArray``: one status ``name`` whose values
    are the fields and ``extra`` entries (``repr`` of each number, so floats round-trip)."""
    msg.validate()
    KV = _T("diagnostic_msgs/msg/KeyValue")
    values = [KV(key=k, value=repr(getattr(msg, k))) for k in _STATS_FIELDS]
    values += [KV(key=f"extra.{k}", value=repr(v)) for k, v in sorted(msg.extra.items())]
    Status = _T("diagnostic_msgs/msg/DiagnosticStatus")
    status = Status(
        level=Status.OK,
        name=name,
        message=f"keyframe {msg.keyframe_id}",
        hardware_id="",
        values=values,
    )
    return _T("diagnostic_msgs/msg/DiagnosticArray")(
        header=_header(msg.stamp_ns, msg.frame_id), status=[status]
    )


def _number(text: str, key: str) -> int | float:
    try:
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError as err:
            raise MessageError(f"value {text!r} is not a number", field=key) from err


def mapstats_from_ros(ros: Any) -> msgs.MapStats:
    """Inverse of :func:`mapstats_to_ros` (first status of the array)."""
    if not ros.status:
        raise MessageError("DiagnosticArray without a status", field="status")
    vals = {kv.key: kv.value for kv in ros.status[0].values}
    missing = [k for k in _STATS_FIELDS if k not in vals]
    if missing:
        raise MessageError(f"missing key(s) {missing}", field="values")
    f = {k: _number(vals[k], k) for k in _STATS_FIELDS}
    extra = {k[6:]: _number(v, k) for k, v in vals.items() if k.startswith("extra.")}
    out = msgs.MapStats(
        stamp_ns=ros_stamp_ns(ros.header),
        frame_id=ros.header.frame_id,
        keyframe_id=int(f["keyframe_id"]),
        n_gaussians=int(f["n_gaussians"]),
        n_keyframes=int(f["n_keyframes"]),
        iterations=int(f["iterations"]),
        loss=float(f["loss"]),
        psnr_db=float(f["psnr_db"]),
        extra=extra,
    )
    out.validate()
    return out


def to_ros(msg: msgs.Message) -> tuple[str, Any] | None:
    """The standard ROS 2 form of ``msg`` as ``(ros type name, message)``, or None if it has none.

    Keyframes become their pose; only metric depth maps convert.
    """
    if isinstance(msg, msgs.Image):
        return ROS_TYPES["Image"], image_to_ros(msg)
    if isinstance(msg, msgs.Imu):
        return ROS_TYPES["Imu"], imu_to_ros(msg)
    if isinstance(msg, msgs.Odometry):
        return ROS_TYPES["Odometry"], odometry_to_ros(msg)
    if isinstance(msg, msgs.PoseStamped | msgs.Keyframe):
        return ROS_TYPES["PoseStamped"], pose_to_ros(msg.stamp_ns, msg.T_world_cam)
    if isinstance(msg, msgs.DepthMap) and msg.kind == "metric":
        return ROS_TYPES["DepthMap"], depth_to_ros(msg)
    if isinstance(msg, msgs.MapStats):
        return ROS_TYPES["MapStats"], mapstats_to_ros(msg)
    return None


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

    ros_image_topic: str = "/camera/image_raw"  # ROS 2 sensor_msgs/Image in -> /camera/image
    ros_imu_topic: str = "/imu"  # ROS 2 sensor_msgs/Imu in -> /imu
    mirror_in: bool = True  # bring the ROS 2 camera and IMU onto the bus
    mirror_out: bool = True  # publish odometry, keyframe poses, depth and map stats to ROS 2
    ros_prefix: str = "/mogs"  # ROS 2 names of the outputs: <prefix>/odometry, /keyframe_pose,
    # /depth, /map_stats, and tf (world -> camera)
    world_frame: str = "world"  # parent frame of poses and tf
    tick_s: float = 0.005  # how often the rclpy executor is spun


class Ros2Mirror(Node):
    """Mirrors the bus to and from ROS 2 through rclpy, with the conversions of this module.

    Messages cross as CDR bytes: rclpy publishers accept serialized messages and subscriptions
    created with ``raw=True`` deliver them, so the rosbags typestore does the (tested) encoding.
    """

    Params = Ros2MirrorParams

    def setup(self) -> None:
        rclpy = require_rclpy()
        from rclpy.qos import qos_profile_sensor_data
        from rosidl_runtime_py.utilities import get_message

        p: Ros2MirrorParams = self.params
        if not rclpy.ok():
            rclpy.init()
        self.rnode = rclpy.create_node(self.name.replace("/", "_"))
        self._rclpy = rclpy
        ts = typestore()
        self._out: dict[str, tuple[Any, str]] = {}

        def out(name: str, rtype: str) -> None:
            pub = self.rnode.create_publisher(get_message(rtype), name, 10)
            self._out[name] = (pub, rtype)

        if p.mirror_in:

            def on_image(raw: bytes) -> None:
                self.publish(
                    "/camera/image",
                    image_from_ros(ts.deserialize_cdr(raw, "sensor_msgs/msg/Image")),
                )

            def on_imu(raw: bytes) -> None:
                self.publish("/imu", imu_from_ros(ts.deserialize_cdr(raw, "sensor_msgs/msg/Imu")))

            self.rnode.create_subscription(
                get_message("sensor_msgs/msg/Image"),
                p.ros_image_topic,
                on_image,
                qos_profile_sensor_data,
                raw=True,
            )
            self.rnode.create_subscription(
                get_message("sensor_msgs/msg/Imu"),
                p.ros_imu_topic,
                on_imu,
                qos_profile_sensor_data,
                raw=True,
            )
        if p.mirror_out:
            pre = p.ros_prefix.rstrip("/")
            out(f"{pre}/odometry", "nav_msgs/msg/Odometry")
            out(f"{pre}/keyframe_pose", "geometry_msgs/msg/PoseStamped")
            out(f"{pre}/depth", "sensor_msgs/msg/Image")
            out(f"{pre}/map_stats", "diagnostic_msgs/msg/DiagnosticArray")
            out("/tf", "tf2_msgs/msg/TFMessage")
            self.subscribe("/frontend/odometry", self.on_odometry, reliable=False)
            self.subscribe("/frontend/keyframe", self.on_keyframe, msg_type=msgs.Keyframe)
            self.subscribe("/metrizer/depth", self.on_depth, msg_type=msgs.DepthMap)
            self.subscribe("/mapper/stats", self.on_stats, msg_type=msgs.MapStats)
        self.every(p.tick_s, self.spin_ros)
        self.log.info("mirroring to ROS 2 as node %s", self.rnode.get_name())

    def _send(self, name: str, rmsg: Any) -> None:
        pub, rtype = self._out[name]
        pub.publish(typestore().serialize_cdr(rmsg, rtype))

    def on_odometry(self, msg: msgs.Message) -> None:
        p = self.params
        assert isinstance(msg, msgs.Odometry)
        self._send(
            f"{p.ros_prefix.rstrip('/')}/odometry", odometry_to_ros(msg, world_frame=p.world_frame)
        )
        self._send(
            "/tf",
            tf_from_pose(
                msg.stamp_ns, msg.T_world_cam, parent=p.world_frame, child=msg.frame_id or "camera"
            ),
        )

    def on_keyframe(self, msg: msgs.Message) -> None:
        p = self.params
        assert isinstance(msg, msgs.Keyframe)
        self._send(
            f"{p.ros_prefix.rstrip('/')}/keyframe_pose",
            pose_to_ros(msg.stamp_ns, msg.T_world_cam, world_frame=p.world_frame),
        )

    def on_depth(self, msg: msgs.Message) -> None:
        assert isinstance(msg, msgs.DepthMap)
        self._send(f"{self.params.ros_prefix.rstrip('/')}/depth", depth_to_ros(msg))

    def on_stats(self, msg: msgs.Message) -> None:
        assert isinstance(msg, msgs.MapStats)
        self._send(f"{self.params.ros_prefix.rstrip('/')}/map_stats", mapstats_to_ros(msg))

    def spin_ros(self) -> None:
        self._rclpy.spin_once(self.rnode, timeout_sec=0.0)

    def teardown(self) -> None:
        self.rnode.destroy_node()
        if self._rclpy.ok():
            self._rclpy.shutdown()
