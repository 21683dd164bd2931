"""IMU samples from text lines and msgpack maps: strict parsing with counted rejections.

Text format (one sample per line, UTF-8, ``\\n`` or ``\\r\\n`` line ends)::

    # comment lines and blank lines are ignored
    t_ns,gx,gy,gz,ax,ay,az
    1700000000000000000,0.001,-0.002,0.0005,0.12,-0.03,9.81

- ``t_ns``: integer nanoseconds (decimal digits, no sign, no exponent), strictly increasing;
- ``gx gy gz``: angular rate in rad/s, ``ax ay az``: specific force in m/s^2, in the IMU frame;
  decimal or exponent notation (``-1.5``, ``2e-3``); ``nan``, ``inf`` and values that overflow are
  rejected; spaces around fields are allowed.

Msgpack format (``mogs live imu-zmq``): a map ``{"t_ns": int, "gyro": [3 numbers], "accel": [3
numbers]}`` (extra keys are rejected) under the same rules.

A rejected sample never stops a stream: :class:`ImuSampleParser` counts it under its reason
(:data:`REJECT_REASONS`) and goes on.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

from mogs_node import msgs
from mogs_node.errors import MogsError

__all__ = [
    "REJECT_REASONS",
    "ImuSample",
    "ImuSampleError",
    "ImuSampleParser",
    "parse_imu_line",
    "parse_imu_map",
]

REJECT_REASONS = ("encoding", "fields", "number", "non_finite", "not_increasing")

_INT = re.compile(r"[0-9]+\Z")
_FLOAT = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?\Z")
_WORD = re.compile(r"[+-]?(?:nan|inf|infinity)\Z", re.IGNORECASE)
_MAX_T_NS = (1 << 63) - 1


class ImuSampleError(MogsError, ValueError):
    """A rejected IMU sample; ``reason`` is one of :data:`REJECT_REASONS`."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(f"{reason}: {message}")
        self.reason = reason


@dataclass(frozen=True)
class ImuSample:
    t_ns: int
    gyro_rad_s: tuple[float, float, float]
    accel_m_s2: tuple[float, float, float]

    def message(self, frame_id: str) -> msgs.Imu:
        """This sample as the ``/imu`` message of frame ``frame_id``."""
        return msgs.Imu(self.t_ns, frame_id, self.gyro_rad_s, self.accel_m_s2)


def _float(text: str, name: str) -> float:
    s = text.strip()
    if _WORD.match(s):
        raise ImuSampleError("non_finite", f"{name} is {s!r}")
    if not _FLOAT.match(s):
        raise ImuSampleError("number", f"{name} is not a decimal number: {s[:32]!r}")
    v = float(s)
    if not math.isfinite(v):
        raise ImuSampleError("non_finite", f"{name} overflows: {s[:32]!r}")
    return v


def _check_t(t: int) -> int:
    if t > _MAX_T_NS:
        raise ImuSampleError("number", f"t_ns {t} beyond int64")
    return t


def parse_imu_line(line: str | bytes) -> ImuSample | None:
    """One text line -> :class:`ImuSample`, None for a blank or ``#`` comment line.

    Raises :class:`ImuSampleError` (reason ``encoding``, ``fields``, ``number`` or
    ``non_finite``); time order is checked by :class:`ImuSampleParser`.
    """
    if isinstance(line, bytes | bytearray):
        try:
            line = bytes(line).decode("utf-8")
        except UnicodeDecodeError as err:
            raise ImuSampleError("encoding", "line is not UTF-8") from err
    s = line.strip()
    if not s or s.startswith("#"):
        return None
    parts = s.split(",")
    if len(parts) != 7:
        raise ImuSampleError("fields", f"expected 7 comma-separated fields, got {len(parts)}")
    t_text = parts[0].strip()
    if not _INT.match(t_text):
        raise ImuSampleError("number", f"t_ns is not a non-negative integer: {t_text[:32]!r}")
    names = ("gx", "gy", "gz", "ax", "ay", "az")
    v = [_float(p, n) for p, n in zip(parts[1:], names)]
    return ImuSample(_check_t(int(t_text)), (v[0], v[1], v[2]), (v[3], v[4], v[5]))


def _vec(value: Any, name: str) -> tuple[float, float, float]:
    if not isinstance(value, list | tuple) or len(value) != 3:
        raise ImuSampleError("fields", f"{name} must be a list of 3 numbers")
    out = []
    for i, x in enumerate(value):
        if isinstance(x, bool) or not isinstance(x, int | float):
            raise ImuSampleError("number", f"{name}[{i}] is not a number")
        fx = float(x)
        if not math.isfinite(fx):
            raise ImuSampleError("non_finite", f"{name}[{i}] is {fx}")
        out.append(fx)
    return (out[0], out[1], out[2])


def parse_imu_map(obj: Any) -> ImuSample:
    """A decoded msgpack map ``{"t_ns", "gyro", "accel"}`` -> :class:`ImuSample` (strict)."""
    if not isinstance(obj, dict):
        raise ImuSampleError("fields", f"expected a map, got {type(obj).__name__}")
    keys = set(obj)
    if keys != {"t_ns", "gyro", "accel"}:
        raise ImuSampleError(
            "fields", f"expected keys t_ns, gyro, accel; got {sorted(map(str, keys))}"
        )
    t = obj["t_ns"]
    if isinstance(t, bool) or not isinstance(t, int) or t < 0:
        raise ImuSampleError("number", f"t_ns must be an int >= 0, got {t!r}")
    return ImuSample(_check_t(t), _vec(obj["gyro"], "gyro"), _vec(obj["accel"], "accel"))


@dataclass
class ImuSampleParser:
    """Stateful: parses lines or maps, rejects time going backwards, counts every rejection."""

    last_t_ns: int | None = None
    accepted: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REJECT_REASONS, 0))
    last_error: str = ""

    def _accept(self, s: ImuSample) -> ImuSample:
        if self.last_t_ns is not None and s.t_ns <= self.last_t_ns:
            raise ImuSampleError(
                "not_increasing", f"t_ns {s.t_ns} is not after the previous {self.last_t_ns}"
            )
        self.last_t_ns = s.t_ns
        self.accepted += 1
        return s

    def _reject(self, err: ImuSampleError) -> None:
        self.rejected[err.reason] += 1
        self.last_error = str(err)

    def feed_line(self, line: str | bytes) -> ImuSample | None:
        """A sample, or None (blank / comment / rejected and counted)."""
        try:
            s = parse_imu_line(line)
            return None if s is None else self._accept(s)
        except ImuSampleError as err:
            self._reject(err)
            return None

    def feed_map(self, obj: Any) -> ImuSample | None:
        try:
            return self._accept(parse_imu_map(obj))
        except ImuSampleError as err:
            self._reject(err)
            return None

    def reject(self, reason: str, message: str) -> None:
        """Count a rejection found outside the parser (e.g. undecodable msgpack)."""
        self._reject(ImuSampleError(reason, message))

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


class LineSplitter:
    """Bytes in arbitrary chunks -> complete lines (the last, unfinished one is kept)."""

    def __init__(self, max_line_bytes: int = 4096) -> None:
        self._buf = b""
        self.max_line_bytes = max_line_bytes
        self.overlong = 0

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        *lines, self._buf = self._buf.split(b"\n")
        if len(self._buf) > self.max_line_bytes:  # garbage without line ends: drop it
            self._buf = b""
            self.overlong += 1
        out = []
        for ln in lines:
            if len(ln) > self.max_line_bytes:
                self.overlong += 1
                continue
            out.append(ln.rstrip(b"\r"))
        return out
