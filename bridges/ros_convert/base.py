"""Typestores, wire bytes, headers and the small pieces every conversion shares."""

from __future__ import annotations

import enum
from functools import lru_cache
from typing import Any

import numpy as np

from mogs_node.errors import GeometryError, MessageError
from mogs_node.geometry import make_T, quat_wxyz_from_rotmat, quat_wxyz_to_rotmat


class Distro(enum.Enum):
    """Which ROS: message layouts differ (Header.seq, CameraInfo field case, time range)."""

    ROS1 = 1
    ROS2 = 2


@lru_cache(maxsize=2)
def typestore(distro: Distro = Distro.ROS2) -> Any:
    """The rosbags typestore of ``distro`` (ROS 1 Noetic or ROS 2 Humble)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if distro is Distro.ROS2:
        return get_typestore(Stores.ROS2_HUMBLE)
    ts = get_typestore(Stores.ROS1_NOETIC)
    # Noetic's store lacks tf2_msgs (tf2_msgs/TFMessage.msg of ROS 1, verbatim)
    ts.register(get_types_from_msg(_TF_MSG_ROS1, "tf2_msgs/msg/TFMessage"))
    return ts


_TF_MSG_ROS1 = "geometry_msgs/TransformStamped[] transforms\n"


def rostype(name: str) -> str:
    """``sensor_msgs/Image`` (ROS 1 spelling) or ``sensor_msgs/msg/Image`` -> the latter."""
    pkg, _, rest = name.partition("/")
    return name if rest.startswith("msg/") else f"{pkg}/msg/{rest}"


def serialize(rmsg: Any, rtype: str, distro: Distro) -> bytes:
    """A typestore message -> its wire bytes (ROS 1 serialization or CDR)."""
    ts, rtype = typestore(distro), rostype(rtype)
    raw = ts.serialize_ros1(rmsg, rtype) if distro is Distro.ROS1 else ts.serialize_cdr(rmsg, rtype)
    return bytes(raw)


def deserialize(raw: bytes | memoryview, rtype: str, distro: Distro) -> Any:
    """Wire bytes -> a typestore message; truncated or garbled bytes raise MessageError."""
    ts, rtype = typestore(distro), rostype(rtype)
    try:
        if distro is Distro.ROS1:
            return ts.deserialize_ros1(bytes(raw), rtype)
        return ts.deserialize_cdr(bytes(raw), rtype)
    except Exception as err:  # rosbags raises struct.error, IndexError, ValueError, ...
        raise MessageError(
            f"cannot decode {len(raw)} bytes as {rtype} ({err})", field=rtype
        ) from err


def msgdef_md5(rtype: str) -> tuple[str, str]:
    """ROS 1 ``(full message definition, md5sum)`` of ``rtype``, as a ROS 1 connection header has."""
    text, md5 = typestore(Distro.ROS1).generate_msgdef(rostype(rtype), ros_version=1)
    return text, md5


def _T(distro: Distro, name: str) -> Any:
    return typestore(distro).types[name]


def header(stamp_ns: int, frame_id: str, distro: Distro, *, seq: int = 0) -> Any:
    """``std_msgs/Header`` of int ``stamp_ns`` (ROS 1: [0, 2^32 s), ROS 2: [0, 2^31 s))."""
    top = (1 << (32 if distro is Distro.ROS1 else 31)) * 1_000_000_000
    if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer):
        raise MessageError(f"needs an int of nanoseconds, got {stamp_ns!r}", field="stamp_ns")
    if not 0 <= int(stamp_ns) < top:
        raise MessageError(f"{stamp_ns} ns is outside {distro.name} time", field="stamp_ns")
    t = _T(distro, "builtin_interfaces/msg/Time")(
        sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)
    )
    if distro is Distro.ROS1:
        return _T(distro, "std_msgs/msg/Header")(seq=seq, stamp=t, frame_id=frame_id)
    return _T(distro, "std_msgs/msg/Header")(stamp=t, frame_id=frame_id)


def ros_stamp_ns(hdr: Any) -> int:
    """``header.stamp`` as int nanoseconds."""
    return int(hdr.stamp.sec) * 1_000_000_000 + int(hdr.stamp.nanosec)


def _pose(T_world_x: np.ndarray, distro: Distro) -> Any:
    T = np.asarray(T_world_x, dtype=np.float64)
    q = quat_wxyz_from_rotmat(T[:3, :3])
    t = T[:3, 3]
    return _T(distro, "geometry_msgs/msg/Pose")(
        position=_T(distro, "geometry_msgs/msg/Point")(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=_T(distro, "geometry_msgs/msg/Quaternion")(
            x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])
        ),
    )


def _pose_T(pose: Any, field: str = "pose") -> np.ndarray:
    q, p = pose.orientation, pose.position
    t = np.array([p.x, p.y, p.z], dtype=np.float64)
    if not np.isfinite(t).all():
        raise MessageError(f"non-finite position {t.tolist()}", field=f"{field}.position")
    try:
        R = quat_wxyz_to_rotmat(np.array([q.w, q.x, q.y, q.z], dtype=np.float64))
    except GeometryError as err:
        raise MessageError(str(err), field=f"{field}.orientation") from err
    return make_T(R, t)


def _check_pose(T_world_x: np.ndarray, field: str) -> np.ndarray:
    T = np.asarray(T_world_x, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise MessageError(f"expected a finite [4, 4] pose, got {T.shape}", field=field)
    return T


def _vec3(v: Any, distro: Distro) -> Any:
    return _T(distro, "geometry_msgs/msg/Vector3")(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _finite3(v: Any, field: str) -> tuple[float, float, float]:
    out = (float(v.x), float(v.y), float(v.z))
    if not np.isfinite(out).all():
        raise MessageError(f"non-finite {out}", field=field)
    return out
