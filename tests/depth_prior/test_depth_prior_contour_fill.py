"""Contour fill (mogs_node/depth_prior/contour_fill.py): untextured regions from their outline."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.depth_prior.contour_fill import (
    ContourFillParams,
    contour_fill,
    flat_regions,
)
from mogs_node.errors import ConfigError

H, W = 80, 120
PILLAR = (slice(20, 70), slice(40, 70))  # rows, columns of the untextured object


def _scene(z_near: float, z_far: float, seed: int = 0):
    """A uniform grey pillar at ``z_near`` in front of a textured background at ``z_far``: the
    image, the pillar mask, and the edge-stereo depth an occluding contour has (the pillar's, on
    the gradient band around its outline)."""
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, (H, W)).astype(np.uint8)  # texture: never flat
    img[PILLAR] = 120
    pillar = np.zeros((H, W), bool)
    pillar[PILLAR] = True
    ring = np.zeros((H, W), bool)
    ring[18:72, 38:72] = True
    ring[22:68, 42:68] = False  # 2 px either side of the outline
    edge = np.where(ring, z_near, 0.0).astype(np.float32)
    return img, pillar, edge


def test_pillar_filled_with_its_outline_depth() -> None:
    z_near, z_far = 2.0, 12.0
    img, pillar, edge = _scene(z_near, z_far)
    depth = np.where(pillar, 0.0, z_far).astype(np.float32)  # the flow has the background only
    conf = np.where(pillar, 0.0, 0.6).astype(np.float32)
    fill, err, stats = contour_fill(img, edge, depth, conf, ContourFillParams())
    inside = np.zeros((H, W), bool)
    inside[24:66, 44:66] = True  # the flat interior
    assert (fill[inside] > 0).all()
    np.testing.assert_allclose(fill[inside], z_near, rtol=1e-5)
    assert (fill[~pillar] == 0).all()  # the background keeps its own depth
    assert np.all(err[fill > 0] >= ContourFillParams().min_rel_err)
    assert np.all(np.isinf(err[fill == 0]))
    assert stats["contour_regions"] >= 1


def test_background_does_not_take_the_occluder_depth() -> None:
    """A uniform background behind a textured near object: the outline's depth is the near
    object's, which its own depth confirms, so the background side gets nothing."""
    z_near = 2.0
    rng = np.random.default_rng(1)
    img = np.full((H, W), 200, np.uint8)  # untextured background
    img[PILLAR] = rng.integers(0, 255, (50, 30)).astype(np.uint8)  # textured near object
    obj = np.zeros((H, W), bool)
    obj[PILLAR] = True
    ring = np.zeros((H, W), bool)
    ring[18:72, 38:72] = True
    ring[22:68, 42:68] = False
    edge = np.where(ring, z_near, 0.0).astype(np.float32)
    depth = np.where(obj, z_near, 0.0).astype(np.float32)
    conf = np.where(obj, 0.6, 0.0).astype(np.float32)
    fill, _, _ = contour_fill(img, edge, depth, conf, ContourFillParams())
    assert not fill.any()


def test_region_whose_depth_disagrees_is_left_alone() -> None:
    z_near, z_far = 2.0, 12.0
    img, pillar, edge = _scene(z_near, z_far)
    depth = np.where(pillar, 0.0, z_far).astype(np.float32)
    depth[30:60, 45:65] = 5.0  # the region already says 5 m, the outline 2 m: 2.5x apart
    conf = np.where(depth > 0, 0.6, 0.0).astype(np.float32)
    fill, _, _ = contour_fill(img, edge, depth, conf, ContourFillParams())
    assert not fill[pillar].any()


def test_weak_pixels_replaced_holes_only_when_off() -> None:
    z_near, z_far = 2.0, 12.0
    img, pillar, edge = _scene(z_near, z_far)
    depth = np.where(pillar, 0.0, z_far).astype(np.float32)
    conf = np.where(pillar, 0.0, 0.6).astype(np.float32)
    depth[40:44, 50:60] = z_near * 1.1  # a weak carried depth inside the pillar
    conf[40:44, 50:60] = 0.05
    on, _, _ = contour_fill(img, edge, depth, conf, ContourFillParams())
    np.testing.assert_allclose(on[40:44, 50:60], z_near, rtol=1e-5)
    off, _, _ = contour_fill(img, edge, depth, conf, ContourFillParams(replace_below=0.0))
    assert not off[40:44, 50:60].any() and (off[45:60, 45:65] > 0).all()


def test_flat_regions_and_bad_parameters() -> None:
    img, pillar, _ = _scene(2.0, 12.0)
    gx = np.zeros((H, W), np.float32)
    labels, n = flat_regions(gx, gx, 2.0, 100)  # everything flat: one region
    assert n == 2 and (labels == 1).all()
    labels, _ = flat_regions(gx, gx, 2.0, H * W + 1)  # too small
    assert (labels == -1).all()
    with pytest.raises(ConfigError):
        ContourFillParams(min_samples=0)
    with pytest.raises(ConfigError):
        ContourFillParams(min_inlier_share=1.5)


@settings(max_examples=25, deadline=None)
@given(
    scale=st.floats(1e-2, 1e3),
    seed=st.integers(0, 1000),
    edge_share=st.floats(0.0, 1.0),
    known_share=st.floats(0.0, 1.0),
)
def test_any_input_finite_and_only_where_allowed(
    scale: float, seed: int, edge_share: float, known_share: float
) -> None:
    """Random edges, depths and images at any scale: the fill is finite, positive only where
    the prior had no depth (or a weak one), with a finite error there and inf elsewhere."""
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, (H, W)).astype(np.uint8)
    img[rng.random((H, W)) < 0.5] = 90  # flat patches
    edge = np.where(rng.random((H, W)) < edge_share, scale * rng.uniform(0.5, 2, (H, W)), 0.0)
    depth = np.where(rng.random((H, W)) < known_share, scale * rng.uniform(0.5, 2, (H, W)), 0.0)
    conf = np.where(depth > 0, rng.random((H, W)), 0.0).astype(np.float32)
    p = ContourFillParams(min_samples=1, min_inlier_share=0.0)
    fill, err, _ = contour_fill(img, edge.astype(np.float32), depth.astype(np.float32), conf, p)
    assert np.all(np.isfinite(fill)) and np.all(fill >= 0)
    assert np.all(np.isfinite(err[fill > 0])) and np.all(np.isinf(err[fill == 0]))
    allowed = (depth <= 0) | (conf < p.replace_below)
    assert not fill[~allowed].any()
    if fill.any():
        lo, hi = edge[edge > 0].min(), edge[edge > 0].max()
        assert fill[fill > 0].min() >= lo * (1 - 1e-5) and fill[fill > 0].max() <= hi * (1 + 1e-5)
