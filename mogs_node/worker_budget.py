"""A worker's processing scale chosen from a time budget per keyframe (issue 28).

The keyframe chain (frontend -> segmentation + prior -> metrizer) must turn each keyframe into
metric depth within a latency budget on whatever machine it runs. A worker whose cost per
keyframe exceeds its share of that budget makes every keyframe late, and the frontend then sheds
keyframes (:mod:`mogs_node.frontend.backlog`), which costs the flow prior its references. A
worker with a :class:`ScaleBudget` instead measures its own cost per keyframe (wall time: on a
busy machine the wall time, not the CPU time, is what the keyframe waits for) and processes at a
smaller image scale when the cost is over budget, back at a larger one when there is room.

Cost model: the cost is proportional to the pixels processed, ``cost(s) = unit * s**2`` for
scale ``s``; ``unit`` is a running mean of ``cost / s**2`` over the keyframes measured. The scale
is the largest of ``scales`` whose predicted cost fits ``budget_s``; a smaller scale is taken at
once (the keyframes are late now), a larger one only when its predicted cost is within
``headroom * budget_s`` and the current scale has served ``hold_keyframes`` keyframes (a worker
whose history depends on the scale, as the flow prior's references do, must not flip-flop).

Pure: no clock, no bus; the node passes each keyframe's measured cost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mogs_node.errors import ConfigError

__all__ = ["ScaleBudget", "ScaleBudgetParams"]

COST_GAIN = 0.3  # weight of the newest cost in the running mean


@dataclass(frozen=True)
class ScaleBudgetParams:
    """A worker's time budget per keyframe and the scales it may process at."""

    budget_s: float = 0.0  # wall time per keyframe the worker may take [s] (0 = off: scale 1)
    scales: tuple[float, ...] = (1.0, 0.75, 0.5)  # allowed image scales, largest first
    headroom: float = 0.8  # a larger scale must be predicted within headroom * budget_s
    hold_keyframes: int = 5  # keyframes at a scale before a larger one is tried

    def __post_init__(self) -> None:
        if not (math.isfinite(self.budget_s) and self.budget_s >= 0):
            raise ConfigError(f"scale_budget.budget_s: must be >= 0, got {self.budget_s}")
        sc = tuple(float(s) for s in self.scales)
        if not sc or any(not (0 < s <= 1) for s in sc) or list(sc) != sorted(sc, reverse=True):
            raise ConfigError(
                f"scale_budget.scales: a non-empty list in (0, 1], largest first, got {self.scales}"
            )
        object.__setattr__(self, "scales", sc)
        if not (0 < self.headroom <= 1):
            raise ConfigError(f"scale_budget.headroom: must be in (0, 1], got {self.headroom}")
        if self.hold_keyframes < 0:
            raise ConfigError(
                f"scale_budget.hold_keyframes: must be >= 0, got {self.hold_keyframes}"
            )


class ScaleBudget:
    """The scale a worker processes its next keyframe at, from its measured cost."""

    def __init__(self, params: ScaleBudgetParams) -> None:
        self.params = params
        self.scale = params.scales[0] if params.budget_s > 0 else 1.0
        self.unit_cost_s = 0.0  # running mean of cost / scale**2 [s]
        self.measured = 0
        self._at_scale = 0  # keyframes processed at the current scale
        self.changes = 0  # scale changes so far

    def predicted_cost_s(self, scale: float) -> float:
        return self.unit_cost_s * scale * scale

    def observe(self, cost_s: float) -> float:
        """One keyframe processed at :attr:`scale` in ``cost_s``; returns the next scale."""
        if not math.isfinite(cost_s) or cost_s < 0:
            raise ConfigError(f"ScaleBudget.observe: cost_s must be >= 0, got {cost_s}")
        unit = cost_s / (self.scale * self.scale)
        self.unit_cost_s = (
            unit if self.measured == 0 else self.unit_cost_s + COST_GAIN * (unit - self.unit_cost_s)
        )
        self.measured += 1
        self._at_scale += 1
        p = self.params
        if p.budget_s <= 0:
            return self.scale
        fits = [s for s in p.scales if self.predicted_cost_s(s) <= p.budget_s]
        best = fits[0] if fits else p.scales[-1]
        if best < self.scale:  # over budget: smaller at once
            self._set(best)
        elif best > self.scale and self._at_scale >= p.hold_keyframes:
            roomy = [s for s in p.scales if self.predicted_cost_s(s) <= p.headroom * p.budget_s]
            if roomy and roomy[0] > self.scale:
                self._set(roomy[0])
        return self.scale

    def _set(self, scale: float) -> None:
        self.scale = scale
        self._at_scale = 0
        self.changes += 1
