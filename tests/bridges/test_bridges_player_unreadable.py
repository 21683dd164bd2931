"""An unreadable frame (a PNG truncated to 100 bytes) is logged once, skipped, counted, and the
stream goes on (issue 18); the same truncated drive through ``mogs launch`` ends with a report
that counts it and a small log."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from mogs_node.launch import load_launch_file

sys.path.insert(0, str(Path(__file__).parents[1]))  # tests/: the helpers
from _reliability_harness import REPO, cli_argv  # noqa: E402
from test_bridges_player import play_to_end  # noqa: E402

BAD = 5  # index of the truncated frame (frame 0 is read when the drive is opened)


def truncated_drive(tmp_path: Path, n_frames: int) -> tuple[Path, Path]:
    """The first ``n_frames`` of the KITTI excerpt as a drive folder of links, with frame
    :data:`BAD` cut to its first 100 bytes; returns the folder and the truncated file."""
    from conftest import shared_data

    src = shared_data("kitti_raw_2011_09_26_78")
    d = tmp_path / "drive"
    (d / "image_02" / "data").mkdir(parents=True)
    for f in src.glob("calib_*.txt"):
        (d / f.name).symlink_to(f)
    (d / "proj_depth").symlink_to(src / "proj_depth")
    bad = None
    for i, f in enumerate(sorted((src / "image_02" / "data").glob("*.png"))[:n_frames]):
        dst = d / "image_02" / "data" / f.name
        if i == BAD:
            dst.write_bytes(f.read_bytes()[:100])
            bad = dst
        else:
            dst.symlink_to(f)
    assert bad is not None
    return d, bad


@pytest.mark.shared_data
def test_a_truncated_frame_is_skipped_counted_and_logged_once(
    broker_bus, bus_subscriber, tmp_path: Path
) -> None:
    drive, bad = truncated_drive(tmp_path, 10)
    sub = bus_subscriber
    for t in ("/camera/image", "/groundtruth/depth", "/diagnostics"):
        sub.subscribe(t)
    got, out = play_to_end(broker_bus, sub, 120, "kitti", str(drive), "--rate", "0", "--gt-depth")
    images = [e.msg.stamp_ns for e in got if e.topic == "/camera/image"]
    depths = [e.msg.keyframe_id for e in got if e.topic == "/groundtruth/depth"]
    # KITTI stamps without timestamps.txt: 0.1 s apart from 0; the bad frame and its depth missing
    assert images == [i * 100_000_000 for i in range(10) if i != BAD]
    assert depths == [i for i in range(10) if i != BAD]
    last = [e.msg for e in got if e.topic == "/diagnostics" and e.msg.node == "player"][-1]
    assert last.status == "stopped"
    assert last.counters["frames_unreadable"] == 1
    assert last.counters["frames_published"] == 9
    assert out.count(str(bad)) == 1, out
    assert "frame 5 unreadable, skipped (1 unreadable so far)" in out
    assert "played 9/10 frames (1 unreadable, skipped)" in out
    assert "Traceback" not in out


def _player_and_report(tmp_path: Path, drive: Path, report_dir: Path) -> Path:
    """launch/kitti.yaml's player (as fast as possible, waiting for no pipeline node) and its
    report node, on ``drive``; the player waits for the report only."""
    kitti = load_launch_file(REPO / "launch" / "kitti.yaml")
    player = next(s for s in kitti.nodes if s.name == "player")
    params = dict(player.params)
    # the report (which imports the rasterizer: slow to start) must hear the whole drive
    params.update(path=str(drive), rate=0.0, wait_for_subscriber_s=0.0, wait_for_nodes=["report"])
    launch = {
        "name": "trunc",
        "exit_when": ["report"],
        "nodes": [
            {"name": "player", "class": player.cls, "params": params, "respawn": "never"},
            {
                "name": "report",
                "class": "mogs_node.report.node:RunReportNode",
                "params": {"out_dir": str(report_dir), "settle_s": 1.0},
                "respawn": "never",
            },
        ],
    }
    path = tmp_path / "trunc.yaml"
    path.write_text(yaml.safe_dump(launch))
    return path


@pytest.mark.shared_data
def test_a_run_with_a_truncated_frame_completes_and_reports_it(tmp_path: Path) -> None:
    drive, bad = truncated_drive(tmp_path, 20)
    report_dir = tmp_path / "run"
    launch = _player_and_report(tmp_path, drive, report_dir)
    log_path = tmp_path / "launch.log"
    env = {**os.environ, "MOGS_BUS_DIR": str(tmp_path / "bus")}
    with log_path.open("wb") as log:
        r = subprocess.run(
            cli_argv("launch", str(launch)),
            cwd=REPO,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            timeout=120,
        )
    text = log_path.read_text()
    assert r.returncode == 0, text
    assert log_path.stat().st_size <= 200_000
    assert text.count(str(bad)) == 1
    summary = json.loads((report_dir / "summary.json").read_text())
    assert summary["nodes"]["player"]["frames_unreadable"] == 1
    assert summary["nodes"]["player"]["frames_published"] == 19


@pytest.mark.slow
@pytest.mark.shared_data
def test_kitti_launch_file_with_a_truncated_frame_completes(tmp_path: Path) -> None:
    """As a user would: ``mogs launch launch/kitti.yaml --set player.path=DIR`` (the whole
    pipeline, camera-only: the excerpt has no IMU) on all 78 frames, one truncated; without the
    map's refinement after the drive (the map is not what this checks)."""
    drive, bad = truncated_drive(tmp_path, 78)
    report_dir = tmp_path / "run"
    log_path = tmp_path / "launch.log"
    env = {**os.environ, "MOGS_BUS_DIR": str(tmp_path / "bus")}
    argv = cli_argv("launch", "launch/kitti.yaml", "--set", f"player.path={drive}")
    argv += ["--set", "mapper.final_refine_iters=0", "--run-dir", str(report_dir)]
    with log_path.open("wb") as log:
        r = subprocess.run(
            argv, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, timeout=300
        )
    text = log_path.read_text()
    assert r.returncode == 0, text[-5000:]
    assert log_path.stat().st_size <= 200_000
    assert text.count(str(bad)) == 1
    summary = json.loads((report_dir / "summary.json").read_text())
    assert summary["nodes"]["player"]["frames_unreadable"] == 1
