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

import enum
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from mogs_node import msgs
from mogs_node.errors import GeometryError, MessageError
from mogs_node.geometry import PinholeCamera, make_T, quat_wxyz_from_rotmat, quat_wxyz_to_rotmat

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


# ------------------------------------------------------------------------------------- images


def image_to_ros(msg: msgs.Image, *, distro: Distro = Distro.ROS2) -> Any:
    """``Image`` -> ``sensor_msgs/Image`` with the same encoding and dense rows."""
    msg.validate()
    data = np.ascontiguousarray(msg.data)
    h, w = data.shape[:2]
    return _T(distro, "sensor_msgs/msg/Image")(
        header=header(msg.stamp_ns, msg.frame_id, distro),
        height=h,
        width=w,
        encoding=msg.encoding,
        is_bigendian=0,
        step=w * (3 if data.ndim == 3 else 1),
        data=data.reshape(-1),
    )


def _rows(ros: Any, channels: int, dtype: np.dtype, where: str) -> np.ndarray:
    """The ``[H, W(, C)]`` pixels of an Image honouring ``step`` (row padding) and endianness."""
    h, w, step = int(ros.height), int(ros.width), int(ros.step)
    item = np.dtype(dtype).itemsize
    data = np.asarray(ros.data, dtype=np.uint8).reshape(-1)
    if h <= 0 or w <= 0 or step < w * channels * item or data.size < h * step:
        raise MessageError(
            f"{data.size} bytes do not hold {w}x{h} {ros.encoding} with step {step}", field=where
        )
    rows = np.ascontiguousarray(data[: h * step].reshape(h, step)[:, : w * channels * item])
    order = ">" if ros.is_bigendian else "<"
    arr = rows.view(np.dtype(dtype).newbyteorder(order)).astype(dtype)
    return arr.reshape(h, w, channels) if channels > 1 else arr.reshape(h, w)


def image_from_ros(ros: Any) -> msgs.Image:
    """``sensor_msgs/Image`` mono8 / 8UC1 / rgb8 / bgr8 -> ``Image`` (encoding kept)."""
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


def compressed_image_to_ros(
    msg: msgs.Image, *, fmt: str = "jpeg", quality: int = 95, distro: Distro = Distro.ROS2
) -> Any:
    """``Image`` -> ``sensor_msgs/CompressedImage`` (``fmt`` jpeg or png; colour stored as BGR,
    as OpenCV and ``image_transport`` do)."""
    msg.validate()
    if fmt not in ("jpeg", "png"):
        raise MessageError(f"compressed format must be jpeg or png, got {fmt!r}", field="format")
    img = msg.data if msg.encoding != "rgb8" else cv2.cvtColor(msg.data, cv2.COLOR_RGB2BGR)
    opts = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if fmt == "jpeg" else []
    ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", img, opts)
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise MessageError(f"OpenCV cannot encode the image as {fmt}", field="data")
    return _T(distro, "sensor_msgs/msg/CompressedImage")(
        header=header(msg.stamp_ns, msg.frame_id, distro), format=fmt, data=buf.reshape(-1)
    )


def compressed_image_from_ros(ros: Any) -> msgs.Image:
    """``sensor_msgs/CompressedImage`` (jpeg / png, grey or colour) -> mono8 or rgb8 ``Image``."""
    buf = np.asarray(ros.data, dtype=np.uint8).reshape(-1)
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if img is None or img.dtype != np.uint8:
        raise MessageError(
            f"{buf.size} bytes are not an 8-bit jpeg/png image (format {ros.format!r})",
            field="data",
        )
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB
        img, enc = cv2.cvtColor(img, code), "rgb8"
    else:
        enc = "mono8"
    out = msgs.Image(
        stamp_ns=ros_stamp_ns(ros.header), frame_id=ros.header.frame_id, encoding=enc, data=img
    )
    out.validate()
    return out


# ------------------------------------------------------------------------------ calibration


@dataclass(frozen=True)
class CameraCalibration:
    """What ``sensor_msgs/CameraInfo`` tells: the pinhole camera and its distortion in our terms
    (``distortion_model`` as the frontend's parameter: none, radtan or equidistant)."""

    stamp_ns: int
    frame_id: str
    camera: PinholeCamera
    distortion_model: str = "none"
    distortion_coeffs: tuple[float, ...] = ()


_ROS_DISTORTION = {
    "plumb_bob": "radtan",
    "rational_polynomial": "radtan",
    "equidistant": "equidistant",
}


def camera_info_to_ros(calib: CameraCalibration, *, distro: Distro = Distro.ROS2) -> Any:
    """:class:`CameraCalibration` -> ``sensor_msgs/CameraInfo`` (R identity, P = [K | 0])."""
    K = calib.camera.K
    model = {"none": "plumb_bob", "radtan": "plumb_bob", "equidistant": "equidistant"}.get(
        calib.distortion_model
    )
    if model is None:
        raise MessageError(f"unknown model {calib.distortion_model!r}", field="distortion_model")
    D = np.zeros(5 if model == "plumb_bob" else 4)
    D[: len(calib.distortion_coeffs)] = calib.distortion_coeffs
    T = typestore(distro).types
    roi = T["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    fields = {"D": D, "K": K.reshape(-1), "R": np.eye(3).reshape(-1), "P": np.c_[K, np.zeros(3)]}
    fields["P"] = fields["P"].reshape(-1)
    if distro is Distro.ROS2:
        fields = {k.lower(): v for k, v in fields.items()}
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(calib.stamp_ns, calib.frame_id, distro),
        height=calib.camera.height,
        width=calib.camera.width,
        distortion_model=model,
        binning_x=0,
        binning_y=0,
        roi=roi,
        **fields,
    )


def camera_info_from_ros(ros: Any) -> CameraCalibration:
    """``sensor_msgs/CameraInfo`` (either distro) -> :class:`CameraCalibration`.

    plumb_bob / rational_polynomial keep k1 k2 p1 p2 (radtan; k3 and beyond must be 0), all-zero
    coefficients become ``none``; binning and ROI must be unset (the full sensor image)."""
    K = np.asarray(getattr(ros, "K", getattr(ros, "k", None)), dtype=np.float64).reshape(-1)
    D = np.asarray(getattr(ros, "D", getattr(ros, "d", ())), dtype=np.float64).reshape(-1)
    if K.size != 9:
        raise MessageError(f"K needs 9 values, got {K.size}", field="K")
    try:
        cam = PinholeCamera.from_K(K.reshape(3, 3), int(ros.width), int(ros.height))
    except Exception as err:  # GeometryError / ShapeError: zero focal length, NaN, no size
        raise MessageError(f"{err}", field="K") from err
    if int(ros.binning_x) > 1 or int(ros.binning_y) > 1 or int(ros.roi.width) > 0:
        raise MessageError("binned or ROI camera info is not supported", field="roi")
    if not np.isfinite(D).all():
        raise MessageError(f"non-finite distortion {D.tolist()}", field="D")
    model = _ROS_DISTORTION.get(ros.distortion_model) if D.any() else "none"
    if model is None:
        raise MessageError(f"unsupported distortion model {ros.distortion_model!r}", field="D")
    coeffs: tuple[float, ...] = ()
    if model == "radtan":
        if D.size < 4 or D[4:].any():
            raise MessageError(f"radtan takes k1 k2 p1 p2 only, got {D.tolist()}", field="D")
        coeffs = tuple(float(x) for x in D[:4])
    elif model == "equidistant":
        if D.size != 4:
            raise MessageError(f"equidistant takes 4 coefficients, got {D.size}", field="D")
        coeffs = tuple(float(x) for x in D)
    return CameraCalibration(ros_stamp_ns(ros.header), ros.header.frame_id, cam, model, coeffs)


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


# ------------------------------------------------------------------------------ point clouds

#: sensor_msgs/PointField datatypes -> numpy
_PF_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def pointcloud_to_ros(
    xyz_world_m: np.ndarray,
    rgb: np.ndarray | None,
    *,
    stamp_ns: int,
    frame_id: str = "world",
    distro: Distro = Distro.ROS2,
) -> Any:
    """Points ``xyz_world_m`` [N, 3] with colours ``rgb`` [N, 3] (float in [0, 1] or uint8) ->
    unorganised ``sensor_msgs/PointCloud2``: fields x, y, z (float32, offsets 0, 4, 8) and rgb
    (offset 12: uint32 0x00RRGGBB stored as FLOAT32, as PCL and RViz read it), point_step 16."""
    xyz = np.asarray(xyz_world_m)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.isfinite(xyz).all():
        raise MessageError(f"expected finite [N, 3] points, got {xyz.shape}", field="xyz_world_m")
    n = len(xyz)
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    fields = ["x", "y", "z"]
    if rgb is not None:
        c = np.asarray(rgb)
        if c.shape != (n, 3):
            raise MessageError(f"expected [{n}, 3] colours, got {c.shape}", field="rgb")
        if c.dtype != np.uint8:
            c = np.round(np.clip(np.nan_to_num(c.astype(np.float64)), 0.0, 1.0) * 255)
        c = c.astype(np.uint32)
        rec["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
        fields.append("rgb")
    PF = _T(distro, "sensor_msgs/msg/PointField")
    pfields = [PF(name=f, offset=4 * i, datatype=PF.FLOAT32, count=1) for i, f in enumerate(fields)]
    return _T(distro, "sensor_msgs/msg/PointCloud2")(
        header=header(stamp_ns, frame_id, distro),
        height=1,
        width=n,
        fields=pfields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * n,
        data=rec.view(np.uint8).reshape(-1),
        is_dense=True,
    )


def pointcloud_from_ros(ros: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """``sensor_msgs/PointCloud2`` -> (``xyz`` float32 [N, 3], ``rgb`` uint8 [N, 3] or None).

    Reads any layout: field offsets and datatypes as declared, ``point_step`` / ``row_step``
    padding, organised clouds (N = height * width), big-endian data; ``rgb`` or ``rgba`` packed
    in 4 bytes (FLOAT32 or UINT32). Points with a non-finite coordinate are dropped."""
    h, w = int(ros.height), int(ros.width)
    pstep, rstep = int(ros.point_step), int(ros.row_step)
    fields = {f.name: f for f in ros.fields}
    missing = [f for f in ("x", "y", "z") if f not in fields]
    if missing:
        raise MessageError(f"no field(s) {missing} (fields: {sorted(fields)})", field="fields")
    order = ">" if ros.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in ("x", "y", "z", "rgb" if "rgb" in fields else "rgba"):
        f = fields.get(name)
        if f is None:
            continue
        if int(f.datatype) not in _PF_DTYPES:
            raise MessageError(f"unknown datatype {f.datatype}", field=f"fields.{name}")
        dt = np.dtype(order + _PF_DTYPES[int(f.datatype)])
        if name in ("rgb", "rgba"):
            dt = np.dtype(order + "u4")
            if int(f.datatype) not in (6, 7):
                raise MessageError("packed colour must be 4 bytes", field=f"fields.{name}")
        if int(f.offset) < 0 or int(f.offset) + dt.itemsize > pstep:
            raise MessageError(
                f"offset {f.offset} + {dt.itemsize} bytes exceeds point_step {pstep}",
                field=f"fields.{name}",
            )
        names.append(name)
        formats.append(dt)
        offsets.append(int(f.offset))
    data = np.asarray(ros.data, dtype=np.uint8).reshape(-1)
    if h < 0 or w < 0 or pstep <= 0 or (h * w and rstep < w * pstep) or data.size < h * rstep:
        raise MessageError(
            f"{data.size} bytes do not hold {h}x{w} points of {pstep} bytes, row_step {rstep}",
            field="data",
        )
    rows = data[: h * rstep].reshape(h, rstep)[:, : w * pstep]
    rec_dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": pstep})
    rec = np.ascontiguousarray(rows).view(rec_dt).reshape(-1)
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float32)
    keep = np.isfinite(xyz).all(axis=1)
    rgb = None
    if len(names) == 4:
        packed = rec[names[3]].astype(np.uint32)[keep]
        rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], 1)
        rgb = rgb.astype(np.uint8)
    return xyz[keep], rgb


# -------------------------------------------------------------------------------------- depth


def depth_to_ros(msg: msgs.DepthMap, *, distro: Distro = Distro.ROS2) -> Any:
    """``DepthMap`` (metric) -> 32FC1 ``sensor_msgs/Image`` in metres, NaN where depth is 0
    (REP 118)."""
    msg.validate()
    if msg.kind != "metric":
        raise MessageError(f"only metric depth maps become 32FC1, got {msg.kind!r}", field="kind")
    d = np.where(msg.depth > 0, msg.depth, np.nan).astype("<f4")
    h, w = d.shape
    return _T(distro, "sensor_msgs/msg/Image")(
        header=header(msg.stamp_ns, msg.frame_id, distro),
        height=h,
        width=w,
        encoding="32FC1",
        is_bigendian=0,
        step=w * 4,
        data=d.reshape(-1).view(np.uint8),
    )


def depth_from_ros(
    ros: Any, *, keyframe_id: int = 0, source: str = "ros", confidence: float = 1.0
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
    out = msgs.DepthMap(
        stamp_ns=ros_stamp_ns(ros.header),
        frame_id=ros.header.frame_id,
        keyframe_id=keyframe_id,
        kind="metric",
        depth=np.where(valid, d, 0.0).astype(np.float32),
        confidence=np.where(valid, np.float32(confidence), np.float32(0)).astype(np.float32),
        source=source,
    )
    out.validate()
    return out


# --------------------------------------------------------------------------------- map stats

_STATS_FIELDS = ("keyframe_id", "n_gaussians", "n_keyframes", "iterations", "loss", "psnr_db")


def mapstats_to_ros(
    msg: msgs.MapStats, *, name: str = "mogs/mapper", distro: Distro = Distro.ROS2
) -> Any:
    """``MapStats`` -> ``diagnostic_msgs/DiagnosticArray``: one status ``name`` whose values are
    the fields and ``extra`` entries (``repr`` of each number, so floats round-trip)."""
    msg.validate()
    KV = _T(distro, "diagnostic_msgs/msg/KeyValue")
    values = [KV(key=k, value=repr(getattr(msg, k))) for k in _STATS_FIELDS]
    values += [KV(key=f"extra.{k}", value=repr(v)) for k, v in sorted(msg.extra.items())]
    Status = _T(distro, "diagnostic_msgs/msg/DiagnosticStatus")
    status = Status(
        level=Status.OK,
        name=name,
        message=f"keyframe {msg.keyframe_id}",
        hardware_id="",
        values=values,
    )
    return _T(distro, "diagnostic_msgs/msg/DiagnosticArray")(
        header=header(msg.stamp_ns, msg.frame_id, distro), status=[status]
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
