"""bench/kitti_camera_only.py: the camera-only frontend's points and speed against the LiDAR."""

from __future__ import annotations

import numpy as np
import pytest

from bench.kitti_camera_only import frontend_params, lidar_at, run
from mogs_node.eval.frontend_runs import DEFAULT_DATA

KITTI = DEFAULT_DATA / "kitti_raw_2011_09_26_78"


def test_lidar_at_takes_the_median_return_within_one_pixel():
    depth = np.zeros((10, 12), np.float32)
    depth[4, 5], depth[5, 5], depth[5, 6] = 10.0, 12.0, 30.0
    depth[0, 0] = 7.0
    uv = np.array([[5.0, 5.0], [5.4, 4.4], [0.2, 0.1], [10.0, 8.0], [6.6, 5.2]])
    z = lidar_at(depth, uv)
    assert z[0] == pytest.approx(12.0)  # 10, 12, 30 around (5, 5)
    assert z[1] == pytest.approx(12.0)  # rounds to (5, 4): 10, 12, 30 within 1 px
    assert z[2] == pytest.approx(7.0)  # the image corner: a clipped window
    assert np.isnan(z[3])  # no return within 1 px
    assert z[4] == pytest.approx(30.0)  # rounds to (7, 5): only the 30 at (6, 5) within 1 px


def test_frontend_params_merge_points_over_the_launch_file():
    p = frontend_params({"max_tracks": 1234})
    assert p.points["max_tracks"] == 1234
    assert p.keyframes["min_parallax_px"] == 40.0  # launch/kitti.yaml's, kept


@pytest.mark.slow
@pytest.mark.skipif(not KITTI.exists(), reason=f"{KITTI} absent (../shared/data)")
def test_points_with_metric_poses_match_the_lidar_on_real_images():
    """With the LiDAR-PnP poses given, the keyframes' points are the triangulation's alone: on
    the real excerpt their median error against the LiDAR is a few percent (measured 1.8 %), and
    the poses' path is the PnP path (docs/frontend.md, round 11)."""
    out = run({}, KITTI, given_poses=True)
    assert len(out["keyframes"]) >= 4
    assert out["points_vs_lidar"] >= 200
    assert out["points_rel_err_median"] < 0.03
    assert abs(out["points_rel_err_signed_median"]) < 0.02
    assert out["path_m"] == pytest.approx(out["path_lidar_pnp_m"], rel=1e-6)
