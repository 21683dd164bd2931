"""Images (raw and compressed), 32FC1 depth (REP 118) and CameraInfo."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from bridges.ros_convert.base import (
    _T,
    Distro,
    header,
    ros_stamp_ns,
    typestore,
)
from mogs_node import msgs
from mogs_node.errors import MessageError
from mogs_node.geometry import PinholeCamera

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

    def message(self, *, T_imu_cam: np.ndarray | None = None, source: str = "") -> msgs.CameraInfo:
        """This calibration (plus ``T_imu_cam`` [4, 4] when known) as the bus's
        :class:`~mogs_node.msgs.CameraInfo`."""
        out = msgs.CameraInfo(
            stamp_ns=self.stamp_ns,
            frame_id=self.frame_id,
            width=int(self.camera.width),
            height=int(self.camera.height),
            K=np.asarray(self.camera.K, dtype=np.float64),
            distortion_model=self.distortion_model,
            distortion_coeffs=np.asarray(self.distortion_coeffs, dtype=np.float64),
            T_imu_cam=None if T_imu_cam is None else np.asarray(T_imu_cam, dtype=np.float64),
            source=source,
        )
        out.validate()
        return out


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
