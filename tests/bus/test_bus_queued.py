"""bus.queued: what a socket has queued, without waiting; bus.Subscriber.arrivals: stamped messages
while a run lasts."""

from __future__ import annotations

import zmq

from mogs_node.bus import Subscriber, queued


def _recv_from(items: list[object]):
    def recv(flags: int) -> object:
        assert flags == zmq.NOBLOCK  # never waits
        if not items:
            raise zmq.Again()
        return items.pop(0)

    return recv


def test_queued_yields_until_again_or_limit():
    assert list(queued(_recv_from([1, 2, 3]))) == [1, 2, 3]
    left = [1, 2, 3]
    assert list(queued(_recv_from(left), limit=2)) == [1, 2]
    assert left == [3]  # the third stays queued for the next call
    assert list(queued(_recv_from([]))) == []


def test_arrivals_stops_when_the_run_ends():
    class _Sub:
        receive_calls = 0

        def receive(self, timeout_ms: int | None = 0) -> str | None:
            self.receive_calls += 1
            return None if self.receive_calls % 2 else "msg"

    sub = _Sub()
    runs = iter([True, True, True, False])
    got = list(Subscriber.arrivals(sub, lambda: next(runs), timeout_ms=5))  # type: ignore[arg-type]
    assert [env for _, env in got] == [None, "msg", None]
    stamps = [t for t, _ in got]
    assert stamps == sorted(stamps)
