"""Segmentation worker: instance masks per keyframe as one int32 label image (-1 = none)."""

from mogs_node.segmentation.graph import GraphSegParams, segment_graph

__all__ = ["GraphSegParams", "segment_graph"]
