"""Append-only, size-bounded, crash-safe log of raw bus messages (no bus, no decoding).

The journal node stores every message of the reliable topics here so that a restarted node can
fetch what it missed. The file holds the multipart frames exactly as they crossed the bus (no
re-encoding), one record per message::

    file   = MAGIC record*
    record = u32 payload_len | u32 crc32(payload) | payload            (little endian)
    payload= i64 key | u16 n_frames | u32 frame_len * n_frames | frame bytes...

``key`` is the message's ``keyframe_id`` when it has one, else its ``stamp_ns``
(:func:`mogs_node.node.message_key`): what a node asks
about ("which keyframes have masks?"). Frame 0 is the topic. A record is written with one
``write`` call; a process killed in the middle leaves at most a torn last record, which a reopen
detects (short or checksum mismatch), ignores and truncates before appending again. Nothing but
the bytes is trusted on reopen: lengths are bounded by the file size.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mogs_node.errors import BusError, ConfigError

__all__ = ["MAGIC", "JournalStore", "encode_record"]

MAGIC = b"MOGSJNL1"
_REC = struct.Struct("<II")  # payload length, crc32
_PAY = struct.Struct("<qH")  # key, number of frames
MAX_FRAMES = 64  # a bus message has topic + header + at most a few arrays


def _view(frame: Any) -> memoryview:
    buf = getattr(frame, "buffer", None)  # zmq.Frame
    return memoryview(buf if buf is not None else frame).cast("B")


def encode_record(frames: Sequence[Any], key: int) -> bytes:
    """One record (header + payload) for ``frames`` (bytes, memoryviews or zmq.Frames)."""
    views = [_view(f) for f in frames]
    if not 1 <= len(views) <= MAX_FRAMES:
        raise ConfigError(f"journal record: expected 1..{MAX_FRAMES} frames, got {len(views)}")
    head = _PAY.pack(int(key), len(views)) + struct.pack(
        f"<{len(views)}I", *(v.nbytes for v in views)
    )
    payload = b"".join([head, *views])
    return _REC.pack(len(payload), zlib.crc32(payload)) + payload


@dataclass(frozen=True)
class _Entry:
    offset: int  # of the payload
    length: int  # of the payload
    topic: str
    key: int


class JournalStore:
    """The journal file of one run: append, index by topic, read back frames.

    ``fresh=True`` starts an empty journal (an existing file is replaced); ``fresh=False``
    reopens one (crash or ``--resume``), keeping every intact record. At most ``max_bytes`` are
    kept: a record that would exceed it is refused (``append`` returns False, counted in
    ``refused``) rather than dropping old records a restarted node may still need.
    """

    def __init__(
        self, path: str | Path, *, max_bytes: int = 4 << 30, fresh: bool = True, fsync: bool = False
    ) -> None:
        if max_bytes <= len(MAGIC):
            raise ConfigError(f"journal.max_bytes: expected > {len(MAGIC)}, got {max_bytes}")
        self.path = Path(path)
        self.max_bytes = int(max_bytes)
        self.fsync = fsync
        self.entries: list[_Entry] = []
        self.by_topic: dict[str, list[int]] = {}
        self.refused = 0
        self.torn_bytes = 0  # ignored tail found on reopen
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if fresh or not self.path.exists() or self.path.stat().st_size == 0:
            with open(self.path, "wb") as f:
                f.write(MAGIC)
            self.size = len(MAGIC)
        else:
            self.size = self._scan()
        self._fd = os.open(self.path, os.O_RDWR)
        os.ftruncate(self._fd, self.size)  # drop a torn tail before appending after it
        self._rfile = open(self.path, "rb")  # noqa: SIM115 - closed in close()

    # ------------------------------------------------------------------ reopen

    def _scan(self) -> int:
        """Index the intact records of an existing file; returns where the intact part ends."""
        total = self.path.stat().st_size
        with open(self.path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise BusError(f"{self.path} is not a MOGS journal (bad magic)")
            pos = len(MAGIC)
            while pos + _REC.size <= total:
                f.seek(pos)
                length, crc = _REC.unpack(f.read(_REC.size))
                start = pos + _REC.size
                if length < _PAY.size or start + length > total:
                    break  # torn: the writer died inside this record
                payload = f.read(length)
                if zlib.crc32(payload) != crc:
                    break
                entry = self._parse(payload, start)
                if entry is None:
                    break
                self._index(entry)
                pos = start + length
        self.torn_bytes = total - pos
        return pos

    @staticmethod
    def _frame_lengths(payload: bytes | memoryview) -> tuple[int, list[int]] | None:
        key, n = _PAY.unpack_from(payload, 0)
        table = _PAY.size + 4 * n
        if not 1 <= n <= MAX_FRAMES or table > len(payload):
            return None
        lens = list(struct.unpack_from(f"<{n}I", payload, _PAY.size))
        if table + sum(lens) != len(payload):
            return None
        return key, lens

    def _parse(self, payload: bytes, start: int) -> _Entry | None:
        parsed = self._frame_lengths(payload)
        if parsed is None:
            return None
        key, lens = parsed
        t0 = _PAY.size + 4 * len(lens)
        try:
            topic = payload[t0 : t0 + lens[0]].decode("utf-8")
        except UnicodeDecodeError:
            return None
        return _Entry(start, len(payload), topic, key)

    def _index(self, entry: _Entry) -> None:
        self.by_topic.setdefault(entry.topic, []).append(len(self.entries))
        self.entries.append(entry)

    # ------------------------------------------------------------------ write

    def append(self, frames: Sequence[Any], key: int) -> bool:
        """Store one message; False (and counted) when the size bound refuses it."""
        rec = encode_record(frames, key)
        if self.size + len(rec) > self.max_bytes:
            self.refused += 1
            return False
        written = os.pwrite(self._fd, rec, self.size)
        if written != len(rec):  # disk full: leave a torn record, the next open ignores it
            raise BusError(f"journal {self.path}: short write ({written} of {len(rec)} bytes)")
        if self.fsync:
            os.fsync(self._fd)
        topic = bytes(_view(frames[0])).decode("utf-8", errors="replace")
        self._index(_Entry(self.size + _REC.size, len(rec) - _REC.size, topic, int(key)))
        self.size += len(rec)
        return True

    # ------------------------------------------------------------------ read

    def __len__(self) -> int:
        return len(self.entries)

    def keys(self, topic: str) -> list[int]:
        """Keys of every stored message of ``topic``, in arrival order."""
        return [self.entries[i].key for i in self.by_topic.get(topic, ())]

    def topics(self) -> dict[str, int]:
        return {t: len(ix) for t, ix in self.by_topic.items()}

    def read(self, index: int) -> list[bytes]:
        """The frames of record ``index`` exactly as they were appended."""
        e = self.entries[index]
        self._rfile.seek(e.offset)
        payload = self._rfile.read(e.length)
        if len(payload) != e.length:
            raise BusError(f"journal {self.path}: record {index} is cut short")
        parsed = self._frame_lengths(payload)
        if parsed is None:
            raise BusError(f"journal {self.path}: record {index} is malformed")
        _, lens = parsed
        pos = _PAY.size + 4 * len(lens)
        out = []
        for n in lens:
            out.append(payload[pos : pos + n])
            pos += n
        return out

    def select(self, topics: Iterable[str], start: int = 0) -> list[int]:
        """Indices >= ``start`` of the records of ``topics``, in arrival order."""
        wanted = set(topics)
        return [i for i in range(start, len(self.entries)) if self.entries[i].topic in wanted]

    def batch(
        self, topics: Iterable[str], start: int, max_records: int = 64, max_bytes: int = 64 << 20
    ) -> tuple[list[list[bytes]], int]:
        """Up to ``max_records`` / ``max_bytes`` (at least one record) of ``topics`` from record
        index ``start``; returns them and the index to continue from (``len(self)`` at the end)."""
        wanted = set(topics)
        out: list[list[bytes]] = []
        size = 0
        i = max(0, int(start))
        while i < len(self.entries) and len(out) < max_records:
            e = self.entries[i]
            if e.topic in wanted:
                if out and size + e.length > max_bytes:
                    break
                out.append(self.read(i))
                size += e.length
            i += 1
        return out, i

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
            self._rfile.close()
