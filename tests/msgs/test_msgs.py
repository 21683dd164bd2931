"""Codec: round trips of every message type (hypothesis) and strict rejection of bad input."""

from __future__ import annotations

import dataclasses

import msgpack
import msgspec
import numpy as np
import pytest
import zmq
from hypothesis import event, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from mogs_node import msgs
from mogs_node.bus import BusConfig, Subscriber
from mogs_node.errors import MessageError
from mogs_node.msgs import codec as msgs_codec

INT64 = st.integers(min_value=-(1 << 63), max_value=(1 << 63) - 1)
FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64)
TEXT = st.text(max_size=40)


def _array(spec: msgs.ArraySpec, dims: dict[str, int], pattern: tuple) -> st.SearchStrategy:
    shape = tuple(p if isinstance(p, int) else dims[p] for p in pattern)
    return st.sampled_from(spec.dtypes).flatmap(
        lambda dt: hnp.arrays(
            np.dtype(dt),
            shape,
            elements=(
                {"allow_nan": False, "allow_infinity": False}
                if spec.finite and np.dtype(dt).kind == "f"
                else None
            ),
        )
    )


def _scalar(kind: str) -> st.SearchStrategy:
    return {
        "int": INT64,
        "float": FINITE,
        "float_or_nan": st.one_of(FINITE, st.just(float("nan"))),
        "str": TEXT,
        "bool": st.booleans(),
        "vec3": st.tuples(FINITE, FINITE, FINITE),
        "dict_num": st.dictionaries(
            TEXT, st.one_of(st.integers(-(2**31), 2**31), FINITE), max_size=5
        ),
        "dict_any": st.dictionaries(
            TEXT,
            st.one_of(
                st.integers(-1000, 1000),
                FINITE,
                TEXT,
                st.dictionaries(TEXT, st.integers(0, 10**9), max_size=3),
            ),
            max_size=4,
        ),
    }[kind]


@st.composite
def messages(draw: st.DrawFn, cls: type[msgs.Message]) -> msgs.Message:
    dims = {s: draw(st.integers(0, 6)) for s in ("N", "M", "D")}
    dims["H"] = draw(st.integers(1, 8))
    dims["W"] = draw(st.integers(1, 8))
    values = {name: draw(_scalar(kind)) for name, kind in cls.SCALARS.items()}
    for name, spec in cls.ARRAYS.items():
        if spec.optional and draw(st.booleans()):
            values[name] = None
            continue
        pattern = draw(st.sampled_from(spec.shapes))
        values[name] = draw(_array(spec, dims, pattern))
    if cls is msgs.Image:
        values["encoding"] = (
            "mono8" if values["data"].ndim == 2 else draw(st.sampled_from(["rgb8", "bgr8"]))
        )
    if cls is msgs.DepthMap:
        values["kind"] = draw(st.sampled_from(msgs.DepthMap.KINDS))
    if cls is msgs.CameraInfo:  # a valid calibration: its fields are checked against each other
        model = draw(st.sampled_from(sorted(msgs.CameraInfo.MODELS)))
        n = draw(st.sampled_from(msgs.CameraInfo.MODELS[model]))
        fx, fy = draw(st.floats(1.0, 5e3)), draw(st.floats(1.0, 5e3))
        values.update(
            distortion_model=model,
            distortion_coeffs=draw(hnp.arrays(np.float64, n, elements=st.floats(-1.0, 1.0))),
            K=np.array([[fx, 0.0, 10.0], [0.0, fy, 5.0], [0.0, 0.0, 1.0]]),
            width=draw(st.integers(1, 4096)),
            height=draw(st.integers(1, 4096)),
            camera_height_m=draw(st.one_of(st.floats(0.0, 10.0), st.just(float("nan")))),
        )
    return cls(**values)


@pytest.mark.parametrize("cls", list(msgs.MESSAGE_TYPES.values()), ids=list(msgs.MESSAGE_TYPES))
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_round_trip_every_type(cls: type[msgs.Message], data: st.DataObject) -> None:
    msg = data.draw(messages(cls))
    seq = data.draw(st.integers(0, 2**62))
    frames = msgs.encode("/t/x", msg, seq=seq, src=7)
    env = msgs.decode([bytes(f) for f in frames])
    assert env.topic == "/t/x" and env.seq == seq and env.src == 7
    assert type(env.msg) is cls
    assert env.msg == msg
    for name in cls.ARRAYS:
        a, b = getattr(msg, name), getattr(env.msg, name)
        if a is not None:
            assert b.dtype == a.dtype and b.shape == a.shape


def test_arrays_are_zero_copy_views_of_the_frames() -> None:
    img = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    frames = msgs.encode(
        "/camera/image", msgs.Image(stamp_ns=1, frame_id="c", encoding="rgb8", data=img)
    )
    # the encoder hands out a view of the array itself, not a copy
    assert np.shares_memory(np.frombuffer(frames[2], np.uint8), img)
    buf = bytearray(frames[2])
    env = msgs.decode([frames[0], frames[1], buf])
    assert np.shares_memory(env.msg.data, np.frombuffer(buf, np.uint8))


def _kf(n: int = 3) -> msgs.Keyframe:
    return msgs.Keyframe(
        stamp_ns=5,
        frame_id="cam",
        keyframe_id=1,
        image=np.zeros((4, 6, 3), np.uint8),
        K=np.eye(3),
        T_world_cam=np.eye(4),
        feature_ids=np.arange(n, dtype=np.int64),
        feature_uv_px=np.zeros((n, 2), np.float32),
        feature_xyz_cam_m=np.ones((n, 3), np.float32),
        feature_weight=np.ones(n, np.float32),
    )


def test_keyframe_rgb_and_result_header() -> None:
    kf = _kf()
    kf.image = np.arange(24, dtype=np.uint8).reshape(4, 6)  # grey
    rgb = kf.rgb()
    assert rgb.shape == (4, 6, 3) and all(np.array_equal(rgb[..., c], kf.image) for c in range(3))
    colour = np.arange(72, dtype=np.uint8).reshape(4, 6, 3)
    kf.image = colour
    assert kf.rgb() is colour  # a colour image is handed out as it is
    masks = msgs.Masks(**kf.result_header(), labels=np.zeros((4, 6), np.int32), backend="graph")
    assert (masks.stamp_ns, masks.frame_id, masks.keyframe_id) == (5, "cam", 1)
    assert msgs.decode(msgs.encode("/seg/masks", masks)).msg == masks


def _header(frames: list) -> dict:
    return msgpack.unpackb(bytes(frames[1]), raw=False)


def _with_header(frames: list, header: dict) -> list:
    return [frames[0], msgpack.packb(header, use_bin_type=True), *frames[2:]]


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda h: h.update(t="Bogus"), "t"),
        (lambda h: h.update(v=2), "v"),
        (lambda h: h["f"].pop("keyframe_id"), "keyframe_id"),
        (lambda h: h["f"].update(extra=1), "extra"),
        (lambda h: h["f"].update(keyframe_id="3"), "keyframe_id"),
        (lambda h: h["f"].update(stamp_ns=1.5), "stamp_ns"),
        (lambda h: h["a"][0].__setitem__(1, "|O"), "image"),
        (lambda h: h["a"][0].__setitem__(1, "<f4"), "image"),
        (lambda h: h["a"][0].__setitem__(2, [4, 6, 4]), "image"),
        (lambda h: h["a"][0].__setitem__(2, [2, 6, 3]), "image"),
        (lambda h: h["a"][3].__setitem__(0, "unknown"), "unknown"),
        (lambda h: h.pop("seq"), "header"),
    ],
)
def test_decoder_names_the_bad_field(mutate, field: str) -> None:
    frames = msgs.encode("/frontend/keyframe", _kf())
    h = _header(frames)
    mutate(h)
    with pytest.raises(MessageError) as exc:
        msgs.decode(_with_header(frames, h))
    assert exc.value.field == field, str(exc.value)


def test_decoder_rejects_inconsistent_dimensions_and_non_finite() -> None:
    kf = _kf(3)
    frames = msgs.encode("/frontend/keyframe", kf)
    h = _header(frames)
    # feature_weight claims N=2 while the other arrays have N=3
    names = [d[0] for d in h["a"]]
    i = names.index("feature_weight")
    h["a"][i][2] = [2]
    frames2 = _with_header(frames, h)
    frames2[2 + i] = np.ones(2, np.float32).tobytes()
    with pytest.raises(MessageError, match="N=2") as exc:
        msgs.decode(frames2)
    assert exc.value.field == "feature_weight"
    bad = dataclasses.replace(kf, feature_uv_px=np.full((3, 2), np.nan, np.float32))
    with pytest.raises(MessageError) as exc:
        msgs.encode("/frontend/keyframe", bad)
    assert exc.value.field == "feature_uv_px"
    good = msgs.encode("/frontend/keyframe", kf)
    j = names.index("feature_uv_px")
    good[2 + j] = np.full((3, 2), np.inf, np.float32).tobytes()
    with pytest.raises(MessageError) as exc:
        msgs.decode(good)
    assert exc.value.field == "feature_uv_px"


def test_decoder_rejects_oversized_messages() -> None:
    frames = msgs.encode("/frontend/keyframe", _kf())
    total = sum(len(bytes(f)) for f in frames)
    msgs.decode(frames, max_bytes=total)
    with pytest.raises(MessageError) as exc:
        msgs.decode(frames, max_bytes=total - 1)
    assert exc.value.field == "size"


def test_encoder_refuses_what_the_decoder_would_reject() -> None:
    with pytest.raises(MessageError) as exc:
        msgs.encode(
            "/imu",
            msgs.Imu(
                stamp_ns=1,
                frame_id="i",
                gyro_rad_s=(0.0, float("nan"), 0.0),
                accel_m_s2=(0.0, 0.0, 9.8),
            ),
        )
    assert exc.value.field == "gyro_rad_s[1]"
    with pytest.raises(MessageError) as exc:
        msgs.encode(
            "/camera/image",
            msgs.Image(stamp_ns=1, frame_id="c", encoding="rgb8", data=np.zeros((2, 2), np.uint8)),
        )
    assert exc.value.field == "data"


def _corrupt(rng: np.random.Generator, frames: list[bytes]) -> list[bytes]:
    """One malformed variant of a valid message (the property: every variant must be rejected)."""
    f = [bytes(x) for x in frames]
    kind = rng.integers(0, 9)
    if len(f) == 2 and kind in (1, 6):  # no array buffer to damage: damage the header instead
        kind = 0
    if kind == 0:  # truncate the header
        f[1] = f[1][: rng.integers(0, len(f[1]))]
    elif kind == 1:  # truncate an array buffer
        i = rng.integers(2, len(f))
        f[i] = f[i][: max(0, len(f[i]) - 1 - rng.integers(0, len(f[i]) + 1))]
    elif kind == 2:  # drop a frame
        del f[rng.integers(1, len(f))]
    elif kind == 3:  # an extra frame
        f.insert(rng.integers(2, len(f) + 1), rng.bytes(rng.integers(0, 64)))
    elif kind == 4:  # random header bytes
        f[1] = rng.bytes(rng.integers(0, 200))
    elif kind == 5:  # flip bytes in the header (re-checked below against accidental validity)
        h = bytearray(f[1])
        for _ in range(rng.integers(1, 4)):
            h[rng.integers(0, len(h))] ^= 1 << rng.integers(0, 8)
        f[1] = bytes(h)
    elif kind == 6:  # a valid header with a wrong-size array
        i = rng.integers(2, len(f))
        f[i] = f[i] + rng.bytes(rng.integers(1, 9))
    elif kind == 7:  # garbage topic
        f[0] = rng.bytes(rng.integers(0, 8))
    else:  # only random frames
        f = [rng.bytes(rng.integers(0, 40)) for _ in range(rng.integers(0, 5))]
    return f


def test_fuzz_10000_malformed_messages_are_all_rejected() -> None:
    rng = np.random.default_rng(1234)
    sources = [
        msgs.encode("/frontend/keyframe", _kf(5)),
        msgs.encode(
            "/imu",
            msgs.Imu(stamp_ns=1, frame_id="i", gyro_rad_s=(0.1, 0.2, 0.3), accel_m_s2=(0, 0, 9.8)),
        ),
        msgs.encode(
            "/prior/depth",
            msgs.DepthMap(
                stamp_ns=1,
                frame_id="c",
                keyframe_id=2,
                kind="metric",
                depth=np.ones((3, 4), np.float32),
                confidence=np.zeros((3, 4), np.float32),
                source="test",
                object_labels=np.zeros((3, 4), np.int32),
                object_model=np.array([1], np.int8),
            ),
        ),
    ]
    sub = Subscriber(BusConfig("inproc://unused-pub", "inproc://unused-sub"))
    subscribed = ("/frontend/keyframe", "/imu", "/prior/depth")
    for t in subscribed:
        sub.subscribe(t)
    rejected = accidentally_valid = 0
    n = 10_000
    for k in range(n):
        good = sources[k % len(sources)]
        bad = _corrupt(rng, good)
        try:
            env0 = msgs.decode(bad)
        except MessageError:
            rejected += 1
            is_bad = True
        else:
            # a well-formed message on a topic nobody subscribed to is refused by the subscriber
            is_bad = env0.topic not in subscribed
            # a bit flip can land on a byte whose change is still a well-formed message
            # (e.g. a digit of a time stamp): such a message is valid, not malformed
            accidentally_valid += 1
        before = sum(s.malformed for s in sub.stats.values()) + sub.malformed
        env = sub.decode_frames(bad)  # the subscriber path never raises
        after = sum(s.malformed for s in sub.stats.values()) + sub.malformed
        assert (env is None) == is_bad
        assert after - before == int(is_bad)  # every rejection is counted, once
    sub.close()
    assert rejected + accidentally_valid == n
    assert accidentally_valid < n * 0.02


# ------------------------------------------------------------------- fast paths vs the reference

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
            st.one_of(_scalar(kind), EDGE_VALUES) if data.draw(st.booleans()) else _scalar(kind)
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
        name: data.draw(st.one_of(_scalar(kind), EDGE_VALUES) if edge else _scalar(kind))
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
    h = _header(frames)
    h["f"]["stamp_ns"] = True
    with pytest.raises(MessageError) as exc:
        msgs.decode(_with_header(frames, h))
    assert exc.value.field == "stamp_ns"
    h["f"]["stamp_ns"] = 1 << 63
    with pytest.raises(MessageError) as exc:
        msgs.decode(_with_header(frames, h))
    assert exc.value.field == "stamp_ns"


def test_decode_takes_bytes_zmq_frames_and_other_buffers_alike() -> None:
    kf = _kf(4)
    frames = msgs.encode("/frontend/keyframe", kf, seq=9, src=3)
    as_bytes = [bytes(f) for f in frames]
    as_zmq = [zmq.Frame(b) for b in as_bytes]
    # what Subscriber.recv_frames hands over: topic and header copied, arrays zero-copy frames
    mixed = as_bytes[:2] + as_zmq[2:]
    # a 2-D buffer of the image bytes: read as its flat bytes
    shaped = [*as_bytes[:2], memoryview(np.frombuffer(as_bytes[2], np.uint8).reshape(4, -1))]
    shaped += as_bytes[3:]
    for variant in (as_bytes, as_zmq, mixed, shaped, [bytearray(b) for b in as_bytes]):
        env = msgs.decode(variant)
        assert env.msg == kf and (env.topic, env.seq, env.src) == ("/frontend/keyframe", 9, 3)
        assert env.nbytes == sum(len(b) for b in as_bytes)
    env = msgs.decode(mixed)
    assert np.shares_memory(env.msg.image, np.frombuffer(as_zmq[2].buffer, np.uint8))


def test_camera_info_round_trip_and_malformed():
    from mogs_node.errors import MessageError as _Err

    K = np.array([[400.0, 0.0, 320.0], [0.0, 401.0, 240.0], [0.0, 0.0, 1.0]])
    info = msgs.CameraInfo(
        stamp_ns=5,
        frame_id="cam0",
        width=640,
        height=480,
        K=K,
        distortion_model="radtan",
        distortion_coeffs=np.array([0.1, -0.05, 0.001, 0.002]),
        T_imu_cam=np.eye(4),
        camera_height_m=float("nan"),
        imu_noise={"gyro_noise_rad_s_rthz": 1.7e-4},
        source="camchain.yaml",
    )
    back = msgs.decode(msgs.encode("/camera/info", info)).msg
    assert back == info and np.isnan(back.camera_height_m)
    no_T = msgs.decode(
        msgs.encode("/camera/info", msgs.CameraInfo(**{**info.__dict__, "T_imu_cam": None}))
    )
    assert no_T.msg.T_imu_cam is None
    for over, field in (
        ({"distortion_model": "fisheye9"}, "distortion_model"),
        ({"distortion_coeffs": np.zeros(3)}, "distortion_coeffs"),
        ({"K": np.diag([0.0, 1.0, 1.0])}, "K"),
        ({"width": 0}, "width"),
        ({"camera_height_m": -1.0}, "camera_height_m"),
        ({"T_imu_cam": np.full((4, 4), np.nan)}, "T_imu_cam"),
    ):
        bad = msgs.CameraInfo(**{**info.__dict__, **over})
        with pytest.raises(_Err, match=field):
            bad.validate()


def test_scalar_kinds_come_from_the_field_annotations():
    """SCALARS is derived from the fields, header first, in field order; FloatOrNaN may be NaN."""
    assert list(msgs.Odometry.SCALARS.items()) == [
        ("stamp_ns", "int"),
        ("frame_id", "str"),
        ("frame_index", "int"),
        ("velocity_world_m_s", "vec3"),
        ("status", "str"),
    ]
    assert msgs.MapStats.SCALARS["loss"] == "float_or_nan"
    assert msgs.Diagnostics.SCALARS["uptime_s"] == "float"
    assert msgs.Diagnostics.SCALARS["topics"] == "dict_any"
    assert msgs.CameraInfo.SCALARS["imu_noise"] == "dict_num"
    assert "K" not in msgs.CameraInfo.SCALARS


def test_schema_mistakes_fail_when_the_class_is_defined():
    from dataclasses import dataclass
    from typing import ClassVar

    from mogs_node.msgs.fields import ArraySpec
    from mogs_node.msgs.schema import Message

    with pytest.raises(TypeError, match="no wire kind"):

        @dataclass(eq=False)
        class _Bad(Message):
            TYPE: ClassVar[str] = "Bad"
            when: list[int]

    with pytest.raises(TypeError, match="array fields"):

        @dataclass(eq=False)
        class _Unspecified(Message):
            TYPE: ClassVar[str] = "Unspecified"
            ARRAYS: ClassVar[dict[str, ArraySpec]] = {"a": ArraySpec(("<f4",), (("N",),))}
            b: np.ndarray
