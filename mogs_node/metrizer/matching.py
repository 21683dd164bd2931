"""The metrizer's keyframe join: keyframe + masks + prior matched by keyframe id, and the adapter
from a matched set of messages to :class:`~mogs_node.metrizer.inputs.MetrizerInputs`.

Pure (no bus; time is passed in), so the node shell (:mod:`mogs_node.metrizer.node`) and the
evaluation (:mod:`mogs_node.eval`) share it. The waiting policy is the node's (see its docstring).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from mogs_node.errors import ConfigError
from mogs_node.metrizer.inputs import MetrizerInputs

__all__ = ["INPUT_SLOTS", "KeyframeMatcher", "MatchedKeyframe", "WorkerPace", "metrizer_inputs"]


@dataclass
class MatchedKeyframe:
    """One keyframe's inputs; ``masks`` / ``prior`` are None when they did not come, and then
    ``missing`` says why (the worker's failure notice, a silent worker, an eviction)."""

    keyframe_id: int
    keyframe: Any = None
    masks: Any = None
    prior: Any = None
    first_seen_s: float = 0.0
    missing: dict[str, str] = field(default_factory=dict)  # input slot -> why it is absent

    @property
    def complete(self) -> bool:
        return self.keyframe is not None and self.masks is not None and self.prior is not None

    def answered(self, slot: str) -> bool:
        """Whether ``slot`` holds its input or the reason it has none."""
        return getattr(self, slot) is not None or slot in self.missing

    @property
    def ready(self) -> bool:
        return self.keyframe is not None and all(self.answered(s) for s in INPUT_SLOTS)


INPUT_SLOTS = ("masks", "prior")  # the worker outputs a keyframe waits for


@dataclass
class WorkerPace:
    """When a worker's outputs arrive: the last one and a running mean of the interval [s]."""

    last_arrival_s: float | None = None
    interval_s: float = 0.0
    alive_s: float = -np.inf  # the worker's last heartbeat (it computes: not silent)
    given_up: int = 0  # keyframes released without this worker's output (it was silent)

    def arrived(self, now_s: float) -> None:
        if self.last_arrival_s is not None:
            dt = max(0.0, now_s - self.last_arrival_s)
            self.interval_s = dt if self.interval_s == 0.0 else 0.7 * self.interval_s + 0.3 * dt
        self.last_arrival_s = now_s


class KeyframeMatcher:
    """Matches keyframe / masks / prior by keyframe id; the wait follows the workers' backlog.

    Pure: time is passed in. ``add`` returns the sets that became ready, ``expire(now_s)`` those
    whose wait is over. A missing input is waited for as long as its worker lives: a keyframe
    gives up on the worker of a slot only when that worker has published nothing, heartbeats
    (:meth:`worker_alive`) included, for ``max_wait_s + stall_factor * interval * (ahead + 1)``
    since its last output (or since the keyframe came, if later), where ``interval`` is the running mean of the worker's output interval
    and ``ahead`` counts the keyframes queued before this one at that worker. Before a worker's
    first output the wait is at least ``first_wait_s`` (start-up, first-use compiles), once.
    A failure notice (:mod:`mogs_node.keyframe_chain`) answers a slot at once, with its reason.
    ``counters``: complete, partial (released without an input), failed_inputs (failure notices),
    stalled_inputs (a silent worker), evicted (beyond ``max_pending``), dropped (inputs without a
    keyframe, or arriving after it was released), duplicates.
    """

    SLOTS = ("keyframe", *INPUT_SLOTS)

    def __init__(
        self,
        max_wait_s: float = 2.0,
        max_pending: int = 32,
        *,
        stall_factor: float = 2.0,
        first_wait_s: float = 0.0,
    ) -> None:
        self.max_wait_s = max_wait_s
        self.max_pending = max_pending
        self.stall_factor = stall_factor
        self.first_wait_s = first_wait_s
        self.pace = {s: WorkerPace() for s in INPUT_SLOTS}
        self._pending: OrderedDict[int, MatchedKeyframe] = OrderedDict()
        self._released: OrderedDict[int, None] = OrderedDict()  # ids released, most recent last
        self.counters = dict.fromkeys(
            (
                "complete",
                "partial",
                "failed_inputs",
                "stalled_inputs",
                "evicted",
                "dropped",
                "duplicates",
            ),
            0,
        )

    def __len__(self) -> int:
        return len(self._pending)

    def add(
        self, slot: str, keyframe_id: int, msg: Any, now_s: float, failure: str | None = None
    ) -> list[MatchedKeyframe]:
        """Store ``msg`` in ``slot`` of ``keyframe_id`` (``failure``: the worker's notice that it
        has none, with the reason); return the sets ready to process."""
        if slot not in self.SLOTS:
            raise ConfigError(f"KeyframeMatcher.add: unknown slot {slot!r}")
        if slot in self.pace:
            self.pace[slot].arrived(now_s)
        if keyframe_id in self._released:
            self.counters["dropped"] += 1  # its keyframe went without it (a stalled worker)
            return []
        entry = self._pending.get(keyframe_id)
        if entry is None:
            entry = self._pending[keyframe_id] = MatchedKeyframe(keyframe_id, first_seen_s=now_s)
        if getattr(entry, slot) is not None or slot in entry.missing:
            self.counters["duplicates"] += 1
        if failure is not None and slot != "keyframe":
            entry.missing[slot] = f"{slot} backend failed: {failure}"
            self.counters["failed_inputs"] += 1
        else:
            setattr(entry, slot, msg)
        ready = self._release_ready()
        while len(self._pending) > self.max_pending:
            _, old = self._pending.popitem(last=False)
            for s in INPUT_SLOTS:
                if not old.answered(s):
                    old.missing[s] = f"evicted: more than {self.max_pending} keyframes waiting"
            self.counters["evicted"] += 1
            ready.extend(self._release(old))
        return ready

    def _release_ready(self) -> list[MatchedKeyframe]:
        out = []
        for kid in [k for k, e in self._pending.items() if e.ready]:
            out.extend(self._release(self._pending.pop(kid)))
        return out

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

    def expire(self, now_s: float) -> list[MatchedKeyframe]:
        """Sets whose wait is over: a worker silent beyond its backlog, or inputs without a
        keyframe (dropped after the same wait)."""
        ahead = dict.fromkeys(INPUT_SLOTS, 0)
        for entry in sorted(self._pending.values(), key=lambda e: e.keyframe_id):
            waits = []
            for slot in INPUT_SLOTS:
                if entry.answered(slot):
                    continue
                pace = self.pace[slot]
                last = pace.last_arrival_s if pace.last_arrival_s is not None else -np.inf
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

    def _release(self, entry: MatchedKeyframe) -> list[MatchedKeyframe]:
        self._released[entry.keyframe_id] = None
        while len(self._released) > 4 * self.max_pending:
            self._released.popitem(last=False)
        if entry.keyframe is None:
            self.counters["dropped"] += 1
            return []
        self.counters["complete" if entry.complete else "partial"] += 1
        return [entry]


def metrizer_inputs(entry: MatchedKeyframe) -> MetrizerInputs:
    """:class:`MetrizerInputs` of one matched set (missing parts handled); it also unpacks as the
    keyword arguments of :func:`~mogs_node.metrizer.pipeline.metrize_depth`."""
    kf = entry.keyframe
    img = kf.image
    H, W = img.shape[:2]
    rgb = img if img.ndim == 3 else np.repeat(img[..., None], 3, axis=2)
    if entry.masks is not None:
        labels = np.asarray(entry.masks.labels, dtype=np.int32)
        if labels.shape != (H, W):
            labels = cv2.resize(labels, (W, H), interpolation=cv2.INTER_NEAREST)
    else:
        labels = np.full((H, W), -1, np.int32)
    if entry.prior is not None:
        prior = np.asarray(entry.prior.depth, dtype=np.float32)
        conf = np.asarray(entry.prior.confidence, dtype=np.float32)
        kind = entry.prior.kind
        if prior.shape != (H, W):
            prior = cv2.resize(prior, (W, H), interpolation=cv2.INTER_LINEAR)
            conf = cv2.resize(conf, (W, H), interpolation=cv2.INTER_LINEAR)
        if kind in ("metric", "relative_depth"):
            conf = np.where(prior > 0, conf, 0.0).astype(np.float32)  # 0 = no value
    else:
        prior, conf, kind = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32), "metric"
    xyz = np.asarray(kf.feature_xyz_cam_m, dtype=np.float64)
    return MetrizerInputs(
        K=np.asarray(kf.K, dtype=np.float64),
        labels=labels,
        feature_uv_px=np.asarray(kf.feature_uv_px, dtype=np.float64),
        feature_depth_m=xyz[:, 2],
        feature_weight=np.asarray(kf.feature_weight),
        prior=prior,
        prior_confidence=conf,
        prior_kind=kind,
        image_rgb=np.ascontiguousarray(rgb),
    )
