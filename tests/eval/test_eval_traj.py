"""Trajectory scoring (issue 28): rotations rounded to six decimals (a typed calibration chained
into every pose) are re-orthonormalised and scored exactly; poses that are no rotations are named
with the reason instead of a bare "not scored"."""

from __future__ import annotations

import numpy as np
import pytest

from mogs_node.errors import ShapeError
from mogs_node.eval.traj import orthonormalized, trajectory_metrics
from mogs_node.geometry import make_T, nearest_rotation, so3_exp


def _drive(n: int = 40) -> np.ndarray:
    """A curving drive, ``T_world_cam`` [n, 4, 4]."""
    yaw = np.linspace(0.0, 1.2, n)
    R = np.stack([so3_exp(np.array([0.02 * np.sin(k), 0.0, y])) for k, y in enumerate(yaw)])
    t = np.stack([np.cumsum(np.cos(yaw)), np.cumsum(np.sin(yaw)), 0.1 * np.sin(yaw)], -1)
    return make_T(R, t)


def test_six_decimal_rotations_are_scored_as_exact_ones() -> None:
    ref = _drive()
    stamps = np.arange(len(ref), dtype=np.int64) * 100_000_000
    T_imu_cam = np.round(make_T(so3_exp(np.array([1.2, -1.1, 0.3])), [1.08, -0.25, 0.73]), 6)
    est = ref @ T_imu_cam  # every pose carries the typed calibration's defect (~1e-6)
    ref_c = ref @ make_T(nearest_rotation(T_imu_cam[:3, :3]), T_imu_cam[:3, 3])
    out = trajectory_metrics(stamps, est, ref_c)
    assert out["ate_se3_rmse_m"] < 1e-5 and out["rpe_rot_deg"] < 1e-3
    assert out["path_length_m"] == pytest.approx(
        np.linalg.norm(np.diff(ref_c[:, :3, 3], axis=0), axis=1).sum()
    )
    P = orthonormalized("poses", est)
    np.testing.assert_allclose(
        P[:, :3, :3] @ np.swapaxes(P[:, :3, :3], 1, 2),
        np.eye(3)[None] + 0 * P[:, :3, :3],
        atol=1e-12,
    )


def test_poses_that_are_no_rotations_are_named_with_the_reason() -> None:
    ref = _drive()
    stamps = np.arange(len(ref), dtype=np.int64)
    est = ref.copy()
    est[7, 0, 1] += 0.2
    est[12, :3, :3] *= 1.5
    with pytest.raises(
        ShapeError, match=r"poses_est: 2 of 40 poses have no rotation.*7 \(0\.19.*12 \(1\.2"
    ):
        trajectory_metrics(stamps, est, ref)
    est = ref.copy()
    est[3, 3, 0] = 1.0
    with pytest.raises(ShapeError, match=r"poses_est: 1 poses have a last row.*index 3"):
        trajectory_metrics(stamps, est, ref)
