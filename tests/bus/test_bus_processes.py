"""Multi-process transport: broker + publisher + subscriber as separate OS processes."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest
from _reliability_harness import free_tcp_port, start_broker, start_node, stop_process

from mogs_node.bus import BusConfig
from mogs_node.shm import shm_available


@pytest.mark.parametrize("transport", ["tcp", "ipc", "ipc+shm"])
def test_500_large_keyframes_arrive_complete_and_in_order(
    transport: str, tmp_path: Path, ipc_endpoints
) -> None:
    """Over tcp and ipc through the broker, and over ipc with the arrays in shared memory (the
    default there) and only the headers through the broker."""
    if transport == "tcp":
        bus = BusConfig(f"tcp://127.0.0.1:{free_tcp_port()}", f"tcp://127.0.0.1:{free_tcp_port()}")
    elif transport == "ipc":
        bus = BusConfig(*ipc_endpoints, shm_min_bytes=0)
    else:
        if not shm_available():
            pytest.skip("no /dev/shm on this machine")
        bus = BusConfig(*ipc_endpoints)
        assert bus.uses_shm
    broker = start_broker(bus)
    summary = tmp_path / "sub.json"
    n = 500
    try:
        sub = start_node(
            "mogs_node.demo_nodes:Recorder",
            "sub",
            {"topics": ["/frontend/keyframe"], "expect": n, "summary_path": str(summary)},
            bus,
        )
        # 800x640 RGB + 500 features = 1.55 MB per keyframe
        pub = start_node(
            "mogs_node.demo_nodes:SyntheticSource",
            "pub",
            {"n_frames": n, "rate_hz": 1000.0, "keyframes": True, "width": 800, "height": 640},
            bus,
        )
        assert pub.wait(120) == 0
        assert sub.wait(120) == 0
    finally:
        for p in (locals().get("pub"), locals().get("sub"), broker):
            if p is not None:
                stop_process(p, 5)
    data = json.loads(summary.read_text())
    assert data["ids"] == list(range(n))
    st = data["topics"]["/frontend/keyframe"]
    assert st["received"] == n and st["lost"] == 0 and st["malformed"] == 0
    assert st["received_bytes"] > n * 1_500_000
    if transport == "ipc+shm":  # a subscriber that keeps up takes most from shared memory
        assert st["shm_received"] > n // 2 and st["shm_missed"] == 0
    else:
        assert st["shm_received"] == 0


@pytest.mark.parametrize("shared_memory", [False, True])
def test_overwhelmed_reliable_subscriber_reports_exact_gap_count(
    shared_memory: bool, tmp_path: Path, ipc_endpoints
) -> None:
    """Tiny high-water marks everywhere, so that a slow subscriber must lose messages; with the
    arrays in shared memory too (a slot it has not taken sends the next message inline, which
    the high-water mark then drops: lost exactly as without)."""
    if shared_memory and not shm_available():
        pytest.skip("no /dev/shm on this machine")
    bus = BusConfig(*ipc_endpoints, reliable_hwm=4, shm_min_bytes=64 * 1024 if shared_memory else 0)
    broker = start_broker(bus)
    summary = tmp_path / "slow.json"
    n = 300
    try:
        sub = start_node(
            "mogs_node.demo_nodes:Recorder",
            "slow",
            {"topics": ["/frontend/keyframe"], "summary_path": str(summary), "delay_ms": 20.0},
            bus,
        )
        pub = start_node(
            "mogs_node.demo_nodes:SyntheticSource",
            "fast",
            {
                "n_frames": n,
                "rate_hz": 2000.0,
                "keyframes": True,
                "width": 320,
                "height": 240,
                "final_after_s": 3.0,
            },
            bus,
        )
        assert pub.wait(60) == 0
        time.sleep(1.0)  # the final frame reaches the idle subscriber
        stop_process(sub, 5)
        assert sub.returncode == 0
    finally:
        for p in (locals().get("pub"), locals().get("sub"), broker):
            if p is not None:
                stop_process(p, 5)
    data = json.loads(summary.read_text())
    ids = data["ids"]
    st = data["topics"]["/frontend/keyframe"]
    published = n + 1  # n frames and the final one
    assert ids[-1] == n, "the final frame must arrive so that trailing loss is visible"
    assert ids == sorted(ids)
    missing = published - len(ids)
    assert missing > 0, "the subscriber was meant to be overwhelmed"
    # the reported count equals exactly what is missing, and gap events match holes in the ids
    assert st["lost"] == missing
    holes = sum(1 for a, b in zip(ids, ids[1:]) if b != a + 1) + (ids[0] != 0)
    assert st["gaps"] == holes
    assert st["shm_missed"] == 0
    assert (st["shm_received"] > 0) == shared_memory


# ------------------------------------------------------- receive path (in-process broker, fast)


@pytest.fixture
def pub_sub(inproc_bus):
    """A Publisher and a Subscriber on an in-process broker, closed whatever the test does."""
    from mogs_node.bus import Publisher, Subscriber

    bus, ctx = inproc_bus
    sub = Subscriber(bus, context=ctx)
    pub = Publisher(bus, context=ctx)
    yield pub, sub
    pub.close(0)  # open sockets would block the fixture's context termination
    sub.close()


def _imu() -> Any:
    from mogs_node import msgs

    return msgs.Imu(
        stamp_ns=1, frame_id="i", gyro_rad_s=(0.0, 0.0, 1.0), accel_m_s2=(0.0, 0.0, 9.8)
    )


def test_frame_by_frame_receive_keeps_message_boundaries(pub_sub) -> None:
    """recv_frames takes exactly one multipart message, however malformed, never a part of the
    next one; topic and header arrive as bytes, arrays as zero-copy frames."""
    import numpy as np
    import zmq

    from mogs_node import msgs

    pub, sub = pub_sub
    sub.subscribe("/imu")
    sub.subscribe("/frontend/keyframe")
    assert pub.wait_for_subscriber("/frontend/keyframe", 5)
    imu = _imu()
    kf = msgs.Keyframe(
        stamp_ns=2,
        frame_id="c",
        keyframe_id=7,
        image=np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3),
        K=np.eye(3),
        T_world_cam=np.eye(4),
        feature_ids=np.arange(3, dtype=np.int64),
        feature_uv_px=np.zeros((3, 2), np.float32),
        feature_xyz_cam_m=np.ones((3, 3), np.float32),
        feature_weight=np.ones(3, np.float32),
    )
    good = msgs.encode("/imu", imu, seq=0, src=5)
    pub.publish_frames([b"/imu"])  # topic alone
    pub.publish_frames([*good[:2], b"stray", b"frames"])  # more buffers than descriptors
    pub.publish_frames(msgs.encode("/imu", imu, seq=1, src=5))
    assert pub.publish("/frontend/keyframe", kf) == 0
    env = sub.receive(timeout_ms=2000)
    assert env is not None and env.seq == 1 and env.msg == imu
    assert sub.stats["/imu"].malformed == 2 and sub.stats["/imu"].received == 1
    frames = None
    for _ in range(200):
        frames = sub.recv_frames()
        if frames is not None:
            break
        sub.socket.poll(10)
    assert frames is not None and len(frames) == 2 + len(msgs.Keyframe.ARRAYS)
    assert [type(f) for f in frames[:2]] == [bytes, bytes]
    assert all(type(f) is zmq.Frame for f in frames[2:])
    env = sub.decode_frames(frames)
    assert env is not None and env.msg == kf
    sent = msgs.encode("/frontend/keyframe", kf, seq=0, src=pub.src)
    assert pub.published_bytes == sum(len(bytes(f)) for f in sent)
    assert sub.receive(timeout_ms=0) is None  # nothing queued: no wait
    assert sub.receive(timeout_ms=20) is None


def test_subscriber_counts_every_gap_and_reordering_exactly(pub_sub) -> None:
    from mogs_node import msgs

    pub, sub = pub_sub
    sub.subscribe("/imu")
    assert pub.wait_for_subscriber("/imu", 5)
    imu = _imu()
    # session 5 joins at seq 3, loses 5 and 8..9, repeats 6; session 6 starts at 0
    order = [(5, 3), (5, 4), (5, 6), (5, 7), (5, 6), (5, 10), (6, 0), (6, 1)]
    for src, seq in order:
        pub.publish_frames(msgs.encode("/imu", imu, seq=seq, src=src))
    got = [sub.receive(timeout_ms=2000) for _ in order]
    assert [(e.src, e.seq) for e in got] == order
    st = sub.stats["/imu"]
    assert (st.received, st.missed_before_join, st.gaps, st.lost, st.reordered) == (8, 3, 2, 3, 1)


def test_socket_buffer_size_is_configurable_and_checked(inproc_bus) -> None:
    from dataclasses import replace

    from mogs_node.bus import Publisher, Subscriber
    from mogs_node.errors import ConfigError

    bus, ctx = inproc_bus
    d = {**bus.to_dict(), "socket_buffer_bytes": 1 << 20}
    cfg = BusConfig.from_dict(d)
    assert cfg.socket_buffer_bytes == 1 << 20 and BusConfig.from_dict(cfg.to_dict()) == cfg
    for bad in (-1, True, "4M", 1.5):
        with pytest.raises(ConfigError, match="socket_buffer_bytes"):
            BusConfig.from_dict({**d, "socket_buffer_bytes": bad})
    pub, sub = Publisher(cfg, context=ctx), Subscriber(cfg, context=ctx)
    default_pub = Publisher(replace(cfg, socket_buffer_bytes=0), context=ctx)
    try:
        assert pub._sock.sndbuf == 1 << 20 and sub.socket.rcvbuf == 1 << 20
        assert default_pub._sock.sndbuf == -1  # 0 leaves the OS default alone
    finally:
        for s in (pub, default_pub):
            s.close(0)
        sub.close()
