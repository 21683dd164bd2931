"""Depth-prior worker: a dense depth prior with per-pixel confidence per keyframe (paper III-A)."""

from mogs_node.depth_prior.flow_prior import (
    FlowPrior,
    FlowPriorParams,
    choose_references,
    compute_flow_prior,
    fit_scale_huber,
    two_view_depth,
)

__all__ = [
    "FlowPrior",
    "FlowPriorParams",
    "choose_references",
    "compute_flow_prior",
    "fit_scale_huber",
    "two_view_depth",
]
