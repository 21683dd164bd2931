"""Large arrays through shared memory on an ipc bus: same messages, nothing lost, bad references
counted (mogs_node/shm.py; the broker runs in a thread of the test process here, the
multi-process cases are in test_bus_processes.py)."""

from __future__ import annotations

import os
import threading
import time
from dataclasses import replace
from typing import Any

import msgpack
import numpy as np
import pytest

from mogs_node import msgs, shm
from mogs_node.bus import BusConfig, Publisher, Subscriber, run_broker
from mogs_node.demo_nodes import make_keyframe

TOPIC = "/frontend/keyframe"


@pytest.fixture
def ipc_bus(ipc_endpoints):
    """A broker thread on private ipc endpoints; shared memory for arrays from 64 kB on."""
    bus = BusConfig(*ipc_endpoints, shm_min_bytes=64 * 1024)
    stop, ready = threading.Event(), threading.Event()
    thread = threading.Thread(target=run_broker, args=(bus, stop), kwargs={"ready": ready})
    thread.start()
    assert ready.wait(10)
    yield bus
    stop.set()
    thread.join(10)


def _pair(bus: BusConfig, topic: str = TOPIC) -> tuple[Publisher, Subscriber]:
    sub = Subscriber(bus)
    sub.subscribe(topic)
    pub = Publisher(bus)
    assert pub.wait_for_subscriber(topic, 5)
    return pub, sub


def _take(sub: Subscriber, n: int, timeout_s: float = 10.0) -> list[msgs.Envelope]:
    out: list[msgs.Envelope] = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        env = sub.receive(timeout_ms=100)
        if env is not None:
            out.append(env)
    return out


def _round_trip(pub: Publisher, sub: Subscriber, sent: list[msgs.Keyframe]) -> Any:
    """Publish all of ``sent`` before reading any; they must arrive equal and in order."""
    for kf in sent:
        pub.publish(TOPIC, kf)
    got = _take(sub, len(sent))
    assert [e.msg for e in got] == sent
    assert [e.seq for e in got] == list(range(len(sent)))
    return sub.stats[TOPIC]


def _keyframes(n: int) -> list[msgs.Keyframe]:
    return [make_keyframe(k, width=320, height=240) for k in range(n)]  # ~0.25 MB each


def test_shared_memory_is_on_for_ipc_only_and_never_with_curve(ipc_endpoints) -> None:
    from mogs_node.bus import CurveConfig

    assert BusConfig(*ipc_endpoints).uses_shm == shm.shm_available()
    assert not BusConfig(*ipc_endpoints, shm_min_bytes=0).uses_shm
    assert not BusConfig("tcp://127.0.0.1:1", "tcp://127.0.0.1:2").uses_shm
    assert not BusConfig("inproc://a", "inproc://b").uses_shm
    curve = CurveConfig("k", "s")
    assert not BusConfig(*ipc_endpoints, curve=curve).uses_shm
    d = BusConfig(*ipc_endpoints, shm_min_bytes=5, shm_ring_bytes=7).to_dict()
    assert BusConfig.from_dict(d) == BusConfig(*ipc_endpoints, shm_min_bytes=5, shm_ring_bytes=7)


pytestmark = pytest.mark.skipif(not shm.shm_available(), reason="no /dev/shm on this machine")


def test_keyframes_arrive_equal_through_shared_memory(ipc_bus) -> None:
    pub, sub = _pair(ipc_bus)
    try:
        sent = _keyframes(6)
        st = _round_trip(pub, sub, sent)
        assert (st.shm_received, st.lost, st.malformed, pub.shm_published) == (6, 0, 0, 6)
        # the accounting counts the message's bytes as if inline
        assert st.received_bytes == pub.published_bytes
    finally:
        pub.close(0)
        sub.close()


def test_subscriber_far_behind_loses_nothing_the_rest_goes_inline(ipc_bus) -> None:
    """A ring of 4 slots and 40 messages published before one is read: the publisher may not
    reuse a slot the subscriber has not taken, so it sends those inline; all 40 arrive."""
    bus = replace(ipc_bus, shm_ring_bytes=1)  # the fewest slots: 4
    pub, sub = _pair(bus)
    try:
        sent = _keyframes(40)
        st = _round_trip(pub, sub, sent)
        assert (st.lost, st.shm_missed, st.malformed) == (0, 0, 0)
        assert st.shm_received == pub.shm_published == 4
        assert pub._rings[TOPIC].busy == 36
        # taken now: the ring is free again
        pub.publish(TOPIC, sent[0])
        assert _take(sub, 1)[0].msg == sent[0] and pub.shm_published == 5
    finally:
        pub.close(0)
        sub.close()


def test_payload_gone_before_read_is_counted_then_shows_as_lost(ipc_bus) -> None:
    pub, sub = _pair(ipc_bus)
    late = Publisher(ipc_bus)
    try:
        kf = _keyframes(1)[0]
        pub.publish(TOPIC, kf)
        pub.publish(TOPIC, kf)
        time.sleep(0.3)  # both references are queued at the subscriber
        pub.close(0)  # the ring's files go before the subscriber has mapped them
        late.wait_for_subscriber(TOPIC, 5)
        late.publish(TOPIC, kf)  # another session: arrives
        got = _take(sub, 1)
        assert len(got) == 1 and got[0].src == late.src
        st = sub.stats[TOPIC]
        assert st.shm_missed == 2 and "cannot be opened" in sub.last_error
        # the lost pair is a gap of the closed session: it shows when a later message of it
        # arrives; until then it is in shm_missed (and the node's diagnostics) only
        assert st.missed_before_join == 0 and st.lost == 0
    finally:
        late.close(0)
        sub.close()


def test_gap_after_a_missed_payload_is_counted_exactly(ipc_bus) -> None:
    pub, sub = _pair(ipc_bus)
    try:
        sent = _keyframes(4)
        for kf in sent[:3]:
            pub.publish(TOPIC, kf)
        assert _take(sub, 1)[0].seq == 0  # message 0 maps the whole ring
        slot = pub._rings[TOPIC]._slots[1]
        slot.header[1] = 12345  # message 1's slot stamped as if written again since
        pub.publish(TOPIC, sent[3])
        got = _take(sub, 2)
        assert [e.seq for e in got] == [2, 3]
        assert [e.msg for e in got] == sent[2:]
        st = sub.stats[TOPIC]
        assert (st.shm_missed, st.gaps, st.lost) == (1, 1, 1)
        assert slot.name in sub.last_error and "overwritten" in sub.last_error
    finally:
        pub.close(0)
        sub.close()


def _bad_references(good_header: bytes) -> list[tuple[str, bytes]]:
    fields = msgpack.unpackb(good_header)
    name, ticket, sizes = fields["m"]

    def with_ref(ref: Any) -> bytes:
        f = dict(fields)
        f["m"] = ref
        return msgpack.packb(f)

    not_last = {"m": fields["m"], **{k: v for k, v in fields.items() if k != "m"}}
    return [
        ("garbage", b"\x87" + os.urandom(40)),
        ("truncated", good_header[:-3]),
        ("no reference", msgpack.packb({**{k: v for k, v in fields.items() if k != "m"}, "x": 1})),
        ("reference not a list", with_ref("nope")),
        ("name not a str", with_ref([5, ticket, sizes])),
        ("negative size", with_ref([name, ticket, [-1]])),
        ("sizes over the limit", with_ref([name, ticket, [1 << 40]])),
        ("not a slot name", with_ref(["../../etc/passwd", ticket, sizes])),
        ("wrong ticket", with_ref([name, ticket + 1000, sizes])),
        ("reference not last", msgpack.packb(not_last)),
    ]


def test_bad_shared_memory_references_are_counted_never_raised(ipc_bus) -> None:
    import zmq

    pub, sub = _pair(ipc_bus)
    raw = Publisher(replace(ipc_bus, shm_min_bytes=0))  # sends frames as they are
    tap = zmq.Context.instance().socket(zmq.SUB)  # sees a genuine reference as it travels
    tap.connect(ipc_bus.sub_endpoint)
    tap.setsockopt(zmq.SUBSCRIBE, TOPIC.encode())
    try:
        time.sleep(0.3)
        kf = _keyframes(1)[0]
        pub.publish(TOPIC, kf)
        assert _take(sub, 1)[0].msg == kf
        assert tap.poll(5000)
        topic, good_header = tap.recv_multipart()
        assert good_header[:1] == b"\x87"
        assert raw.wait_for_subscriber(TOPIC, 5)
        cases = _bad_references(good_header)
        for _, header in cases:
            raw.publish_frames([topic, header])
        pub.publish(TOPIC, kf)  # a good one (two publishers: in any order with the bad ones)
        st = sub.stats[TOPIC]
        got = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and (
            not got or st.malformed + st.shm_missed < len(cases)
        ):
            env = sub.receive(timeout_ms=100)
            if env is not None:
                got.append(env)
        assert [e.seq for e in got] == [1]
        assert st.malformed == len(cases) - 2
        assert st.shm_missed == 2  # the name that is no slot's, and the wrong ticket
        assert st.lost == 0
    finally:
        tap.close(0)
        raw.close(0)
        pub.close(0)
        sub.close()


def test_replayed_frames_go_through_shared_memory_and_arrive_byte_for_byte(ipc_bus) -> None:
    pub, sub = _pair(ipc_bus)
    try:
        kf = _keyframes(1)[0]
        frames = msgs.encode(TOPIC, kf, seq=41, src=99)  # as recorded from another session
        pub.publish_frames([bytes(f) for f in frames])
        got = sub.recv_frames()
        deadline = time.monotonic() + 5
        while got is None and time.monotonic() < deadline:
            sub.socket.poll(100)
            got = sub.recv_frames()
        assert got is not None
        assert [bytes(memoryview(getattr(f, "buffer", f))) for f in got] == [
            bytes(f) for f in frames
        ]
        assert pub.shm_published == 1 and sub.stats[TOPIC].shm_received == 1
    finally:
        pub.close(0)
        sub.close()


def test_small_arrays_and_array_less_messages_stay_inline(ipc_bus) -> None:
    pub, sub = _pair(ipc_bus, "/imu")
    try:
        pub.publish(
            "/imu",
            msgs.Imu(stamp_ns=1, frame_id="i", gyro_rad_s=(0.0, 0.0, 1.0), accel_m_s2=(0, 0, 9.8)),
        )
        assert len(_take(sub, 1)) == 1
        img = msgs.Image(stamp_ns=1, frame_id="c", encoding="mono8", data=np.zeros((8, 8), "u1"))
        sub.subscribe("/camera/image")
        time.sleep(0.2)
        pub.publish("/camera/image", img)
        assert _take(sub, 1)[0].msg == img
        assert pub.shm_published == 0
    finally:
        pub.close(0)
        sub.close()


def test_a_launch_file_turns_shared_memory_off_keeping_the_default_endpoints(tmp_path) -> None:
    from mogs_node.launch import load_launch_file

    path = tmp_path / "x.yaml"
    path.write_text(
        "name: x\nbus: {shm_min_bytes: 0}\n"
        "nodes: [{name: a, class: 'mogs_node.demo_nodes:SyntheticSource'}]\n"
    )
    bus = load_launch_file(path).bus
    assert bus.pub_endpoint.startswith("ipc://") and not bus.uses_shm
    path.write_text(path.read_text().replace("shm_min_bytes: 0", "shm_ring_bytes: 1048576"))
    bus = load_launch_file(path).bus
    assert bus.shm_ring_bytes == 1 << 20 and bus.uses_shm
