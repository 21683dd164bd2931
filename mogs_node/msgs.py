"""Every message type and its wire codec, in one place.

Wire format (DESIGN.md section 5): a multipart ZeroMQ message ``[topic, header, *buffers]``.

- ``topic``: UTF-8 topic name, e.g. ``b"/frontend/keyframe"``.
- ``header``: msgpack map ``{"t": type name, "v": schema version, "seq": per-topic sequence number,
  "src": publisher session id, "f": {scalar fields}, "a": [[array name, dtype, shape], ...]}``.
  ``stamp_ns`` and ``frame_id`` are ordinary scalar fields of every message.
- ``buffers``: one raw C-contiguous little-endian buffer per array descriptor, in order. Arrays are
  sent without a copy and decoded with ``np.frombuffer`` (read-only views of the received frames).

Decoding is strict: anything not exactly as declared (unknown type or version, missing or extra
field, wrong scalar type, non-whitelisted dtype, shape/size mismatch, inconsistent dimensions
between arrays, non-finite values where forbidden, oversized message) raises :class:`MessageError`
naming the field. Nothing is ever fixed silently and pickle is never used.
"""

from __future__ import annotations

import contextlib
import math
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from typing import Annotated, Any, ClassVar, NamedTuple, Union

import msgpack
import msgspec
import numpy as np
import zmq

from mogs_node.errors import MessageError

__all__ = [
    "DEFAULT_MAX_MESSAGE_BYTES",
    "MESSAGE_TYPES",
    "ArraySpec",
    "CameraInfo",
    "DepthMap",
    "Diagnostics",
    "Envelope",
    "GaussianUpdate",
    "Image",
    "Imu",
    "Keyframe",
    "MapStats",
    "Masks",
    "Message",
    "MessageError",
    "Odometry",
    "PoseStamped",
    "Render",
    "decode",
    "encode",
]

DEFAULT_MAX_MESSAGE_BYTES = 256 * 1024 * 1024
MAX_HEADER_BYTES = 64 * 1024
MAX_DIM = 1 << 20  # no single dimension beyond 1M elements
MAX_TOPIC_CHARS = 256
# dtypes that may travel; everything is little-endian on the wire.
_WIRE_DTYPES = {
    "|u1": np.dtype("u1"),
    "|i1": np.dtype("i1"),
    "|b1": np.dtype("?"),
    "<u2": np.dtype("<u2"),
    "<i2": np.dtype("<i2"),
    "<i4": np.dtype("<i4"),
    "<u4": np.dtype("<u4"),
    "<i8": np.dtype("<i8"),
    "<f4": np.dtype("<f4"),
    "<f8": np.dtype("<f8"),
}


@dataclass(frozen=True)
class ArraySpec:
    """What an array field may be.

    ``shapes`` lists accepted shape patterns; a pattern entry is an int (exact size) or a symbol
    (str) bound consistently across all arrays of the message (e.g. ``"H"``, ``"N"``).
    """

    dtypes: tuple[str, ...]
    shapes: tuple[tuple[int | str, ...], ...]
    finite: bool = False
    optional: bool = False


# scalar kinds: "int", "float", "str", "bool", "vec3" (3 finite floats), "dict_num" (str -> number),
# "dict_any" (str -> int/float/str/bool or nested dict of those, depth 2)
_SCALAR_KINDS = {"int", "float", "str", "bool", "vec3", "dict_num", "dict_any", "float_or_nan"}


class Message:
    """Base of every message dataclass: ``TYPE``, ``VERSION``, scalar kinds and array specs."""

    TYPE: ClassVar[str]
    VERSION: ClassVar[int] = 1
    SCALARS: ClassVar[dict[str, str]]
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {}

    def validate(self) -> None:
        """Check the message against its own spec (the same checks the decoder applies)."""
        _validate_fields(type(self), {f.name: getattr(self, f.name) for f in fields(self)})  # type: ignore[arg-type]

    def __eq__(self, other: object) -> bool:  # arrays compare by value
        if type(other) is not type(self):
            return NotImplemented
        for f in fields(self):  # type: ignore[arg-type]
            a, b = getattr(self, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if a is None or b is None or a.dtype != b.dtype or a.shape != b.shape:
                    return False
                if not np.array_equal(a, b, equal_nan=a.dtype.kind == "f"):
                    return False
            elif isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
                continue
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]


_U8 = ("|u1",)
_F32 = ("<f4",)
_F64 = ("<f8",)
_I32 = ("<i4",)
_I64 = ("<i8",)
_I8 = ("|i1",)
_BASE = {"stamp_ns": "int", "frame_id": "str"}


@dataclass(eq=False)
class Image(Message):
    """A camera image (``/camera/image``)."""

    TYPE: ClassVar[str] = "Image"
    SCALARS: ClassVar[dict[str, str]] = {**_BASE, "encoding": "str"}
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "data": ArraySpec(_U8, (("H", "W"), ("H", "W", 3))),
    }
    ENCODINGS: ClassVar[tuple[str, ...]] = ("mono8", "rgb8", "bgr8")

    stamp_ns: int
    frame_id: str
    encoding: str
    data: np.ndarray


@dataclass(eq=False)
class Imu(Message):
    """One IMU sample (``/imu``) in the IMU frame."""

    TYPE: ClassVar[str] = "Imu"
    SCALARS: ClassVar[dict[str, str]] = {**_BASE, "gyro_rad_s": "vec3", "accel_m_s2": "vec3"}

    stamp_ns: int
    frame_id: str
    gyro_rad_s: tuple[float, float, float]
    accel_m_s2: tuple[float, float, float]


@dataclass(eq=False)
class Odometry(Message):
    """Per-frame pose estimate of the frontend (``/frontend/odometry``)."""

    TYPE: ClassVar[str] = "Odometry"
    SCALARS: ClassVar[dict[str, str]] = {
        **_BASE,
        "frame_index": "int",
        "velocity_world_m_s": "vec3",
        "status": "str",
    }
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "T_world_cam": ArraySpec(_F64, ((4, 4),), finite=True)
    }

    stamp_ns: int
    frame_id: str
    frame_index: int
    T_world_cam: np.ndarray
    velocity_world_m_s: tuple[float, float, float]
    status: str


@dataclass(eq=False)
class Keyframe(Message):
    """A keyframe with its metric pose and sparse metric points (``/frontend/keyframe``).

    ``feature_xyz_cam_m`` are metric 3D points of tracked features in this keyframe's camera frame,
    ``feature_weight`` their omega (track length and reprojection error).
    """

    TYPE: ClassVar[str] = "Keyframe"
    SCALARS: ClassVar[dict[str, str]] = {**_BASE, "keyframe_id": "int"}
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "image": ArraySpec(_U8, (("H", "W", 3), ("H", "W"))),
        "K": ArraySpec(_F64, ((3, 3),), finite=True),
        "T_world_cam": ArraySpec(_F64, ((4, 4),), finite=True),
        "feature_ids": ArraySpec(_I64, (("N",),)),
        "feature_uv_px": ArraySpec(_F32, (("N", 2),), finite=True),
        "feature_xyz_cam_m": ArraySpec(_F32, (("N", 3),), finite=True),
        "feature_weight": ArraySpec(_F32, (("N",),), finite=True),
    }

    stamp_ns: int
    frame_id: str
    keyframe_id: int
    image: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray
    feature_ids: np.ndarray
    feature_uv_px: np.ndarray
    feature_xyz_cam_m: np.ndarray
    feature_weight: np.ndarray

    def result_header(self) -> dict[str, Any]:
        """``stamp_ns``, ``frame_id`` and ``keyframe_id`` of this keyframe, as the per-keyframe
        results (masks, depth maps, renders) carry them so the consumer can pair them."""
        return {
            "stamp_ns": self.stamp_ns,
            "frame_id": self.frame_id,
            "keyframe_id": self.keyframe_id,
        }

    def rgb(self) -> np.ndarray:
        """The image as ``[H, W, 3]`` (a grey keyframe repeated into three channels)."""
        return self.image if self.image.ndim == 3 else np.repeat(self.image[..., None], 3, axis=2)


@dataclass(eq=False)
class Masks(Message):
    """Instance masks of a keyframe as one label image, -1 = no mask (``/seg/masks``)."""

    TYPE: ClassVar[str] = "Masks"
    SCALARS: ClassVar[dict[str, str]] = {**_BASE, "keyframe_id": "int", "backend": "str"}
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"labels": ArraySpec(_I32, (("H", "W"),))}

    stamp_ns: int
    frame_id: str
    keyframe_id: int
    labels: np.ndarray
    backend: str


@dataclass(eq=False)
class DepthMap(Message):
    """Dense depth of a keyframe with per-pixel confidence (``/prior/depth``, ``/metrizer/depth``).

    ``depth`` is 0 where there is no value and always finite; ``confidence`` is in [0, 1].
    ``object_labels`` / ``object_model`` (metrizer only) tell which shape model each object got:
    0 none, 1 plane, 2 cylinder, 3 ellipsoid, indexed by object label.
    """

    TYPE: ClassVar[str] = "DepthMap"
    SCALARS: ClassVar[dict[str, str]] = {
        **_BASE,
        "keyframe_id": "int",
        "kind": "str",
        "source": "str",
    }
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "depth": ArraySpec(_F32, (("H", "W"),), finite=True),
        "confidence": ArraySpec(_F32, (("H", "W"),), finite=True),
        "object_labels": ArraySpec(_I32, (("H", "W"),), optional=True),
        "object_model": ArraySpec(_I8, (("M",),), optional=True),
    }
    KINDS: ClassVar[tuple[str, ...]] = ("metric", "relative_depth", "relative_inverse_depth")

    stamp_ns: int
    frame_id: str
    keyframe_id: int
    kind: str
    depth: np.ndarray
    confidence: np.ndarray
    source: str
    object_labels: np.ndarray | None = None
    object_model: np.ndarray | None = None


@dataclass(eq=False)
class MapStats(Message):
    """Mapper statistics after a keyframe (``/mapper/stats``)."""

    TYPE: ClassVar[str] = "MapStats"
    SCALARS: ClassVar[dict[str, str]] = {
        **_BASE,
        "keyframe_id": "int",
        "n_gaussians": "int",
        "n_keyframes": "int",
        "iterations": "int",
        "loss": "float_or_nan",
        "psnr_db": "float_or_nan",
        "extra": "dict_num",
    }

    stamp_ns: int
    frame_id: str
    keyframe_id: int
    n_gaussians: int
    n_keyframes: int
    iterations: int
    loss: float
    psnr_db: float
    extra: dict[str, float] = field(default_factory=dict)


@dataclass(eq=False)
class Render(Message):
    """A rendered view of the map (``/mapper/render``)."""

    TYPE: ClassVar[str] = "Render"
    SCALARS: ClassVar[dict[str, str]] = {**_BASE, "keyframe_id": "int"}
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "image": ArraySpec(_U8, (("H", "W", 3),)),
        "depth": ArraySpec(_F32, (("H", "W"),), finite=True, optional=True),
    }

    stamp_ns: int
    frame_id: str
    keyframe_id: int
    image: np.ndarray
    depth: np.ndarray | None = None


@dataclass(eq=False)
class GaussianUpdate(Message):
    """Incremental map change: Gaussians added or changed (by id) and ids removed."""

    TYPE: ClassVar[str] = "GaussianUpdate"
    SCALARS: ClassVar[dict[str, str]] = {**_BASE, "keyframe_id": "int"}
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "ids": ArraySpec(_I64, (("N",),)),
        "means": ArraySpec(_F32, (("N", 3),), finite=True),
        "log_scales": ArraySpec(_F32, (("N", 3),), finite=True),
        "quats_wxyz": ArraySpec(_F32, (("N", 4),), finite=True),
        "opacity_logit": ArraySpec(_F32, (("N",),), finite=True),
        "colors_rgb": ArraySpec(_F32, (("N", 3),), finite=True),
        "removed_ids": ArraySpec(_I64, (("M",),)),
    }

    stamp_ns: int
    frame_id: str
    keyframe_id: int
    ids: np.ndarray
    means: np.ndarray
    log_scales: np.ndarray
    quats_wxyz: np.ndarray
    opacity_logit: np.ndarray
    colors_rgb: np.ndarray
    removed_ids: np.ndarray


@dataclass(eq=False)
class PoseStamped(Message):
    """A pose, e.g. ground truth on ``/groundtruth/pose``."""

    TYPE: ClassVar[str] = "PoseStamped"
    SCALARS: ClassVar[dict[str, str]] = dict(_BASE)
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "T_world_cam": ArraySpec(_F64, ((4, 4),), finite=True)
    }

    stamp_ns: int
    frame_id: str
    T_world_cam: np.ndarray


@dataclass(eq=False)
class Diagnostics(Message):
    """Heartbeat and counters of one node (``/diagnostics``).

    ``counters`` are node-wide figures (received, published, dropped, malformed, handler_errors,
    queue_depth, loop_latency_ms, ...); ``topics`` maps topic -> its own counters.
    """

    TYPE: ClassVar[str] = "Diagnostics"
    SCALARS: ClassVar[dict[str, str]] = {
        **_BASE,
        "node": "str",
        "pid": "int",
        "uptime_s": "float",
        "status": "str",
        "counters": "dict_num",
        "topics": "dict_any",
    }

    stamp_ns: int
    frame_id: str
    node: str
    pid: int
    uptime_s: float
    status: str
    counters: dict[str, float] = field(default_factory=dict)
    topics: dict[str, Any] = field(default_factory=dict)


@dataclass(eq=False)
class CameraInfo(Message):
    """The source's calibration (``/camera/info``), as ROS ``sensor_msgs/CameraInfo`` plus the rig.

    Published by the source (player, ROS bridges, live camera) before its first image and again
    every few seconds (a node that starts or restarts late still gets it: the bus has no latching);
    nodes take their camera from here and a launch file only overrides. ``K`` / ``width`` /
    ``height`` describe the published images; ``distortion_model`` ('none', 'radtan' k1 k2 p1 p2
    [k3], 'equidistant' k1..k4) the distortion left in them. ``T_imu_cam`` is the camera pose in
    the IMU frame (absent: not known); ``camera_height_m`` the camera centre above the road (NaN:
    not known); ``imu_noise`` the frontend's ``ImuNoise`` fields the source knows (may be empty);
    ``source`` where the calibration came from (a file, a ROS topic), for the log.
    """

    TYPE: ClassVar[str] = "CameraInfo"
    SCALARS: ClassVar[dict[str, str]] = {
        **_BASE,
        "width": "int",
        "height": "int",
        "distortion_model": "str",
        "camera_height_m": "float_or_nan",
        "imu_noise": "dict_num",
        "source": "str",
    }
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "K": ArraySpec(_F64, ((3, 3),), finite=True),
        "distortion_coeffs": ArraySpec(_F64, (("D",),), finite=True),
        "T_imu_cam": ArraySpec(_F64, ((4, 4),), finite=True, optional=True),
    }
    MODELS: ClassVar[dict[str, tuple[int, ...]]] = {
        "none": (0,),
        "radtan": (4, 5),
        "equidistant": (4,),
    }

    stamp_ns: int
    frame_id: str
    width: int
    height: int
    K: np.ndarray
    distortion_model: str
    distortion_coeffs: np.ndarray
    T_imu_cam: np.ndarray | None = None
    camera_height_m: float = float("nan")
    imu_noise: dict[str, float] = field(default_factory=dict)
    source: str = ""


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        Image,
        Imu,
        Odometry,
        Keyframe,
        Masks,
        DepthMap,
        MapStats,
        Render,
        GaussianUpdate,
        PoseStamped,
        Diagnostics,
        CameraInfo,
    )
}


class Envelope(NamedTuple):
    """A decoded message with its transport metadata (a tuple: cheap to make per message)."""

    topic: str
    seq: int
    src: int
    msg: Message
    nbytes: int


_HEADER_KEYS = frozenset({"t", "v", "seq", "src", "f", "a"})
_SCALAR_SETS: dict[type, frozenset[str]] = {
    cls: frozenset(cls.SCALARS) for cls in MESSAGE_TYPES.values()
}
# Per-type tables precomputed once: the codec runs per message on every topic (200 Hz IMU and
# more), and walking a tuple of (name, kind) pairs is cheaper than a dict's items() each time.
_SCALAR_TABLES: dict[type, tuple[tuple[str, str], ...]] = {
    cls: tuple(cls.SCALARS.items()) for cls in MESSAGE_TYPES.values()
}
# types with checks across fields (enumerations, encoding vs shape)
_CROSS_CHECKED = frozenset(
    cls
    for cls in MESSAGE_TYPES.values()
    if hasattr(cls, "ENCODINGS") or hasattr(cls, "KINDS") or cls in (Image, CameraInfo)
)
_ZMQ_FRAME = zmq.Frame
_new_envelope = tuple.__new__  # Envelope(...) without the NamedTuple's Python-level __new__


# ---------------------------------------------------------------------------------------- checks

_INT_MIN, _INT_MAX = -(1 << 63), (1 << 63) - 1


def _check_scalar(kind: str, name: str, value: Any) -> Any:
    # fast paths for the common, valid cases (the codec runs per message on every topic)
    tv = type(value)
    if tv is int and kind == "int" and _INT_MIN <= value <= _INT_MAX:
        return value
    if tv is float and kind == "float" and math.isfinite(value):
        return value
    if tv is str and kind == "str" and len(value) <= 4096:
        return value
    if (tv is tuple or tv is list) and kind == "vec3" and len(value) == 3:
        a, b, c = value
        if type(a) is float and type(b) is float and type(c) is float and math.isfinite(a + b + c):
            return (a, b, c)
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise MessageError(f"expected int, got {type(value).__name__}", field=name)
        if not _INT_MIN <= int(value) <= _INT_MAX:
            raise MessageError("integer out of int64 range", field=name)
        return int(value)
    if kind in ("float", "float_or_nan"):
        if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
            raise MessageError(f"expected float, got {type(value).__name__}", field=name)
        v = float(value)
        if not math.isfinite(v) and not (kind == "float_or_nan" and math.isnan(v)):
            raise MessageError("non-finite value", field=name)
        return v
    if kind == "str":
        if not isinstance(value, str):
            raise MessageError(f"expected str, got {type(value).__name__}", field=name)
        if len(value) > 4096:
            raise MessageError("string longer than 4096 characters", field=name)
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise MessageError(f"expected bool, got {type(value).__name__}", field=name)
        return value
    if kind == "vec3":
        if not isinstance(value, list | tuple | np.ndarray) or len(value) != 3:
            raise MessageError("expected 3 floats", field=name)
        out = tuple(_check_scalar("float", f"{name}[{i}]", v) for i, v in enumerate(value))
        return out
    if kind == "dict_num":
        if not isinstance(value, dict) or len(value) > 4096:
            raise MessageError("expected a dict of str -> number (at most 4096 keys)", field=name)
        out_d: dict[str, float | int] = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise MessageError("dict key is not a str", field=name)
            if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
                raise MessageError(f"value of {k!r} is not a number", field=name)
            out_d[k] = v.item() if isinstance(v, np.generic) else v
        return out_d
    if kind == "dict_any":
        return _check_dict_any(name, value, depth=0)
    raise MessageError(f"unknown scalar kind {kind}", field=name)  # pragma: no cover


def _check_dict_any(name: str, value: Any, depth: int) -> dict[str, Any]:
    if not isinstance(value, dict) or len(value) > 4096 or depth > 2:
        raise MessageError("expected a (nested, depth <= 2) dict of str -> scalars", field=name)
    out: dict[str, Any] = {}
    for k, v in value.items():
        if not isinstance(k, str):
            raise MessageError("dict key is not a str", field=name)
        if isinstance(v, dict):
            out[k] = _check_dict_any(f"{name}.{k}", v, depth + 1)
        elif isinstance(v, bool | int | float | str):
            out[k] = v
        elif isinstance(v, np.generic):
            out[k] = v.item()
        else:
            raise MessageError(
                f"value of {k!r} has unsupported type {type(v).__name__}", field=name
            )
    return out


def _match_shape(
    name: str, spec: ArraySpec, shape: tuple[int, ...], symbols: dict[str, int]
) -> None:
    errors = []
    for pattern in spec.shapes:
        if len(pattern) != len(shape):
            errors.append(f"ndim {len(shape)} != {len(pattern)}")
            continue
        bound = dict(symbols)
        ok = True
        for want, got in zip(pattern, shape):
            if isinstance(want, int):
                if want != got:
                    ok = False
                    errors.append(f"size {got} != {want}")
                    break
            elif want in bound and bound[want] != got:
                ok = False
                errors.append(f"{want}={got} disagrees with {want}={bound[want]} of another array")
                break
            else:
                bound[want] = got
        if ok:
            symbols.update(bound)
            return
    pats = " or ".join("[" + ",".join(str(p) for p in pat) + "]" for pat in spec.shapes)
    raise MessageError(
        f"shape {list(shape)} does not match {pats} ({'; '.join(errors)})", field=name
    )


def _check_array(name: str, spec: ArraySpec, arr: Any, symbols: dict[str, int]) -> np.ndarray:
    if not isinstance(arr, np.ndarray):
        raise MessageError(f"expected a numpy array, got {type(arr).__name__}", field=name)
    dt = arr.dtype
    if dt.str not in spec.dtypes and dt.newbyteorder("<").str not in spec.dtypes:
        raise MessageError(f"dtype {dt.str} not in {list(spec.dtypes)}", field=name)
    _match_shape(name, spec, arr.shape, symbols)
    if spec.finite and dt.kind == "f" and arr.size and not np.isfinite(arr).all():
        raise MessageError("contains NaN or inf", field=name)
    return arr


def _check_scalars(table: tuple[tuple[str, str], ...], values: dict[str, Any]) -> dict[str, Any]:
    """The scalar fields of ``table`` taken from ``values``, checked (the reference checker)."""
    out: dict[str, Any] = {}
    for name, kind in table:
        try:
            value = values[name]
        except KeyError:
            raise MessageError("missing field", field=name) from None
        out[name] = _check_scalar(kind, name, value)
    return out


# Inline acceptance tests of the common valid case of each scalar kind, for the generated fast
# checkers below: each accepts a subset of what _check_scalar accepts and returns it unchanged.
_FAST_CONDITIONS = {
    "int": "type({v}) is int and {lo} <= {v} <= {hi}",
    "float": "type({v}) is float and {v} - {v} == 0.0",  # inf - inf and nan - nan are nan
    "float_or_nan": "type({v}) is float and ({v} - {v} == 0.0 or {v} != {v})",
    "str": "type({v}) is str and len({v}) <= 4096",
    "bool": "type({v}) is bool",
    "vec3": (
        "(type({v}) is list or type({v}) is tuple) and len({v}) == 3"
        " and type({v}[0]) is float and type({v}[1]) is float and type({v}[2]) is float"
        " and {v}[0] - {v}[0] == 0.0 and {v}[1] - {v}[1] == 0.0 and {v}[2] - {v}[2] == 0.0"
    ),
}
_FAST_VALUES = {"vec3": "({v}[0], {v}[1], {v}[2])"}


def _make_fast_scalars(
    table: tuple[tuple[str, str], ...],
) -> Callable[[dict[str, Any]], dict[str, Any] | None]:
    """A checker specialised to one message type's scalar fields, generated once per type.

    It returns the checked fields when every field is present and in the common valid form
    (exact types, finite floats, in-range ints), and None otherwise (keys beyond the fields are
    the caller's business, as in :func:`_check_scalars`); the caller then runs the
    reference :func:`_check_scalars`, which converts what may be converted or raises naming the
    field. Straight-line code per type beats walking the table per message (one IMU sample's
    fields: 0.95 -> 0.65 us CPU), which adds up on 200 Hz-and-up topics.
    """
    conds, items = [], []
    for i, (name, kind) in enumerate(table):
        v = f"v{i}"
        cond = _FAST_CONDITIONS.get(kind)
        if cond is not None:
            conds.append(cond.format(v=v, lo=_INT_MIN, hi=_INT_MAX))
            items.append(f"{name!r}: " + _FAST_VALUES.get(kind, "{v}").format(v=v))
        else:  # dict kinds: the reference check (it raises naming the field, in field order)
            items.append(f"{name!r}: _check_scalar({kind!r}, {name!r}, {v})")
    fetch = "; ".join(f"v{i} = f[{name!r}]" for i, (name, _) in enumerate(table))
    src = (
        "def fast(f):\n"
        "    try:\n"
        f"        {fetch}\n"
        "    except KeyError:\n"
        "        return None\n"
        + (f"    if not ({' and '.join(conds)}):\n        return None\n" if conds else "")
        + f"    return {{{', '.join(items)}}}\n"
    )
    namespace: dict[str, Any] = {"_check_scalar": _check_scalar}
    exec(compile(src, f"<mogs fast scalars {table[:1]}...>", "exec"), namespace)  # noqa: S102
    return namespace["fast"]


def _check_arrays(cls: type[Message], arrays: dict[str, Any], out: dict[str, Any]) -> None:
    """Check the arrays of ``cls`` (in spec order, so symbols bind in a fixed order) into ``out``."""
    symbols: dict[str, int] = {}
    for name, spec in cls.ARRAYS.items():
        arr = arrays.get(name)
        if arr is None:
            if not spec.optional:
                raise MessageError("missing array", field=name)
            out[name] = None
            continue
        out[name] = _check_array(name, spec, arr, symbols)


def _scalars_of(cls: type[Message], values: dict[str, Any]) -> dict[str, Any]:
    """The checked scalar fields of ``cls`` from ``values`` (a message's or a header's)."""
    fast = _FAST_SCALARS.get(cls)
    out = fast(values) if fast is not None else None
    if out is None:
        out = _check_scalars(_SCALAR_TABLES.get(cls) or tuple(cls.SCALARS.items()), values)
    return out


def _validate_fields(cls: type[Message], values: dict[str, Any]) -> dict[str, Any]:
    out = _scalars_of(cls, values)
    if cls.ARRAYS:
        _check_arrays(cls, values, out)
    if cls in _CROSS_CHECKED:
        _check_enums(cls, out)
    return out


def _check_enums(cls: type[Message], out: dict[str, Any]) -> dict[str, Any]:
    enc = getattr(cls, "ENCODINGS", None)
    if enc is not None and out.get("encoding") not in enc:
        raise MessageError(
            f"unknown encoding {out.get('encoding')!r}, expected one of {enc}", field="encoding"
        )
    kinds = getattr(cls, "KINDS", None)
    if kinds is not None and out.get("kind") not in kinds:
        raise MessageError(
            f"unknown kind {out.get('kind')!r}, expected one of {kinds}", field="kind"
        )
    if cls is CameraInfo:
        _check_camera_info(out)
    if cls is Image:
        data = out["data"]
        if (data.ndim == 3) != (out["encoding"] != "mono8"):
            raise MessageError(
                f"encoding {out['encoding']} does not fit shape {list(data.shape)}", field="data"
            )
    return out


def _check_camera_info(out: dict[str, Any]) -> None:
    """Size, focal lengths and the distortion model's number of coefficients of a CameraInfo."""
    need = CameraInfo.MODELS.get(out["distortion_model"])
    if need is None:
        raise MessageError(
            f"unknown model {out['distortion_model']!r}, expected one of "
            f"{tuple(CameraInfo.MODELS)}",
            field="distortion_model",
        )
    if len(out["distortion_coeffs"]) not in need:
        raise MessageError(
            f"{out['distortion_model']} takes {need} coefficients, "
            f"got {len(out['distortion_coeffs'])}",
            field="distortion_coeffs",
        )
    for name in ("width", "height"):
        if not 0 < out[name] <= MAX_DIM:
            raise MessageError(f"image size must be in 1..{MAX_DIM}, got {out[name]}", field=name)
    K = out["K"]
    if not (K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] == 1.0 and K[1, 0] == K[2, 0] == K[2, 1] == 0):
        raise MessageError(
            f"expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {K.tolist()}",
            field="K",
        )
    h = out["camera_height_m"]
    if h == h and h < 0:
        raise MessageError(f"must be >= 0 or NaN (unknown), got {h}", field="camera_height_m")


_FAST_SCALARS = {cls: _make_fast_scalars(table) for cls, table in _SCALAR_TABLES.items()}
# type name -> what decode needs of the type, in one lookup
_CODECS: dict[str, tuple[type[Message], tuple[tuple[str, str], ...], Any, bool, bool]] = {
    name: (cls, _SCALAR_TABLES[cls], _FAST_SCALARS[cls], bool(cls.ARRAYS), cls in _CROSS_CHECKED)
    for name, cls in MESSAGE_TYPES.items()
}
_unpackb = msgpack.unpackb

# Typed headers (msgspec): for every type whose scalar fields are all of the kinds below, a
# header struct that msgspec decodes *and checks* in C in one call (0.5 us for an IMU sample's
# header, against 1.1 us for msgpack.unpackb alone plus ~1.6 us of checks in Python). Each kind
# accepts a subset of what the reference _check_scalar accepts, with the same values (ints for
# floats become floats, bools are no ints, floats are finite, ints are int64, strings at most
# 4096 characters): whatever it refuses goes through the reference path, which converts or
# raises naming the field (test_typed_header_agrees_with_the_reference).
_FINITE = Annotated[float, msgspec.Meta(ge=-sys.float_info.max, le=sys.float_info.max)]
_INT64 = Annotated[int, msgspec.Meta(ge=_INT_MIN, le=_INT_MAX)]
_TYPED_KINDS: dict[str, Any] = {
    "int": _INT64,
    "float": _FINITE,
    "str": Annotated[str, msgspec.Meta(max_length=4096)],
    "bool": bool,
    "vec3": tuple[_FINITE, _FINITE, _FINITE],
}


def _typed_header(cls: type[Message]) -> tuple[type, type] | None:
    """The (header, fields) msgspec structs of ``cls``, or None if a field's kind has none."""
    table = _SCALAR_TABLES[cls]
    if any(kind not in _TYPED_KINDS for _, kind in table):
        return None
    fields_struct = msgspec.defstruct(
        f"{cls.TYPE}Fields",
        [(name, _TYPED_KINDS[kind]) for name, kind in table],
        forbid_unknown_fields=True,
        gc=False,
    )
    header = msgspec.defstruct(
        f"{cls.TYPE}Header",
        [("v", int), ("seq", _INT64), ("src", _INT64), ("f", fields_struct), ("a", list)],
        tag=cls.TYPE,
        tag_field="t",  # first on the wire, as in the packer's map
        forbid_unknown_fields=True,
    )
    return header, fields_struct


_TYPED: dict[type, tuple[type, type]] = {
    cls: typed for cls in MESSAGE_TYPES.values() if (typed := _typed_header(cls)) is not None
}
# header struct -> what decode needs of the type
_TYPED_CODECS: dict[type, tuple[type[Message], bool, bool]] = {
    header: (cls, bool(cls.ARRAYS), cls in _CROSS_CHECKED) for cls, (header, _) in _TYPED.items()
}
_typed_decode = msgspec.msgpack.Decoder(Union[tuple(h for h, _ in _TYPED.values())]).decode  # noqa: UP007
_typed_encode = msgspec.msgpack.Encoder().encode
_typed_convert = msgspec.convert
_struct_fields = msgspec.structs.asdict

# ---------------------------------------------------------------------------------------- codec


def encode(topic: str, msg: Message, *, seq: int = 0, src: int = 0) -> list[bytes | memoryview]:
    """Encode ``msg`` for ``topic`` into multipart frames (arrays are not copied when contiguous).

    Raises :class:`MessageError` if ``msg`` does not satisfy its own spec: a publisher never sends
    what a subscriber would reject.
    """
    cls = type(msg)
    if cls.TYPE not in MESSAGE_TYPES:
        raise MessageError(f"unknown message type {cls.__name__}", field="t")
    values = msg.__dict__
    typed = _TYPED.get(cls)
    fields_value = None
    if typed is not None:  # checked in C; what it refuses, the reference converts or names
        with contextlib.suppress(Exception):
            fields_value = (
                _typed_convert(msg, typed[1], from_attributes=True)
                if cls.ARRAYS
                else _typed_convert(values, typed[1])
            )
    if fields_value is None:
        scalars = _scalars_of(cls, values)
        if typed is not None:
            fields_value = typed[1](**scalars)
    elif cls in _CROSS_CHECKED:
        scalars = _struct_fields(fields_value)
    descs: list[list[Any]] = []
    frames: list[bytes | memoryview] = [topic.encode("utf-8"), b""]
    if cls.ARRAYS:
        arrays: dict[str, Any] = {}
        _check_arrays(cls, values, arrays)
        if cls in _CROSS_CHECKED:
            _check_enums(cls, {**scalars, **arrays})
        for name, arr in arrays.items():
            if arr is None:
                continue
            a = np.ascontiguousarray(arr)
            if a.dtype.byteorder == ">":
                a = a.astype(a.dtype.newbyteorder("<"))
            descs.append([name, a.dtype.str, list(a.shape)])
            # a flat byte view of the array itself: the frame is sent without a copy
            frames.append(memoryview(a).cast("B") if a.size else memoryview(b""))
    elif cls in _CROSS_CHECKED:
        _check_enums(cls, scalars)
    if typed is not None:  # the same bytes as the packer's map, 2x faster
        frames[1] = _typed_encode(typed[0](cls.VERSION, int(seq), int(src), fields_value, descs))
        return frames
    frames[1] = _packer().pack(
        {
            "t": cls.TYPE,
            "v": cls.VERSION,
            "seq": int(seq),
            "src": int(src),
            "f": scalars,
            "a": descs,
        }
    )
    return frames


_tls = threading.local()


def _packer() -> msgpack.Packer:
    """This thread's msgpack packer: reusing one saves ~0.3 us per message over ``packb``
    (which builds a packer per call); a packer is not thread-safe, hence one per thread."""
    try:
        return _tls.packer
    except AttributeError:
        packer = _tls.packer = msgpack.Packer(use_bin_type=True)
        return packer


def _frame_bytes(frame: Any) -> memoryview:
    if isinstance(frame, bytes | bytearray | memoryview):
        return memoryview(frame)
    buf = getattr(frame, "buffer", None)  # zmq.Frame
    if buf is not None:
        return memoryview(buf)
    raise MessageError(f"frame of unsupported type {type(frame).__name__}", field="frame")


def decode(
    frames: Sequence[Any],
    *,
    max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    topic: str | None = None,
) -> Envelope:
    """Decode multipart ``frames`` into an :class:`Envelope`; strict, see the module docstring.

    Frames may be ``bytes`` (what a copying receive gives for small frames), ``zmq.Frame`` (a
    zero-copy receive) or any buffer. Arrays are read-only views of their frames. ``topic``:
    the first frame's text where the caller has already read and checked it (a subscriber that
    matched it against its own topic names), which saves reading it again.
    """
    if not isinstance(frames, list | tuple) or len(frames) < 2:
        raise MessageError("expected at least [topic, header] frames", field="frames")
    f0, f1 = frames[0], frames[1]
    if len(frames) == 2 and type(f0) is bytes and type(f1) is bytes:  # small, array-less
        views: Sequence[Any] = frames
        sizes = [len(f0), len(f1)]
        total = sizes[0] + sizes[1]
    else:
        views = []
        sizes = []
        total = 0
        for f in frames:
            if type(f) is bytes:
                n = len(f)
            else:
                f = f.buffer if type(f) is _ZMQ_FRAME else _frame_bytes(f)
                if f.ndim != 1 or f.itemsize != 1:
                    f = f.cast("B") if f.c_contiguous else memoryview(f.tobytes())
                n = f.nbytes
            views.append(f)
            sizes.append(n)
            total += n
    if total > max_bytes:
        raise MessageError(
            f"message of {total} bytes exceeds the limit of {max_bytes}", field="size"
        )
    if topic is None:
        try:
            topic = str(views[0], "utf-8")
        except UnicodeDecodeError as err:
            raise MessageError("topic is not UTF-8", field="topic") from err
        if not topic.startswith("/") or len(topic) > MAX_TOPIC_CHARS:
            raise MessageError(f"invalid topic name {topic[:64]!r}", field="topic")
    if sizes[1] > MAX_HEADER_BYTES:
        raise MessageError(f"header of {sizes[1]} bytes exceeds {MAX_HEADER_BYTES}", field="header")
    try:  # the common, valid case: header and scalar fields decoded and checked in C
        typed = _typed_decode(views[1])
    except Exception:  # anything else: the reference path below, which names what is wrong
        typed = None
    if typed is not None:
        cls, has_arrays, cross_checked = _TYPED_CODECS[type(typed)]
        if typed.v != cls.VERSION:
            raise MessageError(f"{cls.TYPE} schema version {typed.v!r} != {cls.VERSION}", field="v")
        seq, src, descs = typed.seq, typed.src, typed.a
        out: dict[str, Any] | None = _struct_fields(typed.f)
    else:
        cls, has_arrays, cross_checked, seq, src, descs, scalars = _reference_header(views[1])
        out = None
    if len(descs) != len(views) - 2:
        raise MessageError(
            f"{len(descs)} array descriptors but {len(views) - 2} buffers", field="a"
        )
    arrays: dict[str, np.ndarray] = {}
    if descs:
        for desc, view, size in zip(descs, views[2:], sizes[2:]):
            if not (type(desc) is list and len(desc) == 3 and type(desc[0]) is str):
                raise MessageError("array descriptor must be [name, dtype, shape]", field="a")
            name, dtype_str, shape = desc
            if name not in cls.ARRAYS:
                raise MessageError(f"unexpected array for {cls.TYPE}", field=name)
            if name in arrays:
                raise MessageError("array given twice", field=name)
            dtype = _WIRE_DTYPES.get(dtype_str) if type(dtype_str) is str else None
            if dtype is None:
                raise MessageError(f"dtype {dtype_str!r} is not allowed on the wire", field=name)
            if (
                type(shape) is not list
                or len(shape) > 4
                or not all(type(s) is int and 0 <= s <= MAX_DIM for s in shape)
            ):
                raise MessageError(f"invalid shape {shape!r}", field=name)
            if math.prod(shape) * dtype.itemsize != size:
                raise MessageError(
                    f"buffer of {size} bytes does not fit shape {shape} of {dtype.str}",
                    field=name,
                )
            arrays[name] = np.frombuffer(view, dtype=dtype).reshape(shape)
    if out is None:
        out = _FAST_SCALARS[cls](scalars)
        if out is None:
            out = _check_scalars(_SCALAR_TABLES[cls], scalars)
    if has_arrays:
        _check_arrays(cls, arrays, out)
    if cross_checked:
        _check_enums(cls, out)
    msg = object.__new__(cls)  # the dataclass __init__ would only assign what is validated here
    msg.__dict__.update(out)
    return _new_envelope(Envelope, (topic, seq, src, msg, total))


def _reference_header(
    header_bytes: Any,
) -> tuple[type[Message], bool, bool, int, int, list[Any], dict[str, Any]]:
    """The header checked in Python, for what the typed decoder refuses: it names the field."""
    try:
        header = _unpackb(
            header_bytes,
            # raw=False, strict_map_key=True, use_list=True: msgpack's defaults
            max_str_len=MAX_HEADER_BYTES,
            max_bin_len=0,
            max_array_len=4096,
            max_map_len=4096,
            max_ext_len=0,
        )
    except Exception as err:  # msgpack raises several unrelated types on garbage
        raise MessageError(
            f"header is not valid msgpack ({type(err).__name__}: {err})", field="header"
        ) from err
    if type(header) is not dict:
        raise MessageError("header is not a map", field="header")
    if header.keys() != _HEADER_KEYS:
        missing, extra = _HEADER_KEYS - set(header), set(header) - _HEADER_KEYS
        raise MessageError(
            f"header keys: missing {sorted(missing)}, unexpected {sorted(map(str, extra))}",
            field="header",
        )
    type_name = header["t"]
    codec = _CODECS.get(type_name) if type(type_name) is str else None
    if codec is None:
        raise MessageError(f"unknown message type {type_name!r}", field="t")
    cls, table, _, has_arrays, cross_checked = codec
    version = header["v"]
    if type(version) is not int or version != cls.VERSION:  # type(): True == 1 is no version
        raise MessageError(f"{cls.TYPE} schema version {version!r} != {cls.VERSION}", field="v")
    seq, src = header["seq"], header["src"]
    if not (type(seq) is int and _INT_MIN <= seq <= _INT_MAX):
        seq = _check_scalar("int", "seq", seq)
    if not (type(src) is int and _INT_MIN <= src <= _INT_MAX):
        src = _check_scalar("int", "src", src)
    scalars = header["f"]
    if type(scalars) is not dict:
        raise MessageError("scalar fields are not a map", field="f")
    if len(scalars) != len(table):  # equal sizes with a stranger mean a missing field: found below
        extra = scalars.keys() - _SCALAR_SETS[cls]
        if extra:
            raise MessageError(
                f"unexpected field(s) {sorted(map(str, extra))} for {cls.TYPE}",
                field=str(sorted(map(str, extra))[0]),
            )
    descs = header["a"]
    if type(descs) is not list:
        raise MessageError("array descriptors are not a list", field="a")
    return cls, has_arrays, cross_checked, seq, src, descs, scalars
