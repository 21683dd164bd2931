"""Depth edges of a blurred prior snapped to their object (``MetrizerParams.edge_snap``)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_metrizer_robustness import _absrel, _case, _check_valid

from mogs_node.errors import ConfigError
from mogs_node.metrizer.edge_snap import near_object_boundary, prior_edge_band, snap_edges
from mogs_node.metrizer.pipeline import MetrizerParams, metrize_depth


def test_edge_band_around_a_step_only():
    x = np.full((6, 12), 0.5, np.float32)
    x[:, 6:] = 0.1  # a step in inverse depth between columns 5 and 6
    band = prior_edge_band(x, np.ones_like(x), rel=0.1, radius=0)
    assert set(np.flatnonzero(band.any(axis=0))) == {5, 6}
    band = prior_edge_band(x, np.ones_like(x), rel=0.1, radius=1)
    assert set(np.flatnonzero(band.any(axis=0))) == {4, 5, 6, 7}
    assert not prior_edge_band(np.full((6, 12), 0.3), np.ones((6, 12)), 0.1, 1).any()
    # no prior (confidence 0) and non-finite values: no edge of their own inside
    x[:, :3] = np.nan
    band = prior_edge_band(x, np.where(np.arange(12) < 3, 0.0, 1.0)[None].repeat(6, 0), 0.1, 0)
    assert not band[:, :2].any()


def test_object_boundary_band():
    obj = np.zeros((5, 9), np.int32)
    obj[:, 5:] = 1
    assert set(np.flatnonzero(near_object_boundary(obj, 0).any(axis=0))) == {4, 5}
    assert set(np.flatnonzero(near_object_boundary(obj, 2).any(axis=0))) == {2, 3, 4, 5, 6, 7}
    assert not near_object_boundary(np.zeros((5, 9), np.int32), 3).any()


def test_snap_gives_band_pixels_their_objects_interior_depth():
    H, W = 4, 10
    obj = np.zeros((H, W), np.int32)
    obj[:, 5:] = 1
    depth = np.tile(np.array([2, 2, 2, 3, 5, 7, 9, 10, 10, 10], np.float32), (H, 1))
    conf = np.tile(np.linspace(0.1, 1.0, W, dtype=np.float32), (H, 1))
    band = np.zeros((H, W), bool)
    band[:, 3:7] = True
    depth[0, 4] = 0.0  # no depth: stays without
    n = snap_edges(depth, conf, obj, band)
    assert n == 4 * 4 - 1
    assert np.all(depth[:, 3] == 2) and np.all(depth[1:, 4] == 2) and depth[0, 4] == 0
    assert np.all(depth[:, 5:7] == 10)
    assert np.allclose(conf[:, 3], conf[0, 2]) and np.allclose(conf[:, 6], conf[0, 7])


def test_snap_keeps_pixels_whose_nearest_interior_is_another_object():
    obj = np.zeros((3, 8), np.int32)
    obj[:, 4:] = 1
    depth = np.arange(24, dtype=np.float32).reshape(3, 8) + 1
    before = depth.copy()
    band = np.zeros((3, 8), bool)
    band[:, 2:4] = True  # object 0's band: its nearest interior pixel is column 1 (object 0)
    band[:, 4] = True  # object 1's: column 5
    snap_edges(depth, np.ones_like(depth), obj, band)
    assert np.all(depth[:, 2:4] == before[:, 1:2]) and np.all(depth[:, 4] == before[:, 5])
    # a single object 1 pixel inside object 0's band whose nearest interior is object 0's
    obj[1, 2] = 1
    depth = before.copy()
    snap_edges(depth, np.ones_like(depth), obj, band)
    assert depth[1, 2] == before[1, 2]
    # no band, or nothing but band: nothing changes
    for b in (np.zeros_like(band), np.ones_like(band)):
        depth = before.copy()
        assert snap_edges(depth, np.ones_like(depth), obj, b) == 0
        assert np.array_equal(depth, before)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    band_share=st.sampled_from([0.0, 0.1, 0.5, 0.9, 1.0]),
    n_obj=st.integers(1, 6),
    log_scale=st.floats(-2.0, 3.0),
)
def test_snap_only_copies_values_of_the_same_object(seed, band_share, n_obj, log_scale):
    rng = np.random.default_rng(seed)
    H, W = 9, 13
    obj = rng.integers(0, n_obj, (H, W)).astype(np.int32)
    depth = (rng.uniform(0.5, 2.0, (H, W)) * 10.0**log_scale).astype(np.float32)
    depth[rng.random((H, W)) < 0.1] = 0.0
    conf = rng.random((H, W)).astype(np.float32)
    band = rng.random((H, W)) < band_share
    d0 = depth.copy()
    n = snap_edges(depth, conf, obj, band)
    assert np.all(np.isfinite(depth)) and np.array_equal(depth[~band], d0[~band])
    changed = depth != d0
    assert changed.sum() <= n <= band.sum()
    assert np.all(d0[changed] > 0)  # pixels without depth stay without
    for v, u in zip(*np.nonzero(changed), strict=True):
        same = (obj == obj[v, u]) & ~band & (d0 == depth[v, u])
        assert same.any()


def test_edge_snap_lowers_the_error_of_a_blurred_prior_on_sim_frames():
    """Simulated LFM (2-px blur at depth edges), oracle and graph masks, 40 and 600 ground-truth
    points: the metrizer with edge_snap is closer to the truth on every frame; off by default."""
    assert MetrizerParams().edge_snap is False
    for frame, masks, n in itertools.product(range(3), ("oracle", "graph"), (40, 600)):
        kw, params, gt = _case(frame, n, 1.0, 0.0, 1.0, masks, 1)
        off = metrize_depth(**kw, params=params)
        p_on = MetrizerParams(d_min_m=params.d_min_m, d_max_m=params.d_max_m, edge_snap=True)
        on = metrize_depth(**kw, params=p_on)
        _check_valid(on, params.d_max_m)
        assert on.stats["n_px_edge_snap"] > 0
        m = (gt > 0) & (off.depth_m > 0) & (on.depth_m > 0)
        assert _absrel(on.depth_m, gt, m) < _absrel(off.depth_m, gt, m)


def test_edge_snap_params_are_checked():
    with pytest.raises(ConfigError, match="edge_snap"):
        MetrizerParams(edge_snap_rel=0.0)
    with pytest.raises(ConfigError, match="edge_snap"):
        MetrizerParams(edge_snap_radius=-1)
