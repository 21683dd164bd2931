"""Table II's random initialisation in the live pipeline: a node that re-publishes each metrized
depth map as random depth with zero confidence (``bench/pipeline_table2.py`` starts it for the
random run; ``bench/table2_convergence.py`` regenerates the same maps from a journal)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mogs_node import msgs
from mogs_node.mapper.insertion import random_depth
from mogs_node.node import Node

RANDOM_TOPIC = "/table2/random_depth"


@dataclass(frozen=True)
class RandomDepthParams:
    d_min_m: float = 1.0  # random depth range
    d_max_m: float = 50.0
    seed: int = 0  # depth of keyframe k: random_depth(..., seed * 1000 + k)
    same_pixels: bool = True  # random values only where the metrizer's depth has one (False:
    # on every pixel, the sky included: session 13's table)
    in_topic: str = "/metrizer/depth"
    out_topic: str = RANDOM_TOPIC


class RandomDepthNode(Node):
    """Re-publishes each metrized depth map as random depth with zero confidence (Table II's
    random initialisation, in the live pipeline)."""

    Params = RandomDepthParams

    def setup(self) -> None:
        self.subscribe(self.params.in_topic, self.on_depth, msg_type=msgs.DepthMap)

    def on_depth(self, m: msgs.DepthMap) -> None:
        self.publish(self.params.out_topic, random_depth_msg(m, self.params))


def random_depth_msg(m: msgs.DepthMap, p: RandomDepthParams | None = None) -> msgs.DepthMap:
    """Keyframe ``m``'s random depth (what :class:`RandomDepthNode` publishes for it)."""
    p = p or RandomDepthParams()
    d = random_depth(m.depth.shape, p.d_min_m, p.d_max_m, p.seed * 1000 + m.keyframe_id)
    if p.same_pixels:
        d = np.where(np.isfinite(m.depth) & (m.depth > 0), d, np.float32(0.0))
    return msgs.DepthMap(
        stamp_ns=m.stamp_ns,
        frame_id=m.frame_id,
        keyframe_id=m.keyframe_id,
        kind="metric",
        depth=d,
        confidence=np.zeros_like(d),
        source="random",
    )
