"""Codec: round trips of every message type (hypothesis), zero-copy arrays, the buffers decode takes
and the schema's own checks (rejection: test_msgs_rejection.py; fast paths:
test_msgs_fast_paths.py)."""

from __future__ import annotations

import numpy as np
import pytest
import zmq
from _msgs_strategies import keyframe_msg, messages
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node import msgs


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


def test_keyframe_rgb_and_result_header() -> None:
    kf = keyframe_msg()
    kf.image = np.arange(24, dtype=np.uint8).reshape(4, 6)  # grey
    rgb = kf.rgb()
    assert rgb.shape == (4, 6, 3) and all(np.array_equal(rgb[..., c], kf.image) for c in range(3))
    colour = np.arange(72, dtype=np.uint8).reshape(4, 6, 3)
    kf.image = colour
    assert kf.rgb() is colour  # a colour image is handed out as it is
    masks = msgs.Masks(**kf.result_header(), labels=np.zeros((4, 6), np.int32), backend="graph")
    assert (masks.stamp_ns, masks.frame_id, masks.keyframe_id) == (5, "cam", 1)
    assert msgs.decode(msgs.encode("/seg/masks", masks)).msg == masks


def test_decode_takes_bytes_zmq_frames_and_other_buffers_alike() -> None:
    kf = keyframe_msg(4)
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
