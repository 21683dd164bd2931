"""ZeroMQ transport: broker, publisher, subscriber, security.

Process graph: every publisher connects a socket to the broker's XSUB endpoint, every subscriber
connects a SUB socket to the broker's XPUB endpoint; the broker forwards with ``zmq.proxy`` (C code,
no per-message Python). Publishers use XPUB sockets so that they can see subscriptions arrive
(``Publisher.wait_for_subscriber``) and avoid the PUB/SUB slow-joiner loss at start-up.

Topic policies (DESIGN.md section 5):

- ``reliable`` (keyframes, masks, depth, IMU): large high-water marks; per-topic sequence numbers
  from every publisher session; the subscriber detects gaps and counts every lost message, so
  nothing is lost silently.
- ``best_effort`` (camera images, renders, diagnostics): small high-water marks; the node keeps the
  latest message per topic and counts what it drops.

Security: on tcp endpoints the broker can run as a CURVE server that accepts only client public keys
found in an authorised-keys folder (ZAP via ``zmq.auth``); unauthenticated peers get nothing in or
out. ``generate_keys`` writes key pairs in the ``zmq.auth`` certificate format.
"""

from __future__ import annotations

import logging
import os
import random
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import msgpack
import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from mogs_node import msgs, shm
from mogs_node.errors import BusError, ConfigError, MessageError

__all__ = [
    "BusConfig",
    "CurveConfig",
    "Publisher",
    "Subscriber",
    "TopicStats",
    "default_bus_config",
    "generate_keys",
    "run_broker",
    "tune_malloc_for_large_messages",
]

log = logging.getLogger(__name__)
_SNDMORE = zmq.SNDMORE
# Shared-memory references (mogs_node/shm.py) ride in the header as a seventh, last entry "m":
# the header's first byte (a msgpack map of 6 or of 7 entries) tells the two forms apart.
_HEADER_MAP6, _HEADER_MAP7 = b"\x86", b"\x87"
_SHM_KEY = msgpack.packb("m")
_packb = msgpack.packb


@dataclass(frozen=True)
class CurveConfig:
    """CURVE key files (``zmq.auth`` certificate format) for tcp endpoints."""

    server_public_key: str  # broker's public certificate (clients need it)
    client_secret_key: str = ""  # this client's secret certificate (nodes, tools)
    server_secret_key: str = ""  # broker only
    authorized_keys_dir: str = ""  # broker only: folder of accepted client public certificates

    @staticmethod
    def from_dict(d: dict[str, Any], base_dir: Path | None = None) -> CurveConfig:
        def p(key: str) -> str:
            v = d.get(key, "")
            if not v:
                return ""
            path = Path(v).expanduser()
            if base_dir is not None and not path.is_absolute():
                path = base_dir / path
            return str(path)

        unknown = set(d) - {
            "server_public_key",
            "client_secret_key",
            "server_secret_key",
            "authorized_keys_dir",
        }
        if unknown:
            raise ConfigError(f"bus.curve: unknown key(s) {sorted(unknown)}")
        if not d.get("server_public_key"):
            raise ConfigError("bus.curve.server_public_key is required")
        return CurveConfig(
            server_public_key=p("server_public_key"),
            client_secret_key=p("client_secret_key"),
            server_secret_key=p("server_secret_key"),
            authorized_keys_dir=p("authorized_keys_dir"),
        )


@dataclass(frozen=True)
class BusConfig:
    """Where the broker is and how sockets behave."""

    pub_endpoint: str  # broker binds XSUB here; publishers connect
    sub_endpoint: str  # broker binds XPUB here; subscribers connect
    reliable_hwm: int = 100_000  # high-water mark (messages) of reliable topics
    best_effort_hwm: int = 10  # high-water mark of best-effort sockets
    max_message_bytes: int = msgs.DEFAULT_MAX_MESSAGE_BYTES
    linger_ms: int = 2000  # how long closing sockets keep flushing queued messages
    # kernel socket buffers (SO_SNDBUF of senders, SO_RCVBUF of receivers, broker included);
    # 0 = the OS default. Capped by net.core.wmem_max / rmem_max. See docs/architecture.md.
    socket_buffer_bytes: int = 0
    # messages with at least this many bytes of arrays go through shared memory, not the broker,
    # when every peer is on this host (ipc:// endpoints, no CURVE); 0 = never (mogs_node/shm.py)
    shm_min_bytes: int = 256 * 1024
    shm_ring_bytes: int = 32 << 20  # shared memory per publisher and topic (a bounded history)
    curve: CurveConfig | None = None

    @property
    def uses_shm(self) -> bool:
        """Whether large payloads bypass the broker through ``/dev/shm`` on this bus."""
        return (
            self.shm_min_bytes > 0
            and self.curve is None
            and self.pub_endpoint.startswith("ipc://")
            and self.sub_endpoint.startswith("ipc://")
            and shm.shm_available()
        )

    def to_dict(self) -> dict[str, Any]:
        d = {
            k: getattr(self, k)
            for k in (
                "pub_endpoint",
                "sub_endpoint",
                "reliable_hwm",
                "best_effort_hwm",
                "max_message_bytes",
                "linger_ms",
                "socket_buffer_bytes",
                "shm_min_bytes",
                "shm_ring_bytes",
            )
        }
        if self.curve is not None:
            d["curve"] = {
                k: getattr(self.curve, k)
                for k in (
                    "server_public_key",
                    "client_secret_key",
                    "server_secret_key",
                    "authorized_keys_dir",
                )
            }
        return d

    @staticmethod
    def from_dict(d: dict[str, Any], base_dir: Path | None = None) -> BusConfig:
        allowed = {
            "pub_endpoint",
            "sub_endpoint",
            "reliable_hwm",
            "best_effort_hwm",
            "max_message_bytes",
            "linger_ms",
            "socket_buffer_bytes",
            "shm_min_bytes",
            "shm_ring_bytes",
            "curve",
        }
        unknown = set(d) - allowed
        if unknown:
            raise ConfigError(f"bus: unknown key(s) {sorted(unknown)}; allowed {sorted(allowed)}")
        for key in ("pub_endpoint", "sub_endpoint"):
            v = d.get(key)
            if not isinstance(v, str) or not v.startswith(("tcp://", "ipc://", "inproc://")):
                raise ConfigError(
                    f"bus.{key}: expected a tcp://, ipc:// or inproc:// endpoint, got {v!r}"
                )
        kwargs: dict[str, Any] = {
            "pub_endpoint": d["pub_endpoint"],
            "sub_endpoint": d["sub_endpoint"],
        }
        for key in (
            "reliable_hwm",
            "best_effort_hwm",
            "max_message_bytes",
            "linger_ms",
            "socket_buffer_bytes",
            "shm_min_bytes",
            "shm_ring_bytes",
        ):
            if key in d:
                v = d[key]
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise ConfigError(f"bus.{key}: expected a non-negative int, got {v!r}")
                kwargs[key] = v
        if d.get("curve"):
            kwargs["curve"] = CurveConfig.from_dict(d["curve"], base_dir)
        return BusConfig(**kwargs)


def tune_malloc_for_large_messages(threshold_bytes: int = 64 << 20) -> bool:
    """Serve large message buffers from the heap instead of fresh ``mmap`` pages (glibc only).

    ZeroMQ allocates one buffer per received message; above glibc's mmap threshold each one is a
    new mapping, zero-filled page by page and unmapped after use. For megabyte keyframes that page
    faulting, not copying, bounds throughput: the broker forwarded ~0.8k 1.5 MB messages/s with
    the default and ~1.2k/s with this (bench/bus_throughput.py). Called once at process start by
    ``mogs broker`` and ``mogs node``. Returns False where mallopt is unavailable.
    """
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    ok = libc.mallopt(m_mmap_threshold, min(threshold_bytes, 32 << 20)) == 1
    ok &= libc.mallopt(m_trim_threshold, 2 * threshold_bytes) == 1
    return bool(ok)


def default_bus_config(name: str = "default") -> BusConfig:
    """ipc endpoints in a per-user runtime folder; ``MOGS_BUS_DIR`` overrides the folder."""
    base = Path(os.environ.get("MOGS_BUS_DIR") or f"/tmp/mogs-{os.getuid()}")
    base.mkdir(mode=0o700, parents=True, exist_ok=True)
    return BusConfig(
        pub_endpoint=f"ipc://{base}/{name}-pub.ipc", sub_endpoint=f"ipc://{base}/{name}-sub.ipc"
    )


def generate_keys(
    keys_dir: str | Path, names: Iterable[str] = ("broker", "client")
) -> dict[str, Path]:
    """Write a CURVE key pair per name into ``keys_dir`` (``NAME.key``, ``NAME.key_secret``).

    Client public keys are also copied into ``keys_dir/authorized`` (the broker's accept list).
    """
    d = Path(keys_dir)
    d.mkdir(parents=True, exist_ok=True)
    auth = d / "authorized"
    auth.mkdir(exist_ok=True)
    out = {}
    for name in names:
        public, secret = zmq.auth.create_certificates(str(d), name)
        os.chmod(secret, 0o600)
        out[name] = Path(secret)
        if name != "broker":
            (auth / Path(public).name).write_bytes(Path(public).read_bytes())
    return out


def _load_secret(path: str) -> tuple[bytes, bytes]:
    try:
        public, secret = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as err:
        raise BusError(f"cannot read CURVE key {path}: {err}") from err
    if secret is None:
        raise BusError(f"{path} holds no secret key")
    return public, secret


def _load_public(path: str) -> bytes:
    try:
        public, _ = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as err:
        raise BusError(f"cannot read CURVE key {path}: {err}") from err
    return public


def _apply_client_curve(sock: zmq.Socket, curve: CurveConfig | None, endpoint: str) -> None:
    if curve is None:
        return
    if not curve.client_secret_key:
        raise BusError("bus.curve.client_secret_key is required for a client on a CURVE bus")
    public, secret = _load_secret(curve.client_secret_key)
    sock.curve_publickey = public
    sock.curve_secretkey = secret
    sock.curve_serverkey = _load_public(curve.server_public_key)


def _check_bind_address(endpoint: str, allow_remote: bool) -> None:
    """Refuse to listen on a non-loopback tcp address unless configured to (DESIGN.md section 5)."""
    if not endpoint.startswith("tcp://"):
        return
    host = endpoint[len("tcp://") :].rsplit(":", 1)[0].strip("[]")
    if host in ("127.0.0.1", "localhost", "::1") or host.startswith("127."):
        return
    if not allow_remote:
        raise BusError(
            f"refusing to listen on non-loopback address {endpoint}; pass allow_remote (launch file "
            "`bus.allow_remote: true`, with CURVE keys) to expose the bus"
        )


# ---------------------------------------------------------------------------------------- broker


def run_broker(
    config: BusConfig,
    stop: threading.Event,
    *,
    allow_remote: bool = False,
    ready: threading.Event | None = None,
    context: zmq.Context | None = None,
) -> None:
    """Forward messages between publishers and subscribers until ``stop`` is set.

    The forwarding itself is ``zmq.proxy_steerable`` in a thread; this function waits for ``stop``
    and then terminates the proxy through its control socket.
    """
    # Two I/O threads: reading from publishers and writing to subscribers overlap; measured
    # 0.85k -> 1.2k forwarded 1.5 MB messages/s on 2 cores (bench/bus_throughput.py).
    ctx = context or zmq.Context(io_threads=2)
    auth: ThreadAuthenticator | None = None
    xsub = ctx.socket(zmq.XSUB)
    xpub = ctx.socket(zmq.XPUB)
    ctl_addr = f"inproc://mogs-broker-ctl-{os.getpid()}-{random.getrandbits(32)}"
    ctl_back = ctx.socket(zmq.PAIR)
    ctl_back.bind(ctl_addr)
    ctl_front = ctx.socket(zmq.PAIR)
    ctl_front.connect(ctl_addr)
    try:
        if config.curve is not None:
            if not (config.curve.server_secret_key and config.curve.authorized_keys_dir):
                raise BusError(
                    "broker on a CURVE bus needs server_secret_key and authorized_keys_dir"
                )
            auth = ThreadAuthenticator(ctx)
            auth.start()
            auth.configure_curve(domain="*", location=config.curve.authorized_keys_dir)
            public, secret = _load_secret(config.curve.server_secret_key)
            for s in (xsub, xpub):
                s.curve_server = True
                s.curve_publickey = public
                s.curve_secretkey = secret
        # The broker's queues are per peer: give reliable traffic room; subscribers set their own.
        xpub.sndhwm = config.reliable_hwm
        xsub.rcvhwm = config.reliable_hwm
        if config.socket_buffer_bytes:
            xsub.rcvbuf = xpub.sndbuf = config.socket_buffer_bytes
        for s, ep in ((xsub, config.pub_endpoint), (xpub, config.sub_endpoint)):
            _check_bind_address(ep, allow_remote)
            try:
                s.bind(ep)
            except zmq.ZMQError as err:
                raise BusError(f"broker cannot bind {ep}: {err}") from err
        log.info(
            "broker up: publishers -> %s, subscribers <- %s%s",
            config.pub_endpoint,
            config.sub_endpoint,
            " (CURVE)" if config.curve else "",
        )
        proxy = threading.Thread(
            target=_proxy_thread, args=(xsub, xpub, ctl_back), name="mogs-proxy", daemon=True
        )
        proxy.start()
        if ready is not None:
            ready.set()
        while not stop.wait(0.1):
            if not proxy.is_alive():
                raise BusError("broker proxy thread stopped unexpectedly")
        ctl_front.send(b"TERMINATE")
        proxy.join(timeout=2.0)
    finally:
        for s in (xsub, xpub, ctl_back, ctl_front):
            s.close(linger=0)
        if auth is not None:
            auth.stop()
        if context is None:
            ctx.term()


def _proxy_thread(xsub: zmq.Socket, xpub: zmq.Socket, control: zmq.Socket) -> None:
    try:
        zmq.proxy_steerable(xsub, xpub, None, control)
    except zmq.ContextTerminated:
        pass
    except zmq.ZMQError as err:  # pragma: no cover - logged, the broker loop notices
        log.error("proxy stopped: %s", err)


# ---------------------------------------------------------------------------------------- pub


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
        _apply_client_curve(self._sock, config.curve, config.pub_endpoint)
        try:
            self._sock.connect(config.pub_endpoint)
        except zmq.ZMQError as err:
            raise BusError(f"cannot connect publisher to {config.pub_endpoint}: {err}") from err
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
                header = msgpack.unpackb(_frame_to_bytes(frames[1]), max_bin_len=0)
                src, seq = header["src"], header["seq"]
            except Exception:  # not of our codec's form: it goes as it is
                src = seq = None
            if (
                type(src) is int
                and type(seq) is int
                and self._send_via_shm(topic, frames, src, seq)
            ):
                return
        self._sock.send_multipart(frames, copy=False)

    def _send_via_shm(self, topic: str, frames: list[Any], src: int, seq: int) -> int:
        """Send ``[topic, header + reference]`` with the arrays in this topic's shared-memory
        ring (mogs_node/shm.py); returns the message's bytes, or 0 where it must go inline
        (small arrays, a header not of our codec's form, no shared memory to be had)."""
        header = frames[1] if type(frames[1]) is bytes else _frame_to_bytes(frames[1])
        if header[:1] != _HEADER_MAP6:
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
        header = _HEADER_MAP7 + header[1:] + _SHM_KEY + _packb([ref[0], ref[1], sizes])
        self._sock.send(frames[0], _SNDMORE)
        self._sock.send(header)
        self.shm_published += 1
        return len(frames[0]) + len(frames[1]) + total

    def _drain_subscriptions(self) -> None:
        while True:
            try:
                ev = self._sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                return
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


# ---------------------------------------------------------------------------------------- sub


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
        _apply_client_curve(self._sock, config.curve, config.sub_endpoint)
        try:
            self._sock.connect(config.sub_endpoint)
        except zmq.ZMQError as err:
            raise BusError(f"cannot connect subscriber to {config.sub_endpoint}: {err}") from err
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
                if len(frames) == 2 and frames[1][:1] == _HEADER_MAP7:
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
            fields = msgpack.unpackb(
                header, max_bin_len=0, max_ext_len=0, max_array_len=4096, max_map_len=64
            )
            name, ticket, sizes = fields["m"]
            seq, src = fields["seq"], fields["src"]
            if not (
                type(name) is str
                and type(ticket) is int
                and type(sizes) is list
                and all(type(n) is int and n >= 0 for n in sizes)
                and type(seq) is int
                and type(src) is int
            ):
                raise MessageError("malformed shared-memory reference", field="m")
            tail = _SHM_KEY + _packb([name, ticket, sizes])
            if not header.endswith(tail):
                raise MessageError("the shared-memory reference is not the header's last entry")
            if sum(sizes) > self._max_bytes:
                raise MessageError(
                    f"message of {sum(sizes)} bytes exceeds the limit of {self._max_bytes}",
                    field="size",
                )
        except Exception as err:  # msgpack raises several unrelated types on garbage
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
        return [topic_bytes, _HEADER_MAP6 + header[1 : -len(tail)], *buffers]

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


def with_endpoints(config: BusConfig, pub_endpoint: str, sub_endpoint: str) -> BusConfig:
    """A copy of ``config`` with other endpoints."""
    return replace(config, pub_endpoint=pub_endpoint, sub_endpoint=sub_endpoint)
