"""Shedding whole keyframes when the keyframe chain cannot keep up (issue 28).

The chain frontend -> segmentation + prior -> metrizer is the latency-critical path: a keyframe is
worth having only with its masks and prior. When a real-time source (a live camera, a replay at its
recorded rate) makes keyframes faster than the chain turns them into metric depth, the backlog
grows without bound and every keyframe's depth comes later and later. Dropping a keyframe's
*inputs* to catch up (as a fixed wait in the metrizer did) empties keyframes while still feeding
the mapper; this module sheds *whole keyframes* instead, at the one place that makes them: the
frontend's keyframe selection asks :class:`KeyframeBacklog` before publishing a keyframe.

The backlog is the keyframes published and not yet through the chain (no ``/metrizer/depth``
with their id or a later one: the chain works in keyframe order). It is measured two ways:

- in keyframes: while ``max_backlog`` are in the chain, a new keyframe is shed (reason
  ``backlog``), a hard bound on the chain's memory and queue;
- in time: the chain's *service time* per keyframe (the time from the moment it could start on
  a keyframe, its publication or its predecessor's depth, whichever is later, to that keyframe's
  depth) is measured on every keyframe through it (a running mean plus its mean deviation, so a
  noisy chain is judged by its slow keyframes, not its typical one). A new keyframe whose depth is
  then predicted to come more than ``max_latency_s`` after its image (the time the image already
  spent in the frontend, plus the rest of the work ahead of it, plus its own service time) is
  shed (reason ``latency``), unless the chain is empty: shedding then only loses a keyframe.

A shed keyframe is kept by the frontend for its own tracking and estimator (nothing there
changes) but nothing is published for it; it is counted with its reason. The next keyframe goes
through as soon as the chain can deliver it in time, so the keyframes that go through are the
freshest ones and a keyframe's image -> depth latency stays near ``max_latency_s`` whatever the
machine, the resolution or the keyframe rate (the queue behind a slow chain, not the work on one
keyframe, is what made the latency grow). ``max_backlog`` 0 and ``max_latency_s`` 0 turn
shedding off (a replay that waits for its pipeline never needs it).

Pure: no bus, no clock; the node feeds it the ids it publishes and the ids the chain finished,
with the time of each (seconds on any monotonic clock).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mogs_node.errors import ConfigError

__all__ = ["BacklogParams", "KeyframeBacklog"]

SHED_REASON_BACKLOG = "backlog"  # the chain had max_backlog keyframes in flight
SHED_REASON_LATENCY = "latency"  # its depth would have come later than max_latency_s
SERVICE_GAIN = 0.3  # weight of the newest service time in the running means


@dataclass(frozen=True)
class BacklogParams:
    """Keyframe shedding: at most ``max_backlog`` keyframes in the chain (0 = no bound) and a
    predicted image -> depth latency of at most ``max_latency_s`` (0 = no bound)."""

    max_backlog: int = 0
    max_latency_s: float = 0.0  # image -> metrized depth budget of a keyframe [s]
    deviations: float = 1.0  # service time predicted as mean + this many mean deviations
    done_topic: str = "/metrizer/depth"  # a keyframe's id (or a later one) here: it is through

    def __post_init__(self) -> None:
        if self.max_backlog < 0:
            raise ConfigError(f"backlog.max_backlog: must be >= 0, got {self.max_backlog}")
        if not (math.isfinite(self.max_latency_s) and self.max_latency_s >= 0):
            raise ConfigError(f"backlog.max_latency_s: must be >= 0, got {self.max_latency_s}")
        if not (math.isfinite(self.deviations) and self.deviations >= 0):
            raise ConfigError(f"backlog.deviations: must be >= 0, got {self.deviations}")

    @property
    def enabled(self) -> bool:
        return self.max_backlog > 0 or self.max_latency_s > 0


class KeyframeBacklog:
    """Counts the keyframes in the chain, measures its service time, decides what to shed."""

    def __init__(self, params: BacklogParams) -> None:
        self.params = params
        self._in_flight: list[tuple[int, float]] = []  # (id, published at), ascending ids
        self._last_done_s = -math.inf  # when the chain last finished a keyframe
        self.service_s = 0.0  # running mean of the chain's service time per keyframe [s]
        self.service_dev_s = 0.0  # running mean absolute deviation of it [s]
        self.measured = 0  # keyframes whose service time was measured
        self.shed: dict[str, int] = {}  # reason -> keyframes shed for it
        self.last_shed_id: int | None = None

    @property
    def backlog(self) -> int:
        """Keyframes published and not yet through the chain."""
        return len(self._in_flight)

    @property
    def shed_total(self) -> int:
        return sum(self.shed.values())

    @property
    def service_bound_s(self) -> float:
        """The service time a keyframe is predicted to need: mean + ``deviations`` deviations."""
        return self.service_s + self.params.deviations * self.service_dev_s

    def done(self, keyframe_id: int, now_s: float = 0.0) -> None:
        """The chain finished ``keyframe_id`` at ``now_s``: it and every earlier keyframe are
        through; the service time of ``keyframe_id`` is measured when it was published here."""
        through = [(k, t) for k, t in self._in_flight if k <= keyframe_id]
        if not through:
            return
        self._in_flight = self._in_flight[len(through) :]
        k, published_s = through[-1]
        if k == keyframe_id:
            start = max(published_s, self._last_done_s)
            self._measure(max(0.0, now_s - start))
        self._last_done_s = now_s

    def _measure(self, service_s: float) -> None:
        if self.measured == 0:
            self.service_s, self.service_dev_s = service_s, 0.0
        else:
            dev = abs(service_s - self.service_s)
            self.service_s += SERVICE_GAIN * (service_s - self.service_s)
            self.service_dev_s += SERVICE_GAIN * (dev - self.service_dev_s)
        self.measured += 1

    def predicted_latency_s(self, now_s: float, image_s: float | None = None) -> float:
        """When a keyframe published at ``now_s`` (its image seen at ``image_s``) would get its
        depth, counted from its image: the keyframes ahead finish one service time after the
        other from the first one's start, then this one takes its own."""
        s = self.service_bound_s
        ready_s = now_s
        if self._in_flight:
            first_start = max(self._in_flight[0][1], self._last_done_s)
            ready_s = max(now_s, first_start + s * len(self._in_flight))
        since = now_s if image_s is None else min(image_s, now_s)
        return ready_s + s - since

    def admit(
        self, keyframe_id: int, now_s: float = 0.0, image_s: float | None = None
    ) -> str | None:
        """Whether to publish ``keyframe_id`` at ``now_s`` (its image seen at ``image_s``):
        None (published: it counts as in flight) or the reason it is shed (counted)."""
        p = self.params
        n = len(self._in_flight)
        reason: tuple[str, str] | None = None
        if p.max_backlog > 0 and n >= p.max_backlog:
            reason = (SHED_REASON_BACKLOG, f"{n} keyframes in the chain (max {p.max_backlog})")
        elif p.max_latency_s > 0 and n > 0 and self.measured > 0:
            late = self.predicted_latency_s(now_s, image_s)
            if late > p.max_latency_s:
                reason = (
                    SHED_REASON_LATENCY,
                    f"depth predicted {late:.1f} s after its image (max {p.max_latency_s:.1f} s; "
                    f"{n} in the chain, {self.service_bound_s:.2f} s each)",
                )
        if reason is not None:
            self.shed[reason[0]] = self.shed.get(reason[0], 0) + 1
            self.last_shed_id = keyframe_id
            return f"{reason[0]}: {reason[1]}"
        self._in_flight.append((keyframe_id, now_s))
        return None
