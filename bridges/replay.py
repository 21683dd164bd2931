"""Pure helpers of the players: event order, start/end windows, the replay clock, flow control.

Nothing here touches the bus or the clock of the machine; callers pass ``now_s`` (a monotonic time
in seconds) so that every rule is testable without sleeping.

- :func:`build_events` merges frame and IMU stamps into one time-ordered list (IMU first at equal
  stamps, as a live driver delivers them: a filter has the IMU up to the image time).
- :func:`select_window` keeps the frames in ``[start_s, end_s]`` (seconds after the first frame)
  and the IMU samples from ``imu_lead_s`` before the first kept frame to the last kept frame.
- :class:`ReplayClock` maps recorded stamps to monotonic due times at a rate (1x, Nx), with pause
  and resume that shift the schedule by the paused time.
- :class:`FlowWindow` bounds the number of items in flight: an item is done when an
  acknowledgement with a stamp at or after its own arrives (a later acknowledgement covers earlier
  items, so an item the consumer skipped cannot block the stream forever).
- :class:`RateMeter` counts published frames and reports the recent rate for the progress line.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from mogs_node.errors import ConfigError

__all__ = [
    "IMU",
    "IMAGE",
    "Event",
    "FlowWindow",
    "RateMeter",
    "ReplayClock",
    "build_events",
    "format_progress",
    "select_window",
]

IMU = "imu"
IMAGE = "image"

Event = tuple[int, str, int]  # (stamp_ns, IMU | IMAGE, index into the frames or IMU samples)


def _stamps(name: str, stamps_ns: object) -> np.ndarray:
    a = np.asarray(stamps_ns)
    if a.ndim != 1 or (a.size and a.dtype.kind not in "iu"):
        raise ConfigError(
            f"{name}: expected a 1-D integer array of ns stamps, got {a.dtype} {a.shape}"
        )
    return a.astype(np.int64)


def build_events(frame_stamps_ns: object, imu_stamps_ns: object = ()) -> list[Event]:
    """Time-ordered ``(stamp_ns, kind, index)`` of frames ``[F]`` and IMU samples ``[M]`` (int ns).

    At equal stamps the IMU sample comes first; equal stamps of one kind keep their index order.
    """
    f = _stamps("frame_stamps_ns", frame_stamps_ns)
    m = _stamps("imu_stamps_ns", imu_stamps_ns)
    ev = [(int(t), 0, i) for i, t in enumerate(m)] + [(int(t), 1, i) for i, t in enumerate(f)]
    ev.sort()
    return [(t, IMU if k == 0 else IMAGE, i) for t, k, i in ev]


def select_window(
    events: list[Event],
    *,
    start_s: float = 0.0,
    end_s: float | None = None,
    imu_lead_s: float = 1.2,
) -> list[Event]:
    """Events of the frames whose stamp lies in ``[t0 + start_s, t0 + end_s]`` (``t0``: the first
    frame's stamp) and of the IMU samples from ``imu_lead_s`` before the first kept frame up to the
    last kept frame. ``end_s`` None: to the end. Without frames every IMU sample is kept.
    """
    if start_s < 0 or (end_s is not None and end_s < start_s) or imu_lead_s < 0:
        raise ConfigError(
            f"start_s/end_s/imu_lead_s: need 0 <= start_s <= end_s and imu_lead_s >= 0, got "
            f"{start_s}, {end_s}, {imu_lead_s}"
        )
    frames = [e for e in events if e[1] == IMAGE]
    if not frames:
        return list(events)
    t0 = frames[0][0]
    lo = t0 + round(start_s * 1e9)
    hi = None if end_s is None else t0 + round(end_s * 1e9)
    kept = [e for e in frames if e[0] >= lo and (hi is None or e[0] <= hi)]
    if not kept:
        return []
    imu_lo, imu_hi = kept[0][0] - round(imu_lead_s * 1e9), kept[-1][0]
    keep_frames = {e[2] for e in kept}
    return [
        e
        for e in events
        if (e[1] == IMAGE and e[2] in keep_frames) or (e[1] == IMU and imu_lo <= e[0] <= imu_hi)
    ]


@dataclass
class ReplayClock:
    """Recorded stamps -> monotonic due times at ``rate`` (0 = as fast as possible).

    The schedule starts at the first :meth:`due_s` call: the first event is due then. ``pause``
    freezes the schedule; ``resume`` shifts it by the time spent paused.
    """

    rate: float = 1.0
    _origin_ns: int | None = None
    _origin_s: float = 0.0
    _paused_at_s: float | None = None
    paused_total_s: float = 0.0

    def __post_init__(self) -> None:
        if not (self.rate >= 0 and np.isfinite(self.rate)):
            raise ConfigError(f"rate: expected a finite number >= 0, got {self.rate}")

    @property
    def paused(self) -> bool:
        return self._paused_at_s is not None

    def pause(self, now_s: float) -> None:
        if self._paused_at_s is None:
            self._paused_at_s = now_s

    def resume(self, now_s: float) -> None:
        if self._paused_at_s is not None:
            self.paused_total_s += max(0.0, now_s - self._paused_at_s)
            self._paused_at_s = None

    def due_s(self, stamp_ns: int, now_s: float) -> float:
        """Monotonic time at which ``stamp_ns`` is due (``inf`` while paused)."""
        if self._paused_at_s is not None:
            return float("inf")
        if self._origin_ns is None:
            self._origin_ns, self._origin_s = int(stamp_ns), now_s
        if self.rate == 0:
            return self._origin_s + self.paused_total_s
        return self._origin_s + self.paused_total_s + (stamp_ns - self._origin_ns) / 1e9 / self.rate

    def is_due(self, stamp_ns: int, now_s: float) -> bool:
        return now_s >= self.due_s(stamp_ns, now_s)


@dataclass
class FlowWindow:
    """At most ``max_in_flight`` items (by stamp) sent and not yet acknowledged (0 = unbounded).

    ``ack(stamp_ns)`` marks every item with a stamp ``<= stamp_ns`` done: acknowledgements are
    cumulative, as the consumers process in stamp order.
    """

    max_in_flight: int = 2
    _pending: deque[int] = field(default_factory=deque)
    acked: int = 0
    last_ack_ns: int | None = None

    def __post_init__(self) -> None:
        if self.max_in_flight < 0:
            raise ConfigError(f"max_in_flight: expected >= 0, got {self.max_in_flight}")

    @property
    def in_flight(self) -> int:
        return len(self._pending)

    def can_send(self) -> bool:
        return self.max_in_flight == 0 or len(self._pending) < self.max_in_flight

    def sent(self, stamp_ns: int) -> None:
        if self.last_ack_ns is not None and stamp_ns <= self.last_ack_ns:
            return  # already covered by an acknowledgement
        self._pending.append(int(stamp_ns))

    def ack(self, stamp_ns: int) -> int:
        """Acknowledge everything up to ``stamp_ns``; returns how many items that completed."""
        n = 0
        while self._pending and self._pending[0] <= stamp_ns:
            self._pending.popleft()
            n += 1
        self.acked += n
        if self.last_ack_ns is None or stamp_ns > self.last_ack_ns:
            self.last_ack_ns = int(stamp_ns)
        return n


@dataclass
class RateMeter:
    """Frames per second over the last ``window_s`` seconds."""

    window_s: float = 5.0
    _times: list[float] = field(default_factory=list)

    def tick(self, now_s: float) -> None:
        self._times.append(now_s)
        cut = bisect.bisect_left(self._times, now_s - self.window_s)
        if cut:
            del self._times[:cut]

    def rate_hz(self, now_s: float) -> float:
        times = [t for t in self._times if t >= now_s - self.window_s]
        if len(times) < 2 or times[-1] <= times[0]:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0])


def format_progress(
    done: int, total: int, rate_hz: float, *, imu: int = 0, state: str = "", width: int = 20
) -> str:
    """``[########------------] 34/78 frames (43.6%) 10.0 Hz imu 1234 paused``."""
    frac = 0.0 if total <= 0 else min(1.0, done / total)
    filled = int(round(frac * width))
    bar = "#" * filled + "-" * (width - filled)
    text = f"[{bar}] {done}/{total} frames ({100 * frac:.1f}%) {rate_hz:.1f} Hz imu {imu}"
    return f"{text} {state}" if state else text
