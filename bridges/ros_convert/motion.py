"""IMU, odometry, poses, paths and tf."""

from __future__ import annotations

from typing import Any

import numpy as np

from bridges.ros_convert.base import (
    _T,
    Distro,
    _check_pose,
    _finite3,
    _pose,
    _pose_T,
    _vec3,
    header,
    ros_stamp_ns,
    typestore,
)
from mogs_node import msgs
from mogs_node.errors import MessageError

# ---------------------------------------------------------------------------------------- imu


def imu_to_ros(msg: msgs.Imu, *, distro: Distro = Distro.ROS2) -> Any:
    """``Imu`` -> ``sensor_msgs/Imu`` (orientation unknown, covariances zero = unknown)."""
    msg.validate()
    ocov = np.zeros(9)
    ocov[0] = -1.0  # REP 145: no orientation estimate
    return _T(distro, "sensor_msgs/msg/Imu")(
        header=header(msg.stamp_ns, msg.frame_id, distro),
        orientation=_T(distro, "geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=ocov,
        angular_velocity=_vec3(msg.gyro_rad_s, distro),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=_vec3(msg.accel_m_s2, distro),
        linear_acceleration_covariance=np.zeros(9),
    )


def imu_from_ros(ros: Any) -> msgs.Imu:
    """``sensor_msgs/Imu`` -> ``Imu`` (angular velocity and linear acceleration; finite)."""
    out = msgs.Imu(
        stamp_ns=ros_stamp_ns(ros.header),
        frame_id=ros.header.frame_id,
        gyro_rad_s=_finite3(ros.angular_velocity, "angular_velocity"),
        accel_m_s2=_finite3(ros.linear_acceleration, "linear_acceleration"),
    )
    out.validate()
    return out


# -------------------------------------------------------------------------------------- poses


def odometry_to_ros(
    msg: msgs.Odometry,
    *,
    world_frame: str = "world",
    child_frame: str | None = None,
    distro: Distro = Distro.ROS2,
) -> Any:
    """``Odometry`` -> ``nav_msgs/Odometry``: pose ``T_world_cam`` in ``world_frame``; the twist's
    linear velocity in the child (camera) frame, ``R_world_cam^T v_world`` (REP 103)."""
    msg.validate()
    v_cam = msg.T_world_cam[:3, :3].T @ np.asarray(msg.velocity_world_m_s, dtype=np.float64)
    T = typestore(distro).types
    return T["nav_msgs/msg/Odometry"](
        header=header(msg.stamp_ns, world_frame, distro),
        child_frame_id=child_frame or msg.frame_id,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose(msg.T_world_cam, distro), covariance=np.zeros(36)
        ),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](
                linear=_vec3(v_cam, distro), angular=_vec3((0.0, 0.0, 0.0), distro)
            ),
            covariance=np.zeros(36),
        ),
    )


def odometry_from_ros(ros: Any, *, frame_index: int = 0, status: str = "ros") -> msgs.Odometry:
    """``nav_msgs/Odometry`` -> ``Odometry`` (frame id = child frame; world-frame velocity)."""
    T = _pose_T(ros.pose.pose)
    v_cam = np.array(_finite3(ros.twist.twist.linear, "twist.linear"), dtype=np.float64)
    v_world = T[:3, :3] @ v_cam
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


def pose_to_ros(
    stamp_ns: int,
    T_world_cam: np.ndarray,
    *,
    world_frame: str = "world",
    distro: Distro = Distro.ROS2,
) -> Any:
    """A pose ``T_world_cam`` [4, 4] -> ``geometry_msgs/PoseStamped`` in ``world_frame``."""
    T = _check_pose(T_world_cam, "T_world_cam")
    return _T(distro, "geometry_msgs/msg/PoseStamped")(
        header=header(stamp_ns, world_frame, distro), pose=_pose(T, distro)
    )


def pose_from_ros(ros: Any, *, frame_id: str = "camera") -> msgs.PoseStamped:
    """``geometry_msgs/PoseStamped`` -> ``PoseStamped`` (``frame_id`` names the posed frame)."""
    out = msgs.PoseStamped(
        stamp_ns=ros_stamp_ns(ros.header), frame_id=frame_id, T_world_cam=_pose_T(ros.pose)
    )
    out.validate()
    return out


def path_to_ros(
    stamps_ns: np.ndarray,
    T_world_cam: np.ndarray,
    *,
    stamp_ns: int | None = None,
    world_frame: str = "world",
    distro: Distro = Distro.ROS2,
) -> Any:
    """Poses ``T_world_cam`` [N, 4, 4] at ``stamps_ns`` [N] -> ``nav_msgs/Path`` in ``world_frame``
    (its own stamp ``stamp_ns``, default the last pose's; N = 0 gives an empty path at 0)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    Ts = np.asarray(T_world_cam, dtype=np.float64)
    if Ts.shape != (len(stamps), 4, 4) or not np.isfinite(Ts).all():
        raise MessageError(
            f"expected finite [{len(stamps)}, 4, 4] poses, got {Ts.shape}", field="T_world_cam"
        )
    top = int(stamps[-1]) if len(stamps) else 0
    poses = [
        pose_to_ros(int(s), T, world_frame=world_frame, distro=distro) for s, T in zip(stamps, Ts)
    ]
    return _T(distro, "nav_msgs/msg/Path")(
        header=header(top if stamp_ns is None else stamp_ns, world_frame, distro), poses=poses
    )


def path_from_ros(ros: Any) -> tuple[np.ndarray, np.ndarray]:
    """``nav_msgs/Path`` -> (``stamps_ns`` int64 [N], ``T_world_cam`` float64 [N, 4, 4])."""
    stamps = np.array([ros_stamp_ns(p.header) for p in ros.poses], dtype=np.int64)
    Ts = [_pose_T(p.pose, f"poses[{i}].pose") for i, p in enumerate(ros.poses)]
    return stamps, np.asarray(Ts, dtype=np.float64).reshape(-1, 4, 4)


def tf_from_pose(
    stamp_ns: int,
    T_parent_child: np.ndarray,
    *,
    parent: str = "world",
    child: str = "camera",
    distro: Distro = Distro.ROS2,
) -> Any:
    """One transform ``T_parent_child`` [4, 4] as a ``tf2_msgs/TFMessage``."""
    p = _pose(_check_pose(T_parent_child, "T_parent_child"), distro)
    tfm = _T(distro, "geometry_msgs/msg/Transform")(
        translation=_vec3((p.position.x, p.position.y, p.position.z), distro),
        rotation=p.orientation,
    )
    ts = _T(distro, "geometry_msgs/msg/TransformStamped")(
        header=header(stamp_ns, parent, distro), child_frame_id=child, transform=tfm
    )
    return _T(distro, "tf2_msgs/msg/TFMessage")(transforms=[ts])


def transforms_from_ros(ros: Any) -> dict[tuple[str, str], np.ndarray]:
    """``tf2_msgs/TFMessage`` -> ``{(parent, child): T_parent_child [4, 4]}`` (frame names without a
    leading ``/``)."""
    out: dict[tuple[str, str], np.ndarray] = {}
    for i, ts in enumerate(ros.transforms):
        tr, q = ts.transform.translation, ts.transform.rotation
        pose = type("P", (), {"position": tr, "orientation": q})
        out[(ts.header.frame_id.lstrip("/"), ts.child_frame_id.lstrip("/"))] = _pose_T(
            pose, f"transforms[{i}].transform"
        )
    return out
