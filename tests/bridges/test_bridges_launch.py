"""The EuRoC excerpt through `mogs launch`: the player of launch/euroc.yaml with a recorder in place
of the pipeline (every launch file's nodes and parameters: tests/test_launch_files.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _reliability_harness import REPO, run_cli
from conftest import shared_data

from mogs_node.launch import load_launch_file


@pytest.mark.shared_data
def test_euroc_launch_file_plays_the_excerpt(tmp_path: Path, ipc_endpoints) -> None:
    euroc = shared_data("euroc_v1_01_micro")
    from mogs_node.datasets import read_euroc

    summary = tmp_path / "rec.json"
    env_bus = {"pub_endpoint": ipc_endpoints[0], "sub_endpoint": ipc_endpoints[1]}
    launch = load_launch_file(REPO / "launch" / "euroc.yaml")
    player = next(s for s in launch.nodes if s.name == "player")
    params = {k: v for k, v in player.params.items() if k != "wait_for_nodes"}
    data = {
        "name": "euroc_test",
        "bus": env_bus,
        "exit_when": ["player"],
        "nodes": [
            {"name": "player", "class": player.cls, "params": params, "respawn": "never"},
            {
                "name": "recorder",
                "class": "mogs_node.demo_nodes:Recorder",
                "params": {"topics": ["/groundtruth/pose", "/imu", "/camera/image"]},
                "respawn": "never",
            },
        ],
    }
    path = tmp_path / "euroc.yaml"
    path.write_text(json.dumps(data))  # JSON is YAML
    r = run_cli(
        "launch",
        str(path),
        "--set",
        f"player.path={euroc}",
        "--set",
        "player.rate=0",
        "--set",
        f"recorder.summary_path={summary}",
        timeout_s=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    seq = read_euroc(euroc)
    imu_lo = seq.frames[0].stamp_ns - 100_000_000
    n_imu = int(
        ((seq.imu.stamps_ns >= imu_lo) & (seq.imu.stamps_ns <= seq.frames[-1].stamp_ns)).sum()
    )
    n_gt = sum(f.T_world_cam is not None for f in seq.frames)
    counts = json.loads(summary.read_text())["count"]
    assert counts == {"/camera/image": 95, "/imu": n_imu, "/groundtruth/pose": n_gt}
    assert "95/95 frames (100.0%)" in r.stdout
