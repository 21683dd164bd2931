"""The bridges' launch files: valid node classes and parameters; EuRoC through `mogs launch`."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from mogs_node.commands.node import load_node_class
from mogs_node.launch import load_launch_file
from mogs_node.node import parse_params

REPO = Path(__file__).resolve().parents[1]
EUROC = REPO.parent / "shared" / "data" / "euroc_v1_01_micro"


@pytest.mark.parametrize("name", ["kitti", "euroc", "bag", "live"])
def test_launch_file_nodes_and_params_are_valid(name: str) -> None:
    lf = load_launch_file(REPO / "launch" / f"{name}.yaml")
    for spec in lf.nodes:
        cls = load_node_class(spec.cls)
        parse_params(cls.Params, spec.params, where=f"{name}.{spec.name}")


@pytest.mark.shared_data
def test_euroc_launch_file_plays_the_excerpt(tmp_path: Path, ipc_endpoints) -> None:
    if not EUROC.exists():
        pytest.skip(f"real data excerpt not found: {EUROC} (a user checkout has no ../shared/data)")
    from mogs_node.datasets import read_euroc

    summary = tmp_path / "rec.json"
    env_bus = {"pub_endpoint": ipc_endpoints[0], "sub_endpoint": ipc_endpoints[1]}
    launch = load_launch_file(REPO / "launch" / "euroc.yaml")
    data = {
        "name": "euroc_test",
        "bus": env_bus,
        "exit_when": list(launch.exit_when),
        "nodes": [
            {"name": s.name, "class": s.cls, "params": s.params, "respawn": s.respawn}
            for s in launch.nodes
        ],
    }
    path = tmp_path / "euroc.yaml"
    path.write_text(json.dumps(data))  # JSON is YAML
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "mogs_node.cli",
            "launch",
            str(path),
            "--set",
            f"player.path={EUROC}",
            "--set",
            "player.rate=0",
            "--set",
            f"recorder.summary_path={summary}",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    seq = read_euroc(EUROC)
    imu_lo = seq.frames[0].stamp_ns - 100_000_000
    n_imu = int(
        ((seq.imu.stamps_ns >= imu_lo) & (seq.imu.stamps_ns <= seq.frames[-1].stamp_ns)).sum()
    )
    n_gt = sum(f.T_world_cam is not None for f in seq.frames)
    counts = json.loads(summary.read_text())["count"]
    assert counts == {"/camera/image": 95, "/imu": n_imu, "/groundtruth/pose": n_gt}
    assert "95/95 frames (100.0%)" in r.stdout
