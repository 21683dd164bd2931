"""Simulated LFM prior from ground-truth depth: an evaluation backend, never a default.

What a user with a learned monocular model (Depth Anything V2 style: relative inverse depth,
locally consistent, globally off by an unknown affine map) would feed the metrizer, made from the
sim's ground truth by :func:`mogs_node.sim.simulated_lfm` (unknown scale and shift per frame,
low-frequency warp, blur at depth edges, noise; docs/sim.md). The prior node's ``sim_lfm``
backend takes the player's ``/groundtruth/depth`` at the keyframe's stamp
(``launch/demo_lfm.yaml``), so the running pipeline can be measured with the prior a learned
model gives, on a drive with ground truth. It reads ground truth: evaluation only.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mogs_node.geometry import check_array
from mogs_node.sim import LfmParams, simulated_lfm

__all__ = ["lfm_from_truth"]


def lfm_from_truth(
    depth_m: NDArray[np.floating], keyframe_id: int, *, seed: int = 7, lfm: LfmParams | None = None
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Relative inverse depth ``[H, W]`` f32 and its confidence (1 everywhere) from ground-truth
    z-depth ``depth_m`` ``[H, W]`` (0, inf or NaN: none, e.g. sky). Deterministic per
    ``(seed, keyframe_id)``; ``lfm``: the distortion model (default :class:`LfmParams`)."""
    d = check_array("depth_m", depth_m, shape=(None, None), dtype=np.floating)
    d = np.where(np.isfinite(d) & (d > 0), d, np.inf).astype(np.float32)
    rng = np.random.default_rng([int(seed) & 0x7FFFFFFF, int(keyframe_id) & 0x7FFFFFFF])
    prior = simulated_lfm(d, rng, lfm or LfmParams()).astype(np.float32)
    return prior, np.ones_like(prior)
