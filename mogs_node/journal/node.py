"""Journal node: records the reliable topics to disk and serves them to restarted nodes.

Subscribes (as reliable: large high-water mark, gaps counted) to ``topics`` and appends every
message's raw frames to a :class:`~mogs_node.journal.store.JournalStore` in ``dir``; answers
``keys`` / ``read`` requests (:mod:`mogs_node.journal.protocol`) on a ROUTER socket at
``endpoint`` (default derived from the bus, CURVE server when the bus is). Before answering it
drains its subscriber, so that a reply holds everything that reached the journal until then.

A fresh start replaces the journal file; a restart after a crash (the launcher sets
``MOGS_CATCH_UP=1``) or ``resume: true`` reopens it, ignoring a torn last record.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import zmq
from zmq.auth.thread import ThreadAuthenticator

from mogs_node import msgs
from mogs_node.bus import Subscriber, queued
from mogs_node.bus.config import _check_bind_address, _load_secret
from mogs_node.errors import BusError, ConfigError
from mogs_node.journal.protocol import handle_request, journal_endpoint
from mogs_node.journal.store import JournalStore
from mogs_node.node import CATCH_UP_ENV, Node, message_key

__all__ = ["DEFAULT_TOPICS", "JournalNode", "JournalParams"]

#: every reliable topic of the pipeline plus the camera images (the frontend replays them)
DEFAULT_TOPICS = (
    "/camera/info",
    "/camera/image",
    "/imu",
    "/frontend/odometry",
    "/frontend/keyframe",
    "/seg/masks",
    "/prior/depth",
    "/metrizer/depth",
    "/mapper/stats",
    "/groundtruth/pose",
    "/groundtruth/depth",
)


@dataclass(frozen=True)
class JournalParams:
    """Parameters of the journal node."""

    dir: str = "runs/latest/journal"  # folder of the journal file (the run's folder)
    topics: tuple[str, ...] = DEFAULT_TOPICS  # recorded topics
    max_bytes: int = 8 << 30  # size bound of the journal file; beyond, messages are refused
    fsync: bool = False  # fsync every record (survives power loss, not just a process crash)
    endpoint: str = ""  # request endpoint ("" = derived from the bus, see protocol)
    resume: bool = False  # reopen an existing journal instead of starting a fresh one
    allow_remote: bool = False  # listen on a non-loopback tcp address (multi-host, with CURVE)
    drain_batch: int = 2000  # messages stored per loop turn at most

    def __post_init__(self) -> None:
        if not self.topics or not all(t.startswith("/") for t in self.topics):
            raise ConfigError(f"journal.topics: expected topic names, got {self.topics!r}")
        if self.max_bytes <= 0 or self.drain_batch < 1:
            raise ConfigError("journal: max_bytes > 0 and drain_batch >= 1")


class JournalNode(Node):
    """See the module docstring."""

    Params = JournalParams

    def setup(self) -> None:
        p: JournalParams = self.params
        reopen = p.resume or os.environ.get(CATCH_UP_ENV) == "1"
        self.store = JournalStore(
            Path(p.dir) / "journal.log", max_bytes=p.max_bytes, fresh=not reopen, fsync=p.fsync
        )
        if reopen:
            self.log.info(
                "journal reopened: %d records (%d torn bytes ignored)",
                len(self.store),
                self.store.torn_bytes,
            )
        self.jsub = Subscriber(self.bus, context=self.context)
        for t in p.topics:
            self.jsub.subscribe(t, reliable=True)
        self.endpoint = p.endpoint or journal_endpoint(self.bus)
        self.router = self.context.socket(zmq.ROUTER)
        self.router.linger = 0
        self._auth: ThreadAuthenticator | None = None
        if self.bus.curve is not None:
            c = self.bus.curve
            if not (c.server_secret_key and c.authorized_keys_dir):
                raise BusError(
                    "journal on a CURVE bus needs server_secret_key and "
                    "authorized_keys_dir (it serves like the broker)"
                )
            self._auth = ThreadAuthenticator(self.context)
            self._auth.start()
            self._auth.configure_curve(domain="*", location=c.authorized_keys_dir)
            public, secret = _load_secret(c.server_secret_key)
            self.router.curve_server = True
            self.router.curve_publickey = public
            self.router.curve_secretkey = secret
        _check_bind_address(self.endpoint, self.params.allow_remote)
        if self.endpoint.startswith("ipc://"):
            Path(self.endpoint[len("ipc://") :]).unlink(missing_ok=True)  # stale socket file
        try:
            self.router.bind(self.endpoint)
        except zmq.ZMQError as err:
            raise BusError(f"journal cannot bind {self.endpoint}: {err}") from err
        for k in (
            "journal_records",
            "journal_bytes",
            "journal_refused",
            "journal_requests",
            "journal_bad_requests",
        ):
            self.counters[k] = 0
        self.add_reader(self.jsub.socket, self.drain)
        self.add_reader(self.router, self.serve)

    def drain(self) -> None:
        """Store what the subscriber has received (raw frames, no re-encoding)."""
        for _ in range(self.params.drain_batch):
            frames = self.jsub.recv_frames()  # shared-memory arrays come inline here
            if frames is None:
                break
            env = self.jsub.decode_frames(frames)  # validates and counts (malformed, gaps)
            if env is None:
                continue
            if not self.store.append(frames, message_key(env.msg)) and self.store.refused == 1:
                self.log.warning(
                    "journal full (%d bytes): refusing new messages", self.store.max_bytes
                )
        self.counters["journal_records"] = len(self.store)
        self.counters["journal_bytes"] = self.store.size
        self.counters["journal_refused"] = self.store.refused

    def serve(self) -> None:
        """Answer the waiting requests (after storing everything received so far)."""
        for frames in queued(self.router.recv_multipart):
            self.drain()
            while self.jsub.socket.poll(0, zmq.POLLIN):
                self.drain()
            self.counters["journal_requests"] += 1
            if len(frames) != 3 or frames[1] != b"":
                self.counters["journal_bad_requests"] += 1
                continue  # not a REQ envelope: nothing sensible to answer
            reply, ok = handle_request(self.store, frames[2])
            if not ok:
                self.counters["journal_bad_requests"] += 1
            self.router.send_multipart([frames[0], b"", *reply], copy=False)

    def topic_stats(self) -> dict[str, dict[str, int]]:
        out = super().topic_stats()
        for topic, st in self.jsub.stats.items():
            out.setdefault(topic, {}).update(st.as_dict())
        return out

    def diagnostics(self, status: str | None = None) -> msgs.Diagnostics:
        d = super().diagnostics(status)
        d.counters["lost"] = float(sum(s.lost for s in self.jsub.stats.values()))
        d.counters["malformed"] = float(
            sum(s.malformed for s in self.jsub.stats.values()) + self.jsub.malformed
        )
        return d

    def teardown(self) -> None:
        self.drain()
        self.jsub.close()
        self.router.close(linger=0)
        if self._auth is not None:
            self._auth.stop()
        self.store.close()
        self.log.info("journal closed: %d records, %d bytes", len(self.store), self.store.size)
