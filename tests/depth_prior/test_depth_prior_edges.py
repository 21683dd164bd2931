"""The dense prior's depth-edge error term (``FusionParams.edge_window_px``, issue 16)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.depth_prior.dense_prior import (
    FusionParams,
    PriorHistory,
    compute_dense_prior,
    depth_edge_range,
)
from mogs_node.depth_prior.flow_prior import FlowPriorParams
from mogs_node.depth_prior.road import RoadPriorParams
from mogs_node.depth_prior.sequence import PriorSequence
from mogs_node.errors import ConfigError
from mogs_node.geometry import make_T, so3_exp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _two_view_scene import CAM, render  # noqa: E402

ROAD = RoadPriorParams(up_world=(0.0, -1.0, 0.0))  # the test scene's world: y down
FLOW = FlowPriorParams(far_baseline_m=0.0)
K = CAM.K
EDGE = FusionParams(edge_window_px=5, edge_gain=0.5, edge_far_only=False)
OFF = FusionParams(edge_window_px=0)


@pytest.fixture(scope="module")
def views():
    """The two-view scene: (grey, depth, pose) at the origin and 0.8 m ahead, slightly turned."""
    poses = [np.eye(4), make_T(so3_exp(np.array([0.0, 0.01, 0.0])), np.array([0.05, 0.0, 0.8]))]
    return tuple((*render(T), T) for T in poses)


def test_depth_edge_range_exact_cases() -> None:
    d = np.full((7, 12), 2.0, np.float32)
    d[:, 6:] = 8.0
    r = depth_edge_range(d, 5)
    # within 2 columns of the step the window holds both depths: log(8 / 2)
    np.testing.assert_allclose(r[:, 4:8], np.log(4.0), rtol=1e-5)
    assert np.all(r[:, :4] == 0) and np.all(r[:, 8:] == 0)
    d[3, 1] = 0.0  # no depth: no range, and it does not count for its neighbours
    d[0, 0] = np.nan
    r = depth_edge_range(d, 5)
    assert r[3, 1] == 0 and r[0, 0] == 0 and np.all(r[:, :4] == 0)
    lone = np.zeros((5, 5), np.float32)
    lone[2, 2] = 3.0
    assert not depth_edge_range(lone, 5).any()  # a pixel alone in its window: no jump
    assert not depth_edge_range(d, 1).any()  # a 1-pixel window sees no neighbour


def test_depth_edge_range_far_side_only() -> None:
    """``far_only``: how far a pixel lies behind its window's nearest depth; the near side of
    a jump and a flat surface get 0."""
    d = np.full((7, 12), 2.0, np.float32)
    d[:, 6:] = 8.0
    r = depth_edge_range(d, 5, far_only=True)
    np.testing.assert_allclose(r[:, 6:8], np.log(4.0), rtol=1e-5)
    assert not r[:, :6].any() and not r[:, 8:].any()
    both = depth_edge_range(d, 5)
    assert np.all(r <= both + 1e-7)


@settings(max_examples=50, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    scale=st.floats(1e-2, 1e3),
    window=st.integers(0, 9),
    bad=st.sampled_from([np.nan, np.inf, -1.0, 0.0]),
)
def test_depth_edge_range_is_sane_and_scale_free(
    seed: int, scale: float, window: int, bad: float
) -> None:
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.5, 3.0, (9, 11)).astype(np.float32)
    d[rng.random(d.shape) < 0.3] = bad
    r = depth_edge_range(d, window)
    assert r.shape == d.shape and np.all(np.isfinite(r)) and r.min() >= 0
    ok = np.isfinite(d) & (d > 0)
    assert not r[~ok].any()
    assert np.all(r <= np.log(3.0 / 0.5) + 1e-5)  # never more than the depths' own range
    np.testing.assert_allclose(depth_edge_range(d * np.float32(scale), window), r, atol=1e-4)


def test_edge_term_lowers_confidence_only_near_depth_jumps(views) -> None:
    """Same depth; the confidence is lowered where the depth jumps within the window, kept
    elsewhere; the pixels it marks down are the ones with the larger error."""
    (g0, _, T0), (g1, d1, T1) = views
    past = PriorHistory([(g0, T0)])
    plain = compute_dense_prior(g1, K, T1, past, flow_params=FLOW, road_params=ROAD, params=OFF)
    edged = compute_dense_prior(g1, K, T1, past, flow_params=FLOW, road_params=ROAD, params=EDGE)
    np.testing.assert_array_equal(edged.depth_m, plain.depth_m)
    assert np.all(edged.confidence <= plain.confidence + 1e-7)
    jump = depth_edge_range(plain.depth_m, 5)
    flat = (plain.confidence > 0) & (jump == 0)
    np.testing.assert_allclose(edged.confidence[flat], plain.confidence[flat], rtol=1e-5)
    lowered = edged.confidence < plain.confidence * 0.9
    m = plain.confidence > 0
    assert lowered[m].mean() > 0.01
    rel = np.abs(plain.depth_m - d1) / np.where(d1 > 0, d1, 1.0)
    assert rel[lowered & m].mean() > rel[m & ~lowered].mean()
    assert edged.carry_confidence is None  # edge_carried: the carried prior keeps the term


def test_edge_term_not_carried_leaves_the_carried_confidence(views) -> None:
    """``edge_carried: false``: the next keyframe carries the confidence without this
    keyframe's edge term (it applies its own); the published confidence has it."""
    (g0, _, T0), (g1, _, T1) = views
    params = FusionParams(edge_window_px=5, edge_carried=False)
    past = PriorHistory([(g0, T0)])
    plain = compute_dense_prior(g1, K, T1, past, flow_params=FLOW, road_params=ROAD, params=OFF)
    edged = compute_dense_prior(g1, K, T1, past, flow_params=FLOW, road_params=ROAD, params=params)
    np.testing.assert_allclose(edged.carry_confidence, plain.confidence, rtol=1e-5, atol=1e-7)
    assert (edged.confidence < edged.carry_confidence).any()
    seq = PriorSequence(FLOW, ROAD, params)
    seq.remember(0, g0, K, T0)
    prior, _ = seq.next(1, g1, K, T1)
    np.testing.assert_array_equal(seq.history[-1].prior[1], prior.carry_confidence)
    seq = PriorSequence(FLOW, ROAD, EDGE)
    seq.remember(0, g0, K, T0)
    prior, _ = seq.next(1, g1, K, T1)
    np.testing.assert_array_equal(seq.history[-1].prior[1], prior.confidence)


def test_bad_edge_params() -> None:
    for bad in ({"edge_window_px": -1}, {"edge_gain": -0.1}, {"edge_free": -1.0}):
        with pytest.raises(ConfigError, match="edge"):
            FusionParams(**bad)
