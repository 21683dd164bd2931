"""Shared-memory payloads for large messages between processes on the same host.

Through the broker, every byte of a message crosses the kernel four times (publisher -> broker ->
subscriber), against twice for a direct PUB/SUB pair; for megabyte keyframes, depth maps and
masks those copies are most of the bus's CPU time (docs/benchmarks.md, "Bus throughput"). When
the bus's endpoints are ``ipc://`` (so every peer runs on this host), a publisher instead copies
a large message's array buffers once into a ring of shared-memory slots of its topic and sends
only ``[topic, header]`` through the broker, the header carrying a reference ``"m": [slot name,
ticket, [buffer sizes]]`` (the ticket counts the ring's writes). The subscriber copies the
buffers out of the slot as it takes the message from its socket, so what it hands on is an
ordinary ``[topic, header, *buffers]`` message, byte for byte the one that would have travelled
inline.

Lifetime, without loss: every subscriber on such a bus keeps a *cursor* file in
``/dev/shm/mogs-<uid>-<ns>-cursors-<bus>/``: the topics it takes (with the time it subscribed)
and, per publisher session and topic, the sequence number of the last message with arrays it has
taken. A publisher writes a slot only if some live subscriber of the topic keeps a cursor there
(else the message goes inline: nobody listens, or only processes that could not read the slot),
and reuses a slot only if every live subscriber of the topic, subscribed before the slot's message
was written, has taken that message; otherwise the slot is busy and the new message goes inline
through the broker as before. So shared memory is used while subscribers keep up, and a slow one
falls back to ZeroMQ's queues, losing nothing it would not have lost there. A slot also carries a
stamp (a seqlock: ``-1`` while written, then the write's ticket) that the subscriber checks
before and after its copy, so a slot overwritten all the same (a cursor misjudged) is detected,
never read as another message; such a message is counted on its topic (``shm_missed``, then
``lost``). The ordering of these plain stores and loads relies on numpy releasing and re-taking
the GIL around copies of this size (a lock release and acquire, i.e. a memory barrier, on every
architecture).

Files live in ``/dev/shm`` with mode 0600, named ``mogs-<uid>-<pid namespace>-<pid>-...``; a
publisher removes its own at ``close`` (or at exit), a subscriber its cursor; every new ring, and
the launcher at shutdown, removes those of dead processes of the same user and pid namespace (a
killed node's).
"""

from __future__ import annotations

import contextlib
import mmap
import os
import re
import time
import weakref
import zlib
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "SHM_DIR",
    "ShmCursor",
    "ShmPayloadError",
    "ShmReader",
    "ShmRing",
    "shm_available",
    "sweep_stale",
    "topic_key",
]

SHM_DIR = Path("/dev/shm")
HEADER_BYTES = 64  # before the payload: magic, seq (-1 while being written), payload bytes
MAGIC = int.from_bytes(b"MOGSSHM1", "little")
WRITING = -1
_NAME = re.compile(r"mogs-\d+-[0-9a-f]+-\d+-[0-9a-f]+-[0-9a-f]{8}-\d+-\d+")
_ALIGN = 1 << 16
MIN_SLOTS, MAX_SLOTS = 4, 256
CURSOR_MAGIC = int.from_bytes(b"MOGSCUR1", "little")
MAX_TOPICS, MAX_ENTRIES = 64, 512
_TOPICS = 4
_ENTRIES = _TOPICS + 2 * MAX_TOPICS
_CURSOR_WORDS = _ENTRIES + 3 * MAX_ENTRIES


def _pid_namespace() -> int:
    try:
        return os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        return 0


def _own_prefix() -> str:
    return f"mogs-{os.getuid()}-{_pid_namespace():x}-"


def topic_key(topic: str) -> int:
    """The 32-bit key of a topic in slot headers and cursor files (a collision only makes a
    publisher more careful: it waits for a subscriber of the other topic too)."""
    return zlib.crc32(topic.encode("utf-8"))


def cursor_dir(directory: Path = SHM_DIR, bus: str = "") -> Path:
    """The folder of the cursors of one bus (``bus``: its subscriber endpoint), so that two
    MOGS systems on one machine never wait for each other's subscribers."""
    suffix = f"-{zlib.crc32(bus.encode('utf-8')):08x}" if bus else ""
    return directory / f"{_own_prefix()}cursors{suffix}"


def shm_available(directory: Path = SHM_DIR) -> bool:
    """Whether shared-memory payloads can be used here (Linux ``/dev/shm``, writable)."""
    return directory.is_dir() and os.access(directory, os.W_OK | os.X_OK)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_stale(directory: Path = SHM_DIR) -> int:
    """Remove the slot and cursor files of dead processes (same user and pid namespace);
    returns how many."""
    prefix = _own_prefix()
    removed = 0
    try:
        names = os.listdir(directory)
    except OSError:
        return 0
    for name in names:
        if not name.startswith(prefix) or not _NAME.fullmatch(name):
            continue
        pid = int(name[len(prefix) :].split("-", 1)[0])
        if pid != os.getpid() and not _pid_alive(pid):
            with contextlib.suppress(OSError):
                os.unlink(directory / name)
                removed += 1
    for folder_name in names:
        if not folder_name.startswith(f"{prefix}cursors"):
            continue
        folder = directory / folder_name
        with contextlib.suppress(OSError):
            for name in os.listdir(folder):
                pid = name.split("-")[1] if name.startswith("sub-") else ""
                if pid.isdigit() and not _pid_alive(int(pid)):
                    with contextlib.suppress(OSError):
                        os.unlink(folder / name)
                        removed += 1
            os.rmdir(folder)  # only if empty (else OSError, suppressed)
    return removed


def _unlink_quietly(path: Path) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


def _remove_cursor(path: Path) -> None:
    _unlink_quietly(path)
    with contextlib.suppress(OSError):  # the bus's last cursor: no empty folder left behind
        os.rmdir(path.parent)


def _unlink_all(directory: Path, names: set[str]) -> None:
    for name in list(names):
        _unlink_quietly(directory / name)
    names.clear()


class ShmPayloadError(Exception):
    """A referenced payload cannot be read (overwritten, gone, or not a slot of ours)."""


class _Slot:
    __slots__ = ("name", "mm", "capacity", "header", "data")

    def __init__(self, name: str, mm: mmap.mmap, capacity: int) -> None:
        self.name = name
        self.mm = mm
        self.capacity = capacity
        # magic, ticket (WRITING while written), payload bytes, src, seq, written (monotonic ns)
        self.header = np.frombuffer(mm, dtype="<i8", count=6)
        self.data = np.frombuffer(mm, dtype=np.uint8, offset=HEADER_BYTES)

    def close(self) -> None:
        del self.header, self.data  # the views pin the mapping
        with contextlib.suppress(BufferError):  # a view still held elsewhere: unmapped with it
            self.mm.close()


class ShmCursor:
    """A subscriber's cursor file: the topics it takes and the last message with arrays it took
    of each publisher session and topic. It is the only writer of its file; publishers read it.

    Layout (int64 words): magic, all-topics since (monotonic ns, 0 = no), topics, entries, then
    ``MAX_TOPICS`` x (topic key, since) and ``MAX_ENTRIES`` x (src, topic key, seq). A full table
    makes publishers more careful, never less: a subscriber they cannot account for is one they
    wait for.
    """

    def __init__(self, *, directory: Path = SHM_DIR, bus: str = "") -> None:
        folder = cursor_dir(directory, bus)
        self.path = folder / f"sub-{os.getpid()}-{os.urandom(6).hex()}"
        for attempt in range(3):  # the last cursor of the bus may remove the folder meanwhile
            folder.mkdir(mode=0o700, exist_ok=True)
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_RDWR | os.O_NOFOLLOW, 0o600)
                break
            except FileNotFoundError:
                if attempt == 2:
                    raise
        try:
            os.posix_fallocate(fd, 0, _CURSOR_WORDS * 8)
            self._mm = mmap.mmap(fd, _CURSOR_WORDS * 8, mmap.MAP_SHARED)
        finally:
            os.close(fd)
        self.words = np.frombuffer(self._mm, dtype="<i8")
        self.words[0] = CURSOR_MAGIC
        # a subscriber never closed still leaves no file at a normal exit
        self._finalizer = weakref.finalize(self, _remove_cursor, self.path)
        self._topics: set[int] = set()
        self._entries: dict[tuple[int, int], int] = {}  # (src, key) -> word of its seq

    def add_topic(self, topic: str) -> None:
        w = self.words
        if topic == "/":
            if not w[1]:
                w[1] = time.monotonic_ns()
            return
        key = topic_key(topic)
        if key in self._topics:
            return
        n = int(w[2])
        if n >= MAX_TOPICS:  # no room: say "every topic", which only makes publishers wait more
            w[1] = w[1] or time.monotonic_ns()
            return
        w[_TOPICS + 2 * n], w[_TOPICS + 2 * n + 1] = key, time.monotonic_ns()
        w[2] = n + 1
        self._topics.add(key)

    def taken(self, src: int, key: int, seq: int) -> None:
        """Record that message ``seq`` of publisher session ``src`` on topic ``key`` was taken."""
        word = self._entries.get((src, key))
        if word is not None:
            self.words[word] = seq
            return
        w = self.words
        n = int(w[3])
        if n >= MAX_ENTRIES:
            return  # unrecorded: that publisher keeps this subscriber's messages inline
        base = _ENTRIES + 3 * n
        w[base], w[base + 1], w[base + 2] = src, key, seq
        w[3] = n + 1
        self._entries[(src, key)] = base + 2

    def close(self) -> None:
        self._finalizer()
        del self.words
        with contextlib.suppress(BufferError):
            self._mm.close()


class _Cursors:
    """The publisher's view of every live subscriber's cursor file (re-listed at each look)."""

    def __init__(self, directory: Path, bus: str) -> None:
        self.folder = cursor_dir(directory, bus)
        self._maps: dict[str, tuple[mmap.mmap, np.ndarray]] = {}

    def current(self) -> list[np.ndarray]:
        try:
            names = [e.name for e in os.scandir(self.folder)]
        except OSError:
            names = []
        for gone in self._maps.keys() - set(names):
            del self._maps[gone]  # unmapped when the last view of it goes
        out = []
        for name in names:
            entry = self._maps.get(name)
            if entry is None:
                pid = name.split("-")[1] if name.startswith("sub-") else ""
                if not pid.isdigit():
                    continue
                if not _pid_alive(int(pid)):  # a subscriber that died without closing
                    with contextlib.suppress(OSError):
                        os.unlink(self.folder / name)
                    continue
                try:
                    fd = os.open(self.folder / name, os.O_RDONLY | os.O_NOFOLLOW)
                except OSError:
                    continue
                try:
                    mm = mmap.mmap(fd, _CURSOR_WORDS * 8, mmap.MAP_SHARED, mmap.PROT_READ)
                except (OSError, ValueError):
                    continue
                finally:
                    os.close(fd)
                entry = self._maps[name] = (mm, np.frombuffer(mm, dtype="<i8"))
            elif not _pid_alive(int(name.split("-")[1])):
                continue
            words = entry[1]
            if words[0] == CURSOR_MAGIC:
                out.append(words)
        return out

    def check(self, key: int, held: tuple[int, int, int] | None) -> str:
        """Whether a slot of topic ``key`` may be written now: ``""`` if so, ``"unseen"`` if no
        live subscriber of the topic keeps a cursor here (none at all, or none that shares this
        ``/dev/shm``: it could not read the slot), ``"busy"`` if the slot still holds message
        ``held`` = (src, seq, written_ns) and a subscriber of the topic since before it was
        written has not taken it."""
        seen = False
        for w in self.current():
            since_all = int(w[1])
            n_topics = min(int(w[2]), MAX_TOPICS)
            topics = w[_TOPICS : _TOPICS + 2 * n_topics].reshape(-1, 2)
            of_topic = topics[:, 0] == key
            if not (since_all > 0 or of_topic.any()):
                continue
            seen = True
            if held is None:
                continue
            src, seq, written_ns = held
            if not (
                0 < since_all <= written_ns or bool(np.any(of_topic & (topics[:, 1] <= written_ns)))
            ):
                continue  # subscribed after the slot's message was written: not its own
            n = min(int(w[3]), MAX_ENTRIES)
            entries = w[_ENTRIES : _ENTRIES + 3 * n].reshape(-1, 3)
            mine = entries[(entries[:, 0] == src) & (entries[:, 1] == key), 2]
            if mine.size == 0 or int(mine.max()) < seq:
                return "busy"
        return "" if seen else "unseen"

    def close(self) -> None:
        self._maps.clear()


class ShmRing:
    """The publisher side: the slots of one topic, written in turn.

    All slots are made at the first write (their number follows that message's size), so that a
    subscriber can map the whole ring when it first sees it: then the ring's files may go away
    (the publisher closes or dies) with messages still queued for it, and it reads them all.
    ``write`` returns None where the message must go inline instead: no subscriber of the topic
    keeps a cursor in this ``/dev/shm`` (``unseen``: none, or only ones in another container or
    on another host, which could not read a slot), the next slot is still owed to a subscriber
    (``busy``), or no slot could be made (``failed``: ``/dev/shm`` full or missing). Nothing is
    lost either way.
    """

    def __init__(
        self,
        topic: str,
        src: int,
        ring_bytes: int,
        *,
        directory: Path = SHM_DIR,
        bus: str = "",
    ) -> None:
        self.directory = directory
        self.ring_bytes = ring_bytes
        self.key = topic_key(topic)
        self.prefix = f"{_own_prefix()}{os.getpid()}-{src:x}-{self.key:08x}-"
        self._slots: list[_Slot] = []
        self._names: set[str] = set()  # of the slot files now: removed at close or exit
        self._finalizer = weakref.finalize(self, _unlink_all, directory, self._names)
        self._cursors = _Cursors(directory, bus)  # the subscribers of this bus only
        self._gen = 0
        self.ticket = 0  # writes so far: a slot's stamp says which write it holds
        self.busy = 0  # writes sent inline because the next slot was not yet read by all
        self.unseen = 0  # writes sent inline because no subscriber of the topic reads slots here
        self.failed = 0  # writes sent inline because no slot could be made
        self.last_error = ""

    @property
    def n_slots(self) -> int:
        return len(self._slots)

    def _make_slot(self, index: int, nbytes: int) -> _Slot:
        self._gen += 1
        name = f"{self.prefix}{index}-{self._gen}"
        capacity = -(-(nbytes + nbytes // 4) // _ALIGN) * _ALIGN  # room for messages that grow
        path = self.directory / name
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_RDWR | os.O_NOFOLLOW, 0o600)
        try:
            # allocate now: a full tmpfs fails here with ENOSPC, not later with SIGBUS on a write
            os.posix_fallocate(fd, 0, HEADER_BYTES + capacity)
            mm = mmap.mmap(fd, HEADER_BYTES + capacity, mmap.MAP_SHARED)
        except OSError:
            os.close(fd)
            with contextlib.suppress(OSError):
                os.unlink(path)
            raise
        os.close(fd)
        self._names.add(name)
        slot = _Slot(name, mm, capacity)
        slot.header[:] = (MAGIC, WRITING, 0, 0, 0, 0)
        return slot

    def _fail(self, nbytes: int, err: OSError) -> None:
        self.failed += 1
        self.last_error = f"cannot allocate {nbytes} bytes in {self.directory}: {err}"

    def write(self, buffers: list[Any], nbytes: int, src: int, seq: int) -> tuple[str, int] | None:
        """Copy ``buffers`` (``nbytes`` in all) of message ``seq`` of session ``src`` into the
        next slot: its name and the write's ticket, or None (send it inline)."""
        if not self._slots:
            sweep_stale(self.directory)
            n = int(np.clip(self.ring_bytes // max(nbytes, 1), MIN_SLOTS, MAX_SLOTS))
            try:
                for index in range(n):
                    self._slots.append(self._make_slot(index, nbytes))
            except OSError as err:
                self._fail(nbytes, err)
                self.close()
                return None
        ticket = self.ticket
        index = ticket % len(self._slots)
        slot = self._slots[index]
        header = slot.header
        held = None if header[1] == WRITING else (int(header[3]), int(header[4]), int(header[5]))
        refusal = self._cursors.check(self.key, held)
        if refusal:
            if refusal == "busy":
                self.busy += 1
            else:
                self.unseen += 1
            return None
        if slot.capacity < nbytes:
            try:
                new = self._make_slot(index, nbytes)
            except OSError as err:
                self._fail(nbytes, err)
                return None
            self._drop(slot)
            slot = self._slots[index] = new
            header = slot.header
        self.ticket = ticket + 1
        data = slot.data
        header[1] = WRITING
        offset = 0
        for buf in buffers:
            b = np.frombuffer(buf, dtype=np.uint8)
            np.copyto(data[offset : offset + b.size], b)
            offset += b.size
        header[2:6] = (nbytes, src, seq, time.monotonic_ns())
        header[1] = ticket
        return slot.name, ticket

    def _drop(self, slot: _Slot) -> None:
        _unlink_quietly(self.directory / slot.name)
        self._names.discard(slot.name)
        slot.close()

    def close(self) -> None:
        """Remove the slot files; subscribers that have the ring mapped keep reading it."""
        for slot in self._slots:
            self._drop(slot)
        self._slots = []
        self._cursors.close()


def _ring_prefix(name: str) -> str:
    return name.rsplit("-", 2)[0] + "-"


class ShmReader:
    """The subscriber side: maps rings whole at first sight and copies payloads out.

    Mappings of rings whose files are gone (their publisher closed) and that were not read for
    ``idle_unmap_s`` are dropped when a new ring appears.
    """

    def __init__(self, *, directory: Path = SHM_DIR, idle_unmap_s: float = 30.0) -> None:
        self.directory = directory
        self.idle_unmap_s = idle_unmap_s
        self._maps: dict[str, _Slot] = {}
        self._rings: dict[str, list[str]] = {}  # ring prefix -> its mapped slot names
        self._used: dict[str, float] = {}  # ring prefix -> last read (monotonic s)

    @property
    def n_mapped(self) -> int:
        return len(self._maps)

    def _map(self, name: str) -> _Slot:
        try:
            fd = os.open(self.directory / name, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError as err:
            raise ShmPayloadError(
                f"slot {name} cannot be opened ({err.strerror}): its publisher has closed, or "
                f"does not share {self.directory} with this process (set bus.shm_min_bytes: 0)"
            ) from None
        try:
            size = os.fstat(fd).st_size
            if size < HEADER_BYTES:
                raise ShmPayloadError(f"slot {name} is only {size} bytes")
            mm = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ)
        finally:
            os.close(fd)
        slot = _Slot(name, mm, size - HEADER_BYTES)
        if int(slot.header[0]) != MAGIC:
            slot.close()
            raise ShmPayloadError(f"slot {name} has no MOGS header")
        return slot

    def _slot(self, name: str) -> _Slot:
        slot = self._maps.get(name)
        if slot is not None:
            return slot
        if type(name) is not str or not _NAME.fullmatch(name):
            raise ShmPayloadError(f"{name!r} is not a MOGS shared-memory slot name")
        prefix = _ring_prefix(name)
        if prefix not in self._rings:
            self._forget_idle_rings()
            self._rings[prefix] = []
            try:  # the whole ring now, while its files are surely there
                siblings = [n for n in os.listdir(self.directory) if n.startswith(prefix)]
            except OSError:
                siblings = []
            for sibling in siblings:
                if sibling != name and _NAME.fullmatch(sibling):
                    with contextlib.suppress(ShmPayloadError, OSError, ValueError):
                        self._maps[sibling] = self._map(sibling)
                        self._rings[prefix].append(sibling)
        slot = self._maps[name] = self._map(name)
        self._rings[prefix].append(name)
        return slot

    def _forget_idle_rings(self) -> None:
        now = time.monotonic()
        for prefix, names in list(self._rings.items()):
            if now - self._used.get(prefix, now) < self.idle_unmap_s:
                continue
            if any((self.directory / n).exists() for n in names):
                continue
            for n in names:
                slot = self._maps.pop(n, None)
                if slot is not None:
                    slot.close()
            del self._rings[prefix]
            self._used.pop(prefix, None)

    def read(self, name: str, ticket: int, sizes: list[int]) -> list[memoryview]:
        """The buffers of write ``ticket`` in slot ``name``, copied out; ShmPayloadError if not there."""
        slot = self._slot(name)
        self._used[_ring_prefix(name)] = time.monotonic()
        nbytes = sum(sizes)
        if nbytes > slot.capacity:
            raise ShmPayloadError(f"{nbytes} bytes referenced in a slot of {slot.capacity}")
        header = slot.header
        if int(header[1]) != ticket or int(header[2]) != nbytes:
            raise ShmPayloadError(f"slot {name} no longer holds write {ticket}: overwritten")
        out = np.empty(nbytes, dtype=np.uint8)
        np.copyto(out, slot.data[:nbytes])
        if int(header[1]) != ticket:
            raise ShmPayloadError(f"slot {name} was overwritten while write {ticket} was read")
        view = memoryview(out)
        buffers = []
        offset = 0
        for n in sizes:
            buffers.append(view[offset : offset + n])
            offset += n
        return buffers

    def close(self) -> None:
        for slot in self._maps.values():
            slot.close()
        self._maps.clear()
        self._rings.clear()
        self._used.clear()
