"""Trajectory files (TUM, KITTI) round-trip, and the evo-based trajectory metrics on known cases."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import DatasetError, ShapeError
from mogs_node.eval.traj import trajectory_metrics
from mogs_node.frontend.trajectory_io import read_kitti, read_tum, write_kitti, write_tum
from mogs_node.geometry import make_T, se3_exp, so3_exp


def random_poses(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return se3_exp(rng.normal(0, 1, (n, 6)) * np.array([10, 10, 10, 1, 1, 1]))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 30))
def test_tum_round_trip(tmp_path_factory, seed, n):
    path = tmp_path_factory.mktemp("tum") / "t.txt"
    T = random_poses(seed, n)
    stamps = np.sort(np.random.default_rng(seed).integers(0, 2**62, n)).astype(np.int64)
    write_tum(path, stamps, T)
    s2, T2 = read_tum(path)
    np.testing.assert_array_equal(s2, stamps)
    np.testing.assert_allclose(T2, T, atol=1e-8)


def test_kitti_round_trip_and_errors(tmp_path):
    T = random_poses(1, 7)
    write_kitti(tmp_path / "k.txt", T)
    np.testing.assert_allclose(read_kitti(tmp_path / "k.txt"), T, rtol=1e-8, atol=1e-8)
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match="bad.txt:1"):
        read_kitti(tmp_path / "bad.txt")
    (tmp_path / "bad_tum.txt").write_text("# comment\n0.5 1 2 3\n")
    with pytest.raises(DatasetError, match="bad_tum.txt:2"):
        read_tum(tmp_path / "bad_tum.txt")
    with pytest.raises(ShapeError, match="poses_se3"):
        write_kitti(tmp_path / "x.txt", np.full((2, 4, 4), np.nan))


def straight_line(n: int = 50, step: float = 1.0) -> np.ndarray:
    return make_T(
        np.tile(np.eye(3), (n, 1, 1)), np.c_[np.arange(n) * step, np.zeros(n), np.zeros(n)]
    )


def helix(n: int = 50, scale: float = 1.0) -> np.ndarray:
    t = np.arange(n) * 0.1
    p = np.c_[10 * np.cos(t), 10 * np.sin(t), 0.5 * t] * scale
    return make_T(so3_exp(np.c_[np.zeros(n), np.zeros(n), t]), p)


def test_metrics_perfect_and_rigidly_moved():
    ref = helix()
    stamps = np.arange(50, dtype=np.int64) * 100_000_000
    G = se3_exp(np.array([5.0, -3, 2, 0.1, 0.2, -0.3]))
    m = trajectory_metrics(stamps, G @ ref, ref)
    step = np.linalg.norm(ref[1, :3, 3] - ref[0, :3, 3])
    assert m["path_length_m"] == pytest.approx(49 * step)
    assert m["ate_se3_rmse_m"] < 1e-9 and m["ate_sim3_rmse_m"] < 1e-9
    assert m["scale_error"] < 1e-9 and m["rpe_trans_m"] < 1e-9 and m["rpe_rot_deg"] < 1e-6


def test_metrics_scale_error_and_ate():
    ref = helix()
    stamps = np.arange(50, dtype=np.int64) * 100_000_000
    est = helix(scale=1.1)  # 10 % too large
    m = trajectory_metrics(stamps, est, ref, rpe_delta_frames=1)
    assert m["scale_error"] == pytest.approx(abs(1 / 1.1 - 1), abs=1e-6)
    assert m["ate_sim3_rmse_m"] < 1e-6
    assert m["ate_se3_rmse_m"] > 0.1
    step = np.linalg.norm(ref[1, :3, 3] - ref[0, :3, 3])
    assert m["rpe_trans_m"] == pytest.approx(0.1 * step, rel=1e-6)


def test_metrics_reject_bad_input():
    with pytest.raises(ShapeError):
        trajectory_metrics(np.arange(2), straight_line(2), straight_line(2))
    with pytest.raises(ShapeError, match="poses_ref"):
        trajectory_metrics(np.arange(5), straight_line(5), straight_line(4))
    with pytest.raises(ShapeError, match="degenerate"):
        trajectory_metrics(np.arange(5), straight_line(5), straight_line(5))
