"""complete_planar_masks: an object's plane over its holes only where the plane is supported."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.metrizer.fill import PlaneSelect, colour_share_of, complete_planar_masks

H, W = 60, 80
K = np.array([[70.0, 0, 40.0], [0, 70.0, 30.0], [0, 0, 1]])


def plane_depth(n: np.ndarray, d: float) -> np.ndarray:
    """z-depth of the plane ``n . X = d`` (camera frame) at every pixel."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return (d / (rays @ n)).astype(np.float32)


@settings(max_examples=30, deadline=None)
@given(
    nx=st.floats(-0.5, 0.5),
    ny=st.floats(-0.5, 0.5),
    dist=st.floats(6.0, 40.0),
    hole_share=st.floats(0.05, 0.6),
)
def test_fills_holes_of_a_plane_exactly(nx: float, ny: float, dist: float, hole_share: float):
    n = np.array([nx, ny, 1.0])
    n /= np.linalg.norm(n)
    truth = plane_depth(n, dist)
    depth = truth.copy()
    hole = np.zeros((H, W), bool)
    hole[:, : int(hole_share * W)] = True  # a band: the plane is extrapolated into it
    depth[hole] = 0
    conf = np.where(hole, 0.0, 0.8).astype(np.float32)
    objects = np.zeros((H, W), np.int32)
    max_depth_m = 72.0
    n_filled = complete_planar_masks(
        depth, conf, objects, 1, extrapolation=10.0, max_depth_m=max_depth_m
    )
    # every hole pixel whose plane depth is within the fill's range gets it; beyond (a steep plane
    # towards its horizon) the hole stays empty
    fill = hole & (truth <= max_depth_m)
    assert n_filled == fill.sum()
    np.testing.assert_allclose(depth[fill], truth[fill], rtol=1e-4)
    assert np.all((conf[fill] > 0) & (conf[fill] <= 0.4 + 1e-6))
    assert np.all(depth[hole & ~fill] == 0)


def test_two_surfaces_in_one_mask_are_not_filled():
    """An under-segmented mask (a near wall and a far facade) has no plane: its hole stays."""
    depth = np.where(np.arange(W)[None, :] < W // 2, 8.0, 30.0) * np.ones((H, 1))
    depth = depth.astype(np.float32)
    depth[:20] = 0
    conf = (depth > 0).astype(np.float32)
    objects = np.zeros((H, W), np.int32)
    assert complete_planar_masks(depth, conf, objects, 1) == 0
    assert np.all(depth[:20] == 0)


def test_unsupported_near_and_other_objects_untouched():
    truth = plane_depth(np.array([0.0, 0.0, 1.0]), 10.0)
    objects = np.zeros((H, W), np.int32)
    objects[:, W // 2 :] = 1  # object 1: covered on 10% only
    depth = truth.copy()
    depth[:10, : W // 2] = 0  # object 0: a hole, well supported
    depth[6:, W // 2 :] = 0
    conf = (depth > 0).astype(np.float32)
    n = complete_planar_masks(depth, conf, objects, 2, min_share=0.3)
    assert n == 10 * (W // 2)
    assert np.all(depth[6:, W // 2 :] == 0)
    near = truth * 0.3  # 3 m: below min_depth_m
    near[:10] = 0
    assert complete_planar_masks(near, np.ones_like(near), np.zeros((H, W), np.int32), 1) == 0


def test_sky_and_empty_inputs():
    depth = np.full((H, W), 80.0, np.float32)  # all far: nothing to fit
    depth[:5] = 0
    assert complete_planar_masks(depth, np.ones_like(depth), np.zeros((H, W), np.int32), 1) == 0
    z = np.zeros((H, W), np.float32)
    assert complete_planar_masks(z, z.copy(), np.zeros((H, W), np.int32), 1) == 0


def pillar(weak_share: float, hole_share: float) -> tuple[np.ndarray, ...]:
    """A near fronto-parallel plane (a pillar 1.5 m ahead): confident prior on its left part,
    background depth (12 m, seen through it) at low confidence in the middle, a hole on the
    right. Returns the truth, depth, output confidence and prior confidence."""
    truth = plane_depth(np.array([0.1, 0.0, 1.0]) / np.linalg.norm([0.1, 0.0, 1.0]), 1.5)
    u = np.arange(W)[None, :] * np.ones((H, 1))
    weak = (u >= (1 - weak_share - hole_share) * W) & (u < (1 - hole_share) * W)
    hole = u >= (1 - hole_share) * W
    depth = np.where(weak, 12.0, truth).astype(np.float32)
    depth[hole] = 0
    prior_conf = np.where(weak, 0.03, 0.6).astype(np.float32)
    prior_conf[hole] = 0
    return truth, depth, prior_conf * 0.5, prior_conf


@settings(max_examples=30, deadline=None)
@given(weak_share=st.floats(0.05, 0.5), hole_share=st.floats(0.0, 0.3))
def test_confident_pixels_plane_replaces_weak_background(weak_share: float, hole_share: float):
    """``PlaneSelect``: the plane of the confident pixels replaces the weak (background) depth and
    fills the hole; without it (the default) a near object is left as it was."""
    truth, depth, conf, prior_conf = pillar(weak_share, hole_share)
    weak = (prior_conf > 0) & (prior_conf < 0.3)
    target = weak | (prior_conf == 0)
    before = depth.copy()
    objects = np.zeros((H, W), np.int32)
    sel = PlaneSelect(prior_conf, fit_min_conf=0.4, replace_below=0.3)
    kw = dict(min_depth_m=0.0, min_share=0.02, inlier_rel=0.03, extrapolation=10.0)
    n = complete_planar_masks(depth, conf, objects, 1, select=sel, **kw)
    assert n == target.sum()
    np.testing.assert_allclose(depth[target], truth[target], rtol=1e-4)
    np.testing.assert_array_equal(depth[~target], before[~target])  # confident pixels kept
    d0, c0 = before.copy(), conf.copy()
    complete_planar_masks(d0, c0, objects, 1, **kw)  # default: fitted to the background too
    assert np.all(d0[weak] == 12.0)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    fit_min=st.floats(0.0, 1.0),
    replace=st.floats(0.0, 1.0),
    scale=st.floats(1e-2, 1e3),
    gap=st.floats(0.0, 50.0),
)
def test_plane_select_output_is_finite_and_bounded(seed, fit_min, replace, scale, gap):
    """Any depths, confidences and thresholds: finite output, 0 or within its range, confident
    pixels never changed, confidences in [0, 1]."""
    rng = np.random.default_rng(seed)
    depth = (rng.uniform(0.0, 2.0, (H, W)) * scale).astype(np.float32)
    depth[rng.random((H, W)) < 0.3] = 0
    pc = rng.random((H, W)).astype(np.float32)
    conf = (pc * 0.5).astype(np.float32)
    objects = rng.integers(0, 4, (H, W)).astype(np.int32)
    before = depth.copy()
    max_depth = 1.5 * scale
    complete_planar_masks(
        depth,
        conf,
        objects,
        4,
        min_depth_m=0.0,
        max_depth_m=max_depth,
        min_share=0.0,
        select=PlaneSelect(pc, fit_min, replace, gap),
    )
    assert np.all(np.isfinite(depth)) and np.all(np.isfinite(conf))
    assert np.all((depth == 0) | ((depth > 0) & (depth <= max(max_depth, before.max()))))
    keep = (pc >= replace) & (before > 0)
    np.testing.assert_array_equal(depth[keep], before[keep])
    assert conf.min() >= 0 and conf.max() <= 1


def test_confident_plane_params_are_checked():
    from mogs_node.errors import ConfigError
    from mogs_node.metrizer.params import MetrizerParams

    with pytest.raises(ConfigError, match="confident_plane"):
        MetrizerParams(confident_plane_fit_conf=1.5)
    with pytest.raises(ConfigError, match="confident_plane"):
        MetrizerParams(confident_plane_replace_below=-0.1)


def test_max_gap_keeps_a_plane_off_the_far_part_of_an_under_segmented_object():
    """One object holding a background wall (confident, 10 m, top rows) and a near bonnet without
    depth below it: without a gap limit the wall's plane fills the bonnet; with ``max_gap_px``
    only the rows within reach of the wall's inliers get it."""
    truth = plane_depth(np.array([0.0, 0.0, 1.0]), 10.0)
    depth = truth.copy()
    depth[20:] = 0  # the bonnet: no prior
    prior_conf = np.where(depth > 0, 0.8, 0.0).astype(np.float32)
    objects = np.zeros((H, W), np.int32)
    kw = dict(min_depth_m=0.0, min_share=0.02, inlier_rel=0.03, extrapolation=10.0)
    d0 = depth.copy()
    complete_planar_masks(
        d0, prior_conf * 0.5, objects, 1, select=PlaneSelect(prior_conf, 0.4, 0.3), **kw
    )
    assert np.all(d0[20:] > 0)
    d1 = depth.copy()
    sel = PlaneSelect(prior_conf, 0.4, 0.3, max_gap_px=5.0)
    n = complete_planar_masks(d1, prior_conf * 0.5, objects, 1, select=sel, **kw)
    assert n == 5 * W  # rows 20-24: within 5 px of row 19
    assert np.all(d1[25:] == 0) and np.all(d1[20:25] > 0)


def _wall_over_bonnet(bonnet_rgb: tuple[int, int, int]):
    """One object: a confident wall 10 m away (rows 0-19, two colours) over a bonnet without
    depth (rows 20-59) of colour ``bonnet_rgb``."""
    truth = plane_depth(np.array([0.0, 0.0, 1.0]), 10.0)
    depth = truth.copy()
    depth[20:] = 0
    prior_conf = np.where(depth > 0, 0.8, 0.0).astype(np.float32)
    image = np.zeros((H, W, 3), np.uint8)
    image[:20, : W // 2] = (200, 200, 200)
    image[:20, W // 2 :] = (90, 90, 90)
    image[20:] = bonnet_rgb
    return depth, prior_conf, image


@pytest.mark.parametrize(
    ("bonnet_rgb", "filled_rows"), [((200, 30, 30), 5), ((90, 90, 90), 15), ((95, 88, 92), 15)]
)
def test_colour_gap_reaches_farther_only_over_the_inliers_colours(bonnet_rgb, filled_rows):
    """Beyond ``max_gap_px`` (5 px) and within ``colour_gap_px`` (15 px) only pixels of a colour
    the plane's inliers have get the plane: a red bonnet stays empty, a bonnet of the wall's grey
    (the same colour bin, not the same value) is filled up to the colour gap."""
    depth, prior_conf, image = _wall_over_bonnet(bonnet_rgb)
    objects = np.zeros((H, W), np.int32)
    sel = PlaneSelect(prior_conf, 0.4, 0.3, max_gap_px=5.0, colour_gap_px=15.0, image_rgb=image)
    kw = dict(min_depth_m=0.0, min_share=0.02, inlier_rel=0.03, extrapolation=10.0)
    n = complete_planar_masks(depth, prior_conf * 0.5, objects, 1, select=sel, **kw)
    assert n == filled_rows * W
    assert np.all(depth[20 : 20 + filled_rows] > 0) and np.all(depth[20 + filled_rows :] == 0)
    # without an image the colour gap is not used; a colour gap alone needs the colour everywhere
    depth2, _, _ = _wall_over_bonnet(bonnet_rgb)
    no_img = PlaneSelect(prior_conf, 0.4, 0.3, max_gap_px=5.0, colour_gap_px=15.0)
    assert complete_planar_masks(depth2, prior_conf * 0.5, objects, 1, select=no_img, **kw) == 5 * W
    depth3, _, _ = _wall_over_bonnet(bonnet_rgb)
    alone = PlaneSelect(prior_conf, 0.4, 0.3, colour_gap_px=15.0, image_rgb=image)
    n3 = complete_planar_masks(depth3, prior_conf * 0.5, objects, 1, select=alone, **kw)
    assert n3 == (15 * W if filled_rows == 15 else 0)


def test_colour_share_of_exact():
    """Shares of the reference pixels per object in the query pixel's colour bin."""
    image = np.zeros((1, 6, 3), np.uint8)
    image[0] = [(0, 0, 0), (10, 10, 10), (250, 0, 0), (0, 0, 0), (255, 0, 0), (0, 0, 0)]
    ref = (np.array([0, 1, 2, 3]), np.array([0, 0, 0, 1]))  # object 0: 2 black, 1 red
    query = (np.array([4, 5, 5, 2]), np.array([0, 0, 1, 2]))
    share = colour_share_of(image, ref, query, 3)
    np.testing.assert_allclose(share, [1 / 3, 2 / 3, 1.0, 0.0])


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    n_ref=st.integers(0, 300),
    n_objects=st.integers(1, 6),
    flat=st.booleans(),
)
def test_colour_share_of_is_a_distribution(seed, n_ref, n_objects, flat):
    """Any image (random or one flat colour), any references: shares in [0, 1]; querying every
    reference pixel's own bin gives each object's shares summing to 1 over its distinct bins;
    an object without references has share 0."""
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (7, 9, 3)).astype(np.uint8)
    if flat:
        image[:] = image[0, 0]
    idx = rng.integers(0, 63, n_ref)
    obj = rng.integers(0, n_objects, n_ref)
    share = colour_share_of(image, (idx, obj), (idx, obj), n_objects + 1)
    assert np.all((share >= 0) & (share <= 1))
    if n_ref:
        assert np.all(share > 0)
        q = (image.reshape(-1, 3).astype(int) * 6) // 256
        bins = (q[:, 0] * 6 + q[:, 1]) * 6 + q[:, 2]
        for g in np.unique(obj):
            m = obj == g
            _, first = np.unique(bins[idx[m]], return_index=True)
            assert share[m][first].sum() == pytest.approx(1.0)
    empty = colour_share_of(image, (idx, obj), (np.arange(5), np.full(5, n_objects)), n_objects + 1)
    assert not empty.any()


def test_plane_gap_params_are_checked():
    from mogs_node.errors import ConfigError
    from mogs_node.metrizer.params import MetrizerParams

    for bad in (
        {"confident_plane_colour_gap": -0.1},
        {"mask_plane_max_gap": float("inf")},
        {"mask_plane_colour_gap": float("nan")},
        {"confident_plane_colour_share": 0.0},
        {"confident_plane_colour_share": 1.5},
    ):
        with pytest.raises(ConfigError, match="colour"):
            MetrizerParams(**bad)


def _beam_over_facade():
    """One object of one colour spanning a depth jump: a facade 10 m away measured by the prior
    (rows 30-59), the metrizer's own fill near a few points on it (rows 15-29, the facade's
    depth: correct but not measured) and a near beam without any depth (rows 0-14, 1.4 m in
    truth)."""
    truth = plane_depth(np.array([0.0, 0.0, 1.0]), 10.0)
    depth = truth.copy()
    depth[:15] = 0
    measured = np.zeros((H, W), bool)
    measured[30:] = True
    conf = np.where(measured, 0.8, np.where(depth > 0, 0.1, 0.0)).astype(np.float32)
    image = np.full((H, W, 3), 120, np.uint8)  # the beam has the facade's grey
    sel = dict(colour_gap_px=15.0, image_rgb=image)
    kw = dict(min_depth_m=0.0, extrapolation=10.0)
    return depth, conf, measured, sel, kw


def test_support_keeps_a_plane_off_a_depth_jump_its_measurements_do_not_reach():
    """The beam is within the colour reach of the point fill but not of the measured facade:
    fitted to every depth pixel the plane covers the beam at the facade's 10 m; with the support
    restricted to the measured pixels it stays empty, and the measured plane is unchanged."""
    objects = np.zeros((H, W), np.int32)
    depth, conf, measured, sel, kw = _beam_over_facade()
    n_all = complete_planar_masks(depth, conf, objects, 1, select=PlaneSelect(**sel), **kw)
    assert n_all == 15 * W  # rows 0-14: within 15 px of the fill's inliers (rows 15-29)
    np.testing.assert_allclose(depth[:15], 10.0, rtol=1e-4)
    depth, conf, measured, sel, kw = _beam_over_facade()
    before = depth.copy()
    sel_m = PlaneSelect(support=measured, **sel)
    assert complete_planar_masks(depth, conf, objects, 1, select=sel_m, **kw) == 0
    np.testing.assert_array_equal(depth, before)
    # the share test counts the support only: 50 % measured passes 0.3, not 0.6
    depth, conf, measured, sel, kw = _beam_over_facade()
    kw_share = dict(kw, min_share=0.6)
    assert complete_planar_masks(depth, conf, objects, 1, select=PlaneSelect(**sel), **kw_share)
    depth, conf, measured, sel, kw = _beam_over_facade()
    assert complete_planar_masks(depth, conf, objects, 1, select=sel_m, **kw_share) == 0


def test_support_of_the_wrong_shape_is_one_clear_error():
    from mogs_node.errors import MogsError

    depth, conf, measured, sel, kw = _beam_over_facade()
    with pytest.raises(MogsError, match="support"):
        complete_planar_masks(
            depth, conf, np.zeros((H, W), np.int32), 1, select=PlaneSelect(support=measured[1:])
        )


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    support_share=st.floats(0.0, 1.0),
    scale=st.sampled_from([1e-3, 1.0, 1e3]),
    colour=st.booleans(),
)
def test_support_subset_fills_a_subset_of_the_holes(seed, support_share, scale, colour):
    """Any support: only holes get a depth, finite and positive; the full support is the same as
    none and an empty one fills nothing; a depth field with NaN / inf is tolerated."""
    rng = np.random.default_rng(seed)
    objects = rng.integers(0, 3, (H, W)).astype(np.int32)
    truth = plane_depth(np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0]), 10.0)
    depth0 = (truth * scale).astype(np.float32)
    depth0[rng.random((H, W)) < 0.4] = 0
    depth0[0, 0], depth0[0, 1] = np.nan, np.inf
    conf0 = np.where(depth0 > 0, 0.8, 0.0).astype(np.float32)
    support = rng.random((H, W)) < support_share
    img = rng.integers(0, 256, (H, W, 3)).astype(np.uint8) if colour else None
    sel = dict(colour_gap_px=10.0, image_rgb=img)
    kw = dict(min_depth_m=0.0, max_depth_m=72.0 * scale, min_share=0.1)
    outs = []
    for sup in (support, None, np.ones((H, W), bool), np.zeros((H, W), bool)):
        d, c = depth0.copy(), conf0.copy()
        n = complete_planar_masks(d, c, objects, 3, select=PlaneSelect(support=sup, **sel), **kw)
        changed = ~((d == depth0) | (np.isnan(d) & np.isnan(depth0)))
        assert n == changed.sum() and np.all(depth0[changed] == 0)
        assert np.all(np.isfinite(d[changed]) & (d[changed] > 0)) and np.all(c[changed] >= 0)
        outs.append(d)
    np.testing.assert_array_equal(outs[1], outs[2])
    assert np.array_equal(outs[3], depth0, equal_nan=True)


def test_mask_plane_support_is_checked():
    from mogs_node.errors import ConfigError
    from mogs_node.metrizer.params import MASK_PLANE_SUPPORTS, MetrizerParams

    for name in MASK_PLANE_SUPPORTS:
        assert MetrizerParams(mask_plane_support=name).mask_plane_support == name
    with pytest.raises(ConfigError, match="mask_plane_support"):
        MetrizerParams(mask_plane_support="measures")


def test_mask_plane_support_leaves_out_the_point_fills_no_plane_replaced():
    """compose's support of the whole-mask pass: the prior's pixels ("measured"), or every pixel
    but fill_holes' that still hold their fill ("no_point_fills"; one a plane pass replaced holds
    that plane's depth and is support again), or None ("all")."""
    from mogs_node.metrizer.compose import _mask_plane_support
    from mogs_node.metrizer.params import MetrizerParams

    has_prior = np.array([True, True, False, False, False, False])
    depth = np.array([5.0, 6.0, 9.0, 9.5, 0.0, 7.0], np.float32)
    point_fills = np.array([2, 3, 5])
    point_fill_m = np.array([9.0, 9.5, 6.0], np.float32)  # pixel 5: replaced 6 -> 7 since

    def support(name):
        return _mask_plane_support(
            MetrizerParams(mask_plane_support=name), has_prior, point_fills, point_fill_m, depth
        )

    assert support("all") is None
    np.testing.assert_array_equal(support("measured"), has_prior)
    np.testing.assert_array_equal(support("no_point_fills"), [1, 1, 0, 0, 1, 1])
