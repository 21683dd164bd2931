"""Dense metric anchors (issue 16): a metric depth map beside a relative prior as extra points.

Unit tests of :func:`~mogs_node.metrizer.dense_anchors.anchor_points` against exact expectations,
the metrizer with anchors against ground truth on sim frames (the simulated LFM as prior), the
edges by hypothesis (no anchor, every pixel an anchor, NaN / inf, scales 1e-2..1e3), and the
node's optional anchor input.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_metrizer_robustness import H, W, _absrel, _case, _check_valid

from mogs_node import msgs
from mogs_node.errors import ConfigError, ShapeError
from mogs_node.metrizer.dense_anchors import anchor_points
from mogs_node.metrizer.matching import KeyframeMatcher, MatchedKeyframe, metrizer_inputs
from mogs_node.metrizer.pipeline import MetrizerParams, metrize_depth

KW = dict(stride=4, min_confidence=0.3, gap_px=0.0, weight=0.5, depth_range_m=(0.1, 80.0))


def test_anchor_points_grid_confidence_and_weight():
    d = np.full((8, 12), 5.0)
    c = np.full((8, 12), 0.8)
    c[2, 2] = 0.2  # below min_confidence
    uv, z, w = anchor_points(d, c, np.zeros((0, 2)), **KW)
    # cell centres (2, 6, 10) x (2, 6), one dropped
    assert sorted(map(tuple, uv.astype(int))) == [(2, 6), (6, 2), (6, 6), (10, 2), (10, 6)]
    assert np.all(z == 5.0) and np.allclose(w, 0.5 * 0.8)


def test_anchor_points_drop_bad_values_and_the_points_neighbourhood():
    d = np.full((8, 12), 5.0)
    c = np.ones((8, 12))
    d[2, 2], d[2, 6], c[2, 10] = np.nan, np.inf, np.nan
    d[6, 2] = 200.0  # beyond the depth range
    uv, _, w = anchor_points(d, c, np.zeros((0, 2)), **KW)
    assert sorted(map(tuple, uv.astype(int))) == [(6, 6), (10, 6)]
    assert np.allclose(w, 0.5)
    # a frontend point at (6.2, 5.9): the anchor at (6, 6) is within 2 px, (10, 6) is not
    feats = np.array([[6.2, 5.9], [np.nan, 1.0], [-50.0, 3.0]])
    uv, _, _ = anchor_points(d, c, feats, **{**KW, "gap_px": 2.0})
    assert sorted(map(tuple, uv.astype(int))) == [(10, 6)]


def test_anchor_points_none_and_all():
    d = np.full((9, 9), 3.0)
    uv, z, w = anchor_points(d, np.zeros((9, 9)), np.zeros((0, 2)), **KW)
    assert uv.shape == (0, 2) and z.shape == (0,) and w.shape == (0,)
    uv, z, w = anchor_points(d, np.ones((9, 9)), np.zeros((0, 2)), **{**KW, "stride": 1})
    assert len(z) == 81 and np.allclose(w, 0.5)


def _with_anchors(kw, gt, coverage, noise, rng, nan_share=0.0):
    """``kw`` with the ground truth as anchor depth (relative noise ``noise``) on a ``coverage``
    share of the pixels, ``nan_share`` of them NaN."""
    a = gt * (1.0 + noise * rng.standard_normal(gt.shape))
    conf = (rng.random(gt.shape) < coverage).astype(np.float32)
    a[rng.random(gt.shape) < nan_share] = np.nan
    return {**kw, "anchor_depth_m": a, "anchor_confidence": conf}


def test_accurate_anchors_beat_few_points():
    """Sim frames, simulated LFM, 8 ground-truth points: ground-truth anchors (1 % noise) on the
    whole image bring the metrizer close to the truth, and far below the points alone."""
    for frame in range(3):
        kw, params, gt = _case(frame, 8, 1.0, 0.0, 1.0, "graph", 5)
        rng = np.random.default_rng(frame)
        without = metrize_depth(**kw, params=params)
        with_a = metrize_depth(**_with_anchors(kw, gt, 0.5, 0.01, rng), params=params)
        assert with_a.stats["n_dense_anchors"] > 50
        m = (gt > 0) & (without.depth_m > 0) & (with_a.depth_m > 0)
        assert _absrel(with_a.depth_m, gt, m) < 0.1
        assert _absrel(with_a.depth_m, gt, m) < _absrel(without.depth_m, gt, m)


def test_no_anchor_input_is_the_unchanged_metrizer():
    kw, params, gt = _case(1, 150, 0.5, 0.1, 1.0, "graph", 2)
    base = metrize_depth(**kw, params=params)
    none = _with_anchors(kw, gt, 0.0, 0.0, np.random.default_rng(0))  # confidence 0 everywhere
    out = metrize_depth(**none, params=params)
    assert out.stats["n_dense_anchors"] == 0
    assert np.array_equal(out.depth_m, base.depth_m)
    zero_w = metrize_depth(
        **_with_anchors(kw, gt, 1.0, 0.0, np.random.default_rng(0)),
        params=MetrizerParams(d_min_m=0.1, d_max_m=80.0, dense_anchor_weight=0.0),
    )
    assert np.array_equal(zero_w.depth_m, base.depth_m)


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(
    frame=st.integers(0, 2),
    n_points=st.sampled_from([0, 3, 20, 300]),
    anchor_coverage=st.sampled_from([0.0, 0.01, 0.3, 1.0]),
    nan_share=st.sampled_from([0.0, 0.2, 1.0]),
    log_scale=st.floats(-2.0, 3.0),
    weight=st.sampled_from([0.0, 0.3, 5.0]),
    snap=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_anchors_at_the_edges_keep_the_output_valid_and_never_worse(
    frame, n_points, anchor_coverage, nan_share, log_scale, weight, snap, seed
):
    """Any anchor coverage (none to all), NaN anchors, any scale, with or without the edge snap
    (``launch/demo_lfm.yaml`` sets both): finite valid output, and with accurate anchors never
    more than 10 % worse than the global affine on the same inputs."""
    scale = 10.0**log_scale
    kw, params, gt = _case(frame, n_points, 1.0, 0.0, scale, "graph", seed)
    rng = np.random.default_rng(seed)
    kw = _with_anchors(kw, gt, anchor_coverage, 0.01, rng, nan_share)
    kw["anchor_depth_m"] = np.where(gt > 0, kw["anchor_depth_m"], 0.0)
    params = MetrizerParams(
        d_min_m=params.d_min_m, d_max_m=params.d_max_m, dense_anchor_weight=weight, edge_snap=snap
    )
    out = metrize_depth(**kw, params=params)
    base = metrize_depth(**kw, params=params, mode="no_msc_cdr")
    for o in (out, base):
        _check_valid(o, params.d_max_m)
    assert out.depth_m.shape == (H, W)
    if anchor_coverage == 0.0 or nan_share == 1.0 or weight == 0.0:
        assert out.stats["n_dense_anchors"] == 0
    shared = (gt > 0) & (base.depth_m > 0) & (out.depth_m > 0)
    if shared.any():
        assert _absrel(out.depth_m, gt, shared) <= 1.1 * _absrel(base.depth_m, gt, shared) + 1e-4


def test_anchor_inputs_are_checked():
    kw, params, gt = _case(0, 20, 1.0, 0.0, 1.0, "graph", 0)
    with pytest.raises(ConfigError, match="anchor_depth_m and anchor_confidence"):
        metrize_depth(**{**kw, "anchor_depth_m": gt}, params=params)
    with pytest.raises(ShapeError, match="anchor_confidence"):
        metrize_depth(
            **{**kw, "anchor_depth_m": gt, "anchor_confidence": np.ones((3, 3))}, params=params
        )
    with pytest.raises(ConfigError, match="dense_anchor"):
        MetrizerParams(dense_anchor_stride=0)


def _depth_map(kind, shape, value=4.0):
    return msgs.DepthMap(
        stamp_ns=5,
        frame_id="cam",
        keyframe_id=9,
        kind=kind,
        depth=np.full(shape, value, np.float32),
        confidence=np.ones(shape, np.float32),
        source="t",
    )


def test_matcher_waits_for_the_anchor_only_when_asked():
    m = KeyframeMatcher(max_wait_s=1.0, anchors=True)
    m.add("keyframe", 7, "K", 0.0)
    m.add("masks", 7, "M", 0.0)
    assert m.add("prior", 7, "P", 0.0) == []  # the anchor is still missing
    ready = m.add("anchor", 7, "A", 0.1)
    assert len(ready) == 1 and ready[0].anchor == "A"
    m = KeyframeMatcher(max_wait_s=1.0)
    m.add("keyframe", 7, "K", 0.0)
    m.add("masks", 7, "M", 0.0)
    assert len(m.add("prior", 7, "P", 0.0)) == 1


def test_inputs_from_messages_carry_a_metric_anchor_resized():
    from test_metrizer_node import _keyframe

    kf = _keyframe()
    prior = _depth_map("relative_inverse_depth", (24, 32), 0.2)
    entry = MatchedKeyframe(9, kf, None, prior, anchor=_depth_map("metric", (12, 16)))
    inputs = metrizer_inputs(entry)
    assert inputs.anchor_depth_m.shape == (24, 32) and np.allclose(inputs.anchor_depth_m, 4.0)
    assert inputs.anchor_confidence.shape == (24, 32)
    out = metrize_depth(**inputs)
    assert out.stats["n_dense_anchors"] > 0 and np.all(np.isfinite(out.depth_m))
    # a relative map is no metric anchor: ignored
    entry = MatchedKeyframe(9, kf, None, prior, anchor=prior)
    assert metrizer_inputs(entry).anchor_depth_m is None
