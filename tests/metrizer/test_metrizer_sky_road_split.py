"""The sky pins the global shift (``sky_anchor``), the road plane over a prior's road
(``road_snap_rel``) and masks split at the prior's depth jumps (``mask_split``)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import test_metrizer_ground as tg
from hypothesis import given, settings
from hypothesis import strategies as st
from test_metrizer_robustness import _absrel, _case, _check_valid, _metrize_within_baseline

from mogs_node.errors import ConfigError
from mogs_node.metrizer.alignment import fit_global_affine
from mogs_node.metrizer.ground import GroundParams, snap_road_objects
from mogs_node.metrizer.mask_split import jump_band, split_masks
from mogs_node.metrizer.pipeline import MetrizerParams, metrize_depth

INV = "relative_inverse_depth"


# ---- the sky pins the shift


def test_zero_at_pins_the_shift_that_near_features_leave_loose():
    """Features over a narrow near range with a little noise leave the shift loose; the sky's
    prior value at inverse depth 0 fixes it: far depths come out right."""
    rng = np.random.default_rng(0)
    s, t = 3.0, 0.02  # prior x = s q + t, sky (q = 0) at x = t
    z = rng.uniform(4.0, 6.0, 40)
    x = s / z * (1 + 0.02 * rng.standard_normal(40)) + t
    free, _ = fit_global_affine(x, 1.0 / z, np.ones(40), INV)
    pinned, n = fit_global_affine(x, 1.0 / z, np.ones(40), INV, zero_at=(t, 2.0))
    assert n == 40
    assert abs(pinned[0] * t + pinned[1]) < 0.2 * abs(free[0] * t + free[1])
    x_far = s / 60.0 + t  # a pixel 60 m away
    z_free = 1.0 / (free[0] * x_far + free[1])
    z_pinned = 1.0 / (pinned[0] * x_far + pinned[1])
    assert abs(z_pinned / 60.0 - 1) < abs(z_free / 60.0 - 1)
    assert abs(z_pinned / 60.0 - 1) < 0.1


def test_sky_anchor_on_sim_frames_is_off_by_default_and_not_worse():
    """Simulated LFM (unknown shift per frame), oracle and graph masks, 40 and 600 points: with
    the sky pinning the shift the mean error is lower and no frame is more than 1 % worse."""
    assert MetrizerParams().sky_anchor == 0.0
    off_all, on_all = [], []
    for frame, masks, n in itertools.product(range(3), ("oracle", "graph"), (40, 600)):
        kw, params, gt = _case(frame, n, 1.0, 0.0, 1.0, masks, 1)
        off = metrize_depth(**kw, params=params)
        p_on = MetrizerParams(d_min_m=params.d_min_m, d_max_m=params.d_max_m, sky_anchor=5.0)
        on = metrize_depth(**kw, params=p_on)
        _check_valid(on, params.d_max_m)
        assert "sky_prior" in on.stats and "sky_prior" not in off.stats
        m = (gt > 0) & (off.depth_m > 0) & (on.depth_m > 0)
        off_all.append(_absrel(off.depth_m, gt, m))
        on_all.append(_absrel(on.depth_m, gt, m))
        assert on_all[-1] <= 1.01 * off_all[-1]
    assert np.mean(on_all) < np.mean(off_all)


def test_sky_anchor_needs_a_relative_inverse_depth_prior():
    kw, params, _ = _case(0, 200, 1.0, 0.0, 1.0, "oracle", 1)
    depth = 1.0 / np.maximum(kw["prior"], 1e-3)
    kw = {**kw, "prior": depth, "prior_kind": "relative_depth"}
    on = metrize_depth(**kw, params=MetrizerParams(d_max_m=params.d_max_m, sky_anchor=2.0))
    off = metrize_depth(**kw, params=MetrizerParams(d_max_m=params.d_max_m))
    assert "sky_prior" not in on.stats
    assert np.array_equal(on.depth_m, off.depth_m)


# ---- the road plane over a prior's road

K = np.array([[100.0, 0, 32], [0, 100.0, -2], [0, 0, 1]])  # horizon above the image
UP = np.array([0.0, -1.0, 0.0])


def test_road_snap_sets_agreeing_road_pixels_to_the_plane_only():
    H, W = 24, 64
    z_road = tg.road_plane_depth(K, (H, W), UP, 1.5).ravel()
    obj = np.zeros(H * W, np.intp)
    obj[(np.arange(H * W) % W) >= 48] = 1  # object 1: a wall at 6 m, right of column 48
    rng = np.random.default_rng(1)
    depth = np.where(np.isfinite(z_road), z_road * rng.uniform(0.9, 1.1, H * W), 6.0)
    depth = depth.astype(np.float32)
    depth[obj == 1] = 6.0
    before = depth.copy()
    gp = GroundParams(max_depth_m=40.0)  # rows 0-1 (75 m, 50 m): no depth from the plane
    n = snap_road_objects(depth, obj, 2, z_road.astype(np.float32), gp, 0.15)
    road = (obj == 0) & (z_road <= 40.0)
    assert n == int(road.sum())
    assert np.allclose(depth[road], z_road[road])
    assert np.array_equal(depth[obj == 1], before[obj == 1])  # the wall is not road
    assert np.array_equal(depth[(obj == 0) & ~road], before[(obj == 0) & ~road])  # beyond 40 m
    # too tight an agreement: not a road object, nothing changes
    depth = before.copy()
    assert snap_road_objects(depth, obj, 2, z_road.astype(np.float32), gp, 0.01) == 0
    assert np.array_equal(depth, before)


# ---- masks split at the prior's depth jumps


def _pole_scene(H: int = 30, W: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Inverse depth of a slanted road (affine in v) with a pole (q = 0.5, 10 px wide) in front:
    one mask. (A pole as thin as the band has no piece of its own: it stays with its mask.)"""
    v = np.arange(H, dtype=np.float32)[:, None]
    q = np.repeat(0.02 + 0.01 * v, W, axis=1)  # a plane: inverse depth affine in the pixels
    q[:, 16:26] = 0.5
    return q, np.zeros((H, W), np.int32)


def test_jump_band_ignores_a_slanted_plane_and_finds_a_step():
    q, _ = _pole_scene()
    ones = np.ones_like(q)
    band = jump_band(q, ones, INV, rel=0.1, radius=0)
    cols = set(np.flatnonzero(band[5:-5].any(axis=0)))
    assert cols and cols <= set(range(12, 30))
    plane = np.repeat(0.02 + 0.01 * np.arange(30, dtype=np.float32)[:, None], 40, axis=1)
    assert not jump_band(plane, ones, INV, 0.1, 2).any()
    # the same scene as a depth prior: the same jumps
    assert np.array_equal(jump_band(1.0 / q, ones, "relative_depth", 0.1, 0), band)


def test_split_separates_the_pole_from_the_road_behind_it():
    q, labels = _pole_scene()
    labels[:, 36:] = 1  # a second mask, untouched by any jump
    labels[0, :] = -1  # no mask: kept
    out = split_masks(labels, jump_band(q, np.ones_like(q), INV, 0.1, 1), 10, 6)
    assert np.array_equal(out < 0, labels < 0)
    pole = out[1:, 19:23]
    assert len(np.unique(pole)) == 1
    left, right = out[1:, :12], out[1:, 30:36]
    assert len(np.unique(left)) == 1 and len(np.unique(right)) == 1
    assert pole[0, 0] not in (left[0, 0], right[0, 0])
    assert len(np.unique(out[:, 36:][labels[:, 36:] >= 0])) == 1
    # without prior (confidence 0) nothing is split
    same = split_masks(labels, jump_band(q, np.zeros_like(q), INV, 0.1, 1), 10, 6)
    assert np.array_equal(same, labels)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    n_masks=st.integers(1, 5),
    unmasked=st.sampled_from([0.0, 0.2, 1.0]),
    log_scale=st.floats(-2.0, 3.0),
    min_px=st.sampled_from([1, 5, 50]),
)
def test_split_pieces_lie_in_one_mask_and_cover_it(seed, n_masks, unmasked, log_scale, min_px):
    rng = np.random.default_rng(seed)
    H, W = 16, 21
    labels = rng.integers(0, n_masks, (H // 4, W // 3)).repeat(4, 0).repeat(3, 1).astype(np.int32)
    labels[rng.random((H, W)) < unmasked] = -1
    prior = rng.uniform(0.1, 2.0, (H // 2, W // 3)).repeat(2, 0).repeat(3, 1) * 10.0**log_scale
    conf = (rng.random((H, W)) < 0.9).astype(np.float32)
    out = split_masks(labels, jump_band(prior, conf, INV, 0.1, 1), min_px, 6)
    assert out.dtype == np.int32 and out.shape == labels.shape
    assert np.array_equal(out < 0, labels < 0)
    ids = np.unique(out[out >= 0])
    assert np.array_equal(ids, np.arange(len(ids)))  # compact
    for k in ids:
        assert len(np.unique(labels[out == k])) == 1  # a piece never crosses a mask border
    assert len(ids) >= len(np.unique(labels[labels >= 0]))


def test_mask_split_in_the_metrizer_is_off_by_default_and_valid():
    assert MetrizerParams().mask_split is False
    for masks in ("oracle", "graph"):
        kw, params, gt = _case(1, 300, 1.0, 0.0, 1.0, masks, 2)
        p_on = MetrizerParams(d_min_m=params.d_min_m, d_max_m=params.d_max_m, mask_split=True)
        on = metrize_depth(**kw, params=p_on)
        off = metrize_depth(**kw, params=params)
        _check_valid(on, params.d_max_m)
        assert on.stats["n_masks"] > off.stats["n_masks"]
        m = (gt > 0) & (on.depth_m > 0) & (off.depth_m > 0)
        assert _absrel(on.depth_m, gt, m) < 1.1 * _absrel(off.depth_m, gt, m)


def test_new_params_are_checked():
    with pytest.raises(ConfigError, match="sky_anchor"):
        MetrizerParams(sky_anchor=-1.0)
    with pytest.raises(ConfigError, match="road_snap_rel"):
        MetrizerParams(road_snap_rel=1.0)
    with pytest.raises(ConfigError, match="mask_split"):
        MetrizerParams(mask_split_rel=0.0)
    with pytest.raises(ConfigError, match="mask_split"):
        MetrizerParams(mask_split_min_frac=1.0)


def test_metrize_snaps_a_warped_road_prior_to_the_plane():
    """A metric prior of the road with a smooth 10 % warp: with ``road_snap_rel`` the road's
    output is the plane (camera height and pose known), without it the warp stays."""
    H, W, K_ROAD, HEIGHT = tg.H, tg.W, tg.K, tg.HEIGHT
    z_road = tg.road_plane_depth(K_ROAD, (H, W), tg.UP, HEIGHT)
    below = np.isfinite(z_road) & (z_road <= 40.0)
    u = np.arange(W)[None, :]
    warp = 1.0 + 0.1 * np.sin(2 * np.pi * u / W)
    prior = np.where(np.isfinite(z_road), z_road * warp, 0.0).astype(np.float32)
    T = np.eye(4)
    T[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]
    kw = tg.road_inputs(np.where(np.isfinite(z_road), 0, 1).astype(np.int32), prior, T)
    base = dict(road_camera_height_m=HEIGHT, d_max_m=1e3, mask_plane_fill=False)
    on = metrize_depth(**kw, params=MetrizerParams(**base, road_snap_rel=0.25))
    off = metrize_depth(**kw, params=MetrizerParams(**base))
    assert np.isfinite(on.depth_m).all() and (on.depth_m >= 0).all()
    np.testing.assert_allclose(on.depth_m[below], z_road[below], rtol=1e-4)
    assert on.stats["n_px_road"] >= below.sum() and off.stats["n_px_road"] == 0
    assert np.abs(off.depth_m[below] / z_road[below] - 1).max() > 0.05


@settings(max_examples=20, deadline=None)
@given(
    frame=st.integers(0, 2),
    n_points=st.sampled_from([0, 2, 5, 40, 600, 2000]),
    coverage=st.sampled_from([0.0, 0.2, 0.9, 1.0]),
    outliers=st.floats(0.0, 0.3),
    log_scale=st.floats(-2.0, 3.0),
    masks=st.sampled_from(["oracle", "graph"]),
    seed=st.integers(0, 2**16),
)
def test_sky_anchor_and_split_keep_the_bound_of_the_global_affine(
    frame, n_points, coverage, outliers, log_scale, masks, seed
):
    """The stress test of test_metrizer_robustness with ``sky_anchor`` and ``mask_split`` on:
    finite output, never more than 10 % worse than the global affine of the same parameters."""
    kw, params, gt = _case(frame, n_points, coverage, outliers, 10.0**log_scale, masks, seed)
    p = MetrizerParams(
        d_min_m=params.d_min_m, d_max_m=params.d_max_m, sky_anchor=5.0, mask_split=True
    )
    _metrize_within_baseline(kw, p, gt)
