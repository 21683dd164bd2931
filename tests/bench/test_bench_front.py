"""bench/front.py's pure parts (issue 27): domination and the front, the per-error front, the
preset checks and knob table, the CPU accounting between samples, standing still vs moving, the
grid and one knob's overrides."""

from __future__ import annotations

from dataclasses import MISSING
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_launch_files import _nested

from bench.front import (
    KNOBS,
    Config,
    CpuSampler,
    analyse,
    cpu_between,
    dominates,
    grid,
    knob_overrides,
    measured,
    pipeline_only_ratio,
    scene_figures,
    valid,
)
from bench.front_plot import ERRORS, pareto_2d
from mogs_node.commands.node import load_node_class
from mogs_node.launch import load_launch_file
from mogs_node.node import parse_params
from mogs_node.presets import balanced_value

REPO = Path(__file__).resolve().parents[2]


def _point(name: str, cpu: float, absrel: float, psnr: float, **kw) -> dict:
    p = {
        "name": name,
        "cpu_s_per_frame": cpu,
        "depth_absrel": absrel,
        "depth_coverage": 0.5,
        "ate_pct": 1.0,
        "heldout_psnr_db": psnr,
        "heldout_ssim": 0.8,
    }
    p.update(kw)
    return p


def test_domination_needs_no_worse_everywhere_and_better_somewhere() -> None:
    a = _point("a", 1.0, 0.10, 25.0)
    assert dominates(_point("b", 0.5, 0.10, 25.0), a)  # cheaper, same errors
    assert dominates(_point("b", 1.0, 0.09, 25.0), a)  # same cost, better AbsRel
    assert not dominates(_point("b", 1.0, 0.10, 25.0), a)  # identical: neither
    assert not dominates(_point("b", 0.5, 0.11, 30.0), a)  # cheaper but one error worse
    assert not dominates(_point("b", 0.5, 0.10, 24.0), a)  # PSNR: higher is better
    assert not dominates(_point("b", 0.5, float("nan"), 25.0), a)  # unmeasured: no claim


_pts = st.lists(
    st.tuples(st.floats(0.1, 5), st.floats(0.05, 0.5), st.floats(15, 35)), min_size=1, max_size=8
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_pts)
def test_front_points_are_exactly_the_undominated_ones(raw) -> None:
    points = [_point(f"p{i}", c, a, s) for i, (c, a, s) in enumerate(raw)]
    res = analyse(points)
    for p in points:
        beaten = any(dominates(q, p) for q in points)
        assert (p["name"] in res["front"]) == (not beaten)
    assert res["front"]  # a finite set always has an undominated point
    # per-error fronts: errors only improve as the cost grows
    for error, low in ERRORS.items():
        values = [p[error] for p in pareto_2d(points, error)]
        assert values == sorted(values, reverse=low)


def test_preset_checks_and_knob_table() -> None:
    points = [
        _point("balanced", 1.0, 0.15, 22.0),
        _point("fast", 0.4, 0.17, 20.0),
        _point("quality", 2.0, 0.14, 24.0),
        _point("mapper.iters_per_keyframe=8", 0.7, 0.15, 21.0, knob=["mapper.iters", 8]),
        _point("cheap_and_good", 0.3, 0.17, 20.5),  # dominates fast
    ]
    res = analyse(points)
    checks = res["preset_checks"]
    assert checks["fast_dominated_by"] == ["cheap_and_good"]
    assert checks["balanced_dominated_by"] == [] and checks["quality_dominated_by"] == []
    assert checks["fast_over_quality_cpu"] == 0.2
    assert checks["quality_best_absrel"] and checks["quality_best_heldout_psnr"]
    tie = analyse([points[0], points[1], _point("quality", 2.0, 0.15, 24.0)])["preset_checks"]
    assert not tie["quality_best_absrel"] and tie["quality_best_heldout_psnr"]  # a tie is not best
    (knob,) = res["knobs"]
    assert knob["knob"] == "mapper.iters" and knob["value"] == 8
    assert np.isclose(knob["d_cpu_s_per_frame"], -0.3)
    assert np.isclose(knob["d_heldout_psnr_db"], -1.0) and knob["d_depth_absrel"] == 0.0


class _FakeSampler(CpuSampler):
    def __init__(self, samples):  # (time, node -> cumulative CPU s)
        self.samples = samples


def test_cpu_between_takes_the_samples_at_or_before_each_end() -> None:
    s = _FakeSampler([(0.0, {"a": 0.0}), (1.0, {"a": 1.0, "b": 0.5}), (2.0, {"a": 3.0, "b": 1.0})])
    assert cpu_between(s, 0.0, 2.0) == {"a": 3.0, "b": 1.0}
    assert cpu_between(s, 1.5, 2.5) == {"a": 2.0, "b": 0.5}
    assert cpu_between(s, -1.0, 0.5) == {"a": 0.0}  # before the first sample: the first


def test_standstill_and_moving_cpu_per_frame_from_ground_truth_speed() -> None:
    # 4 frames parked, 4 moving at 1 m/s; 0.1 s apart; arrivals at the stamps (seconds)
    stamps = [int(i * 1e8) for i in range(8)]
    image_t = {s: s * 1e-9 for s in stamps}
    gt = {s: np.array([max(0.0, (i - 3) * 0.1), 0.0, 0.0]) for i, s in enumerate(stamps)}
    # CPU: 0.1 s per frame parked, 1 s per frame moving (cumulative, sampled at each image)
    cum, samples = 0.0, []
    for i, stamp in enumerate(stamps):
        samples.append((image_t[stamp], {"n": cum}))
        cum += 0.1 if i < 4 else 1.0
    samples.append((0.8, {"n": cum}))
    fig = scene_figures(_FakeSampler(samples), image_t, gt, [0.8])
    assert fig["standstill_frames"] == 4 and fig["moving_frames"] == 4
    assert np.isclose(fig["standstill_cpu_s_per_frame"], 0.1)
    assert np.isclose(fig["moving_cpu_s_per_frame"], 1.0)
    assert np.isclose(fig["standstill_over_moving_cpu"], 0.1)
    # never moving: no ratio
    still = {s: np.zeros(3) for s in stamps}
    assert np.isnan(
        scene_figures(_FakeSampler(samples), image_t, still, [])["standstill_over_moving_cpu"]
    )


def test_grid_and_one_knobs_overrides_merge_nested_groups() -> None:
    names = [c.name for c in grid(quick=False)]
    assert names[:3] == ["balanced", "fast", "quality"] and len(names) >= 12
    assert len(set(names)) == len(names)
    assert sorted(c.name for c in grid(quick=True)) == ["balanced", "fast", "quality"]
    lf = load_launch_file(REPO / "launch" / "demo.yaml")
    over = knob_overrides(lf, "prior.flow.dis_preset", "fast")
    flow = over["prior"]["flow"]
    assert flow["dis_preset"] == "fast" and flow["max_flow_gradient"] == 2.0  # the file's kept
    assert knob_overrides(lf, "mapper.window_size", 4) == {"mapper": {"window_size": 4}}
    # every knob of the grid names a node of the demo, loads and validates
    for cfg in grid(quick=False)[3:]:
        moved = load_launch_file(
            REPO / "launch" / "demo.yaml", overrides=knob_overrides(lf, *cfg.knob)
        )
        for spec in moved.nodes:
            _nested(spec, parse_params(load_node_class(spec.cls).Params, spec.params))


def test_every_knob_point_moves_its_knob_away_from_balanced() -> None:
    """The knobs are relative to balanced (the demo's own values): each point moves one."""
    lf = load_launch_file(REPO / "launch" / "demo.yaml")
    assert balanced_value(lf, "mapper.iters_per_keyframe") == 6  # the file's
    assert balanced_value(lf, "metrizer.cdr.irls_iters") == 3  # a default
    for path, values in KNOBS:
        base = balanced_value(lf, path)
        assert base is not MISSING, path
        assert all(v != base for v in values), (path, base, values)


def test_standstill_ratio_without_the_sensor_and_the_scorer() -> None:
    point = {
        "standstill_cpu_s_per_frame_by_node": {"player": 0.2, "report": 0.1, "mapper": 0.05},
        "moving_cpu_s_per_frame_by_node": {"player": 0.2, "report": 0.1, "mapper": 0.5},
    }
    assert pipeline_only_ratio(point) == 0.1
    assert pipeline_only_ratio({}) is None


def test_only_clean_runs_count_and_a_grid_resumes_the_rest() -> None:
    args = SimpleNamespace(redo=[])
    cfg = Config("mapper.window_size=4", knob=("mapper.window_size", 4))
    clean = {"name": cfg.name, **cfg.key(), "frames_requested": 60, "launch_rc": 0}
    assert valid(clean) and measured({cfg.name: clean}, cfg, 60, args)
    assert not measured({cfg.name: clean}, cfg, 40, args)  # another drive length
    assert not measured({cfg.name: clean}, cfg, 60, SimpleNamespace(redo=[cfg.name]))
    q = Config("quality", preset="quality")
    old_quality = {"name": "quality", **q.key(), "frames_requested": 60, "preset_table": {}}
    assert not measured({"quality": old_quality}, q, 60, args)  # the preset was redefined
    for bad in ({"launch_rc": 1}, {"respawns": 2}, {"final_map": False}):
        assert not valid({**clean, **bad})
        assert not measured({cfg.name: {**clean, **bad}}, cfg, 60, args)
