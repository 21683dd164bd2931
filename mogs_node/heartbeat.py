"""Liveness apart from the work: a node's ``/diagnostics`` heartbeat from its own thread (issue 23).

A node's run loop handles one message at a time; a handler that computes for minutes (a mapper
window step on a loaded machine) used to stop its heartbeat, and the launcher killed it "for
thinking". Here the heartbeat has its own thread and its own PUB socket (ZeroMQ sockets are not
shared between threads), as ROS 2 keeps liveliness apart from callbacks:

- the run loop still builds the diagnostics snapshot (its counters are only read on the thread that
  changes them) and hands it over (:meth:`Heartbeat.offer`); the thread sends it at once;
- while the loop is busy, the thread re-sends the latest snapshot every period with a fresh stamp,
  ``busy_s`` (seconds since the work last moved: :class:`Progress`), ``progress`` (how often it
  moved) and the status ``busy: WHAT`` (a handler of a topic, a timer, a catch-up);
- the launcher kills a node whose heartbeat stops (a crashed interpreter, a GIL held for ever) and
  one whose ``busy_s`` passes its ``progress_timeout_s`` (stuck in a handler however alive its
  heartbeat thread is): :mod:`mogs_node.launch`.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from collections.abc import Callable

import zmq

from mogs_node import msgs
from mogs_node.bus import BusConfig, Publisher, Subscriber

__all__ = ["Heartbeat", "Progress", "diagnostics_message", "other_node_busy", "topic_stats"]

DIAGNOSTICS_TOPIC = "/diagnostics"


class Progress:
    """What the run loop is busy with, since when, and a count of steps it finished.

    Written by the run loop only (plain attribute stores, atomic under the GIL); read by the
    heartbeat thread. Long work inside one handler calls :meth:`moved` (e.g. per optimisation
    iteration) so that it is not taken for stuck.
    """

    def __init__(self) -> None:
        self.count = 0
        self._busy: tuple[str, float] | None = None  # (what, monotonic time it last moved)

    def start(self, what: str) -> None:
        self._busy = (what, time.monotonic())

    def moved(self) -> None:
        """The current work advanced (one iteration of a long step)."""
        self.count += 1
        busy = self._busy
        if busy is not None:
            self._busy = (busy[0], time.monotonic())

    def done(self) -> None:
        self.count += 1
        self._busy = None

    def busy(self, now: float | None = None) -> tuple[str, float] | None:
        """``(what, seconds since it last moved)`` while busy, else None."""
        busy = self._busy
        if busy is None:
            return None
        return busy[0], (time.monotonic() if now is None else now) - busy[1]


class Heartbeat:
    """Sends a node's diagnostics every ``period_s`` from a daemon thread; see the module doc."""

    def __init__(
        self,
        bus: BusConfig,
        context: zmq.Context,
        period_s: float,
        progress: Progress,
        *,
        on_error: Callable[[BaseException], None] | None = None,
    ) -> None:
        self.period_s = period_s
        self.progress = progress
        self._pub = Publisher(bus, context=context)
        self._offered: msgs.Diagnostics | None = None
        self._last: msgs.Diagnostics | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._on_error = on_error
        self._last_sent: float | None = None
        self._base_t = 0.0  # when the latest snapshot was taken
        self.gap_max_s = 0.0  # largest interval between two heartbeats sent
        self._thread = threading.Thread(target=self._loop, name="mogs-heartbeat", daemon=True)

    def start(self) -> None:
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def offer(self, diag: msgs.Diagnostics) -> None:
        """A fresh snapshot from the run loop: sent at once by the thread."""
        self._offered = diag
        self._wake.set()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def send_final(self, diag: msgs.Diagnostics) -> None:
        """The last heartbeat (status "stopped"), from the caller's thread once :meth:`stop`ped."""
        self._pub.publish(DIAGNOSTICS_TOPIC, diag)

    def close(self) -> None:
        self._pub.close()

    def beat(self) -> msgs.Diagnostics | None:
        """The heartbeat due now: the offered snapshot, else the latest one re-stamped, with the
        liveness figures; None before the run loop's first snapshot."""
        diag, self._offered = self._offered, None
        if diag is None and self._last is None:
            return None
        base = diag if diag is not None else self._last
        assert base is not None
        now = time.monotonic()
        busy = self.progress.busy(now)
        counters = dict(base.counters)
        counters["progress"] = self.progress.count
        counters["busy_s"] = round(busy[1], 3) if busy is not None else 0.0
        counters["heartbeat_gap_max_s"] = round(self.gap_max_s, 3)
        status = base.status
        if busy is not None and busy[1] >= self.period_s and status != "stopped":
            status = f"busy: {busy[0]}"
        uptime = base.uptime_s + (now - self._base_t) if diag is None else base.uptime_s
        out = dataclasses.replace(
            base, stamp_ns=time.time_ns(), uptime_s=uptime, status=status, counters=counters
        )
        if diag is not None:
            self._last, self._base_t = diag, now
        return out

    def _loop(self) -> None:
        while not self._stop.is_set():
            due = (
                self.period_s
                if self._last_sent is None
                else max(0.0, self._last_sent + self.period_s - time.monotonic())
            )
            self._wake.wait(due)
            self._wake.clear()
            if self._stop.is_set():
                return
            if self._offered is None and (
                self._last_sent is not None
                and time.monotonic() - self._last_sent < self.period_s * 0.999
            ):
                continue
            try:
                out = self.beat()
                if out is None:
                    continue
                self._pub.publish(DIAGNOSTICS_TOPIC, out)
            except Exception as err:  # a heartbeat must never take the node down
                if self._on_error is not None:
                    self._on_error(err)
                continue
            now = time.monotonic()
            if self._last_sent is not None:
                self.gap_max_s = max(self.gap_max_s, now - self._last_sent)
            self._last_sent = now


def topic_stats(sub: Subscriber | None, pub: Publisher) -> dict[str, dict[str, int]]:
    """Per-topic counters of a node's sockets: received / lost / dropped ..., published, shm."""
    out: dict[str, dict[str, int]] = {}
    if sub is not None:
        for topic, st in sub.stats.items():
            out[topic] = st.as_dict()
    for topic, n in pub.published.items():
        out.setdefault(topic, {})["published"] = n
    for topic, counters in pub.shm_counters().items():
        out.setdefault(topic, {}).update(counters)
    return out


def diagnostics_message(
    name: str,
    counters: dict[str, float],
    sub: Subscriber | None,
    pub: Publisher,
    uptime_s: float,
    status: str | None = None,
) -> msgs.Diagnostics:
    """A node's ``/diagnostics`` message; ``counters`` gets the socket totals written into it.
    ``status`` defaults to "ok", or "warn" once a message was lost or a handler failed."""
    stats = topic_stats(sub, pub)
    c = counters
    if sub is not None:
        c["lost"] = sum(s.lost for s in sub.stats.values())
        c["malformed"] = sum(s.malformed for s in sub.stats.values()) + sub.malformed
        c["received"] = sum(s.received for s in sub.stats.values())
    c["dropped"] = sum(s.get("dropped", 0) for s in stats.values())
    if status is None:
        status = "ok" if c["lost"] == 0 and c["handler_errors"] == 0 else "warn"
    return msgs.Diagnostics(
        stamp_ns=time.time_ns(),
        frame_id="",
        node=name,
        pid=os.getpid(),
        uptime_s=uptime_s,
        status=status,
        counters=dict(c),
        topics=stats,
    )


def other_node_busy(msg: msgs.Message, own_name: str) -> bool:
    """Whether a ``/diagnostics`` heartbeat says another (running) node is inside a handler
    (``busy_s`` > 0): the pipeline works, so a node waiting for it waits on (the player's
    acknowledgement timeout, the prior's wait for metrized depth)."""
    if getattr(msg, "node", own_name) == own_name or getattr(msg, "status", "") == "stopped":
        return False
    return (getattr(msg, "counters", None) or {}).get("busy_s", 0.0) > 0
