"""Depth-prior worker: a dense depth prior with per-pixel confidence per keyframe (paper III-A)."""

from mogs_node.depth_prior.dense_prior import (
    DensePrior,
    FusionParams,
    PriorHistory,
    compute_dense_prior,
)
from mogs_node.depth_prior.flow_prior import (
    FlowPrior,
    FlowPriorParams,
    choose_references,
    compute_flow_prior,
    fit_scale_huber,
    two_view_depth,
)
from mogs_node.depth_prior.road import RoadPriorParams
from mogs_node.depth_prior.sequence import PriorSequence
from mogs_node.depth_prior.warp import forward_warp_depth

__all__ = [
    "DensePrior",
    "FusionParams",
    "PriorHistory",
    "PriorSequence",
    "RoadPriorParams",
    "compute_dense_prior",
    "forward_warp_depth",
    "FlowPrior",
    "FlowPriorParams",
    "choose_references",
    "compute_flow_prior",
    "fit_scale_huber",
    "two_view_depth",
]
