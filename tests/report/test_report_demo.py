"""`mogs demo` end to end: the run report scores the final map at held-out frames and keyframes."""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path

import cv2
import pytest
from _reliability_harness import cli_argv

from mogs_node.mapper.ply import read_gaussian_ply
from mogs_node.report.views import map_digest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
@pytest.mark.timeout(2400)  # minutes on 2 shared cores: 60 frames through 8 processes
def test_demo_report_scores_the_final_map(tmp_path: Path) -> None:
    out = tmp_path / "run"
    log = tmp_path / "demo.log"
    with log.open("w") as f:
        proc = subprocess.run(
            cli_argv("demo", "--out", str(out), "--timeout", "2000"),
            cwd=REPO,
            stdout=f,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=2300,
            # a bus of its own: the demo's ipc endpoints are named after the launch file
            env={**os.environ, "MOGS_BUS_DIR": str(tmp_path / "bus")},
        )
    assert proc.returncode == 0, log.read_text()[-4000:]
    fig = json.loads((out / "summary.json").read_text())
    m = fig["map"]
    for key in ("heldout_psnr_db", "heldout_ssim", "keyframe_psnr_db", "keyframe_ssim"):
        assert isinstance(m[key], float), key
    assert m["heldout_frames"] >= 10
    assert m["keyframe_frames"] == fig["keyframes"]
    assert 0 < m["heldout_ssim"] <= 1 and m["heldout_psnr_db"] > 0
    assert "views_not_rendered" not in m
    # the rendered map is the mapper's final map: the same centres, in the same order, as map.ply
    ply = read_gaussian_ply(out / "map.ply")
    assert m["gaussians"] == len(ply["means"])
    assert m["digest"] == map_digest(ply["means"])
    # held-out views are not keyframes, and spread over the drive
    views = m["views"]
    held = sorted(v["stamp_ns"] for v in views if v["kind"] == "heldout")
    kf = sorted(v["stamp_ns"] for v in views if v["kind"] == "keyframe")
    assert not set(held) & set(kf)
    assert held[0] < kf[len(kf) // 2] < held[-1]
    # every picture exists, is ground truth | render | depth at the camera's size, and report.md
    # shows it; snapshots are apart from the final renders
    text = (out / "report.md").read_text()
    for v in views:
        pic = cv2.imread(str(out / v["png"]))
        assert pic is not None and pic.shape[1] == 3 * 621 + 8 and pic.shape[0] > 188
        assert f"]({v['png']})" in text
    assert not list((out / "renders").glob("kf_*"))
    assert re.search(r"\| held-out frames \| \d+ \| [\d.]+ \| [\d.]+ \|", text)
