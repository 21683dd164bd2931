"""Liveness apart from the work (issue 23): a node is never killed for working, a stuck one is."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml
from _reliability_harness import cli_argv  # noqa: F401 - the harness puts the repo on the path
from test_launcher import _diag_until, _launched, _source

from mogs_node import msgs
from mogs_node.heartbeat import Heartbeat, Progress
from mogs_node.launch import Launcher, parse_launch, respawns_without_journal
from mogs_node.supervision import (
    STOPPED_EXIT_TIMEOUTS,
    Beat,
    kill_reason,
    merge_launch_figures,
)


def test_a_step_three_times_the_heartbeat_timeout_is_not_killed(
    tmp_path: Path, ipc_endpoints
) -> None:
    launch = {
        "name": "slow",
        "nodes": [
            _source(32, 24),
            {
                "name": "sink",
                "class": "mogs_node.demo_nodes:Recorder",
                # every keyframe takes 6 s of work: three times the heartbeat timeout (2 s:
                # twice the heartbeat period, so that a beat sent late on a loaded 2-core CI
                # machine is not taken for silence; at 1 s it flaked once)
                "params": {"topics": ["/frontend/keyframe"], "delay_ms": 6000.0},
                "heartbeat_timeout_s": 2.0,
                "progress_timeout_s": 30.0,
                "respawn_delay_s": 0.2,
            },
        ],
    }
    with _launched(tmp_path, launch, ipc_endpoints) as (proc, sub):
        first = _diag_until(sub, lambda d: d.node == "sink", 60)
        busy = _diag_until(sub, lambda d: d.node == "sink" and d.counters["busy_s"] > 1.5, 30)
        assert busy.status == "busy: handler of /frontend/keyframe"
        # three steps later: the same process, heartbeats all along
        last = _diag_until(sub, lambda d: d.node == "sink" and d.counters["progress"] >= 4, 60)
        assert last.pid == first.pid
        # its thread beat during each 6 s step: about one period (1 s) between two heartbeats
        assert last.counters["heartbeat_gap_max_s"] < 2.0
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=20)
    text = out.decode()
    assert "killing it" not in text and "respawning" not in text  # (shutdown may SIGKILL it)


def _timeouts(heartbeat_s: float, progress_s: float, startup_s: float) -> SimpleNamespace:
    """A node spec's three liveness timeouts (what ``kill_reason`` reads of a ``NodeSpec``)."""
    return SimpleNamespace(
        heartbeat_timeout_s=heartbeat_s, progress_timeout_s=progress_s, startup_timeout_s=startup_s
    )


def test_kill_reason_tells_hung_from_stuck_from_working() -> None:
    kw = {"timeouts": _timeouts(2.0, 10.0, 30.0)}
    # not heard from yet: the start-up allowance applies
    assert kill_reason(None, 29.0, started_at=0.0, **kw) is None
    assert kill_reason(None, 31.0, started_at=0.0, **kw)[0] == "heartbeat"
    # heartbeats flow, busy for 9.5 s: working
    assert kill_reason(Beat(100.0, 1, 9.5, "x"), 100.4, started_at=0.0, **kw) is None
    # busy for 9.5 s at the last heartbeat, 0.6 s ago: stuck for 10.1 s
    cause, text = kill_reason(Beat(100.0, 1, 9.5, "handler of /a"), 100.6, started_at=0.0, **kw)
    assert cause == "progress" and text == "made no progress for 10.1 s (handler of /a)"
    # silent for longer than the heartbeat timeout: hung, whatever it was doing
    assert kill_reason(Beat(100.0, 1, 0.0), 102.5, started_at=0.0, **kw)[0] == "heartbeat"
    # idle (busy_s 0) for ever is not stuck; a timeout of 0 turns a check off
    assert kill_reason(Beat(100.0, 1, 0.0), 101.0, started_at=0.0, **kw) is None
    off = {"timeouts": _timeouts(2.0, 0.0, 30.0)}
    assert kill_reason(Beat(100.0, 1, 1e6), 100.1, started_at=0.0, **off) is None


def test_a_node_that_said_it_stopped_is_left_to_exit() -> None:
    """Issue 18: the player said "stopped" and its interpreter then took over 30 s to exit at load
    ~100; the launcher killed it for a missing heartbeat and failed a finished run. A stopped
    node is killed only after STOPPED_EXIT_TIMEOUTS heartbeat timeouts of silence."""
    kw = {"timeouts": _timeouts(2.0, 10.0, 30.0)}
    stopped = Beat(100.0, 1, 0.0, "", stopped=True)
    assert (
        kill_reason(stopped, 100.0 + 2.0 * STOPPED_EXIT_TIMEOUTS - 0.1, started_at=0.0, **kw)
        is None
    )
    cause, text = kill_reason(
        stopped, 100.0 + 2.0 * STOPPED_EXIT_TIMEOUTS + 0.1, started_at=0.0, **kw
    )
    assert cause == "heartbeat" and text.startswith("stopped but did not exit")
    assert kill_reason(Beat(100.0, 1, 0.0), 102.5, started_at=0.0, **kw)[0] == "heartbeat"


def test_launch_figures_reach_the_summary(tmp_path: Path) -> None:
    summary = tmp_path / "summary.json"
    figures = {
        "launch": {"heartbeat_kills": 0, "progress_kills": 1, "respawns": {"mapper": 1}},
        "nodes": {"mapper": {"heartbeat_gap_max_s": 1.02}},
    }
    assert not merge_launch_figures(summary, figures)  # no report: nothing written
    summary.write_text(json.dumps({"keyframes": 3, "nodes": {"mapper": {"received": 7.0}}}))
    assert merge_launch_figures(summary, figures)
    got = json.loads(summary.read_text())
    assert got["keyframes"] == 3 and got["launch"] == figures["launch"]
    assert got["nodes"]["mapper"] == {"received": 7.0, "heartbeat_gap_max_s": 1.02}


def test_launcher_counts_gaps_between_heartbeats_of_one_process() -> None:
    lf = parse_launch({"name": "x", "nodes": [{"name": "a", "class": "m:C"}]})
    launcher = Launcher(lf, out=open("/dev/null", "w"))  # noqa: SIM115
    d = msgs.Diagnostics(stamp_ns=0, frame_id="", node="a", pid=7, uptime_s=0.0, status="ok")
    for t in (10.0, 11.0, 13.5, 14.0):
        launcher._on_heartbeat(d, t)
    launcher._on_heartbeat(msgs.Diagnostics(**{**d.__dict__, "pid": 8}), 30.0)  # a respawn
    launcher._on_heartbeat(msgs.Diagnostics(**{**d.__dict__, "pid": 8}), 31.0)
    f = launcher.figures()
    assert f["nodes"] == {"a": {"heartbeat_gap_max_s": 2.5}}
    assert f["launch"]["heartbeat_kills"] == 0 and f["launch"]["progress_kills"] == 0


def test_heartbeat_reports_busy_work_and_progress() -> None:
    prog = Progress()
    hb = Heartbeat.__new__(Heartbeat)  # its beat() only: no socket, no thread
    hb.period_s, hb.progress, hb.gap_max_s = 0.5, prog, 0.0
    hb._offered = hb._last = None
    hb._base_t = 0.0
    assert hb.beat() is None  # nothing from the run loop yet
    hb._offered = msgs.Diagnostics(
        stamp_ns=0, frame_id="", node="n", pid=1, uptime_s=5.0, status="ok", counters={"a": 1.0}
    )
    first = hb.beat()
    assert first.status == "ok" and first.counters["busy_s"] == 0.0 and first.counters["a"] == 1
    prog.start("handler of /x")
    prog._busy = ("handler of /x", time.monotonic() - 2.0)  # busy for 2 s
    again = hb.beat()  # the loop is busy: the last snapshot, re-stamped, says so
    assert again.status == "busy: handler of /x" and 1.9 < again.counters["busy_s"] < 3.0
    assert again.uptime_s > 5.0 and again.stamp_ns > first.stamp_ns
    prog.moved()  # the work advanced: busy again from now
    assert prog.busy()[1] < 0.5 and prog.count == 1
    prog.done()
    assert prog.busy() is None and hb.beat().counters["progress"] == 2


@pytest.mark.parametrize("name", ["euroc", "kitti", "bag", "demo", "ros1", "live"])
def test_every_launch_file_with_a_mapper_journals_its_inputs(name: str) -> None:
    root = Path(__file__).resolve().parents[1] / "launch"
    data = yaml.safe_load((root / f"{name}.yaml").read_text())
    classes = [n["class"] for n in data["nodes"]]
    assert "mogs_node.mapper.node:MapperNode" in classes
    assert "mogs_node.journal.node:JournalNode" in classes
    assert respawns_without_journal(parse_launch(data)) == []


def test_launch_warns_when_a_respawning_node_has_no_journal() -> None:
    lf = parse_launch(
        {
            "name": "nojournal",
            "nodes": [
                {"name": "mapper", "class": "mogs_node.mapper.node:MapperNode"},
                {"name": "never", "class": "mogs_node.mapper.node:MapperNode", "respawn": "never"},
                {"name": "src", "class": "mogs_node.demo_nodes:SyntheticSource"},
            ],
        }
    )
    assert respawns_without_journal(lf) == ["mapper"]
