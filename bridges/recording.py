"""Bus recordings in MCAP (rosbag2 layout, via ``rosbags``): raw frames plus standard ROS 2 types.

A recording holds, per recorded bus topic ``T``:

- on topic ``T``, type ``mogs_msgs/msg/BusFrames`` (:data:`RAW_MSGDEF`): the multipart message
  exactly as it travelled (``[topic, header, *buffers]``, concatenated in ``data`` with the length
  of each frame in ``frame_sizes``), so a replay re-publishes it bit-exactly
  (:meth:`mogs_node.bus.Publisher.publish_frames`), sequence numbers and session ids included;
- on topic ``/ros2`` + ``T``, the standard ROS 2 form when one exists (:func:`bridges.ros_convert.to_ros`:
  images, IMU, odometry, poses, metric depth, map statistics), for Foxglove, ``ros2 bag play`` and
  other tools.

The log time of each entry is the host time (``time.time_ns()``) at reception. A path ending in
``.mcap`` becomes one bare MCAP file (the rosbag2 folder is written beside it and unpacked on
close); any other path is a rosbag2 folder with ``metadata.yaml``.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mogs_node import msgs
from mogs_node.errors import DatasetError, MessageError

__all__ = [
    "RAW_MSGDEF",
    "RAW_MSGTYPE",
    "ROS2_PREFIX",
    "RecordedMessage",
    "BusRecorder",
    "RecordingWriter",
    "count_recording",
    "is_recording",
    "join_frames",
    "read_recording",
    "split_frames",
]

log = logging.getLogger(__name__)

RAW_MSGTYPE = "mogs_msgs/msg/BusFrames"
RAW_MSGDEF = "uint32[] frame_sizes\nuint8[] data\n"
ROS2_PREFIX = "/ros2"


def _store() -> Any:
    """A ROS 2 Humble typestore with :data:`RAW_MSGTYPE` registered (one per call: registration
    mutates the store)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(RAW_MSGDEF, RAW_MSGTYPE))
    return ts


def _frame_bytes(frame: Any) -> bytes:
    if isinstance(frame, bytes):
        return frame
    buf = getattr(frame, "buffer", None)  # zmq.Frame
    return bytes(buf if buf is not None else memoryview(frame))


def join_frames(frames: list[Any]) -> tuple[np.ndarray, np.ndarray]:
    """Multipart frames -> (``frame_sizes`` u4 ``[K]``, concatenated ``data`` u1 ``[sum]``)."""
    parts = [_frame_bytes(f) for f in frames]
    sizes = np.array([len(p) for p in parts], dtype=np.uint32)
    return sizes, np.frombuffer(b"".join(parts), dtype=np.uint8)


def split_frames(
    frame_sizes: np.ndarray, data: np.ndarray, where: str = "recording"
) -> list[bytes]:
    """Inverse of :func:`join_frames`; raises :class:`DatasetError` when the sizes do not add up."""
    sizes = np.asarray(frame_sizes, dtype=np.int64)
    raw = np.asarray(data, dtype=np.uint8).tobytes()
    if sizes.ndim != 1 or len(sizes) < 2 or (sizes < 0).any() or int(sizes.sum()) != len(raw):
        raise DatasetError(
            f"{where}: frame sizes {sizes.tolist()[:8]} do not add up to {len(raw)} bytes"
        )
    out, pos = [], 0
    for n in sizes.tolist():
        out.append(raw[pos : pos + n])
        pos += n
    return out


@dataclass(frozen=True)
class RecordedMessage:
    """One recorded bus message: host log time, topic and its exact multipart frames."""

    log_time_ns: int
    topic: str
    frames: list[bytes]

    def decode(self) -> msgs.Envelope:
        return msgs.decode(self.frames)


class RecordingWriter:
    """Write bus messages (as received frames) to MCAP; a context manager."""

    def __init__(self, path: str | Path, *, ros2_types: bool = True) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        if self.path.exists():
            raise DatasetError(f"{self.path}: already exists")
        self.bare = self.path.suffix == ".mcap"
        self._dir = self.path.with_name(self.path.name + ".rosbag2") if self.bare else self.path
        if self._dir.exists():
            raise DatasetError(f"{self._dir}: already exists (left over from an earlier run?)")
        self.ros2_types = ros2_types
        self._ts = _store()
        self._w = Writer(self._dir, version=9, storage_plugin=StoragePlugin.MCAP)
        self._conns: dict[tuple[str, str], Any] = {}
        self.counts: dict[str, int] = {}
        self.ros2_counts: dict[str, int] = {}
        self.conversion_errors = 0
        self._open = False

    def __enter__(self) -> RecordingWriter:
        self._w.open()
        self._open = True
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if not self._open:
            return
        self._open = False
        self._w.close()
        if self.bare:
            files = sorted(self._dir.glob("*.mcap"))
            if len(files) != 1:
                raise DatasetError(f"{self._dir}: expected one .mcap file, found {len(files)}")
            files[0].replace(self.path)
            shutil.rmtree(self._dir)
        log.info("recorded %s to %s", self.counts, self.path)

    def _conn(self, topic: str, msgtype: str) -> Any:
        key = (topic, msgtype)
        if key not in self._conns:
            self._conns[key] = self._w.add_connection(topic, msgtype, typestore=self._ts)
        return self._conns[key]

    def write_frames(
        self, log_time_ns: int, frames: list[Any], msg: msgs.Message | None = None
    ) -> None:
        """Record one bus message; ``msg`` (its decoded form) also gets the ROS 2 entry."""
        sizes, data = join_frames(frames)
        topic = _frame_bytes(frames[0]).decode("utf-8", errors="replace")
        raw = self._ts.types[RAW_MSGTYPE](frame_sizes=sizes, data=data)
        self._w.write(
            self._conn(topic, RAW_MSGTYPE),
            int(log_time_ns),
            self._ts.serialize_cdr(raw, RAW_MSGTYPE),
        )
        self.counts[topic] = self.counts.get(topic, 0) + 1
        if not (self.ros2_types and msg is not None):
            return
        from bridges.ros_convert import to_ros

        try:
            conv = to_ros(msg)
        except MessageError as err:
            self.conversion_errors += 1
            log.debug("%s: no ROS 2 form: %s", topic, err)
            return
        if conv is None:
            return
        rtype, rmsg = conv
        rtopic = ROS2_PREFIX + topic
        self._w.write(
            self._conn(rtopic, rtype), int(log_time_ns), self._ts.serialize_cdr(rmsg, rtype)
        )
        self.ros2_counts[rtopic] = self.ros2_counts.get(rtopic, 0) + 1


def _open(path: Path) -> Any:
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([path], default_typestore=_store())
        reader.open()
    except Exception as err:  # rosbags raises several unrelated classes
        raise DatasetError(f"{path}: cannot open recording ({err})") from err
    return reader


def is_recording(path: str | Path) -> bool:
    """Whether ``path`` is a bag holding raw bus frames (written by :class:`RecordingWriter`)."""
    p = Path(path)
    if not p.exists():
        return False
    try:
        reader = _open(p)
    except DatasetError:
        return False
    try:
        return any(c.msgtype == RAW_MSGTYPE for c in reader.connections)
    finally:
        reader.close()


def read_recording(
    path: str | Path, *, topics: tuple[str, ...] | None = None
) -> Iterator[RecordedMessage]:
    """The raw bus messages of a recording in log-time order (``topics``: only these)."""
    p = Path(path)
    if not p.exists():
        raise DatasetError(f"{p}: no such recording")
    reader = _open(p)
    try:
        conns = [
            c
            for c in reader.connections
            if c.msgtype == RAW_MSGTYPE and (topics is None or c.topic in topics)
        ]
        if not conns:
            raise DatasetError(f"{p}: no raw bus frames ({RAW_MSGTYPE}) in this bag")
        for conn, t, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, RAW_MSGTYPE)
            frames = split_frames(m.frame_sizes, m.data, f"{p}:{conn.topic}@{t}")
            yield RecordedMessage(int(t), conn.topic, frames)
    finally:
        reader.close()


def count_recording(path: str | Path) -> dict[str, int]:
    """Raw message count per topic of a recording."""
    reader = _open(Path(path))
    try:
        return {c.topic: c.msgcount for c in reader.connections if c.msgtype == RAW_MSGTYPE}
    finally:
        reader.close()


class BusRecorder:
    """Subscribes to bus topics and writes every valid message to a :class:`RecordingWriter`.

    ``topics`` empty: every topic. Malformed messages are counted by the subscriber and not
    recorded. Call :meth:`run` (blocks until ``stop`` is set, ``duration_s`` passed or
    ``max_messages`` were recorded).
    """

    def __init__(
        self,
        bus: Any,
        path: str | Path,
        *,
        topics: tuple[str, ...] = (),
        ros2_types: bool = True,
        context: Any = None,
    ) -> None:
        import zmq

        from mogs_node.bus import Subscriber

        self.writer = RecordingWriter(path, ros2_types=ros2_types)  # fails first if path exists
        self._own_ctx = context is None
        self._ctx = context or zmq.Context()
        self.sub = Subscriber(bus, context=self._ctx)
        for t in topics or ("/",):
            self.sub.subscribe(t)
        self.recorded = 0

    def run(
        self, stop: Any, *, duration_s: float | None = None, max_messages: int = 0
    ) -> dict[str, int]:
        """Record until ``stop`` (a threading.Event) is set or a limit is reached; returns the
        per-topic counts."""
        import time

        import zmq

        end = None if duration_s is None else time.monotonic() + duration_s
        sock = self.sub.socket
        with self.writer:
            try:
                while not stop.is_set():
                    if end is not None and time.monotonic() >= end:
                        break
                    if not sock.poll(100, zmq.POLLIN):
                        continue
                    frames = self.sub.recv_frames()  # shared-memory arrays come inline here
                    if frames is None:
                        continue
                    t_ns = time.time_ns()
                    env = self.sub.decode_frames(frames)
                    if env is None:
                        continue
                    self.writer.write_frames(t_ns, frames, env.msg)
                    self.recorded += 1
                    if max_messages and self.recorded >= max_messages:
                        break
            finally:
                self.sub.close()
                if self._own_ctx:
                    self._ctx.term()
        lost = {t: s.lost for t, s in self.sub.stats.items() if s.lost}
        bad = {t: s.malformed for t, s in self.sub.stats.items() if s.malformed}
        if lost or bad:
            log.warning("while recording: lost %s, malformed (not recorded) %s", lost, bad)
        return dict(self.writer.counts)
