"""The keyframes' sparse points on the demo's sim drive, against ground truth (docs/frontend.md,
round 6), and the estimator unchanged by them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench.frontend import ROUND9
from mogs_node.eval.frontend_runs import keyframe_point_figures, run_frontend
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.frontend import Frontend, FrontendParams
from mogs_node.frontend.keyframes import KeyframeParams
from mogs_node.sim import SimConfig, make_sequence

# launch/demo.yaml's drive and keyframe policy
DEMO = SimConfig(seed=0, n_frames=60, width=621, height=188, static_start_s=2.0)
DEMO_KEYFRAMES = KeyframeParams(min_parallax_px=20.0, max_interval_s=1.0)
SHORT = dataclasses.replace(DEMO, n_frames=36, static_start_s=1.2)  # the default suite's drive


def _runs(config: SimConfig, **points_fields):
    """The frontend with and without the dense points on ``config``'s drive (``points_fields``
    replace the points' defaults), and the points' figures against ground truth."""
    seq = make_sequence(config)
    frames = [seq.render(i) for i in range(config.n_frames)]
    runs = {}
    for enabled in (True, False):
        base = FrontendParams(keyframes=DEMO_KEYFRAMES)
        points = dataclasses.replace(base.points, enabled=enabled, **points_fields)
        params = dataclasses.replace(base, points=points)
        fe = Frontend(params, CameraModel(seq.camera), seq.T_imu_cam)
        runs[enabled] = run_frontend(
            fe,
            seq.stamps_ns,
            [f.rgb for f in frames],
            seq.imu_stamps_ns,
            seq.imu_gyro_rad_s,
            seq.imu_accel_m_s2,
        )
    index = {int(t): i for i, t in enumerate(seq.stamps_ns)}
    speed = np.linalg.norm(seq.velocity_world_m_s, axis=1)
    figures = {
        k: keyframe_point_figures(
            outs, lambda t: frames[index[t]].depth_m, lambda t: float(speed[index[t]])
        )
        for k, outs in runs.items()
    }
    return runs, figures, speed[[index[o.stamp_ns] for o in runs[True] if o.keyframe]]


@pytest.fixture(scope="module")
def short_runs():
    return _runs(SHORT)


@pytest.fixture(scope="module")
def demo_runs():
    return _runs(DEMO)


@pytest.fixture(scope="module")
def demo_runs_round9():
    return _runs(DEMO, **ROUND9)


def test_the_estimator_is_unchanged_by_the_points(short_runs):
    runs, fig, _ = short_runs
    with_points, without = runs[True], runs[False]
    assert [o.stamp_ns for o in with_points] == [o.stamp_ns for o in without]
    assert [o.status for o in with_points] == [o.status for o in without]
    for a, b in zip(with_points, without, strict=True):
        if a.T_world_cam is None:
            assert b.T_world_cam is None
        else:
            np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
    # the keyframes may differ: the first one after the standstill waits for its points (round 8)
    assert fig[True]["points_rel_err_median"] <= 0.03
    assert fig[True]["points_per_keyframe_median"] > fig[False]["points_per_keyframe_median"]


@pytest.mark.slow
def test_demo_drive_points_against_ground_truth(demo_runs):
    """Measured on this drive (docs/frontend.md, rounds 6 to 9), the default (round 8's points):
    median 164 points per moving keyframe (the estimator's landmarks: 28), 1.31 % median
    relative depth error, 1.27 % of the points straddling a depth edge (the issue's count; the
    landmarks: 13 %), 12.3 % near one (the landmarks: 37 %). The bounds hold the measured
    figures with a margin."""
    _, fig, _ = demo_runs
    new, old = fig[True], fig[False]
    assert new["points_rel_err_median"] <= 0.03
    assert new["points_per_keyframe_median"] >= 140
    assert new["points_per_keyframe_median"] >= 5 * old["points_per_keyframe_median"]
    assert new["points_on_edges_share"] <= 0.02  # straddling: the bound
    assert new["points_on_edges_share"] <= 0.25 * old["points_on_edges_share"]
    assert new["points_near_edges_share"] <= 0.5 * old["points_near_edges_share"]
    assert new["keyframes"] == new["keyframes_moving"] and new["keyframes_without_points"] == 0


@pytest.mark.slow
def test_demo_drive_round9_points_against_ground_truth(demo_runs_round9):
    """Round 9's denser points (opt-in, ``bench/frontend.py: ROUND9``): median 272 per moving
    keyframe, 1.45 % error, 1.57 % straddling (docs/frontend.md "Round 9")."""
    _, fig, _ = demo_runs_round9
    new = fig[True]
    assert new["points_rel_err_median"] <= 0.03
    assert new["points_per_keyframe_median"] >= 240
    assert new["points_on_edges_share"] <= 0.02
    assert new["keyframes_without_points"] == 0


def test_no_keyframe_while_parked_and_none_is_empty(short_runs):
    """Round 8: no keyframe while the car stands still; the first one after the standstill
    waits until it carries ``first_min_points`` triangulated points; none is empty."""
    runs, _, kf_speed_m_s = short_runs
    counts = [len(o.keyframe.feature_ids) for o in runs[True] if o.keyframe is not None]
    assert len(counts) >= 5 and np.all(kf_speed_m_s > 0.5)
    assert counts[0] >= DEMO_KEYFRAMES.first_min_points
    assert all(n > 0 for n in counts)
    for o in runs[True]:
        kf = o.keyframe
        if kf is not None and len(kf.feature_ids):
            assert np.all(np.isfinite(kf.feature_xyz_cam_m)) and np.all(
                kf.feature_xyz_cam_m[:, 2] > 0
            )
            assert np.all((kf.feature_weight > 0) & (kf.feature_weight <= 1))
            assert len(np.unique(kf.feature_ids)) == len(kf.feature_ids)
