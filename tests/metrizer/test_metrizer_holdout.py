"""Departures 22 and 23 (session 15): a shape must explain its object's prior pixels, and a metric
prior keeps its scale unless the features show otherwise."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.metrizer.alignment import fit_global_affine, metric_affine_earned
from mogs_node.metrizer.frame import ShapeModels
from mogs_node.metrizer.holdout import shapes_explain_prior
from mogs_node.metrizer.pipeline import MetrizerParams, metrize_depth

W, H = 64, 48
K = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])


def _plane_at(z0: float) -> ShapeModels:
    """One object whose accepted shape is the fronto-parallel plane ``z = z0``."""
    m = ShapeModels.none(1)
    m.kind[0], m.conf[0] = 1, 0.9
    m.b[0], m.c[0] = (0.0, 0.0, 1.0), -z0
    m.zlo[0], m.zhi[0] = z0 / 2, 2 * z0
    return m


def _check(prior_depth: np.ndarray, z_feat: np.ndarray, d_feat: np.ndarray, z0: float = 10.0):
    pix = np.arange(0, H * W, 7)
    s = (pix, np.zeros(len(pix), np.intp), prior_depth[pix], np.ones(len(pix)))
    f = (np.zeros(len(z_feat), np.intp), z_feat, d_feat)
    return shapes_explain_prior(_plane_at(z0), s, f, W, K, tau=0.8, gate=0.1)


def test_a_shape_on_the_rails_in_front_of_the_surface_is_dropped():
    """The truck's load (session 15, KITTI frames 13-15): the features lie on the frame rails
    at 10 m and agree with the prior there, the prior's surface behind them is 15 % farther."""
    prior = np.full(H * W, 11.5)
    z = np.full(12, 10.0)
    assert _check(prior, z, z.copy())[0]


def test_a_shape_that_the_prior_shows_is_kept_whatever_the_prior_scale():
    rng = np.random.default_rng(0)
    prior = 10.0 * np.exp(rng.normal(0, 0.02, H * W))
    z = np.full(12, 10.0)
    assert not _check(prior, z, np.full(12, 10.0))[0]
    # a prior 20 % off everywhere: its features see the same offset, the shape still holds
    assert not _check(1.2 * prior, z, np.full(12, 12.0))[0]


def test_untestable_shapes_are_kept():
    prior = np.full(H * W, 20.0)
    # no feature to calibrate the prior with: no test
    assert not _check(prior, np.zeros(0), np.zeros(0))[0]
    # the plane misses every ray (behind the camera): no sample to test on
    assert not _check(prior, np.full(5, 10.0), np.full(5, 10.0), z0=-10.0)[0]


def _frame(offset: float, prior_kind: str):
    """A wall at 10 m; the features lie on a parallel plane ``offset`` nearer (rails)."""
    rng = np.random.default_rng(1)
    n = 60
    uv = np.stack([rng.uniform(2, W - 3, n), rng.uniform(2, H - 3, n)], 1)
    z = np.full(n, 10.0 - offset) * np.exp(rng.normal(0, 0.002, n))
    prior = np.full((H, W), 10.0, np.float32)
    if prior_kind == "relative_inverse_depth":
        prior = (1.0 / prior).astype(np.float32)
    return dict(
        K=K,
        labels=np.zeros((H, W), np.int32),
        feature_uv_px=uv,
        feature_depth_m=z,
        feature_weight=np.ones(n),
        prior=prior,
        prior_confidence=np.ones((H, W), np.float32),
        prior_kind=prior_kind,
        image_rgb=np.full((H, W, 3), 128, np.uint8),
    )


def test_pipeline_drops_the_rails_plane_of_a_metric_prior_only():
    p = MetrizerParams(fallback_global=False)
    out = metrize_depth(**_frame(0.0, "metric"), params=p)
    assert out.stats["rejected_held_out"] == 0 and out.stats["models"]["plane"] == 1
    # a metric prior, features on a plane 1.5 m in front of its surface, but the prior at the
    # features agrees (they were sampled off the surface): the held-out pixels disagree
    f = _frame(1.5, "metric")
    f["prior"][...] = 10.0
    uv = np.round(f["feature_uv_px"]).astype(int)
    f["prior"][uv[:, 1], uv[:, 0]] = f["feature_depth_m"]
    out = metrize_depth(**f, params=p)
    assert out.stats["rejected_held_out"] == 1 and out.stats["models"]["plane"] == 0
    out = metrize_depth(**f, params=MetrizerParams(fallback_global=False, shape_prior_check=False))
    assert out.stats["rejected_held_out"] == 0 and out.stats["models"]["plane"] == 1
    # a relative prior has no metric level to hold the shape out with: never tested
    out = metrize_depth(**_frame(1.5, "relative_inverse_depth"), params=p)
    assert out.stats["rejected_held_out"] == 0


def test_metric_identity_unless_the_features_show_a_scale():
    rng = np.random.default_rng(2)
    x = rng.uniform(3, 40, 80)
    noise = np.exp(rng.normal(0, 0.03, 80))
    w = np.ones(80)
    # a metric prior that is right: a fitted affine only chases the noise
    t = x * noise
    th, _ = fit_global_affine(x, t, w, "metric")
    assert not metric_affine_earned(x, t, w, th)
    # a prior 10 % short: the features show it
    t = 1.1 * x * noise
    th, _ = fit_global_affine(x, t, w, "metric")
    assert metric_affine_earned(x, t, w, th)
    assert th[0] + th[1] / 20 == pytest.approx(1.1, rel=0.02)


def test_pipeline_keeps_a_right_metric_prior_as_it_is():
    f = _frame(0.0, "metric")
    p = MetrizerParams(metric_identity_test=True)
    out = metrize_depth(**f, params=p, mode="no_msc_cdr")
    assert out.stats["global_affine"] == [1.0, 0.0]
    np.testing.assert_allclose(out.depth_m, 10.0, rtol=1e-6)
    assert metrize_depth(**f, mode="no_msc_cdr").stats["global_affine"] != [1.0, 0.0]
    f["feature_depth_m"] = 1.3 * f["feature_depth_m"]
    out = metrize_depth(**f, params=p, mode="no_msc_cdr")
    np.testing.assert_allclose(out.depth_m, 13.0, rtol=0.01)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(width=64), st.floats(width=64), st.floats(width=64)),
        max_size=30,
    ),
    st.floats(),
    st.floats(),
)
def test_metric_affine_earned_is_a_plain_bool_on_bad_input(rows, a, b):
    arr = np.asarray(rows, np.float64).reshape(-1, 3)
    res = metric_affine_earned(arr[:, 0], arr[:, 1], arr[:, 2], np.array([a, b]))
    assert isinstance(res, bool)
