"""Metrizer node: keyframe + masks + prior -> ``/metrizer/depth`` (DESIGN.md sections 1, 2).

Subscribes (reliable) to ``/frontend/keyframe``, ``/seg/masks`` and ``/prior/depth``, matches the
three by ``keyframe_id`` in :class:`KeyframeMatcher` (pure, no bus) and runs
:func:`~mogs_node.metrizer.pipeline.metrize_depth` on each complete set. A keyframe is metrized
without its masks or prior only when that input has none, never for being late (issue 28):

- a keyframe whose masks and prior are both in is processed at once;
- a worker that fails on a keyframe says so (a failure notice, :mod:`mogs_node.keyframe_chain`):
  that keyframe is processed at once without the input, with a warning naming the reason;
- otherwise the wait follows the worker's backlog: a missing input is given up only when its
  worker has published nothing, not even a heartbeat on ``/diagnostics``, for ``max_wait_s`` plus
  ``stall_factor`` times its measured output interval for every keyframe queued up to this one
  (a dead or absent worker; ``first_wait_s`` before its first output). Without masks every pixel belongs to one unmasked region (MSC then has nothing
  to merge), without a prior the confidence is 0 everywhere (depth then comes from accepted shape
  models and the edge-aware fill only);
- masks or a prior whose keyframe never arrives are dropped after ``max_wait_s + first_wait_s``;
- at most ``max_pending`` keyframes wait (a memory bound; beyond it the oldest is processed early).

Load is shed upstream by whole keyframes (:mod:`mogs_node.frontend.backlog`), never here.
Masks or a prior at a different resolution than the keyframe image are resized to it (nearest
neighbour for labels, bilinear for the prior and its confidence).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from mogs_node import msgs
from mogs_node.errors import ConfigError
from mogs_node.heartbeat import DIAGNOSTICS_TOPIC
from mogs_node.keyframe_chain import failure_reason
from mogs_node.metrizer.consensus import ConsensusParams
from mogs_node.metrizer.pipeline import MODES, MetrizerInputs, MetrizerParams, metrize
from mogs_node.metrizer.refinement import CdrParams
from mogs_node.node import Node, parse_params

__all__ = ["KeyframeMatcher", "MatchedKeyframe", "MetrizerNode", "MetrizerNodeParams"]


@dataclass(frozen=True)
class MetrizerNodeParams:
    """Parameters of the metrizer node."""

    mode: str = "full"  # "full" | "no_msc" | "no_msc_cdr" (ablations)
    max_wait_s: float = 2.0  # silence of a worker beyond its backlog that gives it up [s]
    stall_factor: float = 2.0  # times the worker's output interval per keyframe queued at it
    first_wait_s: float = 60.0  # least wait before a worker's first output (start-up) [s]
    max_pending: int = 32  # keyframes waiting at most; beyond, the oldest is processed early
    poll_period_s: float = 0.05  # how often timed-out keyframes are checked [s]
    metrizer: dict[str, Any] = field(default_factory=dict)  # MetrizerParams fields (flat ones)
    consensus: dict[str, Any] = field(default_factory=dict)  # ConsensusParams fields
    cdr: dict[str, Any] = field(default_factory=dict)  # CdrParams fields
    keyframe_topic: str = "/frontend/keyframe"  # input keyframes
    masks_topic: str = "/seg/masks"  # input instance masks
    prior_topic: str = "/prior/depth"  # input dense prior
    out_topic: str = "/metrizer/depth"  # output metric depth

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"metrizer.mode: expected one of {MODES}, got {self.mode!r}")
        waits = (self.max_wait_s, self.stall_factor, self.first_wait_s)
        if not all(0 <= w < float("inf") for w in waits):
            raise ConfigError(
                "metrizer: max_wait_s, stall_factor and first_wait_s must be finite and >= 0, "
                f"got {waits}"
            )
        if self.max_pending < 1 or self.poll_period_s <= 0:
            raise ConfigError("metrizer: max_pending >= 1, poll_period_s > 0")


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


class MetrizerNode(Node):
    """Publishes metric depth with confidence and per-object shape models for each keyframe."""

    Params = MetrizerNodeParams

    def setup(self) -> None:
        p: MetrizerNodeParams = self.params
        top = dict(p.metrizer)
        top["consensus"] = parse_params(
            ConsensusParams, p.consensus, where=f"{self.name}.consensus"
        )
        top["cdr"] = parse_params(CdrParams, p.cdr, where=f"{self.name}.cdr")
        self.metrizer_params = parse_params(MetrizerParams, top, where=f"{self.name}.metrizer")
        self.matcher = KeyframeMatcher(
            p.max_wait_s, p.max_pending, stall_factor=p.stall_factor, first_wait_s=p.first_wait_s
        )
        self.clock = time.monotonic
        for topic, handler, typ in (
            (p.keyframe_topic, self.on_keyframe, msgs.Keyframe),
            (p.masks_topic, self.on_masks, msgs.Masks),
            (p.prior_topic, self.on_prior, msgs.DepthMap),
        ):
            self.subscribe(topic, handler, reliable=True, msg_type=typ, idempotent=True)
        # a worker's heartbeats say it lives (and computes): its keyframes wait on
        self.subscribe(DIAGNOSTICS_TOPIC, self.on_heartbeat, reliable=False, queue_size=64)
        self.every(p.poll_period_s, self.on_timer)
        # after a restart: the inputs of every keyframe without a metrized depth in the journal
        self.catch_up((p.keyframe_topic, p.masks_topic, p.prior_topic), (p.out_topic,))

    def _add(self, slot: str, msg: Any) -> None:
        if self.already_published(self.params.out_topic, msg.keyframe_id):
            return  # metrized before this process restarted
        failure = failure_reason(msg) if slot != "keyframe" else None
        self._process(self.matcher.add(slot, msg.keyframe_id, msg, self.clock(), failure))

    def on_keyframe(self, msg: msgs.Keyframe) -> None:
        self._add("keyframe", msg)

    def on_masks(self, msg: msgs.Masks) -> None:
        self._add("masks", msg)

    def on_prior(self, msg: msgs.DepthMap) -> None:
        self._add("prior", msg)

    def on_heartbeat(self, msg: msgs.Message) -> None:
        """The worker of a slot is the node whose heartbeat says it published on its topic."""
        topics = getattr(msg, "topics", None)
        if not isinstance(topics, dict) or getattr(msg, "status", "") == "stopped":
            return
        p: MetrizerNodeParams = self.params
        for slot, topic in (("masks", p.masks_topic), ("prior", p.prior_topic)):
            stats = topics.get(topic)
            published = stats.get("published", 0) if isinstance(stats, dict) else 0
            if isinstance(published, int | float) and published > 0:
                self.matcher.worker_alive(slot, self.clock())

    def on_timer(self) -> None:
        if self.queue_depth == 0:  # inputs read but not handled yet may answer the wait
            self._process(self.matcher.expire(self.clock()))
        for k, v in self.matcher.counters.items():
            self.counters[f"match_{k}"] = v
        self.counters["metrized_without_inputs"] = self.matcher.counters["partial"]

    def _process(self, entries: list[MatchedKeyframe]) -> None:
        for entry in entries:
            kf = entry.keyframe
            if entry.missing:
                self.log.warning(
                    "keyframe %d: metrized without %s (%s)",
                    entry.keyframe_id,
                    " and ".join(entry.missing),
                    "; ".join(entry.missing.values()),
                )
            out = metrize(metrizer_inputs(entry), self.metrizer_params, self.params.mode)
            self.publish(
                self.params.out_topic,
                msgs.DepthMap(
                    **kf.result_header(),
                    kind="metric",
                    depth=out.depth_m,
                    confidence=out.confidence,
                    source=f"metrizer:{self.params.mode}",
                    object_labels=out.object_labels,
                    object_model=out.object_model,
                ),
            )
            self.counters["metrize_ms"] = out.stats["ms"]["total"]
            self.log.debug(
                "keyframe %d: %.1f ms, %s",
                entry.keyframe_id,
                out.stats["ms"]["total"],
                out.stats.get("models"),
            )
