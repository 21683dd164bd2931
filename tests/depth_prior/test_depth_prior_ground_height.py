"""The camera height measured from a metric depth map (mogs_node/depth_prior/ground_height.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.depth_prior.dense_prior import PriorHistory, compute_dense_prior
from mogs_node.depth_prior.flow_prior import FlowPriorParams
from mogs_node.depth_prior.ground_height import (
    MIN_VERIFIED,
    fit_ground_height,
    ground_height_m,
    refine_ground_height,
)
from mogs_node.depth_prior.road import RoadPriorParams
from mogs_node.errors import ConfigError
from mogs_node.geometry import pixel_to_normalized, road_plane_depth

W, H = 480, 180
K = np.array([[270.0, 0.0, 240.0], [0.0, 270.0, 60.0], [0.0, 0.0, 1.0]])


def _rays() -> np.ndarray:
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    return np.stack(pixel_to_normalized(K, u, v)).astype(np.float32)


def _up(pitch_deg: float) -> np.ndarray:
    """Camera frame x right, y down, z forward; up is -y, pitched about x."""
    a = np.radians(pitch_deg)
    return np.array([0.0, -np.cos(a), np.sin(a)])


def _scene(height_m: float, pitch_deg: float, box_drop_m: float | None = None):
    """Depth of a flat ground ``height_m`` below the camera, a wall far ahead above the horizon;
    optionally a box top ``box_drop_m`` below the camera over the lower-left quarter."""
    rays, up = _rays(), _up(pitch_deg)
    ground, _ = road_plane_depth(rays, up, height_m)
    depth = np.where(np.isfinite(ground) & (ground < 60), ground, 80.0).astype(np.float32)
    if box_drop_m is not None:
        top, _ = road_plane_depth(rays, up, box_drop_m)
        box = np.zeros((H, W), bool)
        box[H // 2 :, : W // 4] = True
        box &= np.isfinite(top) & (top < depth)
        depth[box] = top[box]
    return depth, rays, up


@settings(max_examples=60, deadline=None)
@given(
    height=st.floats(0.9, 3.3),
    pitch=st.floats(-5.0, 5.0),
    scale=st.sampled_from([1.0, 1e-2]),
)
def test_the_ground_height_is_found_at_any_pitch_and_small_unit(height, pitch, scale):
    depth, rays, up = _scene(height, pitch)
    # the range scales with the depth unit: the estimate is the same fraction of it
    fit = fit_ground_height(
        depth * scale, np.ones_like(depth), rays, up, (0.8 * scale, 3.5 * scale)
    )
    assert fit is not None and fit[0] == pytest.approx(height * scale, rel=0.02)


def test_ground_beyond_the_usable_depth_gives_no_measurement():
    """Depth is metric: a ground 1000x farther than a car's (kilometres) has too little parallax
    for flow depth to be of use (MAX_DEPTH_M), whatever the height range asked."""
    depth, rays, up = _scene(1.65, 0.0)
    fit = fit_ground_height(depth * 1e3, np.ones_like(depth), rays, up, (0.8e3, 3.5e3))
    assert fit is None


def test_a_box_top_closer_than_the_range_is_not_taken_for_the_ground():
    depth, rays, up = _scene(1.65, 0.0, box_drop_m=0.45)
    fit = fit_ground_height(depth, np.ones_like(depth), rays, up, (0.8, 3.5))
    assert fit is not None and fit[0] == pytest.approx(1.65, rel=0.01)


def test_no_ground_in_view_gives_no_measurement():
    depth = np.full((H, W), 5.0, np.float32)  # a wall facing the camera
    rays, up = _rays(), _up(0.0)
    depth[: H // 2] = 0.0
    assert fit_ground_height(depth, np.ones_like(depth), rays, up, (0.8, 3.5)) is None


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1.0, 0.0])
def test_non_finite_or_empty_depth_gives_no_measurement(bad):
    depth = np.full((H, W), bad, np.float32)
    rays, up = _rays(), _up(0.0)
    assert fit_ground_height(depth, np.ones_like(depth), rays, up, (0.8, 3.5)) is None


def test_low_confidence_depth_is_not_used():
    depth, rays, up = _scene(1.65, 0.0)
    assert fit_ground_height(depth, np.full_like(depth, 0.1), rays, up, (0.8, 3.5)) is None


def test_the_height_used_is_the_median_of_the_measurements():
    assert ground_height_m([]) == 0.0
    assert ground_height_m([1.6, float("nan"), 1.7, 9.0, -1.0]) == pytest.approx(1.7)


def test_an_empty_height_range_is_refused_by_name():
    with pytest.raises(ConfigError, match="auto_height_range_m"):
        RoadPriorParams(auto_height_range_m=(2.0, 1.0))


def test_the_dense_prior_measures_the_height_when_none_is_given():
    """Two keyframes 1 m apart over a textured ground: the flow depth gives the height, and the
    road prior is then built at it (no height typed anywhere)."""
    rng = np.random.default_rng(3)
    big = cv2_texture(rng)
    up = np.array([0.0, -1.0, 0.0])
    height = 1.7
    rays = _rays()
    ground, _ = road_plane_depth(rays, up, height)
    T_w_k = np.eye(4)
    T_w_r = np.eye(4)
    T_w_r[2, 3] = -1.0  # the reference 1 m behind
    img_k = _render_ground(big, ground, rays, np.eye(4))
    img_r = _render_ground(big, ground, rays, T_w_r)
    # world frame: camera frame rotated so that world z is up (camera -y)
    R_w_c = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    Tk, Tr = np.eye(4), np.eye(4)
    Tk[:3, :3] = R_w_c
    Tr[:3, :3] = R_w_c
    Tr[:3, 3] = R_w_c @ T_w_r[:3, 3]
    del T_w_k
    past, flow = (
        PriorHistory([(img_r, Tr)]),
        FlowPriorParams(camera_height_m=0.0, min_baseline_m=0.1),
    )
    prior = compute_dense_prior(
        img_k, K, Tk, past, flow_params=flow, road_params=RoadPriorParams(auto_height=True)
    )
    # the flow depth's band (~2 % high here) refined by the road plane's own tests
    assert prior.stats["ground_height_fit_m"] == pytest.approx(height, rel=0.015)
    assert prior.stats["ground_height_m"] == prior.stats["ground_height_fit_m"]
    given = compute_dense_prior(
        img_k, K, Tk, past, flow_params=flow, road_params=RoadPriorParams(auto_height=False)
    )
    assert "ground_height_m" not in given.stats
    assert prior.stats["share_road"] > given.stats["share_road"] == 0.0


def cv2_texture(rng: np.random.Generator) -> np.ndarray:
    """A ground texture, 1 px = 4 cm, smooth enough for DIS flow."""
    import cv2

    t = rng.uniform(0, 255, (1100, 2000)).astype(np.float32)
    t = cv2.GaussianBlur(t, (0, 0), 4.0)
    return (t - t.min()) / (t.max() - t.min()) * 255.0


def _render_ground(tex: np.ndarray, ground: np.ndarray, rays: np.ndarray, T_cam0_cam: np.ndarray):
    """Grey image of the textured ground seen from a camera displaced by ``T_cam0_cam`` (a pure
    translation along z; same height): sky (above the horizon) a flat grey."""
    import cv2

    dz = T_cam0_cam[2, 3]
    ok = np.isfinite(ground) & (ground < 40)
    x = rays[0] * np.where(ok, ground, 0.0)
    z = ground + dz  # ground point in camera-0 coordinates
    mx = np.where(ok, x * 25 + tex.shape[1] / 2, 0).astype(np.float32)
    my = np.where(ok, z * 25, 0).astype(np.float32)
    img = cv2.remap(tex, mx, my, cv2.INTER_LINEAR)
    return np.where(ok, img, 128).astype(np.uint8)


@pytest.mark.parametrize("truth", [1.52, 1.65, 1.79])
def test_the_refinement_finds_the_peak_of_the_verified_pixels_near_the_centre(truth):
    def verified(h: float) -> int:  # the road plane's tests peak at the true height
        return int(5000 * np.exp(-(((h - truth) / (0.03 * truth)) ** 2)))

    fit = refine_ground_height(1.65, verified)
    assert fit is not None and fit[0] == pytest.approx(truth, rel=0.012)


def test_the_refinement_gives_nothing_when_too_few_pixels_verify():
    assert refine_ground_height(1.65, lambda h: MIN_VERIFIED - 1) is None
    assert refine_ground_height(float("nan"), lambda h: 10**6) is None
    assert refine_ground_height(0.0, lambda h: 10**6) is None
