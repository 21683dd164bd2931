"""The mapper SIGKILLed in the middle of a ``launch/euroc.yaml``, ``launch/kitti.yaml`` and
``launch/bag.yaml`` run (issue 23): it is respawned, catches up from the run's journal, and the run
still writes ``map.ply`` with every keyframe.

Each case is the launch file as a user runs it (the shared EuRoC and KITTI excerpts, a short sim
drive written as a rosbag2 for the bag), on a private bus, with fewer mapper iterations and no
final refinement (a mapper killed after the source stopped would not see its stop again, as in
``tests/integration/test_reliability_kill.py``, whose ``Run`` drives the launcher here).
"""

from __future__ import annotations

import json
import os
import signal
import uuid
from pathlib import Path

import pytest
import yaml
from _reliability_harness import cli_argv
from conftest import shared_data
from test_reliability_kill import Run

from mogs_node.mapper.ply import read_gaussian_ply

REPO = Path(__file__).resolve().parents[2]
TIMEOUT_S = 2400  # a pipeline run takes 3-10 min on 2 shared cores


def _launch(name: str, out: Path, player: dict) -> Path:
    """``launch/<name>.yaml`` with a private bus, outputs in ``out`` and a respawned mapper."""
    launch = yaml.safe_load((REPO / "launch" / f"{name}.yaml").read_text())
    d = Path("/tmp") / f"mogs-killl-{uuid.uuid4().hex[:8]}"
    d.mkdir()
    launch["bus"] = {"pub_endpoint": f"ipc://{d}/pub.ipc", "sub_endpoint": f"ipc://{d}/sub.ipc"}
    for node in launch["nodes"]:
        p = node.setdefault("params", {})
        if node["name"] == "player":
            p.update(player, progress_period_s=0.0)
        elif node["name"] == "mapper":
            node["respawn"] = "on_failure"
            node["respawn_delay_s"] = 0.2
            p.update(iters_per_keyframe=2, final_refine_iters=0, ply_path=str(out / "map.ply"))
        elif node["name"] == "report":
            p.update(out_dir=str(out), wait_final_map=False)
        elif node["name"] == "journal":
            p["dir"] = str(out / "journal")
        elif node["name"] == "frontend" and name == "euroc":
            # the EuRoC excerpt stands still throughout, and a parked camera makes no keyframe
            # (docs/frontend.md, round 8): this test needs keyframes to kill the mapper between
            p.setdefault("keyframes", {})["hold_at_standstill"] = False
    out.mkdir(parents=True, exist_ok=True)
    path = out / "launch.yaml"
    path.write_text(yaml.safe_dump(launch))
    return path


def _sim_bag(tmp_path: Path) -> Path:
    import subprocess

    out = tmp_path / "drive_bag"
    argv = cli_argv(
        "sim", "--frames", "60", "--size", "621x188", "--format", "rosbag2", "--out", str(out)
    )
    subprocess.run(argv, cwd=REPO, check=True, timeout=900, capture_output=True)
    return out


@pytest.mark.slow
@pytest.mark.timeout(TIMEOUT_S)
@pytest.mark.parametrize("name", ["euroc", "kitti", "bag"])
def test_mapper_killed_mid_run_still_maps_every_keyframe(name: str, tmp_path: Path) -> None:
    player = {
        "euroc": lambda: {"path": str(shared_data("euroc_v1_01_micro"))},
        "kitti": lambda: {"path": str(shared_data("kitti_raw_2011_09_26_78"))},
        "bag": lambda: {"path": str(_sim_bag(tmp_path))},
    }[name]()
    out = tmp_path / "run"
    run = Run(_launch(name, out, player), timeout_s=TIMEOUT_S - 300)
    try:
        run.wait_keyframes(2)
        os.kill(run.pids["mapper"], signal.SIGKILL)
    except BaseException:
        run.proc.kill()
        raise
    assert run.wait() == 0, run.log[-4000:]
    assert "respawning mapper (1)" in run.log
    fig = json.loads((out / "summary.json").read_text())
    assert fig["keyframes"] >= 3, run.log[-3000:]  # keyframes came after the kill too
    assert fig["keyframes_mapped"] == fig["keyframes"]
    assert fig["mapper"]["n_keyframes"] == fig["keyframes"]
    n = len(read_gaussian_ply(out / "map.ply")["means"])  # written, readable
    # the EuRoC excerpt (the MAV nearly parked) gets empty depth maps and no Gaussian at all,
    # killed or not (issue 18, item 4; here 7 keyframes mapped, 0 Gaussians); the others map
    assert n > 0 or name == "euroc"
