"""bench/frontend.py's per-frame figures leave out the call that completes the initialisation;
its docs tables and the command line they quote."""

from __future__ import annotations

import pytest

from bench.frontend import bench_command, parse_args, timing_figures
from bench.frontend_tables import speed_lines, sweep_lines
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


def test_the_docs_tables_and_the_command_they_quote():
    argv = ["--frames", "20", "--no-sweep"]
    args = parse_args(argv)
    assert (args.frames, args.no_sweep, args.points_only, args.traj_json) == (20, True, False, [])
    assert bench_command(argv) == "python bench/frontend.py --frames 20 --no-sweep"
    assert bench_command([]) == "python bench/frontend.py"
    t = {"tracking_ms_per_frame": 1.04, "estimation_ms_per_frame": 2.0, "ground_ms_per_frame": 0}
    t |= {"total_ms_per_frame_p50": 3.0, "total_ms_per_frame_p95": 4.56, "frames_per_s": 333.33}
    lines = speed_lines("python bench/frontend.py", 20, 3.14, [("621x188 + road", t)])
    assert lines[:3] == [
        "## Frontend (`bench/frontend.py`)",
        "",
        "Command: `python bench/frontend.py`",
    ]
    assert "20 frames at 10 Hz" in lines[4] and "load average 3.1 during" in lines[4]
    assert lines[-1] == "| 621x188 + road | 1.0 | 2.0 | 0.0 | 3.0 | 4.6 | 333.3 |"
    assert sweep_lines([]) == []
    sweep = sweep_lines([("window_size", 5, 13.74, 73.5, 0.2771, float("nan"))])
    assert sweep[0] == "" and sweep[1].startswith("Run time against ATE (621x188")
    assert sweep[-1] == "| window_size | 5 | 13.7 | 73.5 | 0.277 | nan |"
