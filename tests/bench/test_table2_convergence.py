"""bench/table2_convergence.py: the held-out view of each keyframe, the per-iteration convergence
on a copy of the map, the medians, the common target and the table (no processes)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from bench.table2_convergence import (
    apply,
    common_target,
    common_view_gaussians,
    converge,
    figures,
    heldout_views,
    iterations_to,
    markdown,
    paired_ratios,
)
from mogs_node.geometry import make_T
from mogs_node.mapper.mapper import GaussianMapper, MapperParams

W, H = 64, 32
K = np.array([[40.0, 0, 31.5], [0, 40.0, 15.5], [0, 0, 1]])


def wall(kid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Image, pose, depth, confidence of keyframe ``kid``: a textured wall at 5 m."""
    rng = np.random.default_rng(0)
    coarse = rng.uniform(0, 255, size=(H // 8 + 1, W // 8 + 1, 3))
    img = np.kron(coarse, np.ones((8, 8, 1)))[:H, :W].astype(np.uint8)
    T = make_T(np.eye(3), np.array([0.05 * kid, 0.0, 0.0]))
    return img, T, np.full((H, W), 5.0, np.float32), np.full((H, W), 0.8, np.float32)


def test_a_copy_converges_iteration_by_iteration_and_the_map_stays_as_it_was() -> None:
    m = GaussianMapper(MapperParams(), K, W, H)
    img, T, d, c = wall(0)
    m.add_keyframe(0, img, T, d, c)
    before = {k: v.detach().clone() for k, v in m.map.params.items()}
    gt = img.astype(np.float32) / 255.0
    curve = converge(m, T, gt, stop_db=math.inf, cap=40)  # never stops early: 0..40
    assert len(curve["psnr_db"]) == 41 and len(curve["gaussians"]) == 41
    assert curve["psnr_db"][-1] > curve["psnr_db"][0] + 1.0  # it fits the view
    assert m.iterations == 0 and all(torch.equal(before[k], v) for k, v in m.map.params.items())
    # the same copy again (deterministic), stopped once it reaches a level it reached before
    stop = max(curve["psnr_db"][1:])
    reached = converge(m, T, gt, stop_db=stop, cap=40)
    assert reached["psnr_db"] == curve["psnr_db"][: iterations_to(curve["psnr_db"], stop) + 1]
    assert converge(m, T, gt, stop_db=0.0, cap=6)["psnr_db"] == curve["psnr_db"][:1]


def _msg(**kw: object) -> SimpleNamespace:
    return SimpleNamespace(**kw)


def test_the_held_out_view_is_the_nearest_posed_frame_that_moved() -> None:
    T = [make_T(np.eye(3), np.array([x, 0.0, 0.0])) for x in (0, 0, 0, 0.5, 1.0, 1.5)]
    data = {
        "/frontend/keyframe": [
            _msg(stamp_ns=0, keyframe_id=0, T_world_cam=T[0]),  # next frame: standing still
            _msg(stamp_ns=2, keyframe_id=1, T_world_cam=T[2]),
            _msg(stamp_ns=4, keyframe_id=2, T_world_cam=T[4]),
        ],
        "/frontend/odometry": [_msg(stamp_ns=i, T_world_cam=T[i]) for i in range(6)],
        "/camera/image": [_msg(stamp_ns=i) for i in range(6)],
    }
    assert heldout_views(data, min_move_m=0.1) == {1: 3, 2: 5}
    data["/camera/image"].pop(5)  # no image of frame 5: the nearest before it
    assert heldout_views(data, min_move_m=0.1) == {1: 3, 2: 3}
    assert heldout_views(data, min_move_m=0.1, max_frames=0) == {}


def conv(curves: list[list[float]], start: int = 1000) -> dict:
    return {
        "cap": 10,
        "keyframes": [
            {
                "keyframe_id": i,
                "psnr_db": c,
                "gaussians": [start + 10 * i + j for j in range(len(c))],
            }
            for i, c in enumerate(curves)
        ],
    }


def test_medians_count_a_keyframe_that_never_reaches_the_target_as_never() -> None:
    assert iterations_to([15.0, 19.0, 20.0], 20.0) == 2 and iterations_to([15.0], 20.0) is None
    c = conv([[20.5], [18.0, 19.0, 20.1], [17.0, 18.0]])  # 0, 2, never
    f = figures(c, 20.0)
    assert f["iters_to_target"] == 2.0 and f["keyframes_reaching_target"] == 2
    assert f["gaussians_at_target"] == pytest.approx((1000 + 1012) / 2)
    assert f["psnr_after_insertion_db_median"] == 18.0
    assert figures(conv([[20.5], [17.0], [17.0]]), 20.0)["iters_to_target"] is None


def test_the_common_target_and_the_paired_ratios() -> None:
    convs = {"mogs": conv([[19.0, 20.0], [20.0]]), "random": conv([[15.0, 17.0, 18.5]] * 2)}
    assert common_target(convs) == 18.5
    r = paired_ratios(convs, 18.5)
    assert r["keyframes_both_reach"] == 2 and r["iters_plus1_mogs_over_random_median"] == 0.333
    assert paired_ratios({"mogs": convs["mogs"]}, 18.5) == {}


def test_gaussians_at_target_are_counted_on_the_views_every_init_reaches() -> None:
    """Random reaches only the first view: every init's Gaussians are its map's there, not a
    median over its own (later, larger) views."""
    convs = {
        "mogs": conv([[20.5], [19.0, 20.0], [20.0]], start=100),  # 100, 111, 120
        "prior_global": conv([[20.0], [20.0], [19.0]], start=200),  # 200, 210, never
        "random": conv([[19.0, 19.5, 20.0], [15.0], [16.0]], start=300),  # 302, never, never
    }
    assert figures(convs["mogs"], 20.0)["gaussians_at_target"] == 111.0  # own views: 100, 111, 120
    ids, med = common_view_gaussians(convs, 20.0)
    assert ids == [0] and med == {"mogs": 100.0, "prior_global": 200.0, "random": 302.0}
    ids, med = common_view_gaussians(convs, 21.0)  # nobody reaches 21 dB
    assert ids == [] and med == {"mogs": None, "prior_global": None, "random": None}
    assert common_view_gaussians({}, 20.0) == ([], {})


def test_apply_keeps_the_first_definition_and_writes_the_table() -> None:
    row = {
        "iters_to_target": 60,
        "wall_s_to_target": 30.0,
        "gaussians_at_target": 800,
        "view_frame": 52,
        "curve": {},
        "psnr_at_budget_db": 21.5,
        "ssim_at_budget": 0.75,
        "gaussians_at_budget": 900,
        "gaussians_inserted": 1000,
        "gaussians_pruned": 100,
    }
    res = {
        "target_psnr_db": 15.0,
        "view_frame": 52,
        "frames": 60,
        "iters_per_keyframe": 6,
        "inits": {k: dict(row) for k in ("mogs", "prior_global", "random")},
        "ratios": {"iters_to_target_mogs_over_random": 1.0},
    }
    res["inits"]["prior_global"]["psnr_at_budget_db"] = 21.0
    convs = {
        "mogs": conv([[20.0], [19.0, 20.0]], 500),
        "prior_global": conv([[19.0, 19.5, 20.0]] * 2),
        "random": conv([[15.0, 18.0, 19.0, 20.0]] * 2),
    }
    apply(res, convs, auto=True)
    assert res["target_psnr_db"] == 20.0 and res["fixed_view_target_psnr_db"] == 15.0
    mo = res["inits"]["mogs"]
    assert mo["iters_to_target"] == 0.5 and mo["fixed_view"]["iters_to_target"] == 60
    assert mo["fixed_view"]["view_frame"] == 52 and "view_frame" not in mo
    rt = res["ratios"]
    assert rt["iters_to_target_mogs_over_random"] == pytest.approx(0.5 / 3, abs=1e-3)
    assert rt["psnr_at_budget_mogs_minus_prior_global_db"] == 0.5
    assert rt["fixed_view"] == {"iters_to_target_mogs_over_random": 1.0}
    text = markdown("python bench/pipeline_table2.py", res, "a machine", "Why: the policy.")
    assert "| mogs | 0.5 | 2/2 |" in text and "| 60 |" in text
    assert "iterations to 20 dB 0.167" in text and "Why: the policy." in text


def test_the_bench_replays_each_runs_journal_after_the_live_runs(tmp_path, monkeypatch) -> None:
    import json

    import bench.pipeline_table2 as t2
    from bench.pipeline_table2 import HeldOutViews

    def run_init(init, args, root, gt):
        hv = HeldOutViews({})
        hv.curves = {
            46: [
                {
                    "iterations": 6,
                    "wall_s": 1.0,
                    "n_gaussians": 10,
                    "fixed_view_psnr_db": 16.0,
                    "fixed_view_ssim": 0.5,
                }
            ]
        }
        hv.iterations, hv.inserted, hv.pruned = 72, 100, 10
        fig = {
            "psnr_at_budget_db": {"mogs": 19.0, "prior_global": 18.5}.get(init, 15.0),
            "ssim_at_budget": 0.6,
            "run_dir": str(tmp_path / init),
            "wall_s": 1.0,
        }
        return fig, hv

    measured = []

    def measure(journal, launch, init):
        measured.append((journal, launch, init))
        return conv([[20.0], [19.0, 20.0]] if init == "mogs" else [[15.0, 19.0, 20.0]] * 2)

    monkeypatch.setattr(t2, "run_init", run_init)
    monkeypatch.setattr(t2, "sim_images", lambda frames, idx, sim=None: {})
    monkeypatch.setattr(t2.convergence, "measure", measure)
    out = tmp_path / "t2.json"
    assert t2.main(["--target-db", "auto", "--no-docs", "--json", str(out)]) == 0
    assert [m[2] for m in measured] == ["mogs", "prior_global", "random"]
    assert measured[0][0] == tmp_path / "mogs" / "journal" / "journal.log"
    res = json.loads(out.read_text())
    assert res["target_psnr_db"] == 20.0 and res["inits"]["random"]["iters_to_target"] == 2.0
    assert res["inits"]["mogs"]["fixed_view"]["iters_to_target"] == 6
    assert res["ratios"]["iters_to_target_mogs_over_random"] == 0.25


def test_a_policy_table_replays_all_three_inits_with_the_same_core(tmp_path, monkeypatch) -> None:
    """``--all-inits``: each init's journal (random: the mogs run's, regenerated) replayed with
    the one ``core`` policy; the target, medians and ratios as the bench's."""
    import bench.table2_convergence as tc

    calls = []
    curves = {
        "mogs": conv([[19.0, 20.0], [20.0]], start=100),
        "prior_global": conv([[18.0, 19.5, 20.0], [20.0]], start=120),
        "random": conv([[15.0, 17.0, 18.5]] * 2, start=400),
    }

    def measure(journal, launch, init, stop_db, cap, min_move_m, core):  # noqa: ANN001
        calls.append((journal.parent.parent.name, init, core))
        held = {"mogs": 20.1, "prior_global": 19.7, "random": 16.2}[init]
        return {
            **curves[init],
            "replay_report_heldout_psnr_db": held,
            "replay_gaussians": 7,
            "replay_inserted_pruned": [9, 2],
        }

    monkeypatch.setattr(tc, "measure", measure)
    core = {"insertion.patch_px": 32}
    res = tc.policy_table(tmp_path, core)
    assert calls == [
        ("mogs", "mogs", core),
        ("prior_global", "prior_global", core),
        ("mogs", "random", core),
    ]
    assert res["target_psnr_db"] == 18.5  # random never reaches 20 dB: the highest common one
    assert res["inits"]["mogs"]["gaussians_at_target"] == pytest.approx((100 + 110) / 2)
    r = res["ratios"]
    assert r["gaussians_at_target_mogs_over_random"] == round(105 / ((402 + 412) / 2), 3)
    assert r["iters_to_target_mogs_over_random"] == 0.0
    assert r["replay_heldout_mogs_minus_prior_global_db"] == pytest.approx(0.4)
    assert r["keyframes_both_reach"] == 2
