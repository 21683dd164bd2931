"""bench/points_isolation.py: the points' error figures against the truth at their pixels."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bench.points_isolation import point_errors


def test_point_errors_are_signed_and_binned_by_true_depth():
    depth = np.full((20, 30), 10.0, np.float32)
    depth[:, 15:] = 50.0
    depth[0, 0] = 0.0  # no truth (sky): left out
    uv = np.array([[2.0, 5.0], [4.0, 5.0], [20.0, 5.0], [25.0, 9.0], [0.0, 0.0]], np.float32)
    z = np.array([9.8, 10.0, 45.0, 55.0, 3.0])  # -2 %, 0 %, -10 %, +10 %, (no truth)
    kf = SimpleNamespace(feature_uv_px=uv, feature_xyz_cam_m=np.c_[0 * z, 0 * z, z])
    fig = point_errors([SimpleNamespace(gt_depth_m=depth)], [kf])
    assert fig["points_total"] == 5
    assert fig["rel_err_median"] == pytest.approx(0.06)  # of 0.02, 0, 0.1, 0.1
    assert fig["share_over_3pct"] == pytest.approx(0.5)
    assert fig["signed_err_median_per_keyframe"] == [pytest.approx(-0.01)]
    by = fig["count_and_signed_err_median_by_depth"]
    assert "0-10m" not in by  # 10 m starts the next bin
    assert by["10-20m"] == [2, -0.01]
    assert by["40-1000000000m"] == [2, 0.0]
