"""What each Gaussian contributes to the window's views: the pruning rules' evidence.

Pure functions of the map and the keyframes' latest render records (``visible_ids``,
``visible_weights``, ``weights_next_id``: written by each view's forward pass, so judging costs no
extra rendering). Used by :meth:`mogs_node.mapper.mapper.GaussianMapper._prune`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from mogs_node.mapper.gaussians import GaussianMap
from mogs_node.mapper.keyframe import KeyframeState

__all__ = ["blending_contribution", "rows_of"]


def rows_of(gm: GaussianMap, ids: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows of the Gaussians with ``ids`` that are still in the map, and which ids those are."""
    t = torch.as_tensor(ids, dtype=torch.long, device=gm.ids.device)
    if len(gm) == 0 or len(t) == 0:
        return t[:0], torch.zeros(len(t), dtype=torch.bool, device=gm.ids.device)
    rows = torch.searchsorted(gm.ids, t).clamp_max(len(gm) - 1)
    ok = gm.ids[rows] == t
    return rows[ok], ok


def blending_contribution(
    gm: GaussianMap,
    keyframes: Sequence[KeyframeState],
    K: tuple[float, float, float, float],
    size: tuple[int, int],
    near_m: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-Gaussian summed blending weight ``sum_p alpha_i T_i`` [N] over the latest renders of
    ``keyframes`` (full-resolution pixels), and whether it can be judged [N] bool: its centre lies
    in front of and inside at least one of those views (``K`` = fx, fy, cx, cy; ``size`` = width,
    height) whose render came after the Gaussian's birth (an occluded Gaussian there has weight 0).
    """
    n = len(gm)
    device = gm.ids.device
    contrib = torch.zeros(n, device=device)
    judged = torch.zeros(n, dtype=torch.bool, device=device)
    means = gm.params["means"]
    fx, fy, cx, cy = K
    width, height = size
    for kf in keyframes:
        if kf.weights_next_id == 0:
            continue
        rows, ok = rows_of(gm, kf.visible_ids)
        if len(kf.visible_weights) == len(kf.visible_ids):
            w = torch.as_tensor(kf.visible_weights, device=device)[ok]
            contrib.index_add_(0, rows, w.to(contrib.dtype))
        T = kf.T_cam_world.to(device=device, dtype=means.dtype)
        p_cam = means @ T[:3, :3].T + T[:3, 3]
        z = p_cam[:, 2]
        zs = z.clamp_min(1e-6)
        u, v = fx * p_cam[:, 0] / zs + cx, fy * p_cam[:, 1] / zs + cy
        in_view = (z > near_m) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        judged |= in_view & (gm.ids < kf.weights_next_id)
    return contrib, judged
