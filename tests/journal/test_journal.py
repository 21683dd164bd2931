"""Journal: crash-safe store, request protocol, and a node catching up from it (in one process)."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mogs_node import msgs
from mogs_node.bus import Publisher, Subscriber
from mogs_node.errors import BusError, ConfigError
from mogs_node.journal.node import JournalNode
from mogs_node.journal.protocol import JournalClient, handle_request, journal_endpoint
from mogs_node.journal.store import MAGIC, JournalStore, encode_record
from mogs_node.node import Node, message_key


def _frames(i: int, topic: str = "/t") -> list[bytes]:
    return [topic.encode(), f"header{i}".encode(), bytes([i % 256]) * (i * 7 % 50)]


def test_store_round_trip_and_reopen(tmp_path: Path) -> None:
    path = tmp_path / "j.log"
    s = JournalStore(path)
    for i in range(10):
        assert s.append(_frames(i, "/a" if i % 3 else "/b"), key=100 + i)
    assert len(s) == 10
    assert s.keys("/b") == [100, 103, 106, 109]
    assert s.read(4) == _frames(4, "/a")
    s.close()
    r = JournalStore(path, fresh=False)
    assert len(r) == 10 and r.torn_bytes == 0
    assert [r.read(i) for i in range(10)] == [
        s_ for s_ in (_frames(i, "/a" if i % 3 else "/b") for i in range(10))
    ]
    batch, nxt = r.batch(["/b"], 0, max_records=3)
    assert batch == [_frames(0, "/b"), _frames(3, "/b"), _frames(6, "/b")] and nxt == 7
    batch, nxt = r.batch(["/b"], nxt)
    assert batch == [_frames(9, "/b")] and nxt == 10
    assert r.batch(["/b"], nxt) == ([], 10)
    r.close()
    fresh = JournalStore(path, fresh=True)  # a new run starts empty
    assert len(fresh) == 0 and path.stat().st_size == len(MAGIC)
    fresh.close()


def test_torn_last_record_is_ignored_and_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "j.log"
    s = JournalStore(path)
    for i in range(5):
        s.append(_frames(i), key=i)
    full = path.stat().st_size
    s.close()
    with open(path, "r+b") as f:  # the writer died inside the last record
        f.truncate(full - 3)
    r = JournalStore(path, fresh=False)
    assert len(r) == 4 and r.torn_bytes > 0
    assert r.append(_frames(9), key=9)
    r.close()
    again = JournalStore(path, fresh=False)
    assert [again.read(i) for i in range(5)] == [*(_frames(i) for i in range(4)), _frames(9)]
    assert again.torn_bytes == 0
    again.close()


def test_corrupt_record_ends_the_intact_part(tmp_path: Path) -> None:
    path = tmp_path / "j.log"
    s = JournalStore(path)
    for i in range(6):
        s.append(_frames(i + 10), key=i)
    third = s.entries[2].offset
    s.close()
    data = bytearray(path.read_bytes())
    data[third + 12] ^= 0xFF  # flip a bit inside record 2's payload: checksum mismatch
    path.write_bytes(bytes(data))
    r = JournalStore(path, fresh=False)
    assert len(r) == 2
    r.close()


def test_size_bound_and_bad_files(tmp_path: Path) -> None:
    s = JournalStore(
        tmp_path / "j.log", max_bytes=len(MAGIC) + 2 * len(encode_record(_frames(5), 0))
    )
    assert s.append(_frames(5), 0) and s.append(_frames(5), 1)
    assert not s.append(_frames(5), 2)
    assert s.refused == 1 and len(s) == 2
    s.close()
    (tmp_path / "x.log").write_bytes(b"not a journal at all")
    with pytest.raises(BusError, match="not a MOGS journal"):
        JournalStore(tmp_path / "x.log", fresh=False)
    with pytest.raises(ConfigError, match="max_bytes"):
        JournalStore(tmp_path / "y.log", max_bytes=3)
    with pytest.raises(ConfigError, match="frames"):
        encode_record([], 0)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.lists(st.lists(st.binary(max_size=40), min_size=1, max_size=4), min_size=1, max_size=8),
    st.integers(0, 10_000),
)
def test_any_truncation_keeps_an_intact_prefix(tmp_path: Path, records, cut) -> None:
    path = tmp_path / f"h{os.getpid()}-{time.monotonic_ns()}.log"
    s = JournalStore(path)
    for i, frames in enumerate(records):
        s.append([b"/t", *frames], key=i)
    size = path.stat().st_size
    s.close()
    with open(path, "r+b") as f:
        f.truncate(len(MAGIC) + cut % (size - len(MAGIC) + 1))
    r = JournalStore(path, fresh=False)
    n = len(r)
    assert [r.read(i) for i in range(n)] == [[b"/t", *f] for f in records[:n]]
    assert (n == len(records)) == (path.stat().st_size == size)
    r.close()
    path.unlink()


@settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.one_of(
        st.binary(max_size=200),
        st.builds(
            lambda d: msgpack.packb(d),
            st.dictionaries(
                st.sampled_from(["op", "topics", "start", "max_records", "max_bytes", "x"]),
                st.one_of(
                    st.integers(-5, 5),
                    st.text(max_size=5),
                    st.lists(st.text(max_size=3)),
                    st.none(),
                    st.booleans(),
                ),
            ),
        ),
    )
)
def test_bad_requests_get_an_error_reply(tmp_path: Path, request_bytes: bytes) -> None:
    s = JournalStore(tmp_path / f"r{time.monotonic_ns()}.log")
    s.append(_frames(1), key=1)
    reply, ok = handle_request(s, request_bytes)
    meta = msgpack.unpackb(reply[0], raw=False)
    assert ok == ("error" not in meta)
    s.close()


def test_requests(tmp_path: Path) -> None:
    s = JournalStore(tmp_path / "j.log")
    for i in range(4):
        s.append(_frames(i, "/a"), key=10 * i)
    reply, ok = handle_request(s, msgpack.packb({"op": "keys", "topics": ["/a", "/z"]}))
    assert ok and msgpack.unpackb(reply[0]) == {"keys": {"/a": [0, 10, 20, 30], "/z": []}, "n": 4}
    reply, ok = handle_request(
        s, msgpack.packb({"op": "read", "topics": ["/a"], "start": 1, "max_records": 2})
    )
    assert ok and msgpack.unpackb(reply[0]) == {"next": 3, "counts": [3, 3]}
    assert reply[1:] == [*_frames(1, "/a"), *_frames(2, "/a")]
    s.close()


def test_journal_endpoints() -> None:
    from mogs_node.bus import BusConfig

    assert journal_endpoint(BusConfig("ipc:///r/demo-pub.ipc", "ipc:///r/demo-sub.ipc")) == (
        "ipc:///r/demo-journal.ipc"
    )
    assert journal_endpoint(BusConfig("tcp://127.0.0.1:7700", "tcp://127.0.0.1:7701")) == (
        "tcp://127.0.0.1:7702"
    )
    assert (
        journal_endpoint(BusConfig("inproc://a-pub", "inproc://a-sub")) == "inproc://a-sub-journal"
    )


# ------------------------------------------------------------------------------- catch-up


def _masks(kid: int) -> msgs.Masks:
    return msgs.Masks(
        stamp_ns=1000 + kid,
        frame_id="c",
        keyframe_id=kid,
        labels=np.full((2, 3), kid, np.int32),
        backend="graph",
    )


class Worker(Node):
    """A per-keyframe worker: /in -> /out, one output per keyframe id."""

    def setup(self) -> None:
        self.handled: list[int] = []
        self.subscribe("/in", self.on_in, msg_type=msgs.Masks, idempotent=True)
        self.caught = self.catch_up(["/in"], ["/out"], force=True, timeout_s=10.0)

    def on_in(self, m: msgs.Masks) -> None:
        self.handled.append(m.keyframe_id)
        self.publish("/out", _masks(m.keyframe_id))


def _until(pred, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.02)


def test_restarted_worker_catches_up_from_the_journal(inproc_bus, tmp_path: Path) -> None:
    bus, ctx = inproc_bus
    journal = JournalNode(
        "journal",
        {"dir": str(tmp_path), "topics": ["/in", "/out"]},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    jt = threading.Thread(target=journal.run, kwargs={"install_signal_handlers": False})
    jt.start()
    pub = Publisher(bus, context=ctx)
    out = Subscriber(bus, context=ctx)
    out.subscribe("/out")
    try:
        assert pub.wait_for_subscriber("/in", 5) and pub.wait_for_subscriber("/out", 5)
        for k in range(5):  # the worker died after publishing outputs 0..2
            pub.publish("/in", _masks(k))
        for k in range(3):
            pub.publish("/out", _masks(k))
        _until(lambda: len(journal.store) == 8)
        client = JournalClient(bus, context=ctx, timeout_s=5)
        assert client.keys(["/in", "/out"]) == {"/in": [0, 1, 2, 3, 4], "/out": [0, 1, 2]}
        client.close()
        while out.receive(timeout_ms=100) is not None:  # what the dead worker sent
            pass
        w = Worker("worker", None, bus, context=ctx, diagnostics_period_s=0)
        assert w.caught and w.catching_up and w.already_published("/out", 2)
        wt = threading.Thread(target=w.run, kwargs={"install_signal_handlers": False})
        wt.start()
        try:
            _until(lambda: not w.catching_up)
            assert w.handled == [0, 1, 2, 3, 4]
            assert w.counters["catch_up_suppressed"] == 3
            pub.publish("/in", _masks(4))  # a repeat of the last replayed one: dropped
            pub.publish("/in", _masks(5))
            pub.publish("/in", _masks(5))  # a duplicate keyframe id: processed once
            _until(lambda: w.handled[-1:] == [5])
            got = []
            while (env := out.receive(timeout_ms=300)) is not None:
                got.append(env.msg.keyframe_id)
            assert got == [3, 4, 5]  # every output exactly once across the restart
            assert w.handled == [0, 1, 2, 3, 4, 5]
            assert w.counters["catch_up_duplicates"] + w.counters["duplicates"] == 2
        finally:
            w.request_stop()
            wt.join(5)
    finally:
        journal.request_stop()
        jt.join(5)
        pub.close()
        out.close()
    assert message_key(_masks(7)) == 7


def test_no_catch_up_on_a_first_start(inproc_bus, monkeypatch) -> None:
    bus, ctx = inproc_bus
    monkeypatch.delenv("MOGS_CATCH_UP", raising=False)

    class Plain(Node):
        def setup(self) -> None:
            self.subscribe("/in", lambda m: None)
            self.caught = self.catch_up(["/in"], ["/out"])

    n = Plain("plain", None, bus, context=ctx, diagnostics_period_s=0)
    assert not n.caught and not n.catching_up
    with pytest.raises(ConfigError, match="not subscribed"):
        n.catch_up(["/nope"], force=True)
    # a restart without a journal to catch up from: the node runs on (and says so)
    assert not n.catch_up(["/in"], ["/out"], force=True, timeout_s=0.5, settle_s=0)
    assert not n.catching_up
    n.close()


def test_restarted_player_goes_on_after_the_journal(
    inproc_bus, tmp_path: Path, monkeypatch
) -> None:
    from bridges.player import PlayerNode
    from bridges.replay import IMAGE

    bus, ctx = inproc_bus
    params = {
        "source": "sim",
        "sim": {"n_frames": 8, "width": 64, "height": 48},
        "fast": True,
        "max_frames_in_flight": 1,
    }
    monkeypatch.delenv("MOGS_CATCH_UP", raising=False)
    first = PlayerNode("player", params, bus, context=ctx, diagnostics_period_s=0)
    events = list(first.events)
    first.close()
    images = [e[0] for e in events if e[1] == IMAGE]
    imu = [e[0] for e in events if e[1] != IMAGE]
    journal = JournalNode(
        "journal", {"dir": str(tmp_path)}, bus, context=ctx, diagnostics_period_s=0
    )
    jt = threading.Thread(target=journal.run, kwargs={"install_signal_handlers": False})
    jt.start()
    pub = Publisher(bus, context=ctx)
    try:
        assert pub.wait_for_subscriber("/camera/image", 5)
        played = [e for e in events if e[0] <= images[2]]  # the dead player got to image 3
        for stamp, kind, _ in played:
            if kind == IMAGE:
                pub.publish("/camera/image", _img(stamp))
            else:
                pub.publish(
                    "/imu",
                    msgs.Imu(
                        stamp_ns=stamp,
                        frame_id="imu",
                        gyro_rad_s=(0.0, 0.0, 0.0),
                        accel_m_s2=(0.0, 0.0, 9.81),
                    ),
                )
        _until(lambda: len(journal.store) == len(played))
        monkeypatch.setenv("MOGS_CATCH_UP", "1")
        again = PlayerNode("player", params, bus, context=ctx, diagnostics_period_s=0)
        assert again.events == [e for e in events if e[0] > images[2]]
        assert again.frames_published == 3 and again.total_frames == len(images)
        # image 3 has no odometry in the journal: it counts as in flight until acknowledged
        assert again.frames.in_flight == 1 and not again.frames.can_send()
        again.close()
        assert len(imu) > 0
    finally:
        journal.request_stop()
        jt.join(5)
        pub.close()


def _img(stamp: int) -> msgs.Image:
    return msgs.Image(
        stamp_ns=stamp, frame_id="c", encoding="mono8", data=np.zeros((48, 64), np.uint8)
    )


def test_journal_on_a_curve_bus_answers_only_authenticated_clients(tmp_path: Path) -> None:
    import uuid

    import zmq

    from mogs_node.bus import BusConfig, CurveConfig, generate_keys

    keys = tmp_path / "keys"
    generate_keys(keys, names=("broker", "client", "stranger"))
    (keys / "authorized" / "stranger.key").unlink()  # a key pair the bus does not accept
    d = Path("/tmp") / f"mogs-jc-{uuid.uuid4().hex[:8]}"
    d.mkdir()
    curve = CurveConfig(
        server_public_key=str(keys / "broker.key"),
        client_secret_key=str(keys / "client.key_secret"),
        server_secret_key=str(keys / "broker.key_secret"),
        authorized_keys_dir=str(keys / "authorized"),
    )
    bus = BusConfig(f"ipc://{d}/pub.ipc", f"ipc://{d}/sub.ipc", curve=curve)
    ctx = zmq.Context()
    journal = JournalNode(
        "journal", {"dir": str(tmp_path / "j")}, bus, context=ctx, diagnostics_period_s=0
    )
    jt = threading.Thread(target=journal.run, kwargs={"install_signal_handlers": False})
    jt.start()
    try:
        ok = JournalClient(bus, context=ctx, timeout_s=10)
        assert ok.keys(["/imu"]) == {"/imu": []}
        ok.close()
        stranger = BusConfig(
            bus.pub_endpoint,
            bus.sub_endpoint,
            curve=CurveConfig(
                server_public_key=str(keys / "broker.key"),
                client_secret_key=str(keys / "stranger.key_secret"),
            ),
        )
        for cfg in (stranger, BusConfig(bus.pub_endpoint, bus.sub_endpoint)):  # no CURVE at all
            c = JournalClient(cfg, context=ctx, timeout_s=1.5)
            with pytest.raises(BusError, match="no reply"):
                c.keys(["/imu"])
            c.close()
        assert journal.counters["journal_requests"] == 1
    finally:
        journal.request_stop()
        jt.join(5)
        ctx.term()
