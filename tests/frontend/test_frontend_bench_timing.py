"""bench/frontend.py's per-frame figures leave out the call that completes the initialisation."""

from __future__ import annotations

import pytest

from bench.frontend import timing_figures
from mogs_node.eval.frontend_runs import RunResult
from mogs_node.frontend.frontend_types import FrameOutput


def _out(i: int, status: str, ms: float) -> FrameOutput:
    return FrameOutput(
        stamp_ns=i,
        frame_index=i,
        status=status,
        T_world_cam=None,
        velocity_world_m_s=None,
        timings_ms={"tracking": 1.0, "estimation": ms - 1.0, "ground": 0.0},
    )


def test_the_frame_that_completes_the_initialisation_is_not_a_tracking_frame():
    statuses = ["initializing", "initializing", "tracking", "tracking", "tracking", "reset"]
    statuses += ["tracking", "tracking"]
    ms = [5.0, 5.0, 1200.0, 20.0, 30.0, 5.0, 900.0, 40.0]
    outs = [_out(i, s, m) for i, (s, m) in enumerate(zip(statuses, ms, strict=True))]
    fig = timing_figures(RunResult(outs, None, None, {}, 0.0))
    assert fig["tracking_frames"] == 3  # 20, 30, 40 ms: the 1200 and 900 ms calls initialised
    assert fig["estimation_ms_per_frame"] == pytest.approx(29.0)
    assert fig["frames_per_s"] == pytest.approx(1000.0 / 30.0)
    # the init figure holds every other call (the two completing ones included)
    assert fig["init_ms_per_frame"] == pytest.approx((5 + 5 + 1200 + 5 + 900) / 5)
