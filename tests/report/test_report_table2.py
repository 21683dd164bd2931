"""bench/pipeline_table2.py: its launch set-up, fixed-view tracking and ratios (no processes);
the table itself: tests/bench/test_table2_convergence.py."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from bench.pipeline_table2 import (
    HeldOutViews,
    assemble,
    choose_view,
    common_target,
    depth_statistics,
    launch_dict,
    ratios,
    reached,
    runs_from_json,
)
from bench.table2_convergence import random_params
from bench.table2_random import RANDOM_TOPIC, RandomDepthParams, random_depth_msg
from mogs_node import msgs
from mogs_node.geometry import make_T, so3_exp
from mogs_node.mapper.rasterizer import RasterParams


def test_launch_files_differ_only_in_the_depth_the_mapper_gets(tmp_path: Path) -> None:
    d = {k: launch_dict(k, 30, tmp_path / k) for k in ("mogs", "prior_global", "random")}
    nodes = {k: {n["name"]: n for n in v["nodes"]} for k, v in d.items()}
    assert nodes["mogs"]["metrizer"]["params"]["mode"] == "full"
    assert nodes["prior_global"]["metrizer"]["params"]["mode"] == "no_msc_cdr"
    assert nodes["random"]["mapper"]["params"]["depth_topic"] == RANDOM_TOPIC
    assert "randomizer" in nodes["random"] and "randomizer" not in nodes["mogs"]
    assert "randomizer" in nodes["random"]["player"]["params"]["wait_for_nodes"]
    for k in d:  # the same mapper policy and budget, the same drive
        mp = {
            a: b
            for a, b in nodes[k]["mapper"]["params"].items()
            if a not in ("ply_path", "depth_topic")
        }
        mp0 = {a: b for a, b in nodes["mogs"]["mapper"]["params"].items() if a != "ply_path"}
        assert mp == mp0
        assert nodes[k]["player"]["params"]["sim"]["n_frames"] == 30
    # --set applies to every init alike (e.g. the budget: the drive, no final refinement)
    over = {"mapper": {"final_refine_iters": 0}}
    for k in ("mogs", "random"):
        n = {x["name"]: x for x in launch_dict(k, 30, tmp_path / k, over)["nodes"]}
        assert n["mapper"]["params"]["final_refine_iters"] == 0


def test_random_depth_takes_the_metrizers_pixels_and_only_its_values_are_random(
    tmp_path: Path,
) -> None:
    """Random depth on the pixels where the metrizer has depth (the sky keeps none: the far
    sphere takes it for every init alike), confidence 0; ``same_pixels: false`` (set on the
    randomizer node, read back by the convergence replay) puts it on every pixel."""
    d = np.full((6, 8), 4.0, np.float32)
    d[:2] = 0.0  # sky
    d[3, 3] = np.nan
    m = msgs.DepthMap(
        stamp_ns=5,
        frame_id="cam",
        keyframe_id=3,
        kind="metric",
        depth=d,
        confidence=np.ones_like(d),
        source="metrizer",
    )
    r = random_depth_msg(m)
    has = np.isfinite(d) & (d > 0)
    assert (r.depth[~has] == 0).all() and (r.depth[has] >= 1.0).all() and (r.depth <= 50).all()
    assert not (r.confidence != 0).any() and r.source == "random"
    assert random_depth_msg(m).depth.tobytes() == r.depth.tobytes()  # seeded by the keyframe
    every = random_depth_msg(m, RandomDepthParams(same_pixels=False))
    assert (every.depth >= 1.0).all()
    np.testing.assert_array_equal(every.depth[has], r.depth[has])
    over = {"mapper": {"final_refine_iters": 0}, "randomizer": {"same_pixels": False}}
    launch = launch_dict("random", 30, tmp_path, over)
    node = next(n for n in launch["nodes"] if n["name"] == "randomizer")
    assert node["params"] == {"same_pixels": False}
    path = tmp_path / "launch.yaml"
    path.write_text(yaml.safe_dump(launch))
    assert random_params(path) == RandomDepthParams(same_pixels=False)
    path.write_text(yaml.safe_dump(launch_dict("mogs", 30, tmp_path)))
    assert random_params(path) == RandomDepthParams()  # another init's run: the defaults


def _gaussians(rgb: np.ndarray, depth: float, K: np.ndarray, T: np.ndarray, keyframe_id: int):
    """A map update holding one opaque, 0.1 px Gaussian per pixel of ``rgb`` seen from ``T``."""
    H, W = rgb.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    p = np.stack(
        [(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, np.full_like(u, depth)],
        -1,
    ).reshape(-1, 3)
    n = len(p)
    return SimpleNamespace(
        keyframe_id=keyframe_id,
        ids=np.arange(n, dtype=np.int64),
        removed_ids=np.zeros(0, np.int64),
        means=(p @ T[:3, :3].T + T[:3, 3]).astype(np.float32),
        quats_wxyz=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        log_scales=np.full((n, 3), np.log(0.1 * depth / K[0, 0]), np.float32),
        opacity_logit=np.full(n, 12.0, np.float32),
        colors_rgb=rgb.reshape(-1, 3).astype(np.float32) / 255,
    )


def _feed_frames(hv: HeldOutViews, K: np.ndarray, img: np.ndarray, T_view: np.ndarray) -> None:
    """Frames 0..5 on the bus: frame 1 is a keyframe, frame 2 is seen from ``T_view``, frame 4
    has no pose (the frontend was not tracking)."""
    for i in range(6):
        s = 1000 + i
        if i == 1:
            hv.on("/frontend/keyframe", SimpleNamespace(stamp_ns=s, K=K, image=img), 0.0)
        T = T_view if i == 2 else make_T(np.eye(3), np.array([0.0, 0.0, -5.0]))
        status = "initializing" if i == 4 else "tracking"
        hv.on("/frontend/odometry", SimpleNamespace(stamp_ns=s, status=status, T_world_cam=T), 0.0)


def test_held_out_view_reaches_the_target_when_the_map_holds_the_view() -> None:
    rng = np.random.default_rng(0)
    H, W = 12, 16
    K = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    T_view = make_T(so3_exp(np.array([0.1, 0.2, -0.1])), np.array([3.0, 0.0, 1.0]))
    img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    # candidates 1 (a keyframe), 2 (the view), 4 (no pose); the pure-PyTorch backend (the same
    # semantics as C++, no compilation) with a dilation that ends before the next pixel, so the
    # map of the view's pixels renders it back (test_report_views)
    hv = HeldOutViews(
        {1: img, 2: img, 4: img}, raster=RasterParams(backend="torch", eps2d_px2=0.05)
    )
    _feed_frames(hv, K, img, T_view)
    # update 1: a map that is the view's image darkened; update 2: the view itself
    hv.on("/mapper/stats", SimpleNamespace(iterations=6, extra={"inserted": 5, "pruned": 1}), 1.0)
    hv.on("/mapper/gaussians", _gaussians(img // 4, 5.0, K, T_view, 1), 1.0)
    hv.on("/mapper/stats", SimpleNamespace(iterations=12, extra={"inserted": 2}), 2.0)
    hv.on("/mapper/gaussians", _gaussians(img, 5.0, K, T_view, 2), 2.0)
    assert list(hv.curves) == [2] and hv.keyframe_indices == {1}  # 4 has no pose
    fig = hv.view_figures(2, 20.0)
    assert fig["curve"]["fixed_view_psnr_db"][0] < 20 <= fig["curve"]["fixed_view_psnr_db"][1]
    assert fig["iters_to_target"] == 12 and fig["gaussians_at_target"] == H * W
    assert fig["wall_s_to_target"] == pytest.approx(2.0)
    assert fig["iterations_budget"] == 12
    assert (fig["gaussians_inserted"], fig["gaussians_pruned"]) == (7, 1)
    assert reached(hv.curves, 20.0) == {2} and reached(hv.curves, 500.0) == set()
    # the mapper's final refinement: its update comes first, then its stats marked final
    hv.on("/mapper/gaussians", _gaussians(img, 5.0, K, T_view, 2), 3.0)
    hv.on("/mapper/stats", SimpleNamespace(iterations=15, extra={"final": 1.0}), 3.0)
    fig = hv.view_figures(2, 20.0)
    assert fig["curve"]["iterations"] == [6, 12, 15] and fig["iterations_budget"] == 15
    assert hv.view_figures(None, 20.0)["iters_to_target"] is None


def test_a_view_is_scored_only_once_two_later_frames_have_a_pose() -> None:
    img = np.zeros((2, 2, 3), np.uint8)
    hv = HeldOutViews({3: img})
    hv.on("/frontend/keyframe", SimpleNamespace(stamp_ns=0, K=np.eye(3), image=img), 0.0)
    for i in range(5):  # frames 0..4: frame 3 has one later frame with a pose
        hv.on(
            "/frontend/odometry",
            SimpleNamespace(stamp_ns=i, status="tracking", T_world_cam=np.eye(4)),
            0.0,
        )
    assert hv._scoreable(3) is None
    hv.on(
        "/frontend/odometry",
        SimpleNamespace(stamp_ns=5, status="tracking", T_world_cam=np.eye(4)),
        0,
    )
    assert hv._scoreable(3) == 3


def test_the_fixed_view_is_the_earliest_every_initialisation_reaches() -> None:
    def views(psnr: dict[int, list[float]]) -> HeldOutViews:
        hv = HeldOutViews({})
        hv.curves = {i: [{"fixed_view_psnr_db": x} for x in v] for i, v in psnr.items()}
        return hv

    runs = {
        "mogs": views({21: [19.0, 21.0], 23: [20.5], 25: [22.0]}),
        "prior_global": views({21: [18.0], 23: [19.0, 20.0], 25: [21.0]}),
        "random": views({21: [15.0, 20.1], 23: [20.0], 25: [19.9]}),
    }
    assert choose_view(runs, 20.0) == 23  # 21: prior_global never reaches it
    assert choose_view(runs, 30.0) is None
    # auto: the highest 0.5 dB step some candidate reaches under every init: 20 (view 23)
    assert common_target(runs, 20.0) == 20.0
    runs["random"] = views({21: [15.0, 17.2], 23: [16.9], 25: [17.6]})
    assert choose_view(runs, 20.0) is None  # random reaches 20 dB nowhere: no view, no ratios
    assert common_target(runs, 20.0) == 17.5 and choose_view(runs, 17.5) == 25
    assert common_target(runs, 20.0, floor_db=18.0) is None


def test_ratios_with_and_without_a_target() -> None:
    inits = {
        "mogs": {"iters_to_target": 30, "gaussians_at_target": 800, "psnr_at_budget_db": 22.0},
        "prior_global": {
            "iters_to_target": 60,
            "gaussians_at_target": 900,
            "psnr_at_budget_db": 21.5,
        },
        "random": {"iters_to_target": 60, "gaussians_at_target": 1000, "psnr_at_budget_db": 15.0},
    }
    r = ratios(inits)
    assert r["iters_to_target_mogs_over_random"] == 0.5
    assert r["gaussians_at_target_mogs_over_random"] == 0.8
    assert r["psnr_at_budget_mogs_minus_prior_global_db"] == 0.5
    inits["random"]["iters_to_target"] = None
    assert ratios(inits)["iters_to_target_mogs_over_random"] is None


def test_depth_statistics_follow_the_insertion_stride() -> None:
    # near confident depth: stride 2 doubled once (conf >= 0.7) and planar x2 -> 8; 1/64 per px
    # (a flat plane at 5 m, confidence 1); unconfident: stride 2 -> 1/4; beyond 25 m: doubled
    d = np.full((20, 30), 5.0, np.float32)
    st = depth_statistics(d, np.ones_like(d))
    assert st["valid"] == 1.0 and st["confident"] == 1.0 and st["median_depth_m"] == 5.0
    assert st["gaussians_per_px"] == pytest.approx(1 / 64)
    assert depth_statistics(d, np.zeros_like(d))["gaussians_per_px"] == pytest.approx(1 / 4)
    far = depth_statistics(np.full_like(d, 30.0), np.zeros_like(d))
    assert far["gaussians_per_px"] == pytest.approx(1 / 16)
    d[:10] = 0.0  # no depth in the upper half: not counted
    half = depth_statistics(d, np.zeros_like(d))
    assert half["valid"] == 0.5 and half["gaussians_per_px"] == pytest.approx(1 / 4)
    assert depth_statistics(np.zeros_like(d), np.ones_like(d))["valid"] == 0.0


def test_runs_saved_one_init_each_merge_into_the_same_table(tmp_path: Path) -> None:
    def run(psnr: dict[int, list[float]]) -> tuple[dict, HeldOutViews]:
        hv = HeldOutViews({})
        hv.curves = {
            i: [
                {
                    "iterations": 20 * (k + 1),
                    "wall_s": 10.0 * (k + 1),
                    "n_gaussians": 1000 * (k + 1),
                    "fixed_view_psnr_db": x,
                    "fixed_view_ssim": 0.5,
                }
                for k, x in enumerate(v)
            ]
            for i, v in psnr.items()
        }
        hv.iterations, hv.inserted, hv.pruned = 60, 5000, 400
        return {"wall_s": 99.0, "psnr_at_budget_db": 21.0, "ssim_at_budget": 0.7}, hv

    args = SimpleNamespace(
        frames=60, view_frame=None, candidates_from=40, candidate_step=2, target_db=20.0
    )
    runs = {
        "mogs": run({40: [19.0, 20.5, 21.0], 42: [20.1, 21.0, 22.0]}),
        "random": run({40: [15.0, 18.0, 20.2], 42: [19.0, 19.5, 19.9]}),
    }
    res = assemble(runs, args, "cmd", 20)
    assert res["view_frame"] == 40  # 42: random never reaches it
    assert res["inits"]["mogs"]["iters_to_target"] == 40
    assert res["inits"]["random"]["iters_to_target"] == 60
    assert res["ratios"]["iters_to_target_mogs_over_random"] == pytest.approx(0.667, abs=1e-3)
    paths = []
    for init in runs:  # saved by two invocations, one init each
        one = assemble({init: runs[init]}, args, "cmd", 20)
        paths.append(tmp_path / f"{init}.json")
        paths[-1].write_text(json.dumps(one))
    merged_runs, ipk = runs_from_json([str(p) for p in paths])
    merged = assemble(merged_runs, args, "cmd", ipk)
    assert ipk == 20 and merged["view_frame"] == 40
    for init in runs:
        assert merged["inits"][init] == res["inits"][init]
    assert merged["ratios"] == res["ratios"]
    # a run without candidate scores has no say in the choice of the view
    merged_runs["prior_global"] = ({"psnr_at_budget_db": 20.5}, HeldOutViews({}))
    assert choose_view({k: v for k, (_, v) in merged_runs.items()}, 20.0) == 40


def test_pruned_is_the_mappers_running_total_not_a_sum_of_it() -> None:
    # /mapper/stats' extra "pruned" is GaussianMapper.n_pruned (cumulative); session 11's table
    # summed it over the updates (72302 "pruned" of 65682 inserted in a 6-per-keyframe run)
    hv = HeldOutViews({})
    for inserted, pruned in ((100, 0), (50, 10), (40, 25)):
        stats = SimpleNamespace(iterations=6, extra={"inserted": inserted, "pruned": pruned})
        hv.on("/mapper/stats", stats, 0.0)
    assert hv.inserted == 190 and hv.pruned == 25
