"""The road plane in the metrizer (ground.py): road objects and ground contact, against exact
geometry of a camera at a known height above a planar road."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError
from mogs_node.geometry import pixel_grid_xy
from mogs_node.geometry import road_plane_depth as _plane
from mogs_node.metrizer.ground import (
    GroundParams,
    fill_ground_contact,
    fill_road_objects,
)
from mogs_node.metrizer.params import MetrizerParams
from mogs_node.metrizer.pipeline import metrize_depth


def road_plane_depth(K: np.ndarray, hw: tuple[int, int], up: np.ndarray, h: float) -> np.ndarray:
    """The plane depth ``[H, W]`` the metrizer's road pass uses (geometry's, on the pixel grid)."""
    return _plane(pixel_grid_xy(K, *hw)[2], up, h)[0]


H, W, HEIGHT = 60, 160, 1.5
K = np.array([[100.0, 0.0, 80.0], [0.0, 100.0, 20.0], [0.0, 0.0, 1.0]])
UP = np.array([0.0, -1.0, 0.0])  # a level camera: y points down


def _rays() -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    return ((u - K[0, 2]) / K[0, 0]).ravel(), ((v - K[1, 2]) / K[1, 1]).ravel()


def test_road_plane_depth_of_a_level_camera():
    z = road_plane_depth(K, (H, W), UP, HEIGHT)
    v = np.arange(H)
    below = v > K[1, 2]
    expect = HEIGHT * K[1, 1] / (v[below] - K[1, 2])
    np.testing.assert_allclose(z[below], np.repeat(expect[:, None], W, 1), rtol=1e-6)
    assert np.isinf(z[~below]).all()


@settings(max_examples=40, deadline=None)
@given(
    tilt=st.floats(-0.3, 0.3),
    roll=st.floats(-0.3, 0.3),
    height=st.floats(0.05, 50.0),
)
def test_road_plane_points_lie_on_the_plane(tilt, roll, height):
    up = np.array([np.sin(roll), -np.cos(roll) * np.cos(tilt), np.cos(roll) * np.sin(tilt)])
    z = road_plane_depth(K, (H, W), up, height).ravel()
    x, y = (r.ravel().astype(np.float64) for r in pixel_grid_xy(K, H, W)[2])  # the rays it used
    ok = np.isfinite(z)
    assert (z[ok] > 0).all()
    X = np.stack([x[ok] * z[ok], y[ok] * z[ok], z[ok]], 1)
    np.testing.assert_allclose(X @ up, -height, rtol=1e-4)
    assert (-(np.stack([x, y, np.ones_like(x)], 1)[~ok] @ up) <= 1e-9).all()  # at / above horizon


def _road_scene():
    """Objects: 0 sky (above the horizon), 1 road, 2 road with a car standing in the left half
    (its depth pixels are the car's), 3 a block spanning the horizon."""
    z_road = road_plane_depth(K, (H, W), UP, HEIGHT).ravel()
    v, u = np.divmod(np.arange(H * W), W)
    obj = np.where(v <= 25, 0, np.where(u < 60, 1, np.where(u < 120, 2, 3)))
    obj[(v > 10) & (u >= 120)] = 3
    depth = np.zeros(H * W, np.float32)
    conf = np.zeros(H * W, np.float32)
    road1 = (obj == 1) & (u % 3 == 0)  # a third of the road has depth
    depth[road1] = z_road[road1] * 1.01
    car = (obj == 2) & (u < 90) & (u % 2 == 0)
    depth[car] = 3.0  # a car in front, its depth pixels not on the road
    block = (obj == 3) & (u % 2 == 0) & (v > 25)
    depth[block] = z_road[block]
    conf[depth > 0] = 0.8
    return depth, conf, obj.astype(np.intp), z_road


def test_road_objects_get_the_plane_and_mixed_objects_do_not():
    depth, conf, obj, z_road = _road_scene()
    before = depth.copy()
    p = GroundParams(max_depth_m=1e3)
    n = fill_road_objects(depth, conf, obj, 4, z_road, p)
    filled = (before == 0) & (depth > 0)
    assert n == filled.sum() > 0
    assert (obj[filled] == 1).all()  # not the car's object, not the one spanning the horizon
    assert np.array_equal(filled, (obj == 1) & (before == 0))
    np.testing.assert_allclose(depth[filled], z_road[filled], rtol=1e-6)
    np.testing.assert_allclose(conf[filled], 0.8, rtol=1e-6)
    assert np.array_equal(depth[~filled], before[~filled])  # nothing else changes


def test_road_objects_respect_max_depth():
    depth, conf, obj, z_road = _road_scene()
    before = depth.copy()
    fill_road_objects(depth, conf, obj, 4, z_road, GroundParams(max_depth_m=20.0))
    new = (before == 0) & (depth > 0)
    assert new.any() and (z_road[new] <= 20.0).all()
    assert ((before == 0) & (obj == 1) & (z_road > 20.0)).any()  # some were left out


def _wall_scene(yaw: float, wall_depth: float):
    """A vertical wall (yaw about the up axis) standing on the road: road object 0 with depth
    everywhere, wall object 1 with a confident band and empty elsewhere."""
    x, y = _rays()
    z_road = road_plane_depth(K, (H, W), UP, HEIGHT).ravel()
    n = np.array([np.sin(yaw), 0.0, np.cos(yaw)])  # horizontal normal
    den = n[0] * x + n[2]
    z_wall = np.where(den > 0, wall_depth * np.cos(yaw) / den, np.inf)
    wall = (z_wall < z_road) & (np.abs(x) < 0.5)
    obj = np.where(wall, 1, 0).astype(np.intp)
    truth = np.where(wall, z_wall, np.where(np.isfinite(z_road), z_road, 0.0))
    depth = np.where(obj == 0, truth, 0.0).astype(np.float32)
    v = np.arange(H * W) // W
    band = wall & (v % 7 == 0)
    depth[band] = truth[band]
    prior_conf = np.where(depth > 0, 0.9, 0.0).astype(np.float32)
    return depth, prior_conf.copy(), prior_conf, obj, z_road, truth, wall, (x, y)


@pytest.mark.parametrize("yaw", [0.0, 0.4])
def test_ground_contact_gives_a_standing_wall_its_depth(yaw):
    depth, conf, pconf, obj, z_road, truth, wall, rays = _wall_scene(yaw, 8.0)
    hole = wall & (depth == 0)
    p = GroundParams(max_depth_m=1e3)
    n = fill_ground_contact(depth, conf, pconf, obj, 2, rays, z_road, UP, HEIGHT, p, (H, W))
    assert n == hole.sum() > 100
    np.testing.assert_allclose(depth[hole], truth[hole], rtol=0.03)
    assert (conf[hole] > 0).all()


def test_ground_contact_needs_the_objects_own_pixels_to_agree():
    depth, conf, pconf, obj, z_road, truth, wall, rays = _wall_scene(0.0, 8.0)
    depth[wall & (depth > 0)] = 20.0  # the wall's confident pixels say it is not standing there
    before = depth.copy()
    p = GroundParams(max_depth_m=1e3)
    assert fill_ground_contact(depth, conf, pconf, obj, 2, rays, z_road, UP, HEIGHT, p, (H, W)) == 0
    assert np.array_equal(depth, before)


def test_ground_params_are_checked():
    with pytest.raises(ConfigError, match="shares"):
        GroundParams(min_agree_share=1.5)
    with pytest.raises(ConfigError, match="road_camera_height_m"):
        MetrizerParams(road_camera_height_m=-1.0)


def road_inputs(labels: np.ndarray, prior: np.ndarray, T_world_cam: np.ndarray) -> dict:
    """Metrizer inputs of a road frame of this module's camera: no feature, a metric prior."""
    return dict(
        K=K,
        labels=labels,
        feature_uv_px=np.zeros((0, 2)),
        feature_depth_m=np.zeros(0),
        feature_weight=np.zeros(0),
        prior=prior,
        prior_confidence=(prior > 0).astype(np.float32),
        prior_kind="metric",
        T_world_cam=T_world_cam,
    )


def _metrize_road(T_world_cam, height):
    """A frame of road below the horizon with a third of it covered by a metric prior."""
    z_road = road_plane_depth(K, (H, W), UP, HEIGHT)
    v, u = np.mgrid[0:H, 0:W]
    below = np.isfinite(z_road)
    prior = np.where(below & (u % 3 == 0), z_road, 0.0).astype(np.float32)
    labels = np.where(below, 0, 1).astype(np.int32)
    p = MetrizerParams(
        road_camera_height_m=height, d_max_m=1e3, road_max_depth_m=1e3, mask_plane_fill=False
    )
    return metrize_depth(**road_inputs(labels, prior, T_world_cam), params=p), z_road


def test_metrize_fills_the_road_with_the_pose_and_height():
    # camera frame: x right, y down, z forward; world: z up -> R_world_cam maps y_cam to -z
    T = np.eye(4)
    T[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]
    out, z_road = _metrize_road(T, HEIGHT)
    below = np.isfinite(z_road)
    assert out.stats["n_px_road"] > 0
    assert (out.depth_m[below] > 0).all()
    np.testing.assert_allclose(out.depth_m[below], z_road[below], rtol=1e-4)
    off, _ = _metrize_road(None, HEIGHT)  # no pose: "up" unknown, no road pass
    assert off.stats["n_px_road"] == 0 and (off.depth_m[below] == 0).any()
    off2, _ = _metrize_road(T, float("nan"))  # no height: off
    assert off2.stats["n_px_road"] == 0
