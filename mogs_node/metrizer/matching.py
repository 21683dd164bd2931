"""The metrizer's keyframe join (keyframe + masks + prior by keyframe id, on the one
:mod:`~mogs_node.keyframe_join`), and the adapter from a matched set of messages to
:class:`~mogs_node.metrizer.inputs.MetrizerInputs`.

Pure (no bus; time is passed in), so the node shell (:mod:`mogs_node.metrizer.node`) and the
evaluation (:mod:`mogs_node.eval`) share it. The waiting policy is the join's (see
:mod:`mogs_node.keyframe_join`).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from mogs_node.depth_kind import DepthKind, resample_prior
from mogs_node.keyframe_join import JoinedKeyframe, KeyframeJoin, WorkerPace
from mogs_node.metrizer.inputs import MetrizerInputs

__all__ = ["INPUT_SLOTS", "KeyframeMatcher", "MatchedKeyframe", "WorkerPace", "metrizer_inputs"]


INPUT_SLOTS = ("masks", "prior")  # the worker outputs a keyframe waits for
ANCHOR_SLOT = "anchor"  # optional: a metric depth map as dense anchors (node ``anchor_topic``)


class MatchedKeyframe(JoinedKeyframe):
    """One keyframe's metrizer inputs; ``masks`` / ``prior`` are None when they did not come, and
    then ``missing`` says why (the worker's failure notice, a silent worker, an eviction)."""

    def __init__(
        self,
        keyframe_id: int,
        keyframe: Any = None,
        masks: Any = None,
        prior: Any = None,
        first_seen_s: float = 0.0,
        missing: dict[str, str] | None = None,
        anchor: Any = None,
    ) -> None:
        inputs = {"masks": masks, "prior": prior, ANCHOR_SLOT: anchor}
        super().__init__(keyframe_id, keyframe, inputs, first_seen_s, missing)

    @property
    def masks(self) -> Any:
        return self.inputs.get("masks")

    @property
    def prior(self) -> Any:
        return self.inputs.get("prior")

    @property
    def anchor(self) -> Any:
        return self.inputs.get(ANCHOR_SLOT)

    @property
    def complete(self) -> bool:
        return self.complete_for(INPUT_SLOTS)

    @property
    def ready(self) -> bool:
        return self.ready_for(INPUT_SLOTS)


class KeyframeMatcher(KeyframeJoin):
    """The metrizer's join (:class:`~mogs_node.keyframe_join.KeyframeJoin`): keyframe / masks /
    prior by keyframe id, released partial when a worker stays silent or failed."""

    SLOTS = ("keyframe", *INPUT_SLOTS)

    def __init__(
        self,
        max_wait_s: float = 2.0,
        max_pending: int = 32,
        *,
        stall_factor: float = 2.0,
        first_wait_s: float = 0.0,
        anchors: bool = False,
    ) -> None:
        super().__init__(
            (*INPUT_SLOTS, ANCHOR_SLOT) if anchors else INPUT_SLOTS,
            max_wait_s=max_wait_s,
            max_pending=max_pending,
            stall_factor=stall_factor,
            first_wait_s=first_wait_s,
            entry_type=MatchedKeyframe,
        )


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
        prior, conf = _depth_map(entry.prior, W, H)
        kind = entry.prior.kind
    else:
        prior, conf = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)
        kind = DepthKind.METRIC.value
    anchor, anchor_conf = None, None
    if entry.anchor is not None and entry.anchor.kind == DepthKind.METRIC:
        anchor, anchor_conf = _depth_map(entry.anchor, W, H)
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
        T_world_cam=np.asarray(kf.T_world_cam, dtype=np.float64),
        anchor_depth_m=anchor,
        anchor_confidence=anchor_conf,
    )


def _depth_map(msg: Any, W: int, H: int) -> tuple[np.ndarray, np.ndarray]:
    """A depth-map message's values and confidence at ``W x H`` (bilinear), confidence 0 where a
    depth-space map has no value."""
    depth = np.asarray(msg.depth, dtype=np.float32)
    conf = np.asarray(msg.confidence, dtype=np.float32)
    if depth.shape != (H, W):
        depth, conf = resample_prior(depth, conf, W, H)
    if msg.kind in (DepthKind.METRIC, DepthKind.RELATIVE_DEPTH):
        conf = np.where(depth > 0, conf, 0.0).astype(np.float32)  # 0 = no value
    return depth, conf
