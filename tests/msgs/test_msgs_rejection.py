"""Codec: strict rejection of bad input (named fields, inconsistent dimensions, non-finite values,
oversize) and 10,000 fuzzed malformed messages, every one rejected and counted."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _msgs_strategies import header_of, keyframe_msg, with_header

from mogs_node import msgs
from mogs_node.bus import BusConfig, Subscriber
from mogs_node.errors import MessageError


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
    frames = msgs.encode("/frontend/keyframe", keyframe_msg())
    h = header_of(frames)
    mutate(h)
    with pytest.raises(MessageError) as exc:
        msgs.decode(with_header(frames, h))
    assert exc.value.field == field, str(exc.value)


def test_decoder_rejects_inconsistent_dimensions_and_non_finite() -> None:
    kf = keyframe_msg(3)
    frames = msgs.encode("/frontend/keyframe", kf)
    h = header_of(frames)
    # feature_weight claims N=2 while the other arrays have N=3
    names = [d[0] for d in h["a"]]
    i = names.index("feature_weight")
    h["a"][i][2] = [2]
    frames2 = with_header(frames, h)
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
    frames = msgs.encode("/frontend/keyframe", keyframe_msg())
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
        msgs.encode("/frontend/keyframe", keyframe_msg(5)),
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
