"""Live sources: an OpenCV camera (device, file or stream URL) and IMU adapters.

- :class:`LiveCameraNode` reads ``cv2.VideoCapture(device)`` and publishes ``/camera/image``.
  Time stamps (:class:`CameraStamper`): when the backend gives frame times
  (``CAP_PROP_POS_MSEC`` >= 0 and increasing: V4L2 buffer times, media times of files and streams)
  the stamp is the host wall time of the first frame plus the backend's time since the first
  frame; otherwise (and from the first frame whose backend time does not increase) the host
  monotonic clock at reception, mapped to wall time once at start-up (so NTP steps do not bend the
  stream). A device that cannot be opened raises :class:`DeviceError` naming it.
- :class:`LineImuNode` reads IMU text lines (format in :mod:`bridges.imu_text`) from UDP datagrams
  (``udp://HOST:PORT``, it binds there) or from a serial port / FIFO / file path (configure the
  port's baud rate beforehand, e.g. ``stty -F /dev/ttyUSB0 115200 raw``), and publishes ``/imu``.
- :class:`ZmqImuNode` binds (or connects) a ZeroMQ PULL or SUB socket that accepts msgpack maps
  ``{"t_ns", "gyro", "accel"}``, so that other programs can push IMU samples.

Rejected samples are counted per reason in ``/diagnostics`` (``imu_rejected_<reason>``) and logged
at most once per second; a source never stops on bad input.
"""

from __future__ import annotations

import os
import select
import socket
import time
from dataclasses import dataclass
from typing import Any

import cv2
import msgpack
import numpy as np
import zmq

from bridges.imu_text import REJECT_REASONS, ImuSample, ImuSampleParser, LineSplitter
from mogs_node import msgs
from mogs_node.bus import queued
from mogs_node.errors import ConfigError, DeviceError
from mogs_node.node import Node
from mogs_node.params import check_choice

__all__ = [
    "CameraStamper",
    "DeviceError",
    "LineImuNode",
    "LineImuParams",
    "LiveCameraNode",
    "LiveCameraParams",
    "ZmqImuNode",
    "ZmqImuParams",
    "open_capture",
]


class CameraStamper:
    """Frame stamps (int ns, wall time) from backend frame times or the host clock.

    ``wall0_ns`` / ``mono0_ns``: one reading of the wall and monotonic clocks taken together.
    """

    def __init__(self, wall0_ns: int, mono0_ns: int) -> None:
        self.wall0_ns, self.mono0_ns = wall0_ns, mono0_ns
        self.use_backend = True
        self._first: tuple[float, int] | None = None  # (backend ms, stamp) of the first frame
        self._last_ms: float | None = None

    def host_ns(self, mono_ns: int) -> int:
        return self.wall0_ns + (mono_ns - self.mono0_ns)

    def stamp(self, pos_msec: float, mono_ns: int) -> int:
        """Stamp of a frame with backend time ``pos_msec`` received at monotonic ``mono_ns``."""
        host = self.host_ns(mono_ns)
        if self.use_backend:
            ok = np.isfinite(pos_msec) and pos_msec >= 0
            if ok and self._last_ms is not None:
                ok = pos_msec > self._last_ms
            if not ok:
                self.use_backend = False
            else:
                self._last_ms = pos_msec
                if self._first is None:
                    self._first = (pos_msec, host)
                return self._first[1] + round((pos_msec - self._first[0]) * 1e6)
        return host


def open_capture(device: str, *, width: int = 0, height: int = 0, fps: float = 0.0) -> Any:
    """``cv2.VideoCapture`` of a device index (``"0"``), device path, file or URL; raises
    :class:`DeviceError` naming ``device`` when it cannot be opened."""
    if not device:
        raise ConfigError("device: empty (expected an index like 0, a path or a URL)")
    src: int | str = int(device) if device.isdigit() else device
    cap = cv2.VideoCapture(src)
    if not cap.isOpened():
        cap.release()
        hint = (
            ""
            if isinstance(src, int) or "://" in device
            else (" (no such file)" if not os.path.exists(device) else "")
        )
        raise DeviceError(f"cannot open camera {device!r}{hint}")
    if width:
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
    if height:
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
    if fps:
        cap.set(cv2.CAP_PROP_FPS, fps)
    return cap


@dataclass(frozen=True)
class LiveCameraParams:
    """Parameters of the live camera node."""

    device: str = "0"  # device index ("0"), device path, video file or stream URL
    width: int = 0  # requested width (0 = the device's default)
    height: int = 0  # requested height (0 = the device's default)
    fps: float = 0.0  # requested frame rate (0 = the device's default)
    encoding: str = "rgb8"  # published encoding: rgb8 | bgr8 | mono8
    topic: str = "/camera/image"  # output topic
    frame_id: str = "camera"  # frame_id of the images
    max_frames: int = 0  # stop after this many frames (0 = until the stream ends or a signal)
    max_read_failures: int = 50  # consecutive failed reads on a device before giving up
    wait_for_subscriber_s: float = 0.0  # before streaming, wait this long for a subscriber

    def __post_init__(self) -> None:
        check_choice("camera.encoding", self.encoding, msgs.Image.ENCODINGS)
        if min(self.width, self.height, self.max_frames, self.max_read_failures) < 0:
            raise ConfigError("camera: width, height, max_frames, max_read_failures must be >= 0")


class LiveCameraNode(Node):
    """Publishes every frame of a ``cv2.VideoCapture`` (see the module docstring)."""

    Params = LiveCameraParams

    def setup(self) -> None:
        p: LiveCameraParams = self.params
        self.cap = open_capture(p.device, width=p.width, height=p.height, fps=p.fps)
        self.is_file = os.path.isfile(p.device)  # a video file ends; a device or stream retries
        self.stamper = CameraStamper(time.time_ns(), time.monotonic_ns())
        self.frames = 0
        self.failures = 0
        self.counters["frames_published"] = 0
        self.counters["read_failures"] = 0
        self.log.info("camera %s open (backend %s)", p.device, self.cap.getBackendName())
        self._waited = p.wait_for_subscriber_s <= 0
        self.every(0.001, self.tick)

    def tick(self) -> None:
        p: LiveCameraParams = self.params
        if not self._waited:
            self._waited = True
            self.wait_for_subscriber(p.topic, p.wait_for_subscriber_s)
        ok, bgr = self.cap.read()  # blocks until the next frame on a live device
        mono = time.monotonic_ns()
        if not ok or bgr is None:
            if self.is_file:
                self.log.info("end of %s after %d frames", p.device, self.frames)
                self.request_stop()
                return
            self.failures += 1
            self.counters["read_failures"] += 1
            if self.failures >= p.max_read_failures:
                self.log.error("camera %s: %d reads failed in a row", p.device, self.failures)
                self.request_stop()
            return
        self.failures = 0
        stamp = self.stamper.stamp(self.cap.get(cv2.CAP_PROP_POS_MSEC), mono)
        if bgr.ndim == 2:
            bgr = cv2.cvtColor(bgr, cv2.COLOR_GRAY2BGR)
        if p.encoding == "rgb8":
            data = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        elif p.encoding == "mono8":
            data = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
        else:
            data = np.ascontiguousarray(bgr)
        self.publish(
            p.topic, msgs.Image(stamp_ns=stamp, frame_id=p.frame_id, encoding=p.encoding, data=data)
        )
        self.frames += 1
        self.counters["frames_published"] = self.frames
        if p.max_frames and self.frames >= p.max_frames:
            self.request_stop()

    def teardown(self) -> None:
        self.cap.release()
        self.log.info(
            "camera %s: %d frames (%s stamps)",
            self.params.device,
            self.frames,
            "backend" if self.stamper.use_backend else "host",
        )


# ----------------------------------------------------------------------------------- IMU


class _ImuPublisher(Node):
    """Shared by the IMU adapters: parser state, publishing, rejection counters."""

    def _init_imu(self, topic: str, frame_id: str) -> None:
        self.parser = ImuSampleParser()
        self._imu_topic, self._imu_frame = topic, frame_id
        self._last_warn = 0.0
        self.counters["imu_published"] = 0
        for r in REJECT_REASONS:
            self.counters[f"imu_rejected_{r}"] = 0

    def _emit(self, s: ImuSample | None) -> None:
        if s is not None:
            self.publish(self._imu_topic, s.message(self._imu_frame))
            self.counters["imu_published"] = self.parser.accepted
        for r, n in self.parser.rejected.items():
            self.counters[f"imu_rejected_{r}"] = n
        now = time.monotonic()
        if self.parser.last_error and now - self._last_warn > 1.0:
            self._last_warn = now
            self.log.warning(
                "rejected IMU input (%d so far): %s",
                self.parser.rejected_total,
                self.parser.last_error,
            )
            self.parser.last_error = ""


@dataclass(frozen=True)
class LineImuParams:
    """Parameters of the line-based IMU reader."""

    source: str = "udp://127.0.0.1:9870"  # udp://HOST:PORT (bound) or a serial/FIFO/file path
    topic: str = "/imu"  # output topic
    frame_id: str = "imu"  # frame_id of the samples
    max_samples: int = 0  # stop after this many accepted samples (0 = never)
    stop_at_eof: bool = True  # file source: stop at its end (a FIFO/tty never ends)
    tick_s: float = 0.002  # polling period of a serial port / FIFO / file (UDP needs none)
    wait_for_subscriber_s: float = 0.0  # before reading, wait this long for a subscriber


def parse_udp_source(source: str) -> tuple[str, int]:
    """``udp://HOST:PORT`` -> (host, port); raises ConfigError naming ``source``."""
    rest = source[len("udp://") :]
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"source: expected udp://HOST:PORT, got {source!r}")
    return host.strip("[]"), int(port)


class LineImuNode(_ImuPublisher):
    """IMU text lines from UDP or a serial port / FIFO / file (see the module docstring)."""

    Params = LineImuParams

    def setup(self) -> None:
        p: LineImuParams = self.params
        self._init_imu(p.topic, p.frame_id)
        self.splitter = LineSplitter()
        self.sock: socket.socket | None = None
        self.fd: int | None = None
        if p.source.startswith("udp://"):
            host, port = parse_udp_source(p.source)
            self.sock = socket.socket(
                socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_DGRAM
            )
            try:
                self.sock.bind((host, port))
            except OSError as err:
                self.sock.close()
                raise DeviceError(f"cannot bind UDP {p.source}: {err}") from err
            self.sock.setblocking(False)
        else:
            try:
                self.fd = os.open(p.source, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
            except OSError as err:
                raise DeviceError(f"cannot open IMU port {p.source!r}: {err.strerror}") from err
            self.is_file = os.path.isfile(p.source)
        self.log.info("reading IMU lines from %s", p.source)
        self._waited = p.wait_for_subscriber_s <= 0
        if self.sock is not None:  # a socket wakes the run loop's poll itself
            self.add_reader(self.sock, self.tick)
        else:  # regular files are always "readable"; ports and FIFOs are polled on a timer
            self.every(p.tick_s, self.tick)

    def _read(self) -> bytes | None:
        """Available bytes ("" nothing now), or None at the end of a file."""
        if self.sock is not None:
            chunks = []
            while True:
                try:
                    chunks.append(self.sock.recv(65536) + b"\n")  # a datagram ends its last line
                except BlockingIOError:
                    return b"".join(chunks)
        assert self.fd is not None
        if not select.select([self.fd], [], [], 0)[0]:
            return b""
        try:
            data = os.read(self.fd, 65536)
        except BlockingIOError:
            return b""
        if not data:
            return None if self.is_file else b""
        return data

    def tick(self) -> None:
        p: LineImuParams = self.params
        if not self._waited:
            self._waited = True
            self.wait_for_subscriber(p.topic, p.wait_for_subscriber_s)
        data = self._read()
        if data is None:
            for line in self.splitter.feed(b"\n"):
                self._emit(self.parser.feed_line(line))
            if p.stop_at_eof:
                self.log.info("end of %s", p.source)
                self.request_stop()
            return
        for line in self.splitter.feed(data):
            self._emit(self.parser.feed_line(line))
            if p.max_samples and self.parser.accepted >= p.max_samples:
                self.request_stop()
                return

    def teardown(self) -> None:
        if self.sock is not None:
            self.sock.close()
        if self.fd is not None:
            os.close(self.fd)
        self.log.info(
            "IMU: %d samples, rejected %s",
            self.parser.accepted,
            {k: v for k, v in self.parser.rejected.items() if v},
        )


@dataclass(frozen=True)
class ZmqImuParams:
    """Parameters of the ZeroMQ/msgpack IMU input."""

    endpoint: str = "tcp://127.0.0.1:9871"  # where the input socket binds (or connects)
    socket: str = "pull"  # "pull" (PUSH senders) or "sub" (PUB senders, all messages)
    bind: bool = True  # bind (senders connect) or connect (to a sender that binds)
    topic: str = "/imu"  # output topic
    frame_id: str = "imu"  # frame_id of the samples
    max_samples: int = 0  # stop after this many accepted samples (0 = never)

    def __post_init__(self) -> None:
        if self.socket not in ("pull", "sub"):
            raise ConfigError(f"imu_zmq.socket: expected 'pull' or 'sub', got {self.socket!r}")


class ZmqImuNode(_ImuPublisher):
    """IMU samples as msgpack maps on a PULL/SUB socket (see the module docstring).

    A message is one frame holding one map (``{"t_ns", "gyro", "accel"}``) or a list of maps.
    """

    Params = ZmqImuParams

    def setup(self) -> None:
        p: ZmqImuParams = self.params
        self._init_imu(p.topic, p.frame_id)
        self.input = self.context.socket(zmq.PULL if p.socket == "pull" else zmq.SUB)
        self.input.linger = 0
        if p.socket == "sub":
            self.input.setsockopt(zmq.SUBSCRIBE, b"")
        try:
            (self.input.bind if p.bind else self.input.connect)(p.endpoint)
        except zmq.ZMQError as err:
            self.input.close()
            raise DeviceError(
                f"cannot {'bind' if p.bind else 'connect'} {p.endpoint}: {err}"
            ) from err
        self.log.info(
            "IMU input: %s %s %s", p.socket, "bound at" if p.bind else "connected to", p.endpoint
        )
        self.add_reader(self.input, self.tick)  # served by the run loop's one poll

    def tick(self) -> None:
        p: ZmqImuParams = self.params
        for raw in queued(self.input.recv, limit=10000):
            try:
                obj = msgpack.unpackb(
                    raw,
                    raw=False,
                    strict_map_key=False,
                    max_bin_len=0,
                    max_array_len=100000,
                    max_map_len=16,
                )
            except Exception as err:  # msgpack raises several unrelated types on garbage
                self.parser.reject("fields", f"not msgpack ({type(err).__name__})")
                self._emit(None)
                continue
            for item in obj if isinstance(obj, list) else [obj]:
                self._emit(self.parser.feed_map(item))
            if p.max_samples and self.parser.accepted >= p.max_samples:
                self.request_stop()
                return

    def teardown(self) -> None:
        self.input.close(linger=0)
        self.log.info(
            "IMU: %d samples, rejected %s",
            self.parser.accepted,
            {k: v for k, v in self.parser.rejected.items() if v},
        )
