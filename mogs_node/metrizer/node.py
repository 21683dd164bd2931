"""Metrizer node: keyframe + masks + prior -> ``/metrizer/depth`` (DESIGN.md sections 1, 2).

Subscribes (reliable) to ``/frontend/keyframe``, ``/seg/masks`` and ``/prior/depth`` (and, with
``anchor_topic``, a metric depth map as dense anchors), matches them by ``keyframe_id`` in
:class:`KeyframeMatcher` (pure, no bus) and runs
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
from dataclasses import replace
from typing import Any

import numpy as np

from mogs_node import msgs
from mogs_node.heartbeat import DIAGNOSTICS_TOPIC
from mogs_node.keyframe_chain import failure_reason
from mogs_node.metrizer.consensus import ConsensusParams
from mogs_node.metrizer.matching import (
    ANCHOR_SLOT,
    KeyframeMatcher,
    MatchedKeyframe,
    metrizer_inputs,
)
from mogs_node.metrizer.params import MetrizerNodeParams
from mogs_node.metrizer.pipeline import MetrizerParams, metrize
from mogs_node.metrizer.refinement import CdrParams
from mogs_node.node import Node, parse_params

__all__ = ["KeyframeMatcher", "MatchedKeyframe", "MetrizerNode", "MetrizerNodeParams"]


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
            p.max_wait_s,
            p.max_pending,
            stall_factor=p.stall_factor,
            first_wait_s=p.first_wait_s,
            anchors=bool(p.anchor_topic),
        )
        self.clock = time.monotonic
        self.slot_topics = {"masks": p.masks_topic, "prior": p.prior_topic}
        if p.anchor_topic:  # optional dense metric anchors (a second prior node, metric)
            self.slot_topics[ANCHOR_SLOT] = p.anchor_topic
        inputs = [
            (p.keyframe_topic, self.on_keyframe, msgs.Keyframe),
            (p.masks_topic, self.on_masks, msgs.Masks),
            (p.prior_topic, self.on_prior, msgs.DepthMap),
        ]
        if p.anchor_topic:
            inputs.append((p.anchor_topic, self.on_anchor, msgs.DepthMap))
        for topic, handler, typ in inputs:
            self.subscribe(topic, handler, reliable=True, msg_type=typ, idempotent=True)
        if p.camera_info_topic:
            self.subscribe(
                p.camera_info_topic, self.on_camera_info, reliable=True, msg_type=msgs.CameraInfo
            )
        # a worker's heartbeats say it lives (and computes): its keyframes wait on
        self.subscribe(DIAGNOSTICS_TOPIC, self.on_heartbeat, reliable=False, queue_size=64)
        self.every(p.poll_period_s, self.on_timer)
        # after a restart: the inputs of every keyframe without a metrized depth in the journal
        self.catch_up(tuple(t for t, _, _ in inputs), (p.out_topic,))

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

    def on_anchor(self, msg: msgs.DepthMap) -> None:
        self._add(ANCHOR_SLOT, msg)

    def on_camera_info(self, msg: msgs.CameraInfo) -> None:
        """The camera height of the source's calibration (finite: known) turns the road plane
        on (``MetrizerParams.road_camera_height_m``), unless the launch file sets the height."""
        h = float(msg.camera_height_m)
        if "road_camera_height_m" in self.params.metrizer or not (np.isfinite(h) and h > 0):
            return
        if h != self.metrizer_params.road_camera_height_m:
            self.log.info("road plane: camera %.3f m above the road (from %s)", h, msg.source)
            self.metrizer_params = replace(self.metrizer_params, road_camera_height_m=h)

    def on_heartbeat(self, msg: msgs.Message) -> None:
        """The worker of a slot is the node whose heartbeat says it published on its topic."""
        topics = getattr(msg, "topics", None)
        if not isinstance(topics, dict) or getattr(msg, "status", "") == "stopped":
            return
        for slot, topic in self.slot_topics.items():
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
