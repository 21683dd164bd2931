"""The message types: their scalar kinds and array specs, and the checks across fields.

The wire format is in ``mogs_node.msgs`` (package docstring) and ``codec``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import numpy as np

from mogs_node.depth_kind import DEPTH_KINDS
from mogs_node.errors import MessageError
from mogs_node.msgs.fields import (
    MAX_DIM,
    ArraySpec,
    _check_arrays,
    _check_scalars,
    _make_fast_scalars,
)

FloatOrNaN = float
"""A float field that may be NaN ("not known"); every other float field must be finite."""

# annotation (a string: ``from __future__ import annotations``) -> scalar kind (``fields``)
_SCALAR_KIND_OF = {
    "int": "int",
    "str": "str",
    "bool": "bool",
    "float": "float",
    "FloatOrNaN": "float_or_nan",
    "tuple[float, float, float]": "vec3",
    "dict[str, float]": "dict_num",
    "dict[str, Any]": "dict_any",
}
_ARRAY_ANNOTATIONS = ("np.ndarray", "np.ndarray | None")


@dataclass(eq=False)
class Message:
    """Base of every message dataclass: the header fields (``stamp_ns``, ``frame_id``, first in
    every message), ``TYPE``, ``VERSION``, scalar kinds and array specs.

    A subclass declares its fields once, as annotations; ``SCALARS`` (field -> scalar kind, in
    field order) is derived from them, and every ``np.ndarray`` field must have its ``ARRAYS``
    spec (and every spec a field), checked when the class is defined.
    """

    TYPE: ClassVar[str]
    VERSION: ClassVar[int] = 1
    SCALARS: ClassVar[dict[str, str]]
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {}

    stamp_ns: int
    frame_id: str

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        scalars: dict[str, str] = {}
        arrays: list[str] = []
        declared = [k.__dict__.get("__annotations__", {}) for k in reversed(cls.__mro__)]
        for name, ann in (item for anns in declared for item in anns.items()):
            if ann.startswith("ClassVar["):
                continue
            if ann in _ARRAY_ANNOTATIONS:
                arrays.append(name)
            elif ann in _SCALAR_KIND_OF:
                scalars[name] = _SCALAR_KIND_OF[ann]
            else:  # a schema author's mistake, caught on import
                raise TypeError(f"{cls.__name__}.{name}: no wire kind for annotation {ann!r}")
        if set(arrays) != set(cls.ARRAYS):
            raise TypeError(f"{cls.__name__}: array fields {arrays} != ARRAYS {list(cls.ARRAYS)}")
        cls.SCALARS = scalars

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
_POSE = ArraySpec(_F64, ((4, 4),), finite=True)  # a rigid transform T_a_b
_INTRINSICS = ArraySpec(_F64, ((3, 3),), finite=True)  # a pinhole K


@dataclass(eq=False)
class Image(Message):
    """A camera image (``/camera/image``)."""

    TYPE: ClassVar[str] = "Image"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "data": ArraySpec(_U8, (("H", "W"), ("H", "W", 3))),
    }
    ENCODINGS: ClassVar[tuple[str, ...]] = ("mono8", "rgb8", "bgr8")

    encoding: str
    data: np.ndarray

    def rgb_or_mono(self) -> np.ndarray:
        """The pixels in RGB order (``bgr8`` flipped), or ``[H, W]`` for ``mono8``; contiguous."""
        return np.ascontiguousarray(self.data[..., ::-1] if self.encoding == "bgr8" else self.data)


@dataclass(eq=False)
class Imu(Message):
    """One IMU sample (``/imu``) in the IMU frame."""

    TYPE: ClassVar[str] = "Imu"

    gyro_rad_s: tuple[float, float, float]
    accel_m_s2: tuple[float, float, float]


@dataclass(eq=False)
class Odometry(Message):
    """Per-frame pose estimate of the frontend (``/frontend/odometry``)."""

    TYPE: ClassVar[str] = "Odometry"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"T_world_cam": _POSE}

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
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "image": ArraySpec(_U8, (("H", "W", 3), ("H", "W"))),
        "K": _INTRINSICS,
        "T_world_cam": _POSE,
        "feature_ids": ArraySpec(_I64, (("N",),)),
        "feature_uv_px": ArraySpec(_F32, (("N", 2),), finite=True),
        "feature_xyz_cam_m": ArraySpec(_F32, (("N", 3),), finite=True),
        "feature_weight": ArraySpec(_F32, (("N",),), finite=True),
    }

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
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"labels": ArraySpec(_I32, (("H", "W"),))}

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
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "depth": ArraySpec(_F32, (("H", "W"),), finite=True),
        "confidence": ArraySpec(_F32, (("H", "W"),), finite=True),
        "object_labels": ArraySpec(_I32, (("H", "W"),), optional=True),
        "object_model": ArraySpec(_I8, (("M",),), optional=True),
    }
    KINDS: ClassVar[tuple[str, ...]] = DEPTH_KINDS  # mogs_node.depth_kind.DepthKind

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

    keyframe_id: int
    n_gaussians: int
    n_keyframes: int
    iterations: int
    loss: FloatOrNaN
    psnr_db: FloatOrNaN
    extra: dict[str, float] = field(default_factory=dict)


@dataclass(eq=False)
class Render(Message):
    """A rendered view of the map (``/mapper/render``)."""

    TYPE: ClassVar[str] = "Render"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "image": ArraySpec(_U8, (("H", "W", 3),)),
        "depth": ArraySpec(_F32, (("H", "W"),), finite=True, optional=True),
    }

    keyframe_id: int
    image: np.ndarray
    depth: np.ndarray | None = None


@dataclass(eq=False)
class GaussianUpdate(Message):
    """Incremental map change: Gaussians added or changed (by id) and ids removed."""

    TYPE: ClassVar[str] = "GaussianUpdate"
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "ids": ArraySpec(_I64, (("N",),)),
        "means": ArraySpec(_F32, (("N", 3),), finite=True),
        "log_scales": ArraySpec(_F32, (("N", 3),), finite=True),
        "quats_wxyz": ArraySpec(_F32, (("N", 4),), finite=True),
        "opacity_logit": ArraySpec(_F32, (("N",),), finite=True),
        "colors_rgb": ArraySpec(_F32, (("N", 3),), finite=True),
        "removed_ids": ArraySpec(_I64, (("M",),)),
    }

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
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"T_world_cam": _POSE}

    T_world_cam: np.ndarray


@dataclass(eq=False)
class Diagnostics(Message):
    """Heartbeat and counters of one node (``/diagnostics``).

    ``counters`` are node-wide figures (received, published, dropped, malformed, handler_errors,
    queue_depth, loop_latency_ms, ...); ``topics`` maps topic -> its own counters.
    """

    TYPE: ClassVar[str] = "Diagnostics"

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
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "K": _INTRINSICS,
        "distortion_coeffs": ArraySpec(_F64, (("D",),), finite=True),
        "T_imu_cam": ArraySpec(_F64, ((4, 4),), finite=True, optional=True),
    }
    MODELS: ClassVar[dict[str, tuple[int, ...]]] = {
        "none": (0,),
        "radtan": (4, 5),
        "equidistant": (4,),
    }

    width: int
    height: int
    K: np.ndarray
    distortion_model: str
    distortion_coeffs: np.ndarray
    T_imu_cam: np.ndarray | None = None
    camera_height_m: FloatOrNaN = float("nan")
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
