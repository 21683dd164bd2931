"""The camera-only frontend's memory of its speed and of the road measurement's scale
(docs/frontend.md, rounds 8 and 12).

- the speed gate: a road speed far from the recent ones (a vehicle ahead, a shadow) is replaced
  by their median; ``relock_after`` gated ones in a row on one side are a change of speed;
- the road's gain: the metric step per road-measured step, corrected by the keyframes' road
  points when they find the road measurement grossly off (3x low under a vehicle ahead on KITTI);
- per keyframe interval, the road's distance against the pose chain's over the frames where
  both exist: their ratio corrects the chain's slow drift where the two agree.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SpeedMemory"]


class SpeedMemory:
    """Recent speeds [m/s], the speed gate, the road's gain and the interval's road/chain sums."""

    def __init__(self, gate_rel: float, gate_window: int, relock_after: int) -> None:
        self.gate_rel, self.gate_window, self.relock_after = gate_rel, gate_window, relock_after
        self.speed_m_s: float | None = None  # the current speed (None: none measured yet)
        self.recent: list[float] = []
        self.gated_run: list[float] = []  # consecutive gated road speeds, one side of the median
        self.road_gain = 1.0  # metric step per road-measured step
        self.road_sum = 0.0  # road distance since the keyframe, over the frames with both ...
        self.chain_sum = 0.0  # ... and the chain's there
        self.road_frames = 0
        self.frames = 0  # frames since the keyframe

    def gate(self, speed_m_s: float) -> tuple[float, str]:
        """The speed to use for a road measurement of ``speed_m_s`` and what happened to it:
        ``ground_measurements`` (accepted), ``ground_gated`` (the recent median instead) or
        ``ground_relocked`` (a change of speed: the gated run becomes the recent speeds)."""
        recent, run = self.recent, self.gated_run
        event = "ground_measurements"
        if len(recent) >= 3:
            med = float(np.median(recent))
            if abs(speed_m_s / max(med, 1e-6) - 1) > self.gate_rel:
                if run and (run[-1] > med) != (speed_m_s > med):
                    run.clear()
                run.append(speed_m_s)
                if len(run) < self.relock_after:
                    self.speed_m_s = med
                    return med, "ground_gated"
                event = "ground_relocked"
                recent[:] = run[:-1]
        run.clear()
        recent.append(speed_m_s)
        del recent[: -self.gate_window]
        self.speed_m_s = float(np.median(recent[-3:]))
        return speed_m_s, event

    def remember(self, speed_m_s: float) -> None:
        """A speed taken without the gate becomes the recent one (the gate follows it)."""
        self.recent.append(speed_m_s)
        del self.recent[: -self.gate_window]
        self.gated_run.clear()
        self.speed_m_s = speed_m_s

    def rescale(self, ratio: float, *, gain: bool = True) -> None:
        """The scale was corrected by ``ratio``: the speeds follow, and the road's gain unless
        the road was the reference (``gain`` False)."""
        if gain:
            self.road_gain *= ratio
        self.recent = [v * ratio for v in self.recent]
        self.gated_run = [v * ratio for v in self.gated_run]
        if self.speed_m_s is not None:
            self.speed_m_s *= ratio

    def note(self, road_m: float | None, chain_m: float) -> None:
        """One frame's road step (None: no measurement) and the step the chain took."""
        self.frames += 1
        if road_m is not None:
            self.road_frames += 1
            self.road_sum += road_m
            self.chain_sum += chain_m

    def interval_ratio(self, min_share: float = 0.5) -> float | None:
        """Road over chain distance since the keyframe (None: the road measured fewer than
        ``min_share`` of the frames, or no distance); resets the sums for the next interval."""
        ok = self.frames > 0 and self.road_frames >= min_share * self.frames
        ratio = self.road_sum / self.chain_sum if ok and self.chain_sum > 1e-6 else None
        self.road_sum = self.chain_sum = 0.0
        self.road_frames = self.frames = 0
        return ratio
