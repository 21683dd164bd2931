"""Run report: depth scoring, completeness and trajectory figures on exact inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mogs_node.geometry import make_T, so3_exp
from mogs_node.report.collect import RunCollector, score_depth, summarise, write_report


def test_score_depth_on_known_errors() -> None:
    gt = np.full((4, 5), 10.0)
    gt[0, :] = 0.0  # no ground truth on the first row
    pred = np.full((4, 5), 11.0)  # 10% too far everywhere
    pred[1, 0] = 0.0  # one pixel without a prediction
    s = score_depth(3, 100, pred, gt)
    assert s.count == 14
    assert s.coverage == pytest.approx(14 / 15)
    assert s.absrel == pytest.approx(0.1)
    assert s.rmse == pytest.approx(1.0)
    assert s.delta1 == 1.0


def test_collector_matches_depth_to_ground_truth_in_any_order_and_pools() -> None:
    c = RunCollector()
    gt = np.full((2, 2), 4.0)
    c.add_depth(7, np.full((2, 2), 5.0), np.ones((2, 2)))  # depth first
    c.add_gt_depth(700, gt)  # then ground truth
    assert not c.depth_scores  # the keyframe (and so its stamp) is still unknown
    c.add_keyframe(7, 700, np.eye(4))
    c.add_keyframe(8, 800, np.eye(4))
    c.add_gt_depth(800, gt)
    d8 = np.full((2, 2), 4.0)
    d8[0, 0] = 0.0  # one pixel without depth: coverage 0.75
    c.add_depth(8, d8, np.ones((2, 2)))
    assert [s.keyframe_id for s in c.depth_scores] == [7, 8]
    assert not c.complete  # nothing reached the mapper yet
    c.mapped.update({7, 8})
    assert c.complete
    fig = summarise(c)
    assert fig["depth"]["absrel"] == pytest.approx(1 / 7)  # pooled: (4 * 0.25 + 3 * 0) / 7
    assert fig["depth"]["min_keyframe_coverage"] == pytest.approx(0.75)
    c.mapped.discard(8)  # only what reached the mapper counts
    assert summarise(c)["depth"]["min_keyframe_coverage"] == pytest.approx(1.0)
    assert fig["keyframes_with_depth"] == 2 and fig["keyframes_mapped"] == 2


def test_trajectory_figures_with_a_scaled_estimate(tmp_path: Path) -> None:
    c = RunCollector()
    for k in range(20):
        T = make_T(so3_exp(np.array([0, 0, 0.02 * k])), np.array([k * 1.0, 0.1 * k**1.5, 0]))
        c.gt_poses[k * 10**8] = T
        Te = T.copy()
        Te[:3, 3] *= 1.1  # 10% scale error
        c.odometry[k * 10**8] = Te
    fig = summarise(c)
    assert fig["trajectory"]["scale_error"] == pytest.approx(1 - 1 / 1.1, abs=1e-6)
    assert fig["trajectory"]["ate_sim3_rmse_m"] < 1e-6
    line = write_report(tmp_path / "report.md", fig)
    assert "ATE" in line and (tmp_path / "report.md").read_text().startswith("# MOGS run")


def test_final_map_figures_and_report_section(tmp_path: Path) -> None:
    from mogs_node.report.views import ViewScore

    c = RunCollector()
    c.add_keyframe(0, 100, np.eye(4))
    c.add_keyframe(1, 200, np.eye(4))
    c.mapped.update({0, 1})
    assert not c.map_ready  # the newest keyframe's map update has not arrived
    c.map_updated.add(0)
    assert not c.map_ready
    c.map_updated.add(1)
    assert c.map_ready
    # a mapper that refines after the drive: ready only once its final stats arrived
    c.need_final = True
    assert not c.map_ready
    c.final_seen = True
    assert c.map_ready
    c.view_scores = [
        ViewScore("heldout", 150, -1, 20.0, 0.5, 1.0, "renders/heldout_150.png"),
        ViewScore("heldout", 170, -1, 30.0, 0.9, 0.5, "renders/heldout_170.png"),
        ViewScore("keyframe", 200, 1, 40.0, 0.95, 1.0, "renders/keyframe_000001.png"),
    ]
    fig = summarise(c)["map"]
    assert fig["heldout_frames"] == 2 and fig["keyframe_frames"] == 1
    assert fig["heldout_psnr_db"] == pytest.approx(25.0)  # mean over views
    assert fig["heldout_ssim"] == pytest.approx(0.7)
    assert fig["heldout_coverage"] == pytest.approx(0.75)
    assert fig["keyframe_psnr_db"] == pytest.approx(40.0) and fig["exposure"] == "none"
    assert [v["png"] for v in fig["views"]][-1] == "renders/keyframe_000001.png"
    line = write_report(tmp_path / "report.md", summarise(c))
    text = (tmp_path / "report.md").read_text()
    assert "| held-out frames | 2 | 25.00 | 0.700 | 0.750 |" in text
    assert "![keyframe 1, t = 0.00 s](renders/keyframe_000001.png)" in text
    assert text.count("![") == 3
    assert "held-out PSNR 25.0 dB" in line
