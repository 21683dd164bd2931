"""Every message type and its wire codec: ``schema`` (the types), ``fields`` (what a
field may be, its checks) and ``codec`` (frames).

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

from mogs_node.errors import MessageError
from mogs_node.msgs.codec import Envelope, decode, encode
from mogs_node.msgs.fields import (
    DEFAULT_MAX_MESSAGE_BYTES,
    MAX_DIM,
    MAX_HEADER_BYTES,
    MAX_TOPIC_CHARS,
    ArraySpec,
)
from mogs_node.msgs.schema import (
    MESSAGE_TYPES,
    CameraInfo,
    DepthMap,
    Diagnostics,
    GaussianUpdate,
    Image,
    Imu,
    Keyframe,
    MapStats,
    Masks,
    Message,
    Odometry,
    PoseStamped,
    Render,
)

__all__ = [
    "DEFAULT_MAX_MESSAGE_BYTES",
    "MESSAGE_TYPES",
    "MAX_DIM",
    "MAX_HEADER_BYTES",
    "MAX_TOPIC_CHARS",
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
