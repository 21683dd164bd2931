"""The keyframe join: a keyframe and n inputs (masks, prior, depth, ...) matched by keyframe id,
bounded in count and in time, counting everything it gives up.

One join for every node that pairs inputs: the metrizer joins keyframe + masks + prior
(:class:`~mogs_node.metrizer.matching.KeyframeMatcher`), the mapper keyframe + metrized depth
(``mogs_node.mapper.node``). Pure: no bus, time is passed in, so a unit test drives it with
numbers and the evaluation runs the same code in-process.

Policy, per keyframe id:

- ``add`` stores a message (or a worker's failure notice for that input) and returns the entries
  that became ready: the keyframe and every input answered (a message or the reason it has none).
- count bound: beyond ``max_pending`` waiting entries the oldest is evicted; its missing inputs
  are answered "evicted" and it is released partial (``release_partial``) or dropped.
- time bound (:meth:`KeyframeJoin.expire`): an input is waited for as long as its worker lives.
  A keyframe gives up on the worker of an input when that worker has published nothing,
  heartbeats (:meth:`KeyframeJoin.worker_alive`) included, for
  ``max_wait_s + stall_factor * interval * (ahead + 1)`` since its last output (or since the
  keyframe came, if later), where ``interval`` is the running mean of the worker's output
  interval and ``ahead`` counts the keyframes queued before this one at that worker. Before a
  worker's first output the wait is at least ``first_wait_s`` (start-up, first-use compiles),
  once. Inputs without a keyframe are dropped after ``max_wait_s + first_wait_s``.
  ``max_wait_s = inf`` (the default) never gives up by time.

``counters``: complete, partial (released without an input), failed_inputs (failure notices),
stalled_inputs (a silent worker), evicted (beyond ``max_pending``), dropped (inputs without a
keyframe, arriving after it was released, or an entry given up without ``release_partial``),
duplicates.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

from mogs_node.errors import ConfigError

__all__ = ["COUNTERS", "JoinedKeyframe", "KeyframeJoin", "WorkerPace"]

COUNTERS = (
    "complete",
    "partial",
    "failed_inputs",
    "stalled_inputs",
    "evicted",
    "dropped",
    "duplicates",
)


class JoinedKeyframe:
    """One keyframe's messages: ``keyframe`` and ``inputs`` (input name -> message); an input
    that did not come is absent from ``inputs`` and ``missing`` says why (the worker's failure
    notice, a silent worker, an eviction)."""

    def __init__(
        self,
        keyframe_id: int,
        keyframe: Any = None,
        inputs: dict[str, Any] | None = None,
        first_seen_s: float = 0.0,
        missing: dict[str, str] | None = None,
    ) -> None:
        self.keyframe_id = keyframe_id
        self.keyframe = keyframe
        self.inputs: dict[str, Any] = {k: v for k, v in (inputs or {}).items() if v is not None}
        self.first_seen_s = first_seen_s
        self.missing: dict[str, str] = dict(missing or {})  # input name -> why it is absent

    def get(self, slot: str) -> Any:
        """The message of ``slot`` ("keyframe" or an input name), None if it has none."""
        return self.keyframe if slot == "keyframe" else self.inputs.get(slot)

    def put(self, slot: str, msg: Any) -> None:
        if slot == "keyframe":
            self.keyframe = msg
        else:
            self.inputs[slot] = msg

    def answered(self, slot: str) -> bool:
        """Whether ``slot`` holds its message or the reason it has none."""
        return self.get(slot) is not None or slot in self.missing

    def complete_for(self, names: tuple[str, ...]) -> bool:
        return self.keyframe is not None and all(self.get(s) is not None for s in names)

    def ready_for(self, names: tuple[str, ...]) -> bool:
        return self.keyframe is not None and all(self.answered(s) for s in names)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({self.keyframe_id}, keyframe={self.keyframe!r}, "
            f"inputs={self.inputs!r}, missing={self.missing!r})"
        )


@dataclass
class WorkerPace:
    """When a worker's outputs arrive: the last one and a running mean of the interval [s]."""

    last_arrival_s: float | None = None
    interval_s: float = 0.0
    alive_s: float = -math.inf  # the worker's last heartbeat (it computes: not silent)
    given_up: int = 0  # keyframes released without this worker's output (it was silent)

    def arrived(self, now_s: float) -> None:
        if self.last_arrival_s is not None:
            dt = max(0.0, now_s - self.last_arrival_s)
            self.interval_s = dt if self.interval_s == 0.0 else 0.7 * self.interval_s + 0.3 * dt
        self.last_arrival_s = now_s


class KeyframeJoin:
    """Joins a keyframe with the inputs named ``inputs`` by keyframe id (the policy: see the
    module docstring). ``entry_type`` builds the entries (a subclass may name its inputs)."""

    def __init__(
        self,
        inputs: tuple[str, ...],
        *,
        max_wait_s: float = math.inf,
        max_pending: int = 32,
        stall_factor: float = 2.0,
        first_wait_s: float = 0.0,
        release_partial: bool = True,
        entry_type: type[JoinedKeyframe] = JoinedKeyframe,
    ) -> None:
        if not inputs or "keyframe" in inputs or len(set(inputs)) != len(inputs):
            raise ConfigError(f"KeyframeJoin: inputs {inputs!r} must be distinct, not 'keyframe'")
        if max_pending < 1:
            raise ConfigError(f"KeyframeJoin: max_pending must be >= 1, got {max_pending}")
        self.inputs = tuple(inputs)
        self.slots = ("keyframe", *self.inputs)
        self.max_wait_s = max_wait_s
        self.max_pending = max_pending
        self.stall_factor = stall_factor
        self.first_wait_s = first_wait_s
        self.release_partial = release_partial
        self.entry_type = entry_type
        self.pace = {s: WorkerPace() for s in self.inputs}
        self._pending: OrderedDict[int, JoinedKeyframe] = OrderedDict()
        self._released: OrderedDict[int, None] = OrderedDict()  # ids released, most recent last
        self.counters = dict.fromkeys(COUNTERS, 0)

    def __len__(self) -> int:
        return len(self._pending)

    def add(
        self, slot: str, keyframe_id: int, msg: Any, now_s: float = 0.0, failure: str | None = None
    ) -> list[JoinedKeyframe]:
        """Store ``msg`` in ``slot`` of ``keyframe_id`` (``failure``: the worker's notice that it
        has none, with the reason); return the entries ready to process."""
        if slot not in self.slots:
            raise ConfigError(f"{type(self).__name__}.add: unknown slot {slot!r}")
        if slot in self.pace:
            self.pace[slot].arrived(now_s)
        if keyframe_id in self._released:
            self.counters["dropped"] += 1  # its keyframe went without it (given up on)
            return []
        entry = self._pending.get(keyframe_id)
        if entry is None:
            entry = self._pending[keyframe_id] = self.entry_type(keyframe_id, first_seen_s=now_s)
        if entry.answered(slot):
            self.counters["duplicates"] += 1
        if failure is not None and slot != "keyframe":
            entry.missing[slot] = f"{slot} backend failed: {failure}"
            self.counters["failed_inputs"] += 1
        else:
            entry.put(slot, msg)
        ready = self._release_ready()
        while len(self._pending) > self.max_pending:
            _, old = self._pending.popitem(last=False)
            for s in self.inputs:
                if not old.answered(s):
                    old.missing[s] = f"evicted: more than {self.max_pending} keyframes waiting"
            self.counters["evicted"] += 1
            ready.extend(self._release(old))
        return ready

    def worker_alive(self, slot: str, now_s: float) -> None:
        """A heartbeat of ``slot``'s worker: it lives, so the keyframes waiting for it wait on."""
        self.pace[slot].alive_s = now_s

    def patience_s(self, slot: str, ahead: int) -> float:
        """How long a keyframe waits for ``slot`` after its worker's last output [s]."""
        pace = self.pace[slot]
        wait = self.max_wait_s + self.stall_factor * pace.interval_s * (ahead + 1)
        if pace.last_arrival_s is None and pace.given_up == 0:
            wait = max(wait, self.first_wait_s)
        return wait

    def expire(self, now_s: float) -> list[JoinedKeyframe]:
        """Entries whose wait is over: a worker silent beyond its backlog, or inputs without a
        keyframe (dropped after the same wait)."""
        ahead = dict.fromkeys(self.inputs, 0)
        for entry in sorted(self._pending.values(), key=lambda e: e.keyframe_id):
            waits = []
            for slot in self.inputs:
                if entry.answered(slot):
                    continue
                pace = self.pace[slot]
                last = pace.last_arrival_s if pace.last_arrival_s is not None else -math.inf
                since = max(entry.first_seen_s, last, pace.alive_s)
                if now_s - since >= self.patience_s(slot, ahead[slot]):
                    waits.append((slot, now_s - since))
                ahead[slot] += 1
            if entry.keyframe is None:
                if now_s - entry.first_seen_s >= self.max_wait_s + self.first_wait_s:
                    self._pending.pop(entry.keyframe_id)
                    self.counters["dropped"] += 1
                continue
            for slot, silent_s in waits:
                entry.missing[slot] = f"{slot} worker silent for {silent_s:.1f} s"
                self.pace[slot].given_up += 1
                self.counters["stalled_inputs"] += 1
        return self._release_ready()

    def _release_ready(self) -> list[JoinedKeyframe]:
        out = []
        for kid in [k for k, e in self._pending.items() if e.ready_for(self.inputs)]:
            out.extend(self._release(self._pending.pop(kid)))
        return out

    def _release(self, entry: JoinedKeyframe) -> list[JoinedKeyframe]:
        self._released[entry.keyframe_id] = None
        while len(self._released) > 4 * self.max_pending:
            self._released.popitem(last=False)
        complete = entry.complete_for(self.inputs)
        if entry.keyframe is None or not (complete or self.release_partial):
            self.counters["dropped"] += 1
            return []
        self.counters["complete" if complete else "partial"] += 1
        return [entry]
