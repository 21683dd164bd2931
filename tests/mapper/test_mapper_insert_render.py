"""The insertion render: the whole map's image from the culled rows (bit for bit), and at a
fraction of the resolution (``insert_downsample``), nearest-upsampled to the keyframe's pixels."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.geometry import make_T, rotmat_from_rpy, se3_inverse
from mogs_node.mapper.mapper import GaussianMapper, MapperParams, _upsample_nearest
from mogs_node.mapper.rasterizer import render

W, H = 64, 32
K = np.array([[40.0, 0, 31.5], [0, 40.0, 15.5], [0, 0, 1]])


def view(kid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A textured wall 5 m ahead, the camera moving right."""
    rng = np.random.default_rng(kid)
    coarse = rng.uniform(0, 255, size=(H // 8 + 1, W // 8 + 1, 3))
    img = np.kron(coarse, np.ones((8, 8, 1)))[:H, :W].astype(np.uint8)
    T = make_T(np.eye(3), np.array([0.4 * kid, 0.0, 0.0]))
    depth = np.full((H, W), 5.0, np.float32)
    conf = np.full((H, W), 0.8, np.float32)
    return img, T, depth, conf


def test_render_view_equals_the_whole_maps_render_bit_for_bit() -> None:
    m = GaussianMapper(MapperParams(), K, W, H)
    for k in range(2):
        m.add_keyframe(k, *view(k))
        m.optimize(2)
    T = make_T(rotmat_from_rpy(0.0, 0.5, 0.0), np.array([0.2, 0.0, 0.0]))  # part off screen
    got = m.render_view(T)
    want = render(m.map.tensors(), torch.as_tensor(se3_inverse(T)), m.K, W, H)
    assert torch.equal(got.color, want.color.clamp(0, 1))
    assert torch.equal(got.depth, want.depth) and torch.equal(got.alpha, want.alpha)
    assert torch.equal(got.counts, want.counts) and torch.equal(got.weights, want.weights)
    assert 0 < int((got.counts > 0).sum()) < len(m.map)


@settings(max_examples=40, deadline=None)
@given(h=st.integers(1, 9), w=st.integers(1, 9), f=st.integers(1, 4), c=st.integers(0, 3))
def test_property_nearest_upsampling_repeats_each_block(h: int, w: int, f: int, c: int) -> None:
    src = np.arange(h * w * max(c, 1), dtype=np.float32).reshape((h, w) + ((c,) if c else ()))
    height, width = h * f + (f - 1 if f > 1 else 0), w * f  # a trailing partial block of rows
    up = _upsample_nearest(src, f, height, width)
    assert up.shape == (height, width) + src.shape[2:]
    v, u = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    np.testing.assert_array_equal(up, src[np.minimum(v // f, h - 1), np.minimum(u // f, w - 1)])


def test_half_resolution_insertion_inserts_only_what_the_map_does_not_explain() -> None:
    full = GaussianMapper(MapperParams(), K, W, H)
    half = GaussianMapper(MapperParams(insert_downsample=2), K, W, H)
    for m in (full, half):
        m.add_keyframe(0, *view(0))
        m.optimize(6)
    # the first keyframe renders nothing: both insert the same Gaussians
    assert torch.equal(full.map.params["means"], half.map.params["means"])
    # the same view again: the map explains it, (almost) nothing is inserted at either resolution
    n_full, n_half = (m.add_keyframe(1, *view(0)) for m in (full, half))
    assert n_half <= max(2 * n_full, 0.02 * len(half.map))
    # a view 3.2 m to the right sees new wall on its right: both insert there, as many +-25 %
    img, T, d, c = view(8)
    n_full, n_half = (m.add_keyframe(2, img, T, d, c) for m in (full, half))
    assert n_full > 0 and abs(n_half - n_full) <= 0.25 * n_full
    # the visibility record is in full-resolution pixels at either resolution
    w_full, w_half = (float(m.keyframes[-1].visible_weights.sum()) for m in (full, half))
    assert abs(w_half - w_full) <= 0.1 * w_full
