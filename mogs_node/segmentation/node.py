"""Segmentation worker node: ``/frontend/keyframe`` -> ``/seg/masks`` (DESIGN.md sections 1, 3).

Backends: ``graph`` (weight-free default, :mod:`mogs_node.segmentation.graph`) or ``sam``
(Segment Anything ONNX, :mod:`mogs_node.segmentation.sam_onnx`). The SAM model files are loaded in
``setup``: a missing or malformed model stops the node at start-up with a ModelError, never a
silent fallback to the graph segmenter.
"""

from __future__ import annotations

import numpy as np

from mogs_node import msgs
from mogs_node.keyframe_chain import failed_masks
from mogs_node.node import Node
from mogs_node.params import parse_group
from mogs_node.segmentation.graph import GraphSegParams, require_ximgproc, segment_graph
from mogs_node.segmentation.params import SegmentationParams
from mogs_node.segmentation.sam_onnx import SamOnnx, SamParams

__all__ = ["SegmentationNode", "SegmentationParams"]


class SegmentationNode(Node):
    """One label image per keyframe, in keyframe order (reliable topics)."""

    Params = SegmentationParams

    def setup(self) -> None:
        p: SegmentationParams = self.params
        self.graph_params = parse_group(GraphSegParams, p, "graph", self.name)
        self.sam: SamOnnx | None = None
        if p.backend == "sam":
            self.sam = SamOnnx(parse_group(SamParams, p, "sam", self.name))
        else:
            require_ximgproc(f"node {self.name!r}, backend 'graph'")
        self.subscribe(
            p.in_topic, self.on_keyframe, reliable=True, msg_type=msgs.Keyframe, idempotent=True
        )
        self.catch_up((p.in_topic,), (p.out_topic,))  # after a restart: the keyframes missed

    def on_keyframe(self, kf: msgs.Keyframe) -> None:
        if self.already_published(self.params.out_topic, kf.keyframe_id):
            return  # segmented before this process restarted
        rgb = kf.rgb()
        try:
            if self.sam is not None:
                labels = self.sam.generate(np.ascontiguousarray(rgb)).labels
            else:
                labels = segment_graph(rgb, self.graph_params)
        except Exception as err:  # the metrizer must not wait for masks that never come
            self.publish(self.params.out_topic, failed_masks(kf, err))
            raise  # logged and counted by the node shell (handler_errors)
        self.publish(
            self.params.out_topic,
            msgs.Masks(
                **kf.result_header(),
                labels=labels.astype(np.int32),
                backend=self.params.backend,
            ),
        )
        self.log.debug("keyframe %d: %d segments", kf.keyframe_id, int(labels.max()) + 1)
