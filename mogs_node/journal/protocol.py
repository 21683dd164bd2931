"""The journal's request/reply protocol: endpoint, server-side handler (pure) and client.

A restarted node asks the journal (a ZeroMQ ROUTER; the client is a REQ socket, CURVE when the bus
is) two questions, each one msgpack map in one frame:

- ``{"op": "keys", "topics": [...]}`` -> ``[{"keys": {topic: [key, ...]}, "n": records}]``:
  which outputs exist already (keyframe ids, or stamps for topics without one);
- ``{"op": "read", "topics": [...], "start": i, "max_records": n, "max_bytes": b}`` ->
  ``[{"next": j, "counts": [frames per message]}, frames...]``: the stored messages of
  ``topics`` from record ``i`` on, unchanged, and where to continue (``next == n`` at the end).

Bad requests get ``{"error": "..."}``; the server never dies of one.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Sequence
from typing import Any

import msgpack
import zmq

from mogs_node.bus.config import BusConfig, _apply_client_curve
from mogs_node.errors import BusError
from mogs_node.journal.store import JournalStore

__all__ = ["JournalClient", "handle_request", "journal_endpoint"]

ENDPOINT_ENV = "MOGS_JOURNAL_ENDPOINT"
MAX_REQUEST_BYTES = 64 << 10


def journal_endpoint(bus: BusConfig) -> str:
    """Where the journal of this bus listens: beside the broker's subscriber endpoint.

    ipc ``.../NAME-sub.ipc`` -> ``.../NAME-journal.ipc``; inproc ``X`` -> ``X-journal``; tcp: the
    same host, one port above the broker's higher port. ``MOGS_JOURNAL_ENDPOINT`` overrides.
    """
    env = os.environ.get(ENDPOINT_ENV)
    if env:
        return env
    sub = bus.sub_endpoint
    if sub.startswith("tcp://"):
        ports = [
            int(m.group(1)) for e in (bus.pub_endpoint, sub) if (m := re.search(r":(\d+)$", e))
        ]
        if len(ports) != 2:
            raise BusError(f"cannot derive a journal endpoint from {sub!r}: no port")
        host = sub[len("tcp://") :].rsplit(":", 1)[0]
        return f"tcp://{host}:{max(ports) + 1}"
    if sub.startswith("ipc://"):
        base = sub[:-4] if sub.endswith(".ipc") else sub
        base = base[:-4] if base.endswith("-sub") else base
        return f"{base}-journal.ipc"
    return f"{sub}-journal"


def _error(text: str) -> tuple[list[bytes], bool]:
    return [msgpack.packb({"error": text})], False


def handle_request(store: JournalStore, request: bytes) -> tuple[list[bytes], bool]:
    """The reply frames to one request frame (see the module docstring) and whether it was
    valid; never raises on bad input."""
    if len(request) > MAX_REQUEST_BYTES:
        return _error(f"request of {len(request)} bytes exceeds {MAX_REQUEST_BYTES}")
    try:
        req = msgpack.unpackb(request, raw=False, max_bin_len=0, max_ext_len=0)
    except Exception as err:  # msgpack raises several unrelated types on garbage
        return _error(f"request is not msgpack: {type(err).__name__}")
    if not isinstance(req, dict):
        return _error("request is not a map")
    topics = req.get("topics")
    if not (isinstance(topics, list) and all(isinstance(t, str) for t in topics)):
        return _error("request.topics: expected a list of topic names")
    op = req.get("op")
    if op == "keys":
        return [msgpack.packb({"keys": {t: store.keys(t) for t in topics}, "n": len(store)})], True
    if op == "read":
        vals = [
            req.get(k, d) for k, d in (("start", 0), ("max_records", 64), ("max_bytes", 64 << 20))
        ]
        if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in vals):
            return _error("request.start/max_records/max_bytes: expected ints >= 0")
        start, max_records, max_bytes = vals
        records, nxt = store.batch(topics, start, max(1, max_records), max(1, max_bytes))
        meta = msgpack.packb({"next": nxt, "counts": [len(r) for r in records]})
        return [meta, *(f for r in records for f in r)], True
    return _error(f"request.op: expected 'keys' or 'read', got {op!r}")


class JournalClient:
    """Blocking request/reply client of the journal (a REQ socket, recreated after a timeout)."""

    def __init__(
        self,
        bus: BusConfig,
        *,
        endpoint: str | None = None,
        context: zmq.Context | None = None,
        timeout_s: float = 30.0,
    ) -> None:
        self.bus = bus
        self.endpoint = endpoint or journal_endpoint(bus)
        self._ctx = context or zmq.Context.instance()
        self.timeout_s = timeout_s
        self._sock: zmq.Socket | None = None

    def _socket(self) -> zmq.Socket:
        if self._sock is None:
            s = self._ctx.socket(zmq.REQ)
            s.linger = 0
            s.rcvhwm = 4
            _apply_client_curve(s, self.bus.curve, self.endpoint)
            s.connect(self.endpoint)
            self._sock = s
        return self._sock

    def _ask(self, req: dict[str, Any]) -> tuple[dict[str, Any], list[zmq.Frame]]:
        """Send ``req`` and wait for the reply, retrying on a fresh socket (journal restarting)."""
        deadline = time.monotonic() + self.timeout_s
        while True:
            sock = self._socket()
            sock.send(msgpack.packb(req))
            wait_ms = int(max(0.0, min(5.0, deadline - time.monotonic())) * 1000)
            if sock.poll(wait_ms, zmq.POLLIN):
                frames = sock.recv_multipart(copy=False)
                meta = msgpack.unpackb(frames[0].bytes, raw=False)
                if not isinstance(meta, dict):
                    raise BusError(f"journal {self.endpoint}: malformed reply")
                if "error" in meta:
                    raise BusError(f"journal {self.endpoint}: {meta['error']}")
                return meta, frames[1:]
            self.close()  # REQ is stuck after a lost reply: start over on a new socket
            if time.monotonic() >= deadline:
                raise BusError(f"journal {self.endpoint}: no reply in {self.timeout_s:.0f} s")

    def keys(self, topics: Sequence[str]) -> dict[str, list[int]]:
        """The stored keys (keyframe id or stamp) per topic."""
        meta, _ = self._ask({"op": "keys", "topics": list(topics)})
        return {t: [int(k) for k in v] for t, v in meta["keys"].items()}

    def read(
        self, topics: Sequence[str], start: int, *, max_records: int = 64, max_bytes: int = 64 << 20
    ) -> tuple[list[list[zmq.Frame]], int]:
        """Stored messages of ``topics`` (raw frames) from record ``start``; and the next start."""
        meta, frames = self._ask(
            {
                "op": "read",
                "topics": list(topics),
                "start": int(start),
                "max_records": max_records,
                "max_bytes": max_bytes,
            }
        )
        out, pos = [], 0
        for n in meta["counts"]:
            out.append(frames[pos : pos + n])
            pos += n
        if pos != len(frames):
            raise BusError(f"journal {self.endpoint}: reply frame count mismatch")
        return out, int(meta["next"])

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close(linger=0)
            self._sock = None
