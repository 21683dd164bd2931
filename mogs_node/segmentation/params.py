"""Parameters of the segmentation worker (:mod:`mogs_node.segmentation.node`), pure so that the
evaluation builds the same configuration without the node shell."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from mogs_node.params import check_choice

__all__ = ["BACKENDS", "SegmentationParams"]

BACKENDS = ("graph", "sam")


@dataclass(frozen=True)
class SegmentationParams:
    """Parameters of the segmentation worker."""

    backend: str = "graph"  # "graph" (weight-free) or "sam" (ONNX files in `sam`)
    graph: dict[str, Any] = field(default_factory=dict)  # GraphSegParams fields
    sam: dict[str, Any] = field(default_factory=dict)  # SamParams fields (encoder/decoder paths)
    in_topic: str = "/frontend/keyframe"  # keyframes to segment
    out_topic: str = "/seg/masks"  # label images, keyed by keyframe id

    def __post_init__(self) -> None:
        check_choice("segmentation.backend", self.backend, BACKENDS)
