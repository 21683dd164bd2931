"""Codec fast paths against the reference: the generated scalar checkers, the typed (msgspec)
header decoder and encoder agree with the reference checker on valid and edge values, or defer to
it."""

from __future__ import annotations

import msgpack
import msgspec
import numpy as np
import pytest
from _msgs_strategies import INT64, TEXT, header_of, messages, scalar_values, with_header
from hypothesis import event, given, settings
from hypothesis import strategies as st

from mogs_node import msgs
from mogs_node.errors import MessageError
from mogs_node.msgs import codec as msgs_codec

# values at and around every edge of every scalar kind: the fast checkers must agree with the
# reference checker on all of them (same result, or defer to it with None)
EDGE_VALUES = st.one_of(
    st.sampled_from(
        [
            -(1 << 63),
            (1 << 63) - 1,
            -(1 << 63) - 1,
            1 << 63,
            (1 << 64) - 1,
            0,
            True,
            False,
            None,
            0.0,
            -0.0,
            float("inf"),
            float("-inf"),
            float("nan"),
            1e308,
            "",
            "x" * 4096,
            "x" * 4097,
            b"bytes",
            np.int64(3),
            np.float32(1.5),
            np.float64("nan"),
            {},
        ]
    ),
    INT64,
    st.floats(),
    TEXT,
    st.lists(st.one_of(st.floats(), st.integers(-5, 5), st.booleans()), max_size=4),
    st.tuples(st.floats(), st.floats(), st.floats()),
    st.dictionaries(TEXT, st.one_of(st.integers(-5, 5), st.floats(), TEXT), max_size=3),
)


def _reference(cls: type[msgs.Message], values: dict) -> tuple[str, object]:
    try:
        return "ok", msgs_codec._check_scalars(msgs_codec._SCALAR_TABLES[cls], values)
    except MessageError as err:
        return "error", err.field


@pytest.mark.parametrize("cls", list(msgs.MESSAGE_TYPES.values()), ids=list(msgs.MESSAGE_TYPES))
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_generated_fast_scalar_checker_agrees_with_the_reference(
    cls: type[msgs.Message], data: st.DataObject
) -> None:
    # mostly valid fields with a few edge values mixed in, and sometimes a field missing
    values = {
        name: data.draw(
            st.one_of(scalar_values(kind), EDGE_VALUES)
            if data.draw(st.booleans())
            else scalar_values(kind)
        )
        for name, kind in cls.SCALARS.items()
    }
    if data.draw(st.booleans()) and values:
        values.pop(data.draw(st.sampled_from(sorted(values))))
    ref = _reference(cls, values)
    try:
        fast = msgs_codec._FAST_SCALARS[cls](values)
    except MessageError as err:  # only the dict kinds raise inside the fast path
        assert ref == ("error", err.field)
        return
    if fast is None:
        return  # deferred to the reference
    assert ref[0] == "ok"
    assert fast == ref[1]
    assert [type(v) for v in fast.values()] == [type(v) for v in ref[1].values()]


TYPED = [cls for cls in msgs.MESSAGE_TYPES.values() if cls in msgs_codec._TYPED]


def _reference_header(raw: bytes) -> tuple[str, object]:
    try:
        cls, _, _, seq, src, descs, scalars = msgs_codec._reference_header(raw)
        return "ok", (
            cls,
            seq,
            src,
            descs,
            msgs_codec._check_scalars(msgs_codec._SCALAR_TABLES[cls], scalars),
        )
    except MessageError as err:
        return "error", err.field


def test_typed_headers_cover_the_frequent_types() -> None:
    # the high-rate and the large types; MapStats and Diagnostics (dict fields) use the reference
    assert {msgs.Imu, msgs.Image, msgs.Odometry, msgs.Keyframe, msgs.DepthMap} <= set(TYPED)


def _typed_encode_agrees(cls: type[msgs.Message], values: dict) -> None:
    """The encoder's side: fields msgspec.convert accepts from a message's values, the reference
    accepts too, and both give the same bytes on the wire."""
    try:
        typed = msgspec.convert(values, msgs_codec._TYPED[cls][1])
    except Exception:
        return
    ref = _reference(cls, values)
    assert ref[0] == "ok", ref
    assert msgspec.msgpack.encode(typed) == msgpack.packb(ref[1], use_bin_type=True)


@pytest.mark.parametrize("cls", TYPED, ids=[c.TYPE for c in TYPED])
@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_typed_header_agrees_with_the_reference(
    cls: type[msgs.Message], data: st.DataObject
) -> None:
    """What the C-level typed decoder accepts, the reference accepts too, with equal values of
    equal types; what it refuses goes to the reference, which decides (decode never trusts it
    for a rejection)."""
    edge = data.draw(st.integers(0, 2)) == 0  # a third of the examples mix in edge values
    values = {
        name: data.draw(
            st.one_of(scalar_values(kind), EDGE_VALUES) if edge else scalar_values(kind)
        )
        for name, kind in cls.SCALARS.items()
    }
    if data.draw(st.integers(0, 9)) == 0 and values:
        values.pop(data.draw(st.sampled_from(sorted(values))))
    if data.draw(st.integers(0, 9)) == 0:
        values["extra"] = 1
    header = {
        "t": cls.TYPE,
        "v": data.draw(st.sampled_from([cls.VERSION] * 7 + [True, 2, 1.0])),
        "seq": data.draw(st.one_of(INT64, EDGE_VALUES) if edge else INT64),
        "src": data.draw(st.one_of(INT64, EDGE_VALUES) if edge else INT64),
        "f": values,
        "a": data.draw(st.sampled_from([[]] * 7 + [[["x", "<f4", [1]]], {}, None])),
    }
    if data.draw(st.integers(0, 9)) == 0:
        header.pop(data.draw(st.sampled_from(sorted(header))))
    _typed_encode_agrees(cls, values)
    try:
        raw = msgpack.packb(header, use_bin_type=True)
    except (TypeError, ValueError, OverflowError):
        return  # not representable in msgpack (numpy scalars, ints beyond 64 bits)
    try:
        typed = msgs_codec._typed_decode(raw)
    except Exception:
        event("typed decoder refused")
        return  # refused: the reference decides
    event("typed decoder accepted")
    ref = _reference_header(raw)
    if typed.v != cls.VERSION:  # decode raises on it as the reference does
        assert ref == ("error", "v")
        return
    assert ref[0] == "ok", ref
    ref_cls, seq, src, descs, out = ref[1]
    assert ref_cls is cls and (typed.seq, typed.src, typed.a) == (seq, src, descs)
    fast = msgs_codec._struct_fields(typed.f)
    assert fast == out
    assert [type(v) for v in fast.values()] == [type(v) for v in out.values()]


@pytest.mark.parametrize("cls", TYPED, ids=[c.TYPE for c in TYPED])
@settings(max_examples=20, deadline=None)
@given(data=st.data())
def test_typed_encode_writes_the_packers_bytes(
    cls: type[msgs.Message], data: st.DataObject
) -> None:
    msg = data.draw(messages(cls))
    frames = msgs.encode("/t", msg, seq=7, src=(1 << 62) + 3)
    scalars = msgs_codec._scalars_of(cls, msg.__dict__)
    descs = msgpack.unpackb(frames[1])["a"]
    packed = msgpack.packb(
        {"t": cls.TYPE, "v": cls.VERSION, "seq": 7, "src": (1 << 62) + 3, "f": scalars, "a": descs},
        use_bin_type=True,
    )
    assert bytes(frames[1]) == packed


def test_fast_path_defers_non_canonical_values_to_the_reference() -> None:
    fast = msgs_codec._FAST_SCALARS[msgs.Imu]
    good = {
        "stamp_ns": 1,
        "frame_id": "i",
        "gyro_rad_s": [0.1, 0.2, 0.3],
        "accel_m_s2": [0.0, 0.0, 9.8],
    }
    assert fast(good) == {**good, "gyro_rad_s": (0.1, 0.2, 0.3), "accel_m_s2": (0.0, 0.0, 9.8)}
    for name, bad in [
        ("stamp_ns", True),  # a bool is no int
        ("stamp_ns", 1 << 63),  # outside int64
        ("stamp_ns", 1.0),
        ("frame_id", "x" * 4097),
        ("gyro_rad_s", [0.1, float("inf"), 0.3]),
        ("gyro_rad_s", [0.1, float("nan"), 0.3]),
        ("accel_m_s2", [0, 0, 9.8]),  # ints: valid, but converted by the reference
        ("accel_m_s2", [0.0, 0.0]),
    ]:
        assert fast({**good, name: bad}) is None, name
    assert fast({k: v for k, v in good.items() if k != "frame_id"}) is None
    # the reference converts where the wire form is merely non-canonical ...
    env = msgs.decode(
        msgs.encode(
            "/imu",
            msgs.Imu(stamp_ns=1, frame_id="i", gyro_rad_s=(0, 0, 1), accel_m_s2=(0.0, 0.0, 9.8)),
        )
    )
    assert env.msg.gyro_rad_s == (0.0, 0.0, 1.0) and type(env.msg.gyro_rad_s[0]) is float
    # ... and rejects the rest, naming the field
    frames = msgs.encode(
        "/imu",
        msgs.Imu(stamp_ns=1, frame_id="i", gyro_rad_s=(0.0, 0.0, 1.0), accel_m_s2=(0.0, 0.0, 9.8)),
    )
    h = header_of(frames)
    h["f"]["stamp_ns"] = True
    with pytest.raises(MessageError) as exc:
        msgs.decode(with_header(frames, h))
    assert exc.value.field == "stamp_ns"
    h["f"]["stamp_ns"] = 1 << 63
    with pytest.raises(MessageError) as exc:
        msgs.decode(with_header(frames, h))
    assert exc.value.field == "stamp_ns"
