"""Node shell: params, queue policies, error containment, diagnostics (in one process)."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest

from mogs_node import msgs
from mogs_node.bus import Publisher
from mogs_node.errors import ConfigError, MogsError
from mogs_node.node import Node, parse_params


@dataclass(frozen=True)
class P:
    gain: float = 1.0  # a float
    count: int = 3  # an int
    name: str = "x"  # a string
    sizes: tuple[int, int] = (1, 2)  # a pair
    mode: str | None = None  # optional


def test_parse_params_is_strict_and_names_the_key() -> None:
    p = parse_params(P, {"gain": 2, "sizes": [3, 4]})
    assert p == P(gain=2.0, sizes=(3, 4))
    assert isinstance(p.gain, float)
    with pytest.raises(ConfigError, match=r"unknown parameter\(s\) \['gian'\]"):
        parse_params(P, {"gian": 1})
    with pytest.raises(ConfigError, match=r"params.count: expected an int"):
        parse_params(P, {"count": 1.5})
    with pytest.raises(ConfigError, match=r"params.sizes: expected 2 items"):
        parse_params(P, {"sizes": [1]})
    with pytest.raises(ConfigError, match="params.gain"):
        parse_params(P, {"gain": True})


class Collect(Node):
    def setup(self) -> None:
        self.images: list[int] = []
        self.imu: list[int] = []
        self.subscribe("/camera/image", lambda m: self.images.append(m.stamp_ns), reliable=False)
        self.subscribe("/imu", self.on_imu, reliable=True, msg_type=msgs.Imu)

    def on_imu(self, m: msgs.Imu) -> None:
        if m.stamp_ns == 13:
            raise MogsError("bad sample")
        if m.stamp_ns == 14:
            raise RuntimeError("bug in a handler")
        self.imu.append(m.stamp_ns)


def _img(stamp: int) -> msgs.Image:
    return msgs.Image(
        stamp_ns=stamp, frame_id="c", encoding="mono8", data=np.zeros((2, 2), np.uint8)
    )


def _imu(stamp: int) -> msgs.Imu:
    return msgs.Imu(stamp_ns=stamp, frame_id="i", gyro_rad_s=(0, 0, 0), accel_m_s2=(0, 0, 9.8))


def test_queue_policies_and_error_containment(inproc_bus) -> None:
    bus, ctx = inproc_bus
    node = Collect("collect", {}, bus, context=ctx, diagnostics_period_s=0)
    pub = Publisher(bus, context=ctx)
    assert pub.wait_for_subscriber("/imu", 5) and pub.wait_for_subscriber("/camera/image", 5)
    # a burst of images interleaved with IMU samples, all queued before the node runs
    for k in range(20):
        pub.publish("/camera/image", _img(k))
        pub.publish("/imu", _imu(k))
    pub.publish(
        "/imu",
        msgs.Image(stamp_ns=99, frame_id="c", encoding="mono8", data=np.zeros((1, 1), np.uint8)),
    )
    time.sleep(0.3)
    node.spin_once(500)
    # reliable: every IMU sample, in order, except the two whose handler raised (counted)
    assert node.imu == [k for k in range(20) if k not in (13, 14)]
    assert node.counters["handler_errors"] == 2
    # best effort: only the latest image survives the burst; the rest are counted as dropped
    assert node.images == [19]
    stats = node.topic_stats()
    assert stats["/camera/image"]["dropped"] == 19
    assert stats["/imu"]["malformed"] == 1  # wrong message type on a typed subscription
    d = node.diagnostics()
    assert d.counters["received"] == 41 and d.counters["lost"] == 0
    pub.close(0)
    node.close()


def test_diagnostics_are_published_periodically(inproc_bus) -> None:
    bus, ctx = inproc_bus
    from mogs_node.bus import Subscriber

    watcher = Subscriber(bus, context=ctx)
    watcher.subscribe("/diagnostics")
    node = Node("idle", {}, bus, context=ctx, diagnostics_period_s=0.1)
    assert node._pub.wait_for_subscriber("/diagnostics", 5)
    seen = []
    t = threading.Thread(
        target=node.run, kwargs={"install_signal_handlers": False, "duration_s": 0.6}
    )
    t.start()
    deadline = time.monotonic() + 5
    while len(seen) < 3 and time.monotonic() < deadline:
        env = watcher.receive(timeout_ms=200)
        if env is not None:
            seen.append(env.msg)
    t.join(5)
    watcher.close()
    assert len(seen) >= 3
    assert all(isinstance(m, msgs.Diagnostics) and m.node == "idle" for m in seen)
    assert seen[-1].uptime_s > seen[0].uptime_s


def test_external_reader_is_served_by_the_same_loop(inproc_bus) -> None:
    import os

    bus, ctx = inproc_bus
    node = Node("reader", {}, bus, context=ctx, diagnostics_period_s=0)
    r, w = os.pipe()
    got: list[bytes] = []
    node.add_reader(r, lambda: got.append(os.read(r, 100)))
    node.spin_once(50)
    assert got == []  # nothing readable yet: the poll timed out
    os.write(w, b"imu line\n")
    node.spin_once(1000)
    assert got == [b"imu line\n"]
    node.remove_reader(r)
    os.close(r)
    os.close(w)
    node.close()


def test_external_python_socket_reader(inproc_bus) -> None:
    import socket

    bus, ctx = inproc_bus
    node = Node("udp", {}, bus, context=ctx, diagnostics_period_s=0)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    got: list[bytes] = []
    node.add_reader(rx, lambda: got.append(rx.recv(100)))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        tx.sendto(b"datagram", rx.getsockname())
    node.spin_once(1000)
    assert got == [b"datagram"]
    rx.close()
    node.close()


def test_a_snoozed_timer_sleeps_until_rescheduled(inproc_bus) -> None:
    bus, ctx = inproc_bus
    node = Collect("timers", {}, bus, context=ctx, diagnostics_period_s=0)
    calls: list[int] = []
    tid = node.every(0.001, lambda: calls.append(1))
    node.reschedule(tid, 3600.0)  # snoozed for an hour
    for _ in range(5):
        node.spin_once(0)
    assert calls == []
    node.reschedule(tid, 0.0)  # woken: runs at the next loop turn, then ticks on
    node.spin_once(0)
    assert calls == [1]
    with pytest.raises(IndexError):
        node.reschedule(tid + 1, 0.0)
    node.close()
