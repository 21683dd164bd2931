"""A mistake ends the run with one clear line, never a hang (issue 18): a ``respawn: never`` node
that fails, a node that cannot start with its configuration (never respawned), ``--set`` naming
an unknown node. Each run is bounded by a subprocess timeout."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import yaml
from _reliability_harness import REPO, cli_argv

from mogs_node import msgs
from mogs_node.bus import BusConfig, Subscriber
from mogs_node.errors import ConfigError
from mogs_node.launch import parse_launch
from mogs_node.node import EXIT_CONFIG
from mogs_node.supervision import EXIT_NODE_FAILED, error_of, failure_reason

NODE_NAMES = [
    "frontend",
    "journal",
    "mapper",
    "metrizer",
    "player",
    "prior",
    "report",
    "segmentation",
]


def _mogs(*args: str, timeout_s: float, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    """``mogs ARGS`` in the repository root, on a private bus folder; output as text."""
    env = {**os.environ, "MOGS_BUS_DIR": str(tmp_path / "bus")}
    return subprocess.run(
        cli_argv(*args), cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout_s
    )


def _last_line(text: str) -> str:
    return [ln for ln in text.splitlines() if ln.strip()][-1]


# ---------------------------------------------------------------- rules (no process)


def test_failure_reason_follows_the_policy_and_never_respawns_a_configuration_error() -> None:
    f = failure_reason
    assert f(0, policy="never", respawns=0, max_respawns=5) is None
    assert f(0, policy="always", respawns=9, max_respawns=5) is None
    assert f(1, policy="on_failure", respawns=4, max_respawns=5) is None  # respawn due
    assert f(-9, policy="always", respawns=0, max_respawns=5) is None
    assert f(1, policy="never", respawns=0, max_respawns=5) == (
        "exited with code 1 (respawn: never)"
    )
    assert f(-9, policy="never", respawns=0, max_respawns=5) == (
        "was killed by SIGKILL (respawn: never)"
    )
    assert f(1, policy="on_failure", respawns=5, max_respawns=5) == (
        "exited with code 1 after 5 respawns (max_respawns 5)"
    )
    for policy in ("never", "on_failure", "always"):
        assert f(EXIT_CONFIG, policy=policy, respawns=0, max_respawns=5) == (
            f"could not start with its configuration (exit code {EXIT_CONFIG})"
        )


def test_error_of_finds_the_error_line() -> None:
    assert error_of(["10:00:00 I mogs.a: up", "10:00:01 E mogs.a: cannot start: bad x", "bye"]) == (
        "bad x"
    )
    tb = ["Traceback (most recent call last):", '  File "x.py", line 1', "ValueError: boom"]
    assert error_of(["10:00:00 I mogs.a: up", *tb]) == "ValueError: boom"
    assert error_of(["", "something odd", ""]) == "something odd"
    assert error_of(["odd", "10:00:00 I mogs.a: up", "10:00:00 W mogs.a: hm"]) == "odd"
    assert error_of(["10:00:00 I mogs.a: up"]) == ""
    assert error_of([]) == ""


def test_overrides_of_an_unknown_node_are_an_error_naming_the_nodes() -> None:
    data = {"nodes": [{"name": "player", "class": "m:C"}, {"name": "mapper", "class": "m:D"}]}
    with pytest.raises(ConfigError, match=r"unknown node\(s\) \['playr'\]; the nodes are "):
        parse_launch(data, overrides={"playr": {"path": "x"}})
    assert parse_launch(data, overrides={"player": {"path": "x"}}).nodes[0].params == {"path": "x"}


# ---------------------------------------------------------------- as a user would


def test_set_with_a_misspelt_node_name_fails_naming_the_known_nodes(tmp_path: Path) -> None:
    r = _mogs("launch", "launch/kitti.yaml", "--set", "playr.x=1", timeout_s=60, tmp_path=tmp_path)
    assert r.returncode != 0
    assert "['playr']" in r.stderr
    assert f"the nodes are {NODE_NAMES}" in r.stderr
    assert "started" not in r.stdout  # nothing was launched


def test_wrong_player_path_ends_the_run_with_the_path_in_the_last_line(tmp_path: Path) -> None:
    missing = tmp_path / "no_such_drive"
    # the must-show bound: non-zero exit within 15 s (a hang raises TimeoutExpired)
    r = _mogs(
        "launch",
        "launch/kitti.yaml",
        "--set",
        f"player.path={missing}",
        timeout_s=15,
        tmp_path=tmp_path,
    )
    assert r.returncode == EXIT_NODE_FAILED, r.stdout
    last = _last_line(r.stdout)
    assert last.startswith("[launch] run failed: player could not start"), last
    assert str(missing) in last
    assert "respawning" not in r.stdout
    assert "[launch] all processes stopped" in r.stdout
    # the nodes stopped while still importing exit quietly, not as configuration errors
    assert r.stdout.count("cannot start") == 1, r.stdout


def test_mapper_parameter_typo_exits_non_zero_without_a_respawn_loop(tmp_path: Path) -> None:
    launch = {
        "name": "typo",
        "nodes": [
            {
                "name": "source",
                "class": "mogs_node.demo_nodes:SyntheticSource",
                "params": {"n_frames": 0, "rate_hz": 5.0},
            },
            {  # on_failure (the default): a crash would be respawned, a typo is not
                "name": "mapper",
                "class": "mogs_node.mapper.node:MapperNode",
                "params": {"iters_per_keyfram": 3, "ply_path": str(tmp_path / "map.ply")},
            },
        ],
    }
    path = tmp_path / "typo.yaml"
    path.write_text(yaml.safe_dump(launch))
    r = _mogs("launch", str(path), timeout_s=60, tmp_path=tmp_path)
    assert r.returncode == EXIT_NODE_FAILED, r.stdout
    assert "respawning" not in r.stdout
    assert r.stdout.count("[launch] started mapper") == 1
    last = _last_line(r.stdout)
    assert last.startswith("[launch] run failed: mapper could not start"), last
    assert "['iters_per_keyfram']" in last and "did you mean 'iters_per_keyframe'?" in last


def test_a_never_respawned_node_that_dies_stops_the_others(tmp_path: Path, ipc_endpoints) -> None:
    launch = {
        "name": "die",
        "bus": {"pub_endpoint": ipc_endpoints[0], "sub_endpoint": ipc_endpoints[1]},
        "nodes": [
            {
                "name": "source",
                "class": "mogs_node.demo_nodes:SyntheticSource",
                "params": {"n_frames": 0, "rate_hz": 20.0, "keyframes": True},
            },
            {
                "name": "sink",
                "class": "mogs_node.demo_nodes:Recorder",
                "params": {"topics": ["/frontend/keyframe"]},
                "respawn": "never",
            },
        ],
    }
    path = tmp_path / "die.yaml"
    path.write_text(yaml.safe_dump(launch))
    proc = subprocess.Popen(
        cli_argv("launch", str(path)),
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    sub = Subscriber(BusConfig(*ipc_endpoints))
    sub.subscribe("/diagnostics")
    try:
        deadline = time.monotonic() + 60
        sink_pid = None
        while sink_pid is None and time.monotonic() < deadline:
            env = sub.receive(timeout_ms=200)
            if isinstance(getattr(env, "msg", None), msgs.Diagnostics) and env.msg.node == "sink":
                sink_pid = env.msg.pid
        assert sink_pid is not None, "the sink never sent a heartbeat"
        os.kill(sink_pid, signal.SIGKILL)
        out, _ = proc.communicate(timeout=15)  # ends by itself: no signal to the launcher
    finally:
        sub.close()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == EXIT_NODE_FAILED, out
    assert _last_line(out) == "[launch] run failed: sink was killed by SIGKILL (respawn: never)"
    assert "respawning" not in out
