"""bench/pipeline.py's pieces without processes: the bus recording, the figures of a recorded run,
the docs section and the launch file it runs."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bench.pipeline import Recording, bench_launch, docs_section, parse_args, run_figures
from mogs_node import msgs


def _keyframe(kf_id: int, stamp_ns: int) -> msgs.Keyframe:
    """A keyframe without features (the bench reads its id and stamp only)."""
    empty = {"feature_ids": np.zeros(0, np.int64), "feature_weight": np.zeros(0, np.float32)}
    empty |= {
        f"feature_{k}": np.zeros((0, n), np.float32) for k, n in (("uv_px", 2), ("xyz_cam_m", 3))
    }
    image = np.zeros((4, 6, 3), np.uint8)
    return msgs.Keyframe(stamp_ns, "cam", kf_id, image, np.eye(3), np.eye(4), **empty)


def _recording() -> Recording:
    """Three images at 10, 10.1, 10.2 s; keyframes 0 (image 0) and 1 (image 2); keyframe 1 is
    metrized but not mapped; the final map at 14 s; one node sampled."""
    rec = Recording()
    for i, stamp in enumerate((100, 200, 300)):
        rec.on_message("/camera/image", SimpleNamespace(stamp_ns=stamp), 10.0 + 0.1 * i)
    rec.on_message("/frontend/keyframe", _keyframe(0, 100), 10.5)
    rec.on_message("/frontend/keyframe", _keyframe(1, 300), 10.7)
    depth = SimpleNamespace(keyframe_id=0)
    rec.on_message("/metrizer/depth", depth, 11.0)
    rec.on_message("/metrizer/depth", depth, 11.5)  # a repeat keeps the first arrival
    rec.on_message("/metrizer/depth", SimpleNamespace(keyframe_id=1), 12.2)
    stats = SimpleNamespace(keyframe_id=0, extra={"map_cpu_ms": 400.0})
    rec.on_message("/mapper/stats", stats, 12.0)
    rec.on_message("/mapper/stats", SimpleNamespace(keyframe_id=0, extra={"final": True}), 14.0)
    rec.cpu["mapper"] = [50.0, 100.0]
    rec.cpu_t["mapper"] = [(10.0, 1.0), (11.0, 1.5), (12.2, 2.6), (13.0, 3.0)]
    rec.rss["mapper"] = 123.456
    return rec


def test_the_recording_keeps_first_arrivals_and_the_final_map_apart() -> None:
    rec = _recording()
    assert rec.image_t == pytest.approx({100: 10.0, 200: 10.1, 300: 10.2})
    assert rec.kf_stamp == {0: 100, 1: 300}
    assert rec.kf_t == {0: 10.5, 1: 10.7}
    assert rec.depth_t == {0: 11.0, 1: 12.2}
    assert rec.stats_t == {0: 12.0}
    assert rec.map_cpu_s == {0: 0.4}
    assert rec.final_t == 14.0


def test_the_figures_of_a_recorded_run() -> None:
    f = run_figures(_recording(), wall=20.04, frame_rate_hz=10.0)
    assert (f["frames"], f["keyframes"], f["keyframes_metrized"], f["keyframes_mapped"]) == (
        3,
        2,
        2,
        1,
    )
    assert f["wall_s"] == 20.0
    # image -> depth: 1.0 s (keyframe 0) and 2.0 s (keyframe 1); image -> map: 2.0 s
    assert f["latency_image_to_depth_ms_median"] == 1500.0
    assert f["latency_image_to_depth_ms_max"] == 2000.0
    assert f["latency_image_to_map_ms_median"] == 2000.0
    # the online part: first image 10.0 s -> last depth 12.2 s; the sequence is 0.3 s
    assert f["frames_per_s"] == round(3 / 2.2, 2)
    assert f["keyframes_per_s"] == round(2 / 2.2, 3)
    assert f["real_time_factor"] == round(0.3 / 2.2, 3)
    assert f["real_time_factor_incl_final"] == round(0.3 / 4.0, 3)
    assert f["final_refine_s"] == 2.0
    assert f["timeline_s"] == {"0": [0.0, 0.5, 1.0, 2.0], "1": [0.2, 0.7, 2.2, None]}
    assert f["mapper_map_cpu_s_per_keyframe_mean"] == 0.4
    # the samples inside 10.0-12.2 s: 1.6 CPU s over 2.2 s -> 72.7 %, over one mapped keyframe
    assert f["mapper_cpu_percent_drive"] == 72.7
    assert f["mapper_process_cpu_s_per_keyframe_drive"] == round(0.727 * 2.2, 3)
    assert f["mapper_cpu_percent_mean"] == 75.0
    assert f["mapper_rss_mib_peak"] == 123.5


def test_the_figures_of_an_empty_run_are_nan_or_none() -> None:
    f = run_figures(Recording(), wall=1.0, frame_rate_hz=10.0)
    assert f["frames"] == f["keyframes"] == 0
    assert math.isnan(f["latency_image_to_depth_ms_median"])
    assert math.isnan(f["latency_image_to_map_ms_median"])
    assert f["real_time_factor_incl_final"] is None and f["final_refine_s"] is None
    assert f["timeline_s"] == {}


def test_the_docs_section_lists_the_figures_and_every_node_in_order() -> None:
    f = run_figures(_recording(), wall=20.0, frame_rate_hz=10.0)
    f.update({"player_cpu_percent_mean": 5.0, "player_cpu_percent_drive": 6.0})
    f["player_rss_mib_peak"] = 70.0
    body = docs_section("python bench/pipeline.py --frames 3 ", f, ["player", "mapper"], 3, 10.0)
    assert body.startswith("## Pipeline end to end (issue 8)\n\nCommand: `python bench/pipeline.py")
    assert "--frames 3`\n" in body and "3 frames at 10 Hz" in body
    assert "| frames / keyframes / metrized / mapped | 3 / 2 / 2 / 1 |" in body
    assert (
        "| final refinement after the drive [s] / real-time factor with it | 2.0 / 0.075 |" in body
    )
    rows = body.rstrip("\n").splitlines()[-2:]
    assert rows == ["| player | 5.0 | 6.0 | 70.0 |", "| mapper | 75.0 | 72.7 | 123.5 |"]


def test_the_bench_launch_has_the_frames_the_outputs_and_the_overrides(tmp_path: Path) -> None:
    args = parse_args(["--frames", "7", "--set", "mapper.device=cuda", "--no-docs"])
    assert isinstance(args, argparse.Namespace) and args.no_docs and args.json is None
    launch, rate = bench_launch(args, tmp_path)
    params = {n.name: n.params for n in launch.nodes}
    assert params["player"]["sim"]["n_frames"] == 7
    assert params["report"]["out_dir"] == str(tmp_path)
    assert params["mapper"]["ply_path"] == str(tmp_path / "map.ply")
    assert params["mapper"]["device"] == "cuda"
    assert rate == float(params["player"]["sim"].get("frame_rate_hz", 10.0))
