"""Shedding whole keyframes when the keyframe chain cannot keep up (issue 28).

The chain frontend -> segmentation + prior -> metrizer is the latency-critical path: a keyframe is
worth having only with its masks and prior. When a real-time source (a live camera, a replay at its
recorded rate) makes keyframes faster than the chain turns them into metric depth, the backlog
grows without bound and every keyframe's depth comes later and later. Dropping a keyframe's
*inputs* to catch up (as a fixed wait in the metrizer did) empties keyframes while still feeding
the mapper; this module sheds *whole keyframes* instead, at the one place that makes them: the
frontend's keyframe selection asks :class:`KeyframeBacklog` before publishing a keyframe.

The backlog is the number of keyframes published and not yet through the chain (no
``/metrizer/depth`` with their id or a later one: the chain works in keyframe order). While it is
at ``max_backlog`` a new keyframe is shed: the frontend keeps it for its own tracking and estimator
(nothing there changes) but publishes nothing, and counts it with its reason. The next keyframe is
published as soon as the chain has room again, so the keyframes that go through are the freshest
ones and the chain's latency stays bounded by ``max_backlog`` keyframes' worth of work.
``max_backlog`` 0 turns shedding off (a replay that waits for its pipeline never needs it).

Pure: no bus, no clock; the node feeds it the ids it publishes and the ids the chain finished.
"""

from __future__ import annotations

from dataclasses import dataclass

from mogs_node.errors import ConfigError

__all__ = ["BacklogParams", "KeyframeBacklog"]

SHED_REASON_BACKLOG = "backlog"  # the chain had max_backlog keyframes in flight


@dataclass(frozen=True)
class BacklogParams:
    """Keyframe shedding: ``max_backlog`` keyframes in the chain at most (0 = never shed)."""

    max_backlog: int = 0
    done_topic: str = "/metrizer/depth"  # a keyframe's id (or a later one) here: it is through

    def __post_init__(self) -> None:
        if self.max_backlog < 0:
            raise ConfigError(f"backlog.max_backlog: must be >= 0, got {self.max_backlog}")


class KeyframeBacklog:
    """Counts the keyframes in the chain and decides which new keyframes to shed."""

    def __init__(self, params: BacklogParams) -> None:
        self.params = params
        self._in_flight: list[int] = []  # published ids not yet through, ascending
        self.shed: dict[str, int] = {}  # reason -> keyframes shed for it
        self.last_shed_id: int | None = None

    @property
    def backlog(self) -> int:
        """Keyframes published and not yet through the chain."""
        return len(self._in_flight)

    @property
    def shed_total(self) -> int:
        return sum(self.shed.values())

    def done(self, keyframe_id: int) -> None:
        """The chain finished ``keyframe_id``: it and every earlier keyframe are through."""
        self._in_flight = [k for k in self._in_flight if k > keyframe_id]

    def admit(self, keyframe_id: int) -> str | None:
        """Whether to publish ``keyframe_id``: None (published: it counts as in flight) or the
        reason it is shed (counted)."""
        cap = self.params.max_backlog
        if cap > 0 and len(self._in_flight) >= cap:
            self.shed[SHED_REASON_BACKLOG] = self.shed.get(SHED_REASON_BACKLOG, 0) + 1
            self.last_shed_id = keyframe_id
            return (
                f"{SHED_REASON_BACKLOG}: {len(self._in_flight)} keyframes in the chain (max {cap})"
            )
        self._in_flight.append(keyframe_id)
        return None
