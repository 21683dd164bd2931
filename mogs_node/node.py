"""The process shell every node shares: params, subscriptions, run loop, heartbeat, shutdown.

A node is a subclass of :class:`Node` with a frozen ``Params`` dataclass; its ``setup`` declares
subscriptions, and handlers publish results. The shell owns everything else:

- one SUB socket for all subscriptions, blocked on with ``zmq.Poller`` and a timeout (no spinning);
- per-topic queues in arrival order: reliable topics are handled one by one, in order; best-effort
  topics keep only the latest message (older ones are dropped and counted);
- handler exceptions are caught, logged and counted: a node never dies of bad input;
- ``/diagnostics`` heartbeat with counters (received, published, dropped, lost, malformed,
  handler_errors, queue_depth, loop_latency_ms) every ``diagnostics_period_s``, sent by a thread of
  its own while :meth:`Node.run` runs (:mod:`mogs_node.heartbeat`): a handler that computes for
  minutes does not silence it; the heartbeat says what the loop is busy with and for how long
  (``busy_s``), and long work calls :meth:`Node.progress` to say it still advances;
- clean shutdown on SIGINT/SIGTERM: stop reading, call ``teardown``, flush outgoing messages;
- catch-up after a restart (:meth:`Node.catch_up`): a respawned node replays its inputs from the
  journal (:mod:`mogs_node.journal`) before reading live messages, does not re-publish outputs the
  journal already holds, and drops the live messages it has already seen in the replay.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import zmq

from mogs_node import msgs
from mogs_node.bus import BusConfig, Publisher, Subscriber
from mogs_node.errors import ConfigError, DatasetError, ModelError, MogsError
from mogs_node.failure_log import FailureLog
from mogs_node.heartbeat import (
    DIAGNOSTICS_TOPIC,
    Heartbeat,
    Progress,
    diagnostics_message,
    topic_stats,
)
from mogs_node.params import EmptyParams, parse_params

if TYPE_CHECKING:
    from mogs_node.journal.replay import JournalReplay

__all__ = [
    "CATCH_UP_ENV",
    "EXIT_CONFIG",
    "STARTUP_ERRORS",
    "EmptyParams",
    "Node",
    "parse_params",
]

log = logging.getLogger(__name__)

#: set to "1" by the launcher for a respawned node and on ``mogs launch --resume``
CATCH_UP_ENV = "MOGS_CATCH_UP"
#: exit code of a node that cannot start with its configuration (sysexits' EX_CONFIG): a typo'd or
#: bad parameter, a missing dataset or model file. Starting it again cannot help, so the launcher
#: never respawns it and ends the run (docs/reliability.md, "Failures that end a run").
EXIT_CONFIG = 78
#: errors that, raised while a node is built (parameters, ``setup``), mean :data:`EXIT_CONFIG`
STARTUP_ERRORS: tuple[type[MogsError], ...] = (ConfigError, DatasetError, ModelError)


def message_key(msg: msgs.Message) -> int:
    """Identity of a message within its topic: ``keyframe_id`` if it has one, else ``stamp_ns``."""
    kid = getattr(msg, "keyframe_id", None)
    return int(kid) if kid is not None else int(msg.stamp_ns)


Handler = Callable[[msgs.Message], None]


@dataclass
class _Subscription:
    topic: str
    handler: Handler
    reliable: bool
    msg_type: type[msgs.Message] | None
    queue_size: int
    pending: int = 0
    # best effort: boxes ([envelope]) of this topic still in the node queue, oldest first; a box
    # superseded beyond queue_size is emptied at once (memory freed, drop counted)
    waiting: deque[list[Any]] = dataclasses.field(default_factory=deque)
    idempotent: bool = False  # handle each key (keyframe id / stamp) once; repeats are dropped
    handled: set[int] = dataclasses.field(default_factory=set)


class Node:
    """Base class of every node process; see the module docstring."""

    Params: ClassVar[type] = EmptyParams

    def __init__(
        self,
        name: str,
        params: Any = None,
        bus: BusConfig | None = None,
        *,
        diagnostics_period_s: float = 1.0,
        context: zmq.Context | None = None,
    ) -> None:
        if bus is None:
            raise ConfigError(f"node {name}: no bus configuration")
        self.name = name
        self.params = (
            params
            if isinstance(params, self.Params)
            else parse_params(self.Params, params, where=f"{name}.params")
        )
        self.bus = bus
        self.log = logging.getLogger(f"mogs.{name}")
        # a failure repeating on every message or tick is logged once, then counted (issue 18)
        self.failures = FailureLog(self.log)
        # A node owns its context unless given one: closing it then waits until every queued
        # (zero-copy) outgoing frame is sent, before the interpreter frees the arrays behind them.
        self._own_ctx = context is None
        self._ctx = context or zmq.Context()
        self._pub = Publisher(bus, context=self._ctx)
        self._sub: Subscriber | None = None
        self._subs: dict[str, _Subscription] = {}
        # (subscription, [envelope]) in arrival order; a best-effort box may be emptied (None)
        self._queue: deque[tuple[_Subscription, list[Any]]] = deque()
        self._timers: list[list[Any]] = []  # [period_s, next_due, callback]
        # external socket / fd -> on-readable callback
        self._extra: dict[Any, Callable[[], None]] = {}
        self._stop = threading.Event()
        self._catch_up: JournalReplay | None = None
        self._replayed: dict[str, set[int]] = {}  # topic -> keys replayed from the journal
        self._published_keys: dict[str, set[int]] = {}  # topic -> keys the journal already has
        self._t0 = time.monotonic()
        self.liveness = Progress()  # what the loop is busy with (read by the heartbeat thread)
        self._heartbeat: Heartbeat | None = None  # started by run()
        self.counters: dict[str, float] = {
            "received": 0,
            "published": 0,
            "dropped": 0,
            "lost": 0,
            "malformed": 0,
            "handler_errors": 0,
            "queue_depth": 0,
            "loop_latency_ms": 0.0,
            "handler_ms_max": 0.0,
        }
        self._latency_ewma_ms = 0.0
        self.diagnostics_period_s = diagnostics_period_s
        self.setup()
        if diagnostics_period_s > 0:
            self.every(diagnostics_period_s, self.publish_diagnostics)

    # ------------------------------------------------------------------ API for subclasses

    def setup(self) -> None:
        """Declare subscriptions and timers (override)."""

    def teardown(self) -> None:
        """Release resources and write final outputs (override); called once on shutdown."""

    def subscribe(
        self,
        topic: str,
        handler: Handler,
        *,
        reliable: bool = True,
        msg_type: type[msgs.Message] | None = None,
        queue_size: int | None = None,
        idempotent: bool = False,
    ) -> None:
        """Call ``handler(msg)`` for each message of ``topic``.

        ``idempotent``: a message whose key (keyframe id, else stamp) was handled before is
        dropped and counted (``duplicates``): per-keyframe workers process each keyframe once.

        Reliable topics are handled in order with a bounded queue (``queue_size``, default the
        bus's reliable HWM); when it is full the node stops reading, ZeroMQ's own queue fills, and
        any loss shows up as a sequence gap (counted, reported). Best-effort topics keep only the
        latest message (``queue_size`` default 1), dropping and counting older ones.
        """
        if self._sub is None:
            hwm = self.bus.reliable_hwm if reliable else self.bus.best_effort_hwm
            self._sub = Subscriber(self.bus, context=self._ctx, hwm=hwm)
        elif reliable:
            self._sub.socket.rcvhwm = self.bus.reliable_hwm
        qs = queue_size if queue_size is not None else (self.bus.reliable_hwm if reliable else 1)
        self._subs[topic] = _Subscription(
            topic, handler, reliable, msg_type, max(1, qs), idempotent=idempotent
        )
        self._sub.subscribe(topic, reliable=reliable)

    def publish(self, topic: str, msg: msgs.Message) -> None:
        """Publish ``msg``; an invalid message is a bug in this node and raises MessageError.

        After :meth:`catch_up`, an output the journal already held is not sent again.
        """
        done = self._published_keys.get(topic)
        if done is not None and message_key(msg) in done:
            self.counters["catch_up_suppressed"] += 1
            return
        self._pub.publish(topic, msg)
        self.counters["published"] += 1

    def every(self, period_s: float, callback: Callable[[], None]) -> int:
        """Call ``callback`` every ``period_s`` seconds from the run loop; returns the timer's id."""
        if period_s <= 0:
            raise ConfigError(f"{self.name}: timer period must be > 0, got {period_s}")
        self._timers.append([period_s, time.monotonic() + period_s, callback])
        return len(self._timers) - 1

    def reschedule(self, timer_id: int, delay_s: float) -> None:
        """Next call of timer ``timer_id`` in ``delay_s`` seconds (0: at the next loop turn).

        A timer that has nothing to do until some input arrives snoozes, and the input's handler
        wakes it: the loop then sleeps in its poll instead of ticking (a fast-mode player waiting
        for acknowledgements used half a core at a 2 ms tick)."""
        self._timers[timer_id][1] = time.monotonic() + max(0.0, delay_s)

    def wait_for_subscriber(self, topic: str, timeout_s: float = 5.0) -> bool:
        """Block until someone subscribes to ``topic`` (sources use this before streaming);
        False after ``timeout_s`` or as soon as the node is asked to stop."""
        deadline = time.monotonic() + timeout_s
        while not self._stop.is_set():
            remaining = deadline - time.monotonic()
            if self._pub.wait_for_subscriber(topic, max(0.0, min(0.2, remaining))):
                return True
            if remaining <= 0:
                return False
        return False

    def has_subscriber(self, topic: str) -> bool:
        return self._pub.has_subscriber(topic)

    # ------------------------------------------------------------------ catch-up

    def catch_up(
        self,
        inputs: tuple[str, ...] | list[str],
        outputs: tuple[str, ...] | list[str] = (),
        *,
        force: bool = False,
        endpoint: str | None = None,
        timeout_s: float = 30.0,
        settle_s: float = 0.3,
    ) -> bool:
        """After a restart, replay the journaled ``inputs`` through their handlers (call from
        ``setup`` after subscribing); returns whether a catch-up was started.

        Only when the launcher flagged this process as a restart (``MOGS_CATCH_UP=1``: respawn
        or ``--resume``) or ``force``. The journal's keys of ``outputs`` are fetched first: those
        outputs are not published again (:meth:`already_published` lets a handler skip the work).
        The run loop then handles journal batches before any live message (heartbeats go on);
        live messages seen in the replay are dropped. ``settle_s`` lets this node's
        subscriptions reach the broker, so that nothing falls between the journal and the live
        stream.
        """
        if not (force or os.environ.get(CATCH_UP_ENV) == "1"):
            return False
        from mogs_node.journal.replay import JournalReplay

        missing = [t for t in inputs if t not in self._subs]
        if missing:
            raise ConfigError(f"{self.name}: catch_up inputs {missing} are not subscribed")
        try:
            replay = JournalReplay.open(
                self.bus,
                self._ctx,
                inputs,
                outputs,
                endpoint=endpoint,
                timeout_s=timeout_s,
                settle_s=settle_s,
            )
        except MogsError as err:  # no journal: run on without the missed messages, loudly
            self.log.error("no catch-up, journal unavailable: %s", err)
            return False
        self._published_keys = replay.published
        self._catch_up = replay
        for k in ("catch_up_replayed", "catch_up_suppressed", "catch_up_duplicates"):
            self.counters.setdefault(k, 0)
        self.counters["catching_up"] = 1
        self.log.info(
            "catching up from %s: inputs %s; already published %s",
            replay.client.endpoint,
            list(inputs),
            {t: len(v) for t, v in self._published_keys.items()},
        )
        return True

    def already_published(self, topic: str, key: int) -> bool:
        """Whether the journal held an output of ``topic`` with ``key`` when this node restarted."""
        return key in self._published_keys.get(topic, ())

    @property
    def catching_up(self) -> bool:
        return self._catch_up is not None

    def _catch_up_step(self, max_records: int = 32) -> None:
        """Handle one journal batch; switch to live input when the journal has nothing newer."""
        cu = self._catch_up
        assert cu is not None
        try:
            batch = cu.next_batch(max_records, self.bus.max_message_bytes)
        except MogsError as err:
            self.log.error("catch-up stopped, journal unavailable: %s", err)
            batch = None
        if batch is None:
            self._catch_up = None
            self.counters["catching_up"] = 0
            self.log.info(
                "caught up: %d messages replayed in %.1f s; %d outputs not re-published",
                cu.replayed,
                time.monotonic() - cu.t0,
                self.counters["catch_up_suppressed"],
            )
            return
        envelopes, rejected = batch
        for reason in rejected:
            self.log.warning("journal record rejected: %s", reason)
        for env in envelopes:
            sub = self._subs.get(env.topic)
            if sub is None or (sub.msg_type is not None and not isinstance(env.msg, sub.msg_type)):
                continue
            cu.replayed += 1
            self.counters["catch_up_replayed"] += 1
            self._replayed.setdefault(env.topic, set()).add(message_key(env.msg))
            self._dispatch(sub, env)
            self._run_timers()  # heartbeats go on during a long replay (e.g. a map rebuild)
            if self._stop.is_set():
                return

    def _dispatch(self, sub: _Subscription, env: msgs.Envelope) -> None:
        """Call the handler of ``sub`` (errors counted, never raised), once per key if idempotent."""
        if sub.idempotent:
            key = message_key(env.msg)
            if key in sub.handled:
                self.counters["duplicates"] = self.counters.get("duplicates", 0) + 1
                return
            sub.handled.add(key)
        t0 = time.perf_counter()
        self.liveness.start(f"handler of {env.topic}")
        try:
            sub.handler(env.msg)
        except MogsError as err:
            self.counters["handler_errors"] += 1
            self.failures.failed(
                env.topic, err, f"rejected message seq {env.seq}", with_traceback=False
            )
        except Exception as err:  # a node never dies of one message; the traceback is logged
            self.counters["handler_errors"] += 1
            self.failures.failed(env.topic, err, f"handler failed on seq {env.seq}")
        finally:
            self.liveness.done()
        dt_ms = (time.perf_counter() - t0) * 1000
        self._latency_ewma_ms = 0.9 * self._latency_ewma_ms + 0.1 * dt_ms
        self.counters["handler_ms_max"] = max(self.counters["handler_ms_max"], dt_ms)

    def _seen_in_replay(self, env: msgs.Envelope) -> bool:
        """A live message already handled from the journal (the overlap after a catch-up)."""
        seen = self._replayed.get(env.topic)
        if seen is None:
            return False
        if message_key(env.msg) in seen:
            self.counters["catch_up_duplicates"] += 1
            return True
        del self._replayed[env.topic]  # past the overlap: live order is publication order
        return False

    def progress(self) -> None:
        """Say that the current (long) work advanced, e.g. once per optimisation iteration:
        the launcher kills a node busy for ``progress_timeout_s`` without any progress."""
        self.liveness.moved()

    def request_stop(self) -> None:
        """Ask the run loop to finish (thread- and signal-safe)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    # ------------------------------------------------------------------ diagnostics

    def topic_stats(self) -> dict[str, dict[str, int]]:
        return topic_stats(self._sub, self._pub)

    def diagnostics(self, status: str | None = None) -> msgs.Diagnostics:
        self.counters["queue_depth"] = len(self._queue)
        self.counters["loop_latency_ms"] = round(self._latency_ewma_ms, 3)
        return diagnostics_message(
            self.name, self.counters, self._sub, self._pub, time.monotonic() - self._t0, status
        )

    def publish_diagnostics(self) -> None:
        """Send the node's diagnostics now: through the heartbeat thread while it runs (its
        socket is its own), else from this thread."""
        hb = self._heartbeat
        if hb is not None and hb.running:
            hb.offer(self.diagnostics())
            self.counters["published"] += 1
        else:
            self.publish(DIAGNOSTICS_TOPIC, self.diagnostics())

    # ------------------------------------------------------------------ loop

    def _read_available(self, max_batch: int = 1000) -> None:
        """Move queued socket messages into the node queue without blocking."""
        assert self._sub is not None
        reliable_room = min(
            (s.queue_size for s in self._subs.values() if s.reliable), default=max_batch
        )
        n = 0
        while n < max_batch and len(self._queue) < reliable_room:
            frames = self._sub.recv_frames()  # zero-copy arrays, cheaper than recv_multipart
            if frames is None:
                return
            n += 1
            env = self._sub.decode_frames(frames)
            if env is None:
                continue
            sub = self._subs.get(env.topic)
            if sub is None:
                continue
            if sub.msg_type is not None and not isinstance(env.msg, sub.msg_type):
                st = self._sub.stats[env.topic]
                st.malformed += 1
                if st.malformed & (st.malformed - 1) == 0:  # 1st, 2nd, 4th, ...: no log flood
                    self.log.warning(
                        "%s: expected %s, got %s (%d such messages so far)",
                        env.topic,
                        sub.msg_type.TYPE,
                        env.msg.TYPE,
                        st.malformed,
                    )
                continue
            sub.pending += 1
            box: list[Any] = [env]
            if not sub.reliable:
                # latest wins, decided on arrival: a superseded image does not wait in the
                # queue behind a reliable backlog (memory bounded under a burst, issue 9)
                if len(sub.waiting) >= sub.queue_size:
                    sub.waiting.popleft()[0] = None
                    self._sub.stats[env.topic].dropped += 1
                sub.waiting.append(box)
            self._queue.append((sub, box))

    def _handle_queue(self) -> None:
        assert self._sub is not None
        while self._queue and not self._stop.is_set():
            sub, box = self._queue.popleft()
            sub.pending -= 1
            env = box[0]
            if not sub.reliable and env is not None:
                sub.waiting.popleft()  # this box: boxes leave the queue in arrival order
            if env is None:  # superseded on arrival (dropped and counted then)
                continue
            if self._replayed and self._seen_in_replay(env):
                continue
            self._dispatch(sub, env)
            if self._sub.socket.poll(0, zmq.POLLIN):
                self._read_available()
            self._run_timers()

    def _run_timers(self) -> None:
        now = time.monotonic()
        for timer in self._timers:
            if now >= timer[1]:
                timer[1] = max(timer[1] + timer[0], now)
                name = getattr(timer[2], "__name__", str(timer[2]))
                self.liveness.start(f"timer {name}")
                try:
                    self._call_counted(f"timer {name}", timer[2])
                finally:
                    self.liveness.done()

    def _call_counted(self, what: str, callback: Callable[[], None]) -> None:
        """Call ``callback``; an error is counted and logged (once per repeat), never raised."""
        try:
            callback()
        except Exception as err:
            self.counters["handler_errors"] += 1
            self.failures.failed(what, err, "failed")

    def spin_once(self, timeout_ms: int = 100) -> None:
        """Wait up to ``timeout_ms`` for input, then handle everything queued and due timers."""
        if self._catch_up is not None:  # journal first; live input waits in the socket
            self._catch_up_step()
            self._run_timers()
            return
        now = time.monotonic()
        if self._timers:
            next_due = min(t[1] for t in self._timers)
            timeout_ms = max(0, min(timeout_ms, int((next_due - now) * 1000)))
        if self._queue:
            timeout_ms = 0
        if self._sub is None and not self._extra:
            if timeout_ms:
                self._stop.wait(timeout_ms / 1000)
        else:
            poller = zmq.Poller()
            if self._sub is not None:
                poller.register(self._sub.socket, zmq.POLLIN)
            for sock in self._extra:
                poller.register(sock, zmq.POLLIN)
            ready = dict(poller.poll(timeout_ms))
            for sock, callback in list(self._extra.items()):
                # zmq reports its own sockets as themselves and anything else by file descriptor
                key = sock if isinstance(sock, zmq.Socket | int) else sock.fileno()
                if key in ready:
                    self._call_counted(f"reader of {sock}", callback)
            if self._sub is not None and (self._queue or self._sub.socket in ready):
                self._read_available()
                self._handle_queue()
        self._run_timers()

    # ------------------------------------------------------------------ extension points

    @property
    def context(self) -> zmq.Context:
        """The node's ZeroMQ context, for extra sockets (e.g. an input from outside the bus)."""
        return self._ctx

    @property
    def queue_depth(self) -> int:
        """Messages received but not yet handled."""
        return len(self._queue)

    def add_reader(self, socket_or_fd: Any, callback: Callable[[], None]) -> None:
        """Call ``callback()`` from the run loop whenever ``socket_or_fd`` (a zmq socket or a
        file descriptor / object with ``fileno()``) is readable; the loop still blocks in one poll."""
        self._extra[socket_or_fd] = callback

    def remove_reader(self, socket_or_fd: Any) -> None:
        self._extra.pop(socket_or_fd, None)

    def publish_frames(self, frames: list[Any]) -> None:
        """Forward already-encoded multipart frames unchanged (bit-exact replay of recordings)."""
        self._pub.publish_frames(frames)
        self.counters["published"] += 1

    def run(self, *, install_signal_handlers: bool = True, duration_s: float | None = None) -> int:
        """Run until stopped (signal, ``request_stop``, or ``duration_s``); returns an exit code."""
        if install_signal_handlers and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda *_: self._stop.set())
        end = None if duration_s is None else time.monotonic() + duration_s
        self.log.info("node %s up (pid %d)", self.name, os.getpid())
        if self.diagnostics_period_s > 0 and self._heartbeat is None:
            self._heartbeat = Heartbeat(
                self.bus,
                self._ctx,
                self.diagnostics_period_s,
                self.liveness,
                on_error=lambda err: self.failures.failed("heartbeat", err, "failed"),
            )
            self._heartbeat.start()
            self.publish_diagnostics()  # the first heartbeat: subscriptions are in place
        try:
            while not self._stop.is_set():
                self.spin_once(100)
                if end is not None and time.monotonic() >= end:
                    break
        finally:
            self.close()
        return 0

    def close(self) -> None:
        """Teardown, final diagnostics, then close sockets (flushing outgoing messages)."""
        try:
            self.teardown()
        except Exception:
            self.log.exception("teardown failed")
        hb, self._heartbeat = self._heartbeat, None
        if hb is not None:
            hb.stop()
        try:
            if self.diagnostics_period_s > 0:  # the last heartbeat says the node has stopped
                final = self.diagnostics(status="stopped")
                if hb is not None:
                    hb.send_final(final)
                else:
                    self.publish(DIAGNOSTICS_TOPIC, final)
        except Exception:  # pragma: no cover
            self.log.exception("final diagnostics failed")
        if hb is not None:
            hb.close()
        if self._sub is not None:
            self._sub.close()
        self._pub.close()
        if self._own_ctx:
            self._ctx.term()
        self.log.info("node %s down: %s", self.name, {k: v for k, v in self.counters.items() if v})
