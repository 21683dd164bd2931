"""The wire codec: a message to multipart frames and back, strictly (see ``mogs_node.msgs``)."""

from __future__ import annotations

import contextlib
import math
import sys
import threading
from collections.abc import Sequence
from typing import Annotated, Any, NamedTuple, Union

import msgpack
import msgspec
import numpy as np
import zmq

from mogs_node.errors import MessageError
from mogs_node.msgs.fields import (
    _INT_MAX,
    _INT_MIN,
    DEFAULT_MAX_MESSAGE_BYTES,
    MAX_DIM,
    MAX_HEADER_BYTES,
    MAX_TOPIC_CHARS,
    _check_arrays,
    _check_scalar,
    _check_scalars,
)
from mogs_node.msgs.schema import (
    _CROSS_CHECKED,
    _FAST_SCALARS,
    _SCALAR_TABLES,
    MESSAGE_TYPES,
    Message,
    _check_enums,
    _scalars_of,
)

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
_ZMQ_FRAME = zmq.Frame
_new_envelope = tuple.__new__  # Envelope(...) without the NamedTuple's Python-level __new__
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


# ------------------------------------------------------------------- shared-memory references

# Arrays that travel through shared memory (mogs_node/shm.py) leave the frames; a reference to
# them rides in the header as a seventh, last entry "m". The header's first byte (a msgpack map
# of 6 or of 7 entries) tells the two forms apart, so the bus need not decode the header.
_HEADER_MAP6, _HEADER_MAP7 = b"\x86", b"\x87"
_SHM_KEY = msgpack.packb("m")


def is_inline_header(header: bytes) -> bool:
    """Whether ``header`` is of this codec's form with its arrays in the frames."""
    return header[:1] == _HEADER_MAP6


def has_shm_ref(header: bytes) -> bool:
    """Whether ``header`` carries a shared-memory reference instead of array frames."""
    return header[:1] == _HEADER_MAP7


def header_src_seq(header: bytes) -> tuple[int, int] | None:
    """The (src, seq) of an encoded header, or None where it is not of this codec's form."""
    try:
        fields = msgpack.unpackb(header, max_bin_len=0)
        src, seq = fields["src"], fields["seq"]
    except Exception:  # msgpack raises several unrelated types on garbage
        return None
    return (src, seq) if type(src) is int and type(seq) is int else None


def add_shm_ref(header: bytes, name: str, ticket: int, sizes: list[int]) -> bytes:
    """``header`` (inline form) with a reference to its arrays in shared memory appended."""
    return _HEADER_MAP7 + header[1:] + _SHM_KEY + msgpack.packb([name, ticket, sizes])


def take_shm_ref(header: bytes, max_bytes: int) -> tuple[bytes, str, int, list[int], int, int]:
    """Split a header made by :func:`add_shm_ref` into (inline header, shared-memory name,
    ticket, array sizes, src, seq); :class:`MessageError` where the reference is malformed."""
    try:
        fields = msgpack.unpackb(
            header, max_bin_len=0, max_ext_len=0, max_array_len=4096, max_map_len=64
        )
        name, ticket, sizes = fields["m"]
        seq, src = fields["seq"], fields["src"]
    except MessageError:
        raise
    except Exception as err:  # msgpack raises several unrelated types on garbage
        raise MessageError(f"malformed shared-memory reference ({err})", field="m") from err
    if not (
        type(name) is str
        and type(ticket) is int
        and type(sizes) is list
        and all(type(n) is int and n >= 0 for n in sizes)
        and type(seq) is int
        and type(src) is int
    ):
        raise MessageError("malformed shared-memory reference", field="m")
    tail = _SHM_KEY + msgpack.packb([name, ticket, sizes])
    if not header.endswith(tail):
        raise MessageError("the shared-memory reference is not the header's last entry")
    if sum(sizes) > max_bytes:
        raise MessageError(
            f"message of {sum(sizes)} bytes exceeds the limit of {max_bytes}", field="size"
        )
    return _HEADER_MAP6 + header[1 : -len(tail)], name, ticket, sizes, src, seq
