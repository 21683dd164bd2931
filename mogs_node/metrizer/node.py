"""Metrizer node: keyframe + masks + prior -> ``/metrizer/depth`` (DESIGN.md sections 1, 2).

Subscribes (reliable) to ``/frontend/keyframe``, ``/seg/masks`` and ``/prior/depth``, matches the
three by ``keyframe_id`` in :class:`KeyframeMatcher` (pure, no bus) and runs
:func:`~mogs_node.metrizer.pipeline.metrize_depth` on each complete set. The wait is bounded:

- a keyframe whose masks and prior are both in is processed at once;
- after ``max_wait_s`` a keyframe is processed with what arrived: without masks every pixel
  belongs to one unmasked region (MSC then has nothing to merge), without a prior the confidence is
  0 everywhere (depth then comes from accepted shape models and the edge-aware fill only);
- masks or a prior whose keyframe never arrives are dropped after ``max_wait_s`` (counted);
- at most ``max_pending`` keyframes wait; beyond that the oldest is processed early.

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
from mogs_node.metrizer.consensus import ConsensusParams
from mogs_node.metrizer.pipeline import MODES, MetrizerInputs, MetrizerParams, metrize
from mogs_node.metrizer.refinement import CdrParams
from mogs_node.node import Node, parse_params

__all__ = ["KeyframeMatcher", "MatchedKeyframe", "MetrizerNode", "MetrizerNodeParams"]


@dataclass(frozen=True)
class MetrizerNodeParams:
    """Parameters of the metrizer node."""

    mode: str = "full"  # "full" | "no_msc" | "no_msc_cdr" (ablations)
    max_wait_s: float = 2.0  # bounded wait for the masks / prior of a keyframe [s]
    max_pending: int = 8  # keyframes waiting at most; beyond, the oldest is processed early
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
        if self.max_wait_s < 0 or self.max_pending < 1 or self.poll_period_s <= 0:
            raise ConfigError("metrizer: max_wait_s >= 0, max_pending >= 1, poll_period_s > 0")


@dataclass
class MatchedKeyframe:
    """One keyframe's inputs; ``masks`` / ``prior`` are None when they did not arrive in time."""

    keyframe_id: int
    keyframe: Any = None
    masks: Any = None
    prior: Any = None
    first_seen_s: float = 0.0

    @property
    def complete(self) -> bool:
        return self.keyframe is not None and self.masks is not None and self.prior is not None


class KeyframeMatcher:
    """Matches keyframe / masks / prior by keyframe id with a bounded wait (pure: time passed in).

    ``add`` returns the sets that became ready; ``expire(now_s)`` those whose wait is over.
    ``counters`` counts complete, partial (timed out or evicted) and dropped (no keyframe) sets.
    """

    SLOTS = ("keyframe", "masks", "prior")

    def __init__(self, max_wait_s: float = 2.0, max_pending: int = 8) -> None:
        self.max_wait_s = max_wait_s
        self.max_pending = max_pending
        self._pending: OrderedDict[int, MatchedKeyframe] = OrderedDict()
        self.counters = {"complete": 0, "partial": 0, "dropped": 0, "duplicates": 0}

    def __len__(self) -> int:
        return len(self._pending)

    def add(self, slot: str, keyframe_id: int, msg: Any, now_s: float) -> list[MatchedKeyframe]:
        """Store ``msg`` in ``slot`` of ``keyframe_id``; return the sets ready to process."""
        if slot not in self.SLOTS:
            raise ConfigError(f"KeyframeMatcher.add: unknown slot {slot!r}")
        entry = self._pending.get(keyframe_id)
        if entry is None:
            entry = self._pending[keyframe_id] = MatchedKeyframe(keyframe_id, first_seen_s=now_s)
        if getattr(entry, slot) is not None:
            self.counters["duplicates"] += 1
        setattr(entry, slot, msg)
        ready = []
        if entry.complete:
            del self._pending[keyframe_id]
            self.counters["complete"] += 1
            ready.append(entry)
        while len(self._pending) > self.max_pending:
            _, old = self._pending.popitem(last=False)
            ready.extend(self._release(old))
        return ready

    def expire(self, now_s: float) -> list[MatchedKeyframe]:
        """Sets whose wait is over (keyframe present: partial; else dropped and not returned)."""
        out = []
        for kid in [
            k for k, e in self._pending.items() if now_s - e.first_seen_s >= self.max_wait_s
        ]:
            out.extend(self._release(self._pending.pop(kid)))
        return out

    def _release(self, entry: MatchedKeyframe) -> list[MatchedKeyframe]:
        if entry.keyframe is None:
            self.counters["dropped"] += 1
            return []
        self.counters["partial"] += 1
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
        self.matcher = KeyframeMatcher(p.max_wait_s, p.max_pending)
        self.clock = time.monotonic
        for topic, handler, typ in (
            (p.keyframe_topic, self.on_keyframe, msgs.Keyframe),
            (p.masks_topic, self.on_masks, msgs.Masks),
            (p.prior_topic, self.on_prior, msgs.DepthMap),
        ):
            self.subscribe(topic, handler, reliable=True, msg_type=typ, idempotent=True)
        self.every(p.poll_period_s, self.on_timer)
        # after a restart: the inputs of every keyframe without a metrized depth in the journal
        self.catch_up((p.keyframe_topic, p.masks_topic, p.prior_topic), (p.out_topic,))

    def _add(self, slot: str, msg: Any) -> None:
        if self.already_published(self.params.out_topic, msg.keyframe_id):
            return  # metrized before this process restarted
        self._process(self.matcher.add(slot, msg.keyframe_id, msg, self.clock()))

    def on_keyframe(self, msg: msgs.Keyframe) -> None:
        self._add("keyframe", msg)

    def on_masks(self, msg: msgs.Masks) -> None:
        self._add("masks", msg)

    def on_prior(self, msg: msgs.DepthMap) -> None:
        self._add("prior", msg)

    def on_timer(self) -> None:
        self._process(self.matcher.expire(self.clock()))
        for k, v in self.matcher.counters.items():
            self.counters[f"match_{k}"] = v

    def _process(self, entries: list[MatchedKeyframe]) -> None:
        for entry in entries:
            kf = entry.keyframe
            if entry.masks is None or entry.prior is None:
                self.log.warning(
                    "keyframe %d: processed without %s",
                    entry.keyframe_id,
                    " and ".join(n for n in ("masks", "prior") if getattr(entry, n) is None),
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
