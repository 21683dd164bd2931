"""Insertion with one confidence for every depth source (``InsertionParams.fixed_confidence``):
the rules then read only the depth and the map, so two sources that give the same depth with
different confidences get the same Gaussians (Table II's fair treatment, docs/mapper.md)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError
from mogs_node.mapper.insertion import (
    InsertionParams,
    insertion_confidence,
    insertion_mask,
    sample_gaussians,
)

H, W = 16, 24
K = np.array([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])
P = dict(stride_px=2, max_stride_px=8, max_footprint_rad=1.0, planar_tol=0.0)


def test_the_sources_confidence_is_kept_by_default_and_replaced_where_there_is_depth() -> None:
    d = np.array([[2.0, 0.0], [np.nan, 40.0]], np.float32)
    c = np.array([[0.1, 0.9], [0.3, 0.0]], np.float32)
    np.testing.assert_array_equal(insertion_confidence(d, c, InsertionParams()), c)
    fixed = insertion_confidence(d, c, InsertionParams(fixed_confidence=0.8))
    np.testing.assert_array_equal(fixed, np.array([[0.8, 0.0], [0.0, 0.8]], np.float32))


@pytest.mark.parametrize("bad", [-0.5, 1.5, float("nan")])
def test_a_fixed_confidence_outside_0_1_is_one_config_error(bad: float) -> None:
    with pytest.raises(ConfigError, match="fixed_confidence"):
        InsertionParams(fixed_confidence=bad)


def test_the_same_depth_with_any_confidence_gives_the_same_gaussians() -> None:
    """Random depth (confidence 0) and the same values claimed confident: with a fixed
    confidence both are sampled at the confident stride, 4 px here, on every pixel."""
    rng = np.random.default_rng(0)
    d = rng.uniform(1.0, 20.0, (H, W)).astype(np.float32)
    img = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    mask = np.ones((H, W), bool)
    p = InsertionParams(**P, fixed_confidence=1.0)
    out = [
        sample_gaussians(img, d, np.full((H, W), c, np.float32), mask, K, np.eye(4), p)
        for c in (0.0, 0.5, 1.0)
    ]
    assert len(out[0]["means"]) == (H // 4) * (W // 4)
    for o in out[1:]:
        for k, v in o.items():
            np.testing.assert_array_equal(v.numpy(), out[0][k].numpy())
    # the source's own confidence: 0 is sampled at the base stride (2 px)
    zero = np.zeros((H, W), np.float32)
    own = sample_gaussians(img, d, zero, mask, K, np.eye(4), InsertionParams(**P))
    assert len(own["means"]) == (H // 2) * (W // 2)


def test_a_fixed_confidence_lets_every_source_disagree_with_the_map() -> None:
    """A surface 5 m in front of an opaque map at 10 m: confidence 0 never disagrees; with a
    fixed confidence every such pixel does, whatever the source claimed."""
    d = np.full((H, W), 5.0, np.float32)
    c = np.zeros((H, W), np.float32)
    alpha = np.ones((H, W), np.float32)
    rdepth = np.full((H, W), 10.0, np.float32)
    assert not insertion_mask(d, c, alpha, rdepth, InsertionParams()).any()
    assert insertion_mask(d, c, alpha, rdepth, InsertionParams(fixed_confidence=1.0)).all()
    # a map surface that agrees within the tolerance explains the view for every source
    near = np.full((H, W), 5.5, np.float32)
    assert not insertion_mask(d, c, alpha, near, InsertionParams(fixed_confidence=1.0)).any()


@settings(max_examples=40, deadline=None)
@given(
    fixed=st.floats(0.0, 1.0),
    scale=st.sampled_from([1e-3, 1.0, 1e4]),
    holes=st.floats(0.0, 1.0),
)
def test_property_a_fixed_confidence_never_depends_on_the_sources(
    fixed: float, scale: float, holes: float
) -> None:
    """Any source confidence (NaN and inf included) gives the same insertion mask; pixels
    without usable depth stay out, at any depth scale."""
    rng = np.random.default_rng(1)
    d = (rng.uniform(0.5, 2.0, (H, W)) * scale).astype(np.float32)
    d[rng.uniform(size=(H, W)) < holes] = 0.0
    d[0, 0] = np.nan
    alpha = rng.uniform(0.0, 1.0, (H, W)).astype(np.float32)
    rdepth = (rng.uniform(0.5, 2.0, (H, W)) * scale).astype(np.float32)
    p = InsertionParams(fixed_confidence=fixed)
    ref = insertion_mask(d, np.zeros((H, W), np.float32), alpha, rdepth, p)
    for c in (np.ones((H, W)), rng.uniform(size=(H, W)), np.full((H, W), np.nan)):
        c = c.astype(np.float32)
        c[0, 1] = np.inf
        np.testing.assert_array_equal(insertion_mask(d, c, alpha, rdepth, p), ref)
    assert not (ref & ~(np.isfinite(d) & (d >= p.min_depth_m))).any()
