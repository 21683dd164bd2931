"""Shared-memory payloads (mogs_node/shm.py): rings, cursors and readers without a bus.

The ring's folder is the test's own (any file system that mmaps works), so the tests neither see
nor disturb other users of /dev/shm.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node import shm

TOPIC = "/frontend/keyframe"
KEY = shm.topic_key(TOPIC)


def _slot_files(folder: Path) -> list[str]:
    return [n for n in os.listdir(folder) if n.startswith("mogs-") and not n.endswith("cursors")]


def _buffers(rng: np.random.Generator, sizes: list[int]) -> list[memoryview]:
    return [memoryview(rng.integers(0, 256, n, dtype=np.uint8)) for n in sizes]


def _subscriber_that_took_everything(folder: Path, *srcs: int) -> shm.ShmCursor:
    """A cursor of the topic that has taken every message of ``srcs``: slots are free."""
    cursor = shm.ShmCursor(directory=folder)
    cursor.add_topic(TOPIC)
    for src in srcs:
        cursor.taken(src, KEY, 1 << 62)
    return cursor


@pytest.fixture
def ring(tmp_path: Path):
    r = shm.ShmRing(TOPIC, src=77, ring_bytes=4 * 100_000, directory=tmp_path)
    yield r
    r.close()


@pytest.fixture
def keeping_up(tmp_path: Path):
    cursor = _subscriber_that_took_everything(tmp_path, 77)
    yield cursor
    cursor.close()


@pytest.fixture
def reader(tmp_path: Path):
    r = shm.ShmReader(directory=tmp_path)
    yield r
    r.close()


@settings(max_examples=40, deadline=None)
@given(sizes=st.lists(st.integers(0, 70_000), min_size=1, max_size=6), seed=st.integers(0, 2**31))
def test_payload_round_trips_byte_for_byte(tmp_path_factory, sizes: list[int], seed: int) -> None:
    folder = tmp_path_factory.mktemp("shm")
    ring = shm.ShmRing(TOPIC, src=1, ring_bytes=1 << 20, directory=folder)
    reader = shm.ShmReader(directory=folder)
    cursor = _subscriber_that_took_everything(folder, 1)
    try:
        bufs = _buffers(np.random.default_rng(seed), sizes)
        ref = ring.write(bufs, sum(sizes), 1, 0)
        assert ref is not None
        out = reader.read(ref[0], ref[1], sizes)
        assert [bytes(b) for b in out] == [bytes(b) for b in bufs]
    finally:
        ring.close()
        reader.close()
        cursor.close()


def test_ring_length_follows_the_first_message_and_its_bounds(tmp_path: Path, keeping_up) -> None:
    keeping_up.taken(1, KEY, 1 << 62)
    keeping_up.taken(2, KEY, 1 << 62)
    bufs = [memoryview(bytes(100_000))]
    r = shm.ShmRing(TOPIC, 1, ring_bytes=1_000_000, directory=tmp_path)
    assert r.write(bufs, 100_000, 1, 0) is not None and r.n_slots == 10
    r.close()
    big = shm.ShmRing(TOPIC, 2, ring_bytes=1_000, directory=tmp_path)  # smaller than one message
    assert big.write(bufs, 100_000, 2, 0) is not None and big.n_slots == shm.MIN_SLOTS
    big.close()
    assert not _slot_files(tmp_path)  # close removes all


def test_a_slot_written_again_is_never_read_as_the_old_message(ring, reader, keeping_up) -> None:
    rng = np.random.default_rng(0)
    sizes = [99_997, 3]
    refs = [ring.write(_buffers(rng, sizes), sum(sizes), 77, seq) for seq in range(4)]
    assert all(r is not None for r in refs)  # no subscriber: nothing to wait for
    assert ring.n_slots == 4  # 400 kB for 100 kB messages
    old = refs[0]
    again = ring.write(_buffers(rng, sizes), sum(sizes), 77, 4)  # reuses slot 0
    assert again is not None and again[0] == old[0]
    with pytest.raises(shm.ShmPayloadError, match="overwritten"):
        reader.read(old[0], old[1], sizes)
    assert len(reader.read(again[0], again[1], sizes)) == 2


def test_a_referenced_size_the_slot_cannot_hold_is_refused(ring, reader, keeping_up) -> None:
    ref = ring.write([memoryview(bytes(10))], 10, 77, 0)
    with pytest.raises(shm.ShmPayloadError, match="bytes referenced"):
        reader.read(ref[0], ref[1], [10, 1 << 30])
    with pytest.raises(shm.ShmPayloadError, match="overwritten"):  # the stamp's size disagrees
        reader.read(ref[0], ref[1], [9])


@pytest.mark.parametrize(
    "name",
    ["../../etc/passwd", "mogs-0-1-2-3-deadbeef-0", "x" * 300, "", "mogs-0-1-2-3-deadbeef-0-1/.."],
)
def test_reader_opens_only_slot_names(reader, name: str) -> None:
    with pytest.raises(shm.ShmPayloadError):
        reader.read(name, 0, [1])


def test_reader_reports_a_slot_that_is_gone(ring, reader, keeping_up, tmp_path: Path) -> None:
    ref = ring.write([memoryview(bytes(10))], 10, 77, 0)
    os.unlink(tmp_path / ref[0])
    with pytest.raises(shm.ShmPayloadError, match="cannot be opened"):
        reader.read(ref[0], ref[1], [10])


def test_subscriber_that_saw_a_ring_reads_it_after_the_publisher_closed(
    ring, reader, keeping_up, tmp_path: Path
) -> None:
    """Messages still queued for a subscriber stay readable when the publisher goes away."""
    sizes = [40_000]
    refs = [ring.write([memoryview(np.full(40_000, s, np.uint8))], 40_000, 77, s) for s in range(3)]
    reader.read(refs[0][0], refs[0][1], sizes)  # the first message maps the whole ring
    ring.close()
    assert not _slot_files(tmp_path)
    for s in (1, 2):
        (out,) = reader.read(refs[s][0], refs[s][1], sizes)
        assert np.all(np.frombuffer(out, np.uint8) == s)


# ----------------------------------------------------------------- cursors: no slot is reused early


def _fill(ring: shm.ShmRing, n: int, first_seq: int = 0) -> list:
    return [ring.write([memoryview(bytes(100_000))], 100_000, 77, first_seq + i) for i in range(n)]


def test_slot_not_yet_taken_by_a_subscriber_sends_the_next_message_inline(
    ring, reader, tmp_path: Path
) -> None:
    cursor = shm.ShmCursor(directory=tmp_path)
    try:
        cursor.add_topic(TOPIC)
        refs = _fill(ring, 4)  # slots 0..3, all written after the subscription
        assert all(r is not None for r in refs)
        assert ring.write([memoryview(bytes(100_000))], 100_000, 77, 4) is None  # slot 0 owed
        assert ring.busy == 1
        cursor.taken(77, KEY, 0)  # message 0 taken: slot 0 is free
        assert ring.write([memoryview(bytes(100_000))], 100_000, 77, 5) is not None
        assert ring.write([memoryview(bytes(100_000))], 100_000, 77, 6) is None  # slot 1 owed
        cursor.taken(77, KEY, 3)  # a later seq frees every earlier one (a HWM drop included)
        assert _fill(ring, 3, first_seq=7) != [None] * 3
        assert ring.busy == 2
    finally:
        cursor.close()


def test_only_subscribers_of_the_topic_before_the_write_are_waited_for(
    ring, keeping_up, tmp_path: Path
) -> None:
    other = shm.ShmCursor(directory=tmp_path)
    late = shm.ShmCursor(directory=tmp_path)
    try:
        other.add_topic("/imu")  # another topic: never waited for
        assert all(r is not None for r in _fill(ring, 8))
        late.add_topic(TOPIC)  # subscribed after messages 4..7 were written: not its own
        assert all(r is not None for r in _fill(ring, 4, first_seq=8))
        assert ring.write([memoryview(bytes(100_000))], 100_000, 77, 12) is None  # 8 is its own
        late.taken(77, KEY, 8)
        assert ring.write([memoryview(bytes(100_000))], 100_000, 77, 12) is not None
    finally:
        other.close()
        late.close()


def test_a_tool_on_every_topic_is_waited_for(ring, tmp_path: Path) -> None:
    tool = shm.ShmCursor(directory=tmp_path)
    try:
        tool.add_topic("/")
        _fill(ring, 4)
        assert ring.write([memoryview(bytes(100_000))], 100_000, 77, 4) is None
        tool.taken(77, KEY, 0)
        assert ring.write([memoryview(bytes(100_000))], 100_000, 77, 4) is not None
    finally:
        tool.close()


def test_cursor_of_a_dead_subscriber_is_ignored_and_removed(ring, tmp_path: Path) -> None:
    code = (
        "import sys; from pathlib import Path; from mogs_node import shm;"
        f"c = shm.ShmCursor(directory=Path({str(tmp_path)!r})); c.add_topic({TOPIC!r});"
        "print(c.path.name, flush=True); import os; os._exit(0)"  # dies as if killed
    )
    name = subprocess.run(
        [sys.executable, "-c", code], check=True, capture_output=True, text=True
    ).stdout.strip()
    folder = shm.cursor_dir(tmp_path)
    assert (folder / name).exists()  # the process died without closing its cursor
    assert _fill(ring, 1) == [None] and ring.unseen == 1  # a dead subscriber reads nothing
    assert not (folder / name).exists()
    alive = _subscriber_that_took_everything(tmp_path, 77)
    assert all(r is not None for r in _fill(ring, 8, first_seq=1))  # never waited for
    alive.close()


def test_files_of_a_process_that_exits_without_closing_are_removed(tmp_path: Path) -> None:
    code = (
        "from pathlib import Path; from mogs_node import shm;"
        f"d = Path({str(tmp_path)!r}); r = shm.ShmRing('/x', 5, 40, directory=d);"
        "c = shm.ShmCursor(directory=d); c.add_topic('/x');"
        "assert r.write([memoryview(bytes(10))], 10, 5, 0)"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    assert not _slot_files(tmp_path)
    assert not shm.cursor_dir(tmp_path).exists()  # the bus's last cursor took its folder along


def test_subscribers_of_another_bus_are_neither_takers_nor_waited_for(tmp_path: Path) -> None:
    """Two MOGS systems on one machine: same topic names, different buses."""
    r = shm.ShmRing(TOPIC, 77, ring_bytes=4 * 100_000, directory=tmp_path, bus="ipc:///a/sub")
    theirs = shm.ShmCursor(directory=tmp_path, bus="ipc:///b/sub")
    theirs.add_topic(TOPIC)  # never takes anything of ours
    try:
        assert _fill(r, 1) == [None] and r.unseen == 1  # not a reader of our slots
        ours = shm.ShmCursor(directory=tmp_path, bus="ipc:///a/sub")
        ours.add_topic(TOPIC)
        ours.taken(77, KEY, 1 << 62)
        assert all(x is not None for x in _fill(r, 12, first_seq=1))  # theirs is not waited for
        ours.close()
    finally:
        theirs.close()
        r.close()


def test_full_cursor_tables_make_publishers_wait_not_race(ring, tmp_path: Path) -> None:
    cursor = shm.ShmCursor(directory=tmp_path)
    try:
        for i in range(shm.MAX_TOPICS + 1):  # one more than fits: "every topic"
            cursor.add_topic(f"/t{i}")
        assert cursor.words[1] > 0
        for src in range(shm.MAX_ENTRIES + 1):  # the last one cannot be recorded
            cursor.taken(1000 + src, KEY, 10)
        _fill(ring, 4)
        assert ring.write([memoryview(bytes(100_000))], 100_000, 77, 4) is None
    finally:
        cursor.close()


def test_no_room_for_a_ring_means_inline(tmp_path: Path, keeping_up) -> None:
    keeping_up.taken(1, KEY, 1 << 62)
    r = shm.ShmRing(TOPIC, 1, ring_bytes=1 << 20, directory=tmp_path)
    (tmp_path / f"{r.prefix}0-1").write_bytes(b"")  # the first slot cannot be made
    assert r.write([memoryview(bytes(10))], 10, 1, 0) is None
    assert r.failed == 1 and "cannot allocate" in r.last_error
    assert r.n_slots == 0 and _slot_files(tmp_path) == [f"{r.prefix}0-1"]  # none half-made
    r.close()


def test_no_subscriber_reading_slots_here_means_inline(tmp_path: Path) -> None:
    """A subscriber in another container or on another host keeps no cursor in this /dev/shm:
    with none of the topic's here, nothing goes to slots it could not read."""
    r = shm.ShmRing(TOPIC, 1, ring_bytes=1 << 20, directory=tmp_path)
    other = shm.ShmCursor(directory=tmp_path)
    other.add_topic("/imu")
    try:
        assert r.write([memoryview(bytes(10))], 10, 1, 0) is None
        assert (r.unseen, r.busy, r.failed) == (1, 0, 0)
        mine = shm.ShmCursor(directory=tmp_path)
        mine.add_topic(TOPIC)
        assert r.write([memoryview(bytes(10))], 10, 1, 1) is not None
        mine.close()
    finally:
        other.close()
        r.close()


def test_sweep_removes_the_slots_of_dead_publishers_only(tmp_path: Path) -> None:
    code = (
        "from pathlib import Path; from mogs_node import shm;"
        f"d = Path({str(tmp_path)!r}); r = shm.ShmRing('/x', 5, 40, directory=d);"
        "c = shm.ShmCursor(directory=d); c.add_topic('/x');"
        "assert r.write([memoryview(bytes(10))], 10, 5, 0); import os; os._exit(0)"  # as if killed
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    assert len(_slot_files(tmp_path)) == shm.MIN_SLOTS
    mine = shm.ShmRing("/y", 6, 40, directory=tmp_path)
    cursor = shm.ShmCursor(directory=tmp_path)
    cursor.add_topic("/y")
    assert mine.write([memoryview(bytes(10))], 10, 6, 0)  # a new ring sweeps first
    cursor.close()
    left = _slot_files(tmp_path)
    assert sorted(left) == sorted(f"{mine.prefix}{i}-{i + 1}" for i in range(shm.MIN_SLOTS))
    mine.close()


def test_message_larger_than_its_slot_gets_a_new_slot(ring, reader, keeping_up) -> None:
    first = ring.write([memoryview(bytes(100_000))], 100_000, 77, 0)
    _fill(ring, 3, first_seq=1)
    big = np.arange(300_000, dtype=np.uint8)
    ref = ring.write([memoryview(big)], big.size, 77, 4)
    assert ref is not None and ref[0] != first[0]  # a new file: readers of the old keep theirs
    (out,) = reader.read(ref[0], ref[1], [big.size])
    assert bytes(out) == big.tobytes()
