"""Live sources: the IMU text parser (property tests), the camera stamper, and the camera, UDP and
ZeroMQ IMU nodes as real processes (127.0.0.1 and ipc only, bounded loops)."""

from __future__ import annotations

import math
import socket
import time
from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest
import zmq
from _reliability_harness import cli_process, receive_for, receive_until, run_cli
from hypothesis import given
from hypothesis import strategies as st

from bridges.imu_text import (
    ImuSample,
    ImuSampleError,
    ImuSampleParser,
    LineSplitter,
    parse_imu_line,
    parse_imu_map,
)
from bridges.live import CameraStamper, DeviceError, LiveCameraNode, parse_udp_source
from mogs_node import msgs
from mogs_node.bus import BusConfig
from mogs_node.errors import ConfigError

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
t_ns = st.integers(0, (1 << 63) - 1)


def _line(t: int, v: list[float]) -> str:
    return f"{t}," + ",".join(repr(x) for x in v)


# ----------------------------------------------------------------------------- parser


@given(t_ns, st.lists(finite, min_size=6, max_size=6), st.sampled_from(["", " ", "\r"]))
def test_valid_lines_round_trip_exactly(t: int, v: list[float], pad: str) -> None:
    s = parse_imu_line(pad + _line(t, v).replace(",", pad + "," + pad) + pad)
    assert s == ImuSample(t, tuple(v[:3]), tuple(v[3:]))


@given(t_ns, st.lists(finite, min_size=6, max_size=6))
def test_a_parsed_sample_is_the_imu_message_it_publishes(t: int, v: list[float]) -> None:
    m = parse_imu_line(_line(t, v)).message("imu0")
    assert m == msgs.Imu(
        stamp_ns=t, frame_id="imu0", gyro_rad_s=tuple(v[:3]), accel_m_s2=tuple(v[3:])
    )
    m.validate()


@given(st.text(max_size=80))
def test_arbitrary_text_is_parsed_or_rejected_never_crashes(text: str) -> None:
    try:
        s = parse_imu_line(text)
    except ImuSampleError as err:
        assert err.reason in ("fields", "number", "non_finite")
        return
    if s is not None:
        assert all(math.isfinite(x) for x in (*s.gyro_rad_s, *s.accel_m_s2)) and s.t_ns >= 0


@given(st.binary(max_size=60))
def test_arbitrary_bytes_are_parsed_or_rejected(data: bytes) -> None:
    try:
        parse_imu_line(data)
    except ImuSampleError as err:
        assert err.reason in ("encoding", "fields", "number", "non_finite")


@given(
    t_ns,
    st.lists(finite, min_size=6, max_size=6),
    st.integers(0, 5),
    st.sampled_from(["nan", "NaN", "inf", "-inf", "+Infinity", "1e999", "-2e400"]),
)
def test_non_finite_values_are_rejected(t: int, v: list[float], k: int, bad: str) -> None:
    parts = _line(t, v).split(",")
    parts[1 + k] = bad
    with pytest.raises(ImuSampleError) as err:
        parse_imu_line(",".join(parts))
    assert err.value.reason == "non_finite"


@pytest.mark.parametrize(
    ("line", "reason"),
    [
        ("1,2,3,4,5,6", "fields"),
        ("1,2,3,4,5,6,7,8", "fields"),
        ("1;2;3;4;5;6;7", "fields"),
        ("-5,0,0,0,0,0,9.8", "number"),
        ("1e9,0,0,0,0,0,9.8", "number"),
        ("1.0,0,0,0,0,0,9.8", "number"),
        ("10,0x1,0,0,0,0,9.8", "number"),
        ("10,1_0,0,0,0,0,9.8", "number"),
        ("10,,0,0,0,0,9.8", "number"),
        ("99999999999999999999,0,0,0,0,0,9.8", "number"),
        ("10,0,0,0,0,0,nan", "non_finite"),
    ],
)
def test_malformed_lines_name_their_reason(line: str, reason: str) -> None:
    with pytest.raises(ImuSampleError) as err:
        parse_imu_line(line)
    assert err.value.reason == reason


def test_comments_and_blank_lines_are_skipped_not_counted() -> None:
    p = ImuSampleParser()
    assert p.feed_line("# t_ns,gx,gy,gz,ax,ay,az") is None
    assert p.feed_line("   ") is None
    assert p.accepted == 0 and p.rejected_total == 0


@given(st.lists(st.integers(0, 50), max_size=40))
def test_time_must_increase_and_every_rejection_is_counted(times: list[int]) -> None:
    p = ImuSampleParser()
    accepted = [s.t_ns for t in times if (s := p.feed_line(f"{t},0,0,0,0,0,9.81")) is not None]
    expected, last = [], None
    for t in times:
        if last is None or t > last:
            expected.append(t)
            last = t
    assert accepted == expected
    assert p.accepted == len(expected)
    assert p.rejected["not_increasing"] == len(times) - len(expected)


def test_parse_imu_map_is_strict() -> None:
    good = {"t_ns": 5, "gyro": [0.0, 1, 2.5], "accel": (0, 0, 9.81)}
    assert parse_imu_map(good) == ImuSample(5, (0.0, 1.0, 2.5), (0.0, 0.0, 9.81))
    bad = [
        ({"t_ns": 5, "gyro": [0, 0, 0]}, "fields"),
        ({**good, "extra": 1}, "fields"),
        ({**good, "t_ns": 1.5}, "number"),
        ({**good, "t_ns": True}, "number"),
        ({**good, "t_ns": -1}, "number"),
        ({**good, "gyro": [0, 0]}, "fields"),
        ({**good, "gyro": [0, "1", 0]}, "number"),
        ({**good, "accel": [0, float("nan"), 0]}, "non_finite"),
        ([1, 2, 3], "fields"),
    ]
    for obj, reason in bad:
        with pytest.raises(ImuSampleError) as err:
            parse_imu_map(obj)
        assert err.value.reason == reason, obj


@given(
    st.lists(st.binary(min_size=0, max_size=20).filter(lambda b: b"\n" not in b), max_size=10),
    st.lists(st.integers(1, 30), min_size=1, max_size=10),
)
def test_line_splitter_is_independent_of_chunking(lines: list[bytes], cuts: list[int]) -> None:
    stream = b"".join(ln + b"\n" for ln in lines)
    sp, out, pos, i = LineSplitter(), [], 0, 0
    while pos < len(stream):
        n = cuts[i % len(cuts)]
        out += sp.feed(stream[pos : pos + n])
        pos, i = pos + n, i + 1
    assert out == [ln.rstrip(b"\r") for ln in lines]


# ----------------------------------------------------------------------------- camera stamps


def test_camera_stamper_uses_backend_times_then_falls_back_to_host() -> None:
    s = CameraStamper(wall0_ns=1_000_000_000_000, mono0_ns=500)
    assert s.stamp(0.0, mono_ns=10_500) == 1_000_000_010_000  # anchored at the host time
    assert s.stamp(33.5, mono_ns=99_999_999) == 1_000_000_010_000 + 33_500_000
    assert s.use_backend
    assert s.stamp(33.5, mono_ns=70_000_500) == 1_000_070_000_000  # not increasing: host clock
    assert not s.use_backend
    assert s.stamp(100.0, mono_ns=80_000_500) == 1_000_080_000_000  # and it stays there
    h = CameraStamper(wall0_ns=7, mono0_ns=0)
    assert h.stamp(-1.0, mono_ns=3) == 10 and not h.use_backend  # backend gives nothing


def test_missing_camera_is_a_clear_error(ipc_endpoints) -> None:
    with pytest.raises(DeviceError, match="cannot open camera '/dev/video99'"):
        LiveCameraNode("camera", {"device": "/dev/video99"}, BusConfig(*ipc_endpoints))
    r = run_cli(
        "live",
        "camera",
        "/nonexistent/cam.mp4",
        "--sub",
        ipc_endpoints[1],
        "--pub",
        ipc_endpoints[0],
    )
    assert r.returncode == 1
    assert "cannot open camera '/nonexistent/cam.mp4' (no such file)" in r.stderr
    with pytest.raises(ConfigError, match="udp://HOST:PORT"):
        parse_udp_source("udp://127.0.0.1")


# ----------------------------------------------------------------------------- processes


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _final_diag(got: list[msgs.Envelope], node: str) -> msgs.Diagnostics:
    diags = [e.msg for e in got if e.topic == "/diagnostics" and e.msg.node == node]
    assert diags, f"no diagnostics from {node}"
    return diags[-1]


def test_camera_node_streams_a_video_file_with_media_time_stamps(
    broker_bus, bus_subscriber, tmp_path: Path
) -> None:
    video = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    assert w.isOpened()
    for i in range(12):
        w.write(np.full((48, 64, 3), (10 * i, 100, 200), np.uint8))  # BGR
    w.release()
    sub = bus_subscriber
    sub.subscribe("/camera/image")
    proc = cli_process(broker_bus, "live", "camera", str(video), "--wait", "10")
    got: list[msgs.Envelope] = []
    deadline = time.monotonic() + 60
    while len(got) < 12 and time.monotonic() < deadline:
        env = sub.receive(timeout_ms=200)
        if env is not None:
            got.append(env)
    out = proc.communicate(timeout=30)[0].decode()
    assert proc.returncode == 0, out
    assert len(got) == 12
    stamps = np.array([e.msg.stamp_ns for e in got])
    np.testing.assert_array_equal(np.diff(stamps), 100_000_000)  # CAP_PROP_POS_MSEC, 10 fps
    for i, e in enumerate(got):
        assert e.msg.encoding == "rgb8" and e.msg.data.shape == (48, 64, 3)
        mean_rgb = e.msg.data.reshape(-1, 3).mean(0)
        np.testing.assert_allclose(mean_rgb, (200, 100, 10 * i), atol=4)  # MJPG is lossy
    assert "camera" in out and "12 frames (backend stamps)" in out


def test_udp_imu_reader_publishes_good_lines_and_counts_bad_ones(
    broker_bus, bus_subscriber
) -> None:
    port = _free_udp_port()
    sub = bus_subscriber
    sub.subscribe("/imu")
    sub.subscribe("/diagnostics")
    good = [(1000 + 10 * k, [0.01 * k, -0.02, 0.5, 0.1, -0.2, 9.81 + k]) for k in range(20)]
    proc = cli_process(
        broker_bus, "live", "imu-lines", f"udp://127.0.0.1:{port}", "--samples", "20"
    )
    receive_until(sub, lambda e: e.topic == "/diagnostics" and e.msg.node == "imu", 30)
    lines = ["# t_ns,gx,gy,gz,ax,ay,az"]
    for k, (t, v) in enumerate(good):
        lines.append(_line(t, v))
        if k == 3:
            lines += ["1035,0,0,0,0,0,nan", "garbage", "1035,1,2,3", "abc,0,0,0,0,0,9.8"]
        if k == 7:
            lines.append(_line(good[2][0], good[2][1]))  # time going backwards
    payload = "\n".join(lines).encode()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        half = payload.index(b"\n", len(payload) // 2)
        tx.sendto(payload[:half] + b"\n", ("127.0.0.1", port))  # a line never spans datagrams
        tx.sendto(payload[half + 1 :], ("127.0.0.1", port))
    got = receive_until(
        sub,
        lambda e: (
            e.topic == "/diagnostics"
            and e.msg.status
            and e.msg.counters.get("imu_published") == 20
            and e.msg.node == "imu"
        ),
        30,
    )
    out = proc.communicate(timeout=30)[0].decode()
    got += receive_for(sub, 0.3)
    assert proc.returncode == 0, out
    imu = [e.msg for e in got if e.topic == "/imu"]
    assert [(m.stamp_ns, [*m.gyro_rad_s, *m.accel_m_s2]) for m in imu] == good
    d = _final_diag(got, "imu")
    assert d.counters["imu_published"] == 20
    assert d.counters["imu_rejected_non_finite"] == 1
    assert d.counters["imu_rejected_number"] == 1  # "abc" as t_ns
    assert d.counters["imu_rejected_fields"] == 2  # "garbage" and "1035,1,2,3"
    assert d.counters["imu_rejected_not_increasing"] == 1


def test_zmq_imu_input_accepts_msgpack_maps_and_counts_bad_ones(
    broker_bus, bus_subscriber, tmp_path: Path
) -> None:
    endpoint = f"ipc://{tmp_path}/imu-in.ipc"
    sub = bus_subscriber
    sub.subscribe("/imu")
    sub.subscribe("/diagnostics")
    ctx = zmq.Context()
    push = ctx.socket(zmq.PUSH)
    push.linger = 1000
    try:
        proc = cli_process(broker_bus, "live", "imu-zmq", "--endpoint", endpoint, "--samples", "5")
        receive_until(sub, lambda e: e.topic == "/diagnostics" and e.msg.node == "imu", 30)
        push.connect(endpoint)
        push.send(msgpack.packb({"t_ns": 10, "gyro": [0.1, 0.2, 0.3], "accel": [0, 0, 9.81]}))
        push.send(b"\xc1 not msgpack")
        push.send(msgpack.packb({"t_ns": 20, "gyro": [0, 0, 0], "accel": [0, float("inf"), 0]}))
        push.send(msgpack.packb({"t_ns": 5, "gyro": [0, 0, 0], "accel": [0, 0, 9.8]}))
        push.send(
            msgpack.packb(
                [
                    {"t_ns": 30 + k, "gyro": [float(k), 0.0, 0.0], "accel": [0.0, 0.0, 9.8]}
                    for k in range(4)
                ]
            )
        )
        got = receive_until(sub, lambda e: e.topic == "/imu" and e.msg.stamp_ns == 33, 30)
        out = proc.communicate(timeout=30)[0].decode()
        got += receive_for(sub, 0.3)
    finally:
        push.close()
        ctx.term()
    assert proc.returncode == 0, out
    imu = [e.msg for e in got if e.topic == "/imu"]
    assert [m.stamp_ns for m in imu] == [10, 30, 31, 32, 33]
    assert imu[0].gyro_rad_s == (0.1, 0.2, 0.3) and imu[4].gyro_rad_s == (3.0, 0.0, 0.0)
    d = _final_diag(got, "imu")
    assert d.counters["imu_rejected_fields"] == 1  # not msgpack
    assert d.counters["imu_rejected_non_finite"] == 1
    assert d.counters["imu_rejected_not_increasing"] == 1


def test_line_reader_on_a_file_stops_at_its_end(broker_bus, bus_subscriber, tmp_path: Path) -> None:
    """The serial-port path of the line reader (os.read on a non-blocking fd), on a plain file."""
    src = tmp_path / "imu.txt"
    src.write_bytes(
        b"# header\r\n10,0,0,0,0,0,9.8\r\n20,1e-3,0,0,0,0,9.8\r\n15,0,0,0,0,0,9.8\n30,0,0,0,0,0,9.8"
    )
    sub = bus_subscriber
    sub.subscribe("/imu")
    proc = cli_process(broker_bus, "live", "imu-lines", str(src), "--wait", "10")
    got = receive_until(sub, lambda e: e.msg.stamp_ns == 30, 30)
    out = proc.communicate(timeout=30)[0].decode()
    assert proc.returncode == 0, out
    assert [e.msg.stamp_ns for e in got] == [10, 20, 30]  # the last line has no line end
    assert got[1].msg.gyro_rad_s == (1e-3, 0.0, 0.0)
    assert "rejected {'not_increasing': 1}" in out
