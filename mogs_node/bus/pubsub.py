"""Publisher and subscriber: per-topic sequence numbers, gap counting, shared-memory payloads."""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

import zmq

from mogs_node import msgs, shm
from mogs_node.bus.config import BusConfig, _apply_client_curve
from mogs_node.errors import BusError, ConfigError, MessageError
from mogs_node.msgs import codec as msgs_codec

log = logging.getLogger(__name__)
_SNDMORE = zmq.SNDMORE


def _connect_client(sock: zmq.Socket, config: BusConfig, endpoint: str, what: str) -> None:
    """Connect a client socket to the broker at ``endpoint``, with CURVE when the bus has it."""
    _apply_client_curve(sock, config.curve, endpoint)
    try:
        sock.connect(endpoint)
    except zmq.ZMQError as err:
        raise BusError(f"cannot connect {what} to {endpoint}: {err}") from err


_T = TypeVar("_T")


def queued(recv: Callable[[int], _T], limit: int | None = None) -> Iterator[_T]:
    """What a socket's ``recv`` (or ``recv_multipart``) has queued now, without waiting: one
    item per call with ``zmq.NOBLOCK`` until ``zmq.Again`` (or ``limit`` items), so that one
    poll's worth of work never blocks the run loop."""
    n = 0
    while limit is None or n < limit:
        try:
            item = recv(zmq.NOBLOCK)
        except zmq.Again:
            return
        n += 1
        yield item


class Publisher:
    """Publishes typed messages on topics; stamps per-topic sequence numbers.

    Arrays are sent zero-copy: do not modify an array after publishing it.
    """

    def __init__(
        self, config: BusConfig, *, context: zmq.Context | None = None, hwm: int | None = None
    ) -> None:
        self._ctx = context or zmq.Context.instance()
        self.config = config
        self.src = random.getrandbits(62) or 1  # session id: seq restart detection at subscribers
        self._seq: dict[str, int] = {}
        self.published: dict[str, int] = {}
        self.published_bytes = 0
        self._subscribed: set[bytes] = set()
        self._sock = self._ctx.socket(zmq.XPUB)
        self._sock.sndhwm = config.reliable_hwm if hwm is None else hwm
        self._sock.linger = config.linger_ms
        if config.socket_buffer_bytes:
            self._sock.sndbuf = config.socket_buffer_bytes
        _connect_client(self._sock, config, config.pub_endpoint, "publisher")
        self._shm_min = config.shm_min_bytes if config.uses_shm else 0
        self._rings: dict[str, shm.ShmRing] = {}
        self.shm_published = 0  # messages whose arrays went through shared memory

    def publish(self, topic: str, msg: msgs.Message) -> int:
        """Send ``msg`` on ``topic``; returns its sequence number."""
        seq = self._seq.get(topic, 0)
        frames = msgs.encode(topic, msg, seq=seq, src=self.src)
        self._seq[topic] = seq + 1
        n = len(frames)
        nbytes = len(frames[0]) + len(frames[1])
        if n > 2 and self._shm_min:
            sent = self._send_via_shm(topic, frames, self.src, seq)
            if sent:
                self.published[topic] = self.published.get(topic, 0) + 1
                self.published_bytes += sent
                return seq
        # frame by frame rather than send_multipart (which re-checks every frame in Python):
        # topic and header are small bytes, copied; array buffers go zero-copy (pyzmq still
        # copies those under its copy threshold, where a copy is cheaper than tracking)
        send = self._sock.send
        send(frames[0], _SNDMORE)
        if n == 2:
            send(frames[1])
        else:
            send(frames[1], _SNDMORE)
            for i in range(2, n):
                f = frames[i]
                nbytes += f.nbytes
                send(f, 0 if i == n - 1 else _SNDMORE, copy=False)
        self.published[topic] = self.published.get(topic, 0) + 1
        self.published_bytes += nbytes
        return seq

    def publish_frames(self, frames: list[Any]) -> None:
        """Forward already-encoded frames (bag replay of recorded bus traffic, fuzzing).

        A subscriber receives them byte for byte, also where large arrays go through shared
        memory on the way.
        """
        if len(frames) > 2 and self._shm_min:
            try:
                topic = _frame_to_bytes(frames[0]).decode("utf-8")
                src_seq = msgs_codec.header_src_seq(_frame_to_bytes(frames[1]))
            except Exception:  # not of our codec's form: it goes as it is
                topic, src_seq = None, None
            if (
                topic is not None
                and src_seq is not None
                and self._send_via_shm(topic, frames, *src_seq)
            ):
                return
        self._sock.send_multipart(frames, copy=False)

    def _send_via_shm(self, topic: str, frames: list[Any], src: int, seq: int) -> int:
        """Send ``[topic, header + reference]`` with the arrays in this topic's shared-memory
        ring (mogs_node/shm.py); returns the message's bytes, or 0 where it must go inline
        (small arrays, a header not of our codec's form, no shared memory to be had)."""
        header = frames[1] if type(frames[1]) is bytes else _frame_to_bytes(frames[1])
        if not msgs_codec.is_inline_header(header):
            return 0
        buffers = [f.buffer if isinstance(f, zmq.Frame) else f for f in frames[2:]]
        sizes = [memoryview(b).nbytes for b in buffers]
        total = sum(sizes)
        if total < self._shm_min:
            return 0
        ring = self._rings.get(topic)
        if ring is None:
            ring = self._rings[topic] = shm.ShmRing(
                topic, self.src, self.config.shm_ring_bytes, bus=self.config.sub_endpoint
            )
        ref = ring.write(buffers, total, src, seq)
        if ref is None:
            if ring.failed and ring.failed & (ring.failed - 1) == 0:
                log.warning(
                    "%s: shared memory unavailable (%d times), sending inline: %s",
                    topic,
                    ring.failed,
                    ring.last_error,
                )
            return 0
        header = msgs_codec.add_shm_ref(header, ref[0], ref[1], sizes)
        self._sock.send(frames[0], _SNDMORE)
        self._sock.send(header)
        self.shm_published += 1
        return len(frames[0]) + len(frames[1]) + total

    def _drain_subscriptions(self) -> None:
        for ev in queued(self._sock.recv):
            if ev and ev[0] == 1:
                self._subscribed.add(ev[1:])

    def has_subscriber(self, topic: str) -> bool:
        """Whether some subscriber's filter matches ``topic`` (as seen through the broker)."""
        self._drain_subscriptions()
        t = topic.encode()
        return any(t.startswith(prefix) for prefix in self._subscribed)

    def wait_for_subscriber(self, topic: str, timeout_s: float = 5.0) -> bool:
        """Block until a subscription matching ``topic`` has reached this publisher."""
        deadline = time.monotonic() + timeout_s
        while not self.has_subscriber(topic):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            self._sock.poll(min(100, int(remaining * 1000) + 1), zmq.POLLIN)
        return True

    def shm_counters(self) -> dict[str, dict[str, int]]:
        """Per topic: messages sent through shared memory, and sent inline because no
        subscriber of the topic reads slots on this host (unseen), the next slot was still owed
        to a subscriber (busy) or no slot could be made (failed)."""
        return {
            topic: {
                "shm_published": r.ticket,
                "shm_unseen": r.unseen,
                "shm_busy": r.busy,
                "shm_failed": r.failed,
            }
            for topic, r in self._rings.items()
        }

    def close(self, linger_ms: int | None = None) -> None:
        self._sock.close(linger=self.config.linger_ms if linger_ms is None else linger_ms)
        for ring in self._rings.values():
            ring.close()
        self._rings.clear()


@dataclass
class TopicStats:
    """Receive-side counters of one topic."""

    received: int = 0
    received_bytes: int = 0
    gaps: int = 0  # gap events
    lost: int = 0  # messages missing between received sequence numbers
    reordered: int = 0  # sequence number not after the last one of the same publisher session
    dropped: int = 0  # dropped on purpose by a best-effort queue (latest wins)
    malformed: int = 0
    missed_before_join: int = 0  # first seq seen from a publisher session: what it sent earlier
    shm_received: int = 0  # messages whose arrays came through shared memory
    shm_missed: int = 0  # shared-memory payloads gone before read (also in ``lost`` once known)
    last_seq: dict[int, int] = field(default_factory=dict)  # src -> last seq

    def as_dict(self) -> dict[str, int]:
        return {
            "received": self.received,
            "received_bytes": self.received_bytes,
            "gaps": self.gaps,
            "lost": self.lost,
            "reordered": self.reordered,
            "dropped": self.dropped,
            "malformed": self.malformed,
            "missed_before_join": self.missed_before_join,
            "shm_received": self.shm_received,
            "shm_missed": self.shm_missed,
        }


class Subscriber:
    """Receives and decodes messages of exact topics, with gap detection per publisher session."""

    def __init__(
        self,
        config: BusConfig,
        *,
        context: zmq.Context | None = None,
        hwm: int | None = None,
    ) -> None:
        self._ctx = context or zmq.Context.instance()
        self.config = config
        self._sock = self._ctx.socket(zmq.SUB)
        self._sock.rcvhwm = config.reliable_hwm if hwm is None else hwm
        self._sock.linger = 0
        if config.socket_buffer_bytes:
            self._sock.rcvbuf = config.socket_buffer_bytes
        _connect_client(self._sock, config, config.sub_endpoint, "subscriber")
        self.topics: dict[str, bool] = {}  # topic -> reliable
        self.stats: dict[str, TopicStats] = {}
        self.malformed = 0  # frames that could not be attributed to a subscribed topic
        self.last_error: str = ""
        self.all_topics = False
        self._max_bytes = config.max_message_bytes
        self._topic_names: dict[bytes, str] = {}  # subscribed topic names as they arrive
        self._poller = zmq.Poller()  # one poller: Socket.poll would build a new one per call
        self._poller.register(self._sock, zmq.POLLIN)
        self._shm: shm.ShmReader | None = None  # made at the first shared-memory payload
        # what this subscriber takes and has taken, for publishers' shared-memory rings
        self._cursor: shm.ShmCursor | None = None
        if config.uses_shm:
            try:
                self._cursor = shm.ShmCursor(bus=config.sub_endpoint)
            except OSError as err:  # e.g. /dev/shm full: still reads slots, only not waited for
                log.warning("no shared-memory cursor (%s): large messages may be missed", err)
        self._topic_keys: dict[str, int] = {}

    @property
    def socket(self) -> zmq.Socket:
        return self._sock

    def subscribe(self, topic: str, *, reliable: bool = True) -> None:
        """Receive ``topic`` (exact name; ``"/"`` alone means every topic, for tools)."""
        if not topic.startswith("/") or len(topic) > msgs.MAX_TOPIC_CHARS:
            raise ConfigError(
                f"topic {topic[:64]!r} must start with '/' and have at most "
                f"{msgs.MAX_TOPIC_CHARS} characters"
            )
        if self._cursor is not None:  # before the subscription: no message can come earlier
            self._cursor.add_topic(topic)
        self.topics[topic] = reliable
        self._topic_names[topic.encode()] = topic
        if topic == "/":
            self.all_topics = True
        self._sock.setsockopt(zmq.SUBSCRIBE, topic.encode())

    def _stats(self, topic: str) -> TopicStats:
        st = self.stats.get(topic)
        if st is None:
            st = self.stats[topic] = TopicStats()
        return st

    def recv_frames(self) -> list[Any] | None:
        """One multipart message from the socket without waiting (None if none is queued).

        Topic and header frames are small and come as ``bytes`` (what ``msgs.decode`` reads
        fastest); array frames come zero-copy as ``zmq.Frame``.
        ZeroMQ delivers multipart messages atomically, so once the first frame is here, all are.
        Arrays that came through shared memory are copied out here (as ``memoryview`` frames):
        what this returns is the message as it would have travelled inline.
        """
        sock = self._sock
        while True:
            try:
                first = sock.recv(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return None
            # Frame.more is a plain read; getsockopt(RCVMORE) would build an enum per call
            frames: list[Any] = [first.bytes]
            if first.more:
                header = sock.recv(copy=False)
                frames.append(header.bytes)
                more = header.more
                while more:
                    frame = sock.recv(copy=False)
                    frames.append(frame)
                    more = frame.more
                if len(frames) == 2 and msgs_codec.has_shm_ref(frames[1]):
                    resolved = self._resolve_shm(frames[0], frames[1])
                    if resolved is None:
                        continue  # counted; take the next queued message
                    return resolved
            return frames

    def _topic_of(self, topic_bytes: bytes) -> str | None:
        """The name under which ``topic_bytes`` is counted here (None: not one of ours)."""
        topic = self._topic_names.get(topic_bytes)
        if topic is None and self.all_topics:
            topic = topic_bytes.decode("utf-8", errors="replace")
        return topic

    def _resolve_shm(self, topic_bytes: bytes, header: bytes) -> list[Any] | None:
        """``[topic, header, *buffers]`` of a message whose arrays are in shared memory; None
        where the reference is malformed or the payload is gone (both counted on the topic)."""
        topic = self._topic_of(topic_bytes)
        if topic is None:
            return None  # a prefix match of another topic: not ours, as in decode_frames
        st = self.stats.get(topic) or self._stats(topic)
        try:
            inline, name, ticket, sizes, src, seq = msgs_codec.take_shm_ref(header, self._max_bytes)
        except MessageError as err:  # a malformed reference
            st.malformed += 1
            self.last_error = f"{topic}: {err}"
            return None
        if self._shm is None:
            self._shm = shm.ShmReader()
        try:
            buffers = self._shm.read(name, ticket, sizes)
        except shm.ShmPayloadError as err:
            # not received: the next message of this publisher shows the gap and counts it lost
            st.shm_missed += 1
            if src not in st.last_seq:
                st.missed_before_join += seq
                st.last_seq[src] = seq - 1
            self.last_error = f"{topic}: {err}"
            if st.shm_missed & (st.shm_missed - 1) == 0:
                log.warning("%s: %d shared-memory payload(s) missed: %s", topic, st.shm_missed, err)
            return None
        st.shm_received += 1
        return [topic_bytes, inline, *buffers]

    def arrivals(
        self, alive: Callable[[], bool], timeout_ms: int = 100
    ) -> Iterator[tuple[float, msgs.Envelope | None]]:
        """``(monotonic time, message or None)`` after each :meth:`receive` while ``alive()``
        (a run's thread): a watcher stamps each message as it arrives and, between messages
        (None after ``timeout_ms``), samples what it watches."""
        while alive():
            env = self.receive(timeout_ms=timeout_ms)
            yield time.monotonic(), env

    def receive(self, timeout_ms: int | None = 0) -> msgs.Envelope | None:
        """The next valid message of a subscribed topic, or None if none arrives in time.

        Malformed messages are counted (per topic when the topic frame is readable) and skipped;
        this never raises for bad input.
        """
        deadline = time.monotonic() + timeout_ms / 1000 if timeout_ms else None
        while True:
            frames = self.recv_frames()  # queued messages are taken without a poll
            if frames is None:
                if timeout_ms == 0:
                    return None
                wait = -1  # no deadline: until something arrives
                if deadline is not None:
                    wait = int((deadline - time.monotonic()) * 1000)
                    if wait <= 0:
                        return None
                if not self._poller.poll(wait):
                    return None
                continue
            env = self.decode_frames(frames)
            if env is not None:
                return env

    def decode_frames(self, frames: list[Any]) -> msgs.Envelope | None:
        """Decode and account one received multipart message (None if it is rejected)."""
        if not frames:
            self.malformed += 1
            return None
        t0 = frames[0]
        topic_bytes = t0 if type(t0) is bytes else _frame_to_bytes(t0)
        topic = known = self._topic_names.get(topic_bytes)  # one of ours: a checked name
        if topic is None:  # not one of ours by exact name: a tool's "/" or a stranger
            try:
                topic = topic_bytes.decode("utf-8")
            except UnicodeDecodeError:
                topic = ""
            if not self.all_topics:
                if any(topic.startswith(t) for t in self.topics):
                    return None  # prefix match of another topic (e.g. /imu_raw for /imu): not ours
                self.malformed += 1
                return None
        st = self.stats.get(topic) or self._stats(topic)
        try:
            env = msgs.decode(frames, max_bytes=self._max_bytes, topic=known)
        except MessageError as err:
            st.malformed += 1
            self.last_error = f"{topic}: {err}"
            log.debug("malformed message on %s: %s", topic, err)
            return None
        _, seq, src, _, nbytes = env
        st.received += 1
        st.received_bytes += nbytes
        if self._cursor is not None and len(frames) > 2:  # a message that may use a ring
            key = self._topic_keys.get(topic)
            if key is None:
                key = self._topic_keys[topic] = shm.topic_key(topic)
            self._cursor.taken(src, key, seq)
        last_seq = st.last_seq
        last = last_seq.get(src)
        if last is not None and seq == last + 1:  # the common case: the next one in order
            last_seq[src] = seq
            return env
        if last is None:
            st.missed_before_join += seq  # published before this subscriber was connected
        elif seq > last + 1:
            st.gaps += 1
            st.lost += seq - last - 1
        else:
            st.reordered += 1
        last_seq[src] = seq if last is None else max(last, seq)
        return env

    def close(self) -> None:
        self._sock.close(linger=0)
        if self._shm is not None:
            self._shm.close()
        if self._cursor is not None:
            self._cursor.close()
            self._cursor = None


def _frame_to_bytes(frame: Any) -> bytes:
    """The bytes of a received frame of any kind (b"" for what is no buffer: then malformed)."""
    try:
        return bytes(memoryview(getattr(frame, "buffer", frame)))
    except TypeError:
        return b""
