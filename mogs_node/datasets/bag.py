"""rosbag1 / rosbag2 (sqlite3, MCAP) reading and writing via ``rosbags`` (no ROS installation).

Standard message types only: ``sensor_msgs/Image`` (mono8, rgb8, bgr8; 32FC1 / 16UC1 depth),
``sensor_msgs/CompressedImage``, ``sensor_msgs/CameraInfo``, ``sensor_msgs/Imu`` and
``geometry_msgs/PoseStamped`` (ground-truth ``T_world_cam``). Topic names are configurable through
:class:`BagTopics`. Message stamps (``header.stamp``) are the time stamps; images are decoded
lazily.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mogs_node.datasets.base import Frame, ImuSamples, Sequence
from mogs_node.errors import DatasetError
from mogs_node.geometry import (
    PinholeCamera,
    make_T,
    quat_wxyz_from_rotmat,
    quat_wxyz_to_rotmat,
    tf_lookup,
)

__all__ = ["BAG_FORMATS", "BagTopics", "BagWriter", "decode_image_msg", "read_bag"]

log = logging.getLogger(__name__)

BAG_FORMATS = ("rosbag2", "mcap", "rosbag1")


@dataclass(frozen=True)
class BagTopics:
    """Topic names (None: not read / not written)."""

    image: str = "/camera/image_raw"  # sensor_msgs/Image or sensor_msgs/CompressedImage
    camera_info: str | None = "/camera/camera_info"  # sensor_msgs/CameraInfo (intrinsics)
    imu: str | None = "/imu"  # sensor_msgs/Imu
    pose: str | None = "/ground_truth/pose"  # geometry_msgs/PoseStamped, T_world_cam
    depth: str | None = "/ground_truth/depth"  # sensor_msgs/Image 32FC1 (m) or 16UC1 (mm)
    tf_static: str | None = "/tf_static"  # tf2_msgs/TFMessage: T_imu_cam between the frames of
    # the IMU and image messages


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def decode_image_msg(msg: Any, where: str = "image") -> tuple[np.ndarray, str]:
    """A sensor_msgs Image/CompressedImage -> (array, encoding); colour comes out RGB.

    Returns uint8 ``[H, W, 3]`` "rgb8", uint8 ``[H, W]`` "mono8", or float32 ``[H, W]`` "32FC1"
    (16UC1 is converted from millimetres to metres and reported as "32FC1").
    """
    if hasattr(msg, "format"):  # CompressedImage
        img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"{where}: undecodable compressed image ({msg.format!r})")
        if img.ndim == 3:
            return cv2.cvtColor(
                img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGB
            ), "rgb8"
        return img, "mono8"
    enc = msg.encoding
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    chans = {
        "mono8": (1, np.uint8),
        "rgb8": (3, np.uint8),
        "bgr8": (3, np.uint8),
        "8UC1": (1, np.uint8),
        "32FC1": (1, np.float32),
        "16UC1": (1, np.uint16),
    }
    if enc not in chans:
        raise DatasetError(f"{where}: unsupported image encoding {enc!r}")
    c, dt = chans[enc]
    item = np.dtype(dt).itemsize
    if data.size < h * step or step < w * c * item:
        raise DatasetError(f"{where}: {data.size} bytes for {w}x{h} {enc} with step {step}")
    rows = data[: h * step].reshape(h, step)[:, : w * c * item]
    arr = np.ascontiguousarray(rows).view(
        np.dtype(dt).newbyteorder(">" if msg.is_bigendian else "<")
    )
    arr = arr.astype(dt).reshape(h, w, c) if c == 3 else arr.astype(dt).reshape(h, w)
    if enc == "bgr8":
        return arr[..., ::-1].copy(), "rgb8"
    if enc == "16UC1":
        return arr.astype(np.float32) / 1000.0, "32FC1"
    return arr, {"8UC1": "mono8"}.get(enc, enc)


def _open_reader(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as err:  # rosbags raises several unrelated error classes
        raise DatasetError(f"{path}: cannot open bag ({err})") from err
    return reader


def read_bag(
    path: str | Path, *, topics: BagTopics | None = None, camera: PinholeCamera | None = None
) -> Sequence:
    """Read a rosbag1 file, a rosbag2 folder (sqlite3 or MCAP) or a bare ``.mcap`` into a Sequence.

    Intrinsics and distortion come from ``topics.camera_info`` (first message) or ``camera``;
    one of them is required. ``T_imu_cam`` comes from ``topics.tf_static`` when it connects the
    IMU messages' frame to the images' frame. Ground-truth poses and depth are matched to frames
    by identical stamps.
    """
    tp = topics or BagTopics()
    p = Path(path)
    if not p.exists():
        raise DatasetError(f"{p}: no such bag")
    reader = _open_reader(p)
    try:
        conns = {c.topic: c for c in reader.connections}
        if tp.image not in conns:
            raise DatasetError(f"{p}: no image topic {tp.image!r} (topics: {sorted(conns)})")
        img_msgs: list[tuple[int, Any]] = []
        gyro, accel, imu_t = [], [], []
        poses: dict[int, np.ndarray] = {}
        depth_msgs: dict[int, Any] = {}
        K_cam = camera
        distortion: dict[str, object] | None = None
        tf_edges: dict[tuple[str, str], np.ndarray] = {}
        frames_of = {"image": "", "imu": ""}
        names = (tp.image, tp.camera_info, tp.imu, tp.pose, tp.depth, tp.tf_static)
        wanted = [conns[t] for t in names if t in conns]
        for conn, _, raw in reader.messages(connections=wanted):
            if conn.topic == tp.image:
                msg = reader.deserialize(raw, conn.msgtype)  # pixel decoding stays lazy
                img_msgs.append((_stamp_ns(msg.header), msg))
                frames_of["image"] = frames_of["image"] or msg.header.frame_id
            elif conn.topic == tp.camera_info and K_cam is None:
                msg = reader.deserialize(raw, conn.msgtype)
                k = np.asarray(
                    getattr(msg, "k", getattr(msg, "K", None)), dtype=np.float64
                ).reshape(3, 3)
                K_cam = PinholeCamera.from_K(k, int(msg.width), int(msg.height))
                d = np.asarray(getattr(msg, "d", getattr(msg, "D", ())), dtype=np.float64)
                distortion = {"model": msg.distortion_model, "coeffs": d.tolist()}
            elif conn.topic == tp.tf_static:
                msg = reader.deserialize(raw, conn.msgtype)
                for tr in msg.transforms:
                    q, t = tr.transform.rotation, tr.transform.translation
                    R = quat_wxyz_to_rotmat(np.array([q.w, q.x, q.y, q.z]))
                    key = (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))
                    tf_edges[key] = make_T(R, np.array([t.x, t.y, t.z]))
            elif conn.topic == tp.imu:
                msg = reader.deserialize(raw, conn.msgtype)
                frames_of["imu"] = frames_of["imu"] or msg.header.frame_id
                imu_t.append(_stamp_ns(msg.header))
                g, a = msg.angular_velocity, msg.linear_acceleration
                gyro.append((g.x, g.y, g.z))
                accel.append((a.x, a.y, a.z))
            elif conn.topic == tp.pose:
                msg = reader.deserialize(raw, conn.msgtype)
                q, t = msg.pose.orientation, msg.pose.position
                R = quat_wxyz_to_rotmat(np.array([q.w, q.x, q.y, q.z]))
                poses[_stamp_ns(msg.header)] = make_T(R, np.array([t.x, t.y, t.z]))
            elif conn.topic == tp.depth:
                msg = reader.deserialize(raw, conn.msgtype)
                depth_msgs[_stamp_ns(msg.header)] = msg
    finally:
        reader.close()
    if K_cam is None:
        raise DatasetError(f"{p}: no CameraInfo on {tp.camera_info!r} and no camera given")
    img_msgs.sort(key=lambda x: x[0])

    def depth_loader(stamp: int):
        if stamp not in depth_msgs:
            return None

        def load() -> np.ndarray:
            d = decode_image_msg(depth_msgs[stamp], f"{p}:{tp.depth}@{stamp}")[0].astype(np.float32)
            return np.where(np.isfinite(d), d, 0.0).astype(np.float32)

        return load

    frames: list[Frame] = []
    for i, (stamp, msg) in enumerate(img_msgs):
        where = f"{p}:{tp.image}@{stamp}"
        if i == 0:
            enc = "mono8" if decode_image_msg(msg, where)[0].ndim == 2 else "rgb8"
        frames.append(
            Frame(
                i,
                stamp,
                K_cam,
                (lambda m=msg, w=where: decode_image_msg(m, w)[0]),
                enc,
                poses.get(stamp),
                depth_loader(stamp),
                f"{p}:{tp.image}",
            )
        )
    imu = None
    if imu_t:
        order = np.argsort(imu_t, kind="stable")
        imu = ImuSamples(
            np.asarray(imu_t, dtype=np.int64)[order],
            np.asarray(gyro)[order],
            np.asarray(accel)[order],
        )
    T_imu_cam = None
    if tf_edges and frames_of["imu"] and frames_of["image"]:
        T_imu_cam = tf_lookup(
            tf_edges, frames_of["imu"].lstrip("/"), frames_of["image"].lstrip("/")
        )
        if T_imu_cam is None:
            log.warning(
                "%s: %s does not connect the IMU frame %r to the camera frame %r",
                p,
                tp.tf_static,
                frames_of["imu"],
                frames_of["image"],
            )
    meta = {"bag": str(p), "calibration": f"{p}:{tp.camera_info}"}
    return Sequence(p.stem, tuple(frames), imu, T_imu_cam, None, distortion, meta)


class BagWriter:
    """Write standard sensor messages to a bag (``fmt`` in :data:`BAG_FORMATS`); context manager."""

    def __init__(
        self, path: str | Path, fmt: str = "rosbag2", *, topics: BagTopics | None = None
    ) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        if fmt not in BAG_FORMATS:
            raise DatasetError(f"format: expected one of {BAG_FORMATS}, got {fmt!r}")
        self.path, self.fmt, self.topics = Path(path), fmt, topics or BagTopics()
        if self.path.exists():
            raise DatasetError(f"{self.path}: already exists")
        self.ros1 = fmt == "rosbag1"
        self.ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:  # Noetic's store lacks tf2_msgs (its ROS 1 definition, verbatim)
            tf = "geometry_msgs/TransformStamped[] transforms\n"
            self.ts.register(get_types_from_msg(tf, "tf2_msgs/msg/TFMessage"))
        if self.ros1:
            from rosbags.rosbag1 import Writer

            self._w = Writer(self.path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self._w = Writer(self.path, version=9, storage_plugin=plugin)
        self._conns: dict[str, Any] = {}
        self._seq = 0

    def __enter__(self) -> BagWriter:
        self._w.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self._w.close()

    # -- message construction ------------------------------------------------------------------
    def _header(self, stamp_ns: int, frame_id: str) -> Any:
        T = self.ts.types
        t = T["builtin_interfaces/msg/Time"](
            sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)
        )
        if self.ros1:
            self._seq += 1
            return T["std_msgs/msg/Header"](seq=self._seq, stamp=t, frame_id=frame_id)
        return T["std_msgs/msg/Header"](stamp=t, frame_id=frame_id)

    def _write(self, topic: str, msgtype: str, msg: Any, stamp_ns: int) -> None:
        if topic not in self._conns:
            self._conns[topic] = self._w.add_connection(topic, msgtype, typestore=self.ts)
        data = (
            self.ts.serialize_ros1(msg, msgtype)
            if self.ros1
            else self.ts.serialize_cdr(msg, msgtype)
        )
        self._w.write(self._conns[topic], int(stamp_ns), data)

    def image(
        self,
        stamp_ns: int,
        image: np.ndarray,
        *,
        topic: str | None = None,
        frame_id: str = "camera",
        compress: str | None = None,
    ) -> None:
        """uint8 ``[H, W, 3]`` RGB -> rgb8, ``[H, W]`` -> mono8, float32 ``[H, W]`` -> 32FC1;
        with ``compress`` ('png' or 'jpeg') a uint8 RGB or grey image -> CompressedImage."""
        if compress is not None:
            msg = self._compressed(image, compress, stamp_ns, frame_id)
            msgtype = "sensor_msgs/msg/CompressedImage"
        else:
            msgtype, msg = "sensor_msgs/msg/Image", self._raw_image(image, stamp_ns, frame_id)
        self._write(topic or self.topics.image, msgtype, msg, stamp_ns)

    def _raw_image(self, image: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
        img = np.ascontiguousarray(image)
        if img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3:
            enc, step = "rgb8", img.shape[1] * 3
        elif img.dtype == np.uint8 and img.ndim == 2:
            enc, step = "mono8", img.shape[1]
        elif img.dtype == np.float32 and img.ndim == 2:
            enc, step = "32FC1", img.shape[1] * 4
        else:
            raise DatasetError(f"image: unsupported array {img.dtype} {img.shape}")
        return self.ts.types["sensor_msgs/msg/Image"](
            header=self._header(stamp_ns, frame_id),
            height=img.shape[0],
            width=img.shape[1],
            encoding=enc,
            is_bigendian=0,
            step=step,
            data=img.reshape(-1).view(np.uint8),
        )

    def _compressed(self, image_rgb: np.ndarray, fmt: str, stamp_ns: int, frame_id: str) -> Any:
        img = image_rgb if image_rgb.ndim == 2 else cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR)
        ok, buf = cv2.imencode("." + fmt, img)
        if not ok:
            raise DatasetError(f"image: cannot compress as {fmt}")
        return self.ts.types["sensor_msgs/msg/CompressedImage"](
            header=self._header(stamp_ns, frame_id), format=fmt, data=buf.reshape(-1)
        )

    def camera_info(
        self, stamp_ns: int, camera: PinholeCamera, *, frame_id: str = "camera"
    ) -> None:
        T = self.ts.types
        K = camera.K.reshape(-1)
        P = np.c_[camera.K, np.zeros(3)].reshape(-1)
        roi = T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        fields = {"D": np.zeros(5), "K": K, "R": np.eye(3).reshape(-1), "P": P}
        if not self.ros1:
            fields = {k.lower(): v for k, v in fields.items()}
        msg = T["sensor_msgs/msg/CameraInfo"](
            header=self._header(stamp_ns, frame_id),
            height=camera.height,
            width=camera.width,
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **fields,
        )
        self._write(self.topics.camera_info, "sensor_msgs/msg/CameraInfo", msg, stamp_ns)

    def tf_static(
        self,
        stamp_ns: int,
        T_parent_child: np.ndarray,
        *,
        parent: str = "imu",
        child: str = "camera",
    ) -> None:
        """One static transform (``child`` in ``parent``) as tf2_msgs/TFMessage on tf_static."""
        if self.topics.tf_static is None:
            raise DatasetError("tf_static: no topic configured")
        T = self.ts.types
        q = quat_wxyz_from_rotmat(np.asarray(T_parent_child, dtype=np.float64)[:3, :3])
        t = np.asarray(T_parent_child, dtype=np.float64)[:3, 3]
        tr = T["geometry_msgs/msg/TransformStamped"](
            header=self._header(stamp_ns, parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[1], y=q[2], z=q[3], w=q[0]),
            ),
        )
        msg = T["tf2_msgs/msg/TFMessage"](transforms=[tr])
        self._write(self.topics.tf_static, "tf2_msgs/msg/TFMessage", msg, stamp_ns)

    def imu(
        self,
        stamp_ns: int,
        gyro_rad_s: np.ndarray,
        accel_m_s2: np.ndarray,
        *,
        frame_id: str = "imu",
    ) -> None:
        T = self.ts.types
        V, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        cov = np.zeros(9)
        ocov = np.zeros(9)
        ocov[0] = -1.0  # orientation unknown (REP 145)
        msg = T["sensor_msgs/msg/Imu"](
            header=self._header(stamp_ns, frame_id),
            orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=ocov,
            angular_velocity=V(
                x=float(gyro_rad_s[0]), y=float(gyro_rad_s[1]), z=float(gyro_rad_s[2])
            ),
            angular_velocity_covariance=cov,
            linear_acceleration=V(
                x=float(accel_m_s2[0]), y=float(accel_m_s2[1]), z=float(accel_m_s2[2])
            ),
            linear_acceleration_covariance=cov,
        )
        self._write(self.topics.imu, "sensor_msgs/msg/Imu", msg, stamp_ns)

    def pose(self, stamp_ns: int, T_world_cam: np.ndarray, *, frame_id: str = "world") -> None:
        T = self.ts.types
        q = quat_wxyz_from_rotmat(np.asarray(T_world_cam)[:3, :3])
        t = np.asarray(T_world_cam)[:3, 3]
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
            orientation=T["geometry_msgs/msg/Quaternion"](
                w=float(q[0]), x=float(q[1]), y=float(q[2]), z=float(q[3])
            ),
        )
        msg = T["geometry_msgs/msg/PoseStamped"](header=self._header(stamp_ns, frame_id), pose=pose)
        self._write(self.topics.pose, "geometry_msgs/msg/PoseStamped", msg, stamp_ns)
