"""The run report's idle timer and the mapper's final refinement (a slow machine's refinement
outlasted ``idle_timeout_s`` and the report scored the unrefined map)."""

from __future__ import annotations

from pathlib import Path

from mogs_node import msgs
from mogs_node.report.node import RunReportNode


def _diag(node: str, counters: dict[str, float]) -> msgs.Diagnostics:
    return msgs.Diagnostics(
        stamp_ns=0, frame_id="", node=node, pid=1, uptime_s=1.0, status="ok",
        counters=counters, topics={},
    )  # fmt: skip


def test_an_advancing_refinement_keeps_the_run_from_idling_and_a_stuck_one_does_not(
    inproc_bus, tmp_path: Path
) -> None:
    bus, ctx = inproc_bus
    params = {"out_dir": str(tmp_path), "render_backend": "torch"}
    node = RunReportNode("report", params, bus, context=ctx, diagnostics_period_s=0)
    try:
        node.last_input = 0.0
        node.on_diagnostics(_diag("frontend", {"received": 3.0}))
        assert node.last_input == 0.0  # heartbeats are not input
        node.on_diagnostics(_diag("mapper", {"refine_left": 795.0}))
        assert node.last_input > 0.0  # the refinement started
        node.last_input = 0.0
        node.on_diagnostics(_diag("mapper", {"refine_left": 790.0}))
        assert node.last_input > 0.0  # it advances
        node.last_input = 0.0
        node.on_diagnostics(_diag("mapper", {"refine_left": 790.0}))
        assert node.last_input == 0.0  # stuck: the idle timeout still ends the run
    finally:
        node.close()
