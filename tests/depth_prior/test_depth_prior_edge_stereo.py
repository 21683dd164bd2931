"""Edge stereo (mogs_node/depth_prior/edge_stereo.py): depth of image edges along epipolar lines."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.depth_prior.dense_prior import (
    SOURCES,
    FusionParams,
    PriorHistory,
    compute_dense_prior,
)
from mogs_node.depth_prior.edge_stereo import EdgeStereoParams, edge_stereo_depth, match_edges
from mogs_node.errors import ConfigError

H, W = 120, 200
K = np.array([[150.0, 0, W / 2], [0, 150.0, H / 2], [0, 0, 1]])


def _pose(x: float, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, z
    return T


def _plane_view(cam_x: float, depth_m: float, seed: int = 0) -> np.ndarray:
    """A fronto-parallel plane at ``depth_m`` with random vertical bands (steps every 5 cm of
    X), seen from a camera at ``(cam_x, 0, 0)`` looking along +z: every band edge is vertical,
    the epipolar lines of a sideways baseline are horizontal (no aperture problem)."""
    rng = np.random.default_rng(seed)
    levels = rng.integers(30, 225, 400).astype(np.float64)
    u = np.arange(W)[:, None] - 0.5 + (np.arange(16) + 0.5) / 16  # 16 samples per pixel
    X = (u - W / 2) / 150.0 * depth_m + cam_x  # the plane point each sample sees
    idx = np.clip(np.floor(X / 0.05).astype(int) + 200, 0, 399)
    row = levels[idx].mean(1)  # the pixel's area average: edges at sub-pixel positions
    return np.tile(np.round(row), (H, 1)).astype(np.uint8)


def test_edges_of_a_plane_get_its_depth() -> None:
    z = 4.0
    k = _plane_view(0.0, z)
    refs = [(_plane_view(-0.3, z), _pose(-0.3)), (_plane_view(-0.6, z), _pose(-0.6))]
    d, e = edge_stereo_depth(k, K, _pose(0.0), refs, EdgeStereoParams(enabled=True))
    got = d[d > 0]
    assert len(got) > 200  # the band edges, on every row
    # area-averaged edges: the SSD's parabola is good to ~0.1-0.2 px of the ~11 px disparity
    assert np.median(np.abs(got - z) / z) < 0.02
    # ... and the predicted error (a 0.5-px shift along the line) bounds the actual one on 8 of
    # the 9 band edges; the ninth is matched to a similar-looking edge in both references (75 %
    # off: the agreement test cannot catch an ambiguity both views share)
    assert np.mean(np.abs(got - z) / z <= 2 * e[d > 0]) > 0.85
    assert np.all(np.isfinite(e[d > 0])) and np.all(e[d > 0] >= 0.02)
    assert np.all(np.isinf(e[d == 0]))


def test_one_reference_and_where() -> None:
    z = 2.5
    k = _plane_view(0.0, z, seed=3)
    refs = [(_plane_view(-0.2, z, seed=3), _pose(-0.2))]
    where = np.zeros((H, W), bool)
    where[:, : W // 2] = True
    d, _ = edge_stereo_depth(k, K, _pose(0.0), refs, EdgeStereoParams(enabled=True), where=where)
    assert (d[:, W // 2 :] == 0).all()
    got = d[d > 0]
    assert len(got) > 50 and np.median(np.abs(got - z) / z) < 0.02


def test_no_baseline_no_texture_nothing() -> None:
    k = _plane_view(0.0, 3.0)
    p = EdgeStereoParams(enabled=True)
    d, e = edge_stereo_depth(k, K, _pose(0.0), [(k, _pose(0.0))], p)  # standstill
    assert not d.any() and np.isinf(e).all()
    flat = np.full((H, W), 128, np.uint8)
    d, _ = edge_stereo_depth(flat, K, _pose(0.0), [(flat, _pose(-0.3))], p)
    assert not d.any()
    d, _ = edge_stereo_depth(k, K, _pose(0.0), [], p)
    assert not d.any()


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ConfigError):
        EdgeStereoParams(ratio=0.0)
    with pytest.raises(ConfigError):
        EdgeStereoParams(min_depth_m=5.0, max_depth_m=1.0)


@settings(max_examples=20, deadline=None)
@given(
    scale=st.floats(1e-2, 1e3),
    baseline=st.floats(-2.0, 2.0),
    forward=st.floats(-1.0, 1.0),
    seed=st.integers(0, 5),
)
def test_finite_at_any_scale_and_motion(
    scale: float, baseline: float, forward: float, seed: int
) -> None:
    """Scene and baseline scaled together (tiny to huge), any sideways / forward motion:
    depths finite, in range, scaled like the scene where the plane is in range."""
    z = 4.0 * scale
    k = _plane_view(0.0, z, seed)
    Tr = _pose(baseline * scale, forward * scale)
    r = _plane_view(baseline * scale, z - forward * scale, seed) if z - forward * scale > 0 else k
    p = EdgeStereoParams(enabled=True, min_depth_m=1e-3, max_depth_m=1e5)
    v, u, d, e = match_edges(k, r, K, np.linalg.inv(Tr) @ _pose(0.0), p)
    assert np.all(np.isfinite(d)) and np.all(np.isfinite(e))
    assert np.all((d >= p.min_depth_m) & (d <= p.max_depth_m)) and np.all(e >= p.min_rel_err)
    assert np.all((v >= 0) & (v < H) & (u >= 0) & (u < W))


def _pillar_view(cam_x: float, z_far: float, z_near: float) -> np.ndarray:
    """``_plane_view``'s banded plane at ``z_far`` (faint: its band edges are not edges) with a
    uniform dark pillar (X in [-0.2, 0.2] m, rows 20-99) at ``z_near`` in front of it."""
    back = 115.0 + (_plane_view(cam_x, z_far).astype(np.float64) - 128.0) / 20.0  # faint bands
    u = np.arange(W)[:, None] - 0.5 + (np.arange(16) + 0.5) / 16
    X = (u - W / 2) / 150.0 * z_near + cam_x
    hit = (np.abs(X) <= 0.2).mean(1)  # the pillar's share of each column's pixel
    img = back.copy()
    img[20:100] = hit * 20.0 + (1 - hit) * back[20:100]
    return np.round(img).astype(np.uint8)


def test_dense_prior_contour_source() -> None:
    """Off (default): no contour source; on: the pillar, which the flow cannot match inside,
    gets its outline's depth."""
    z_far, z_near = 8.0, 2.0
    k = _pillar_view(0.0, z_far, z_near)
    refs = [(_pillar_view(-d, z_far, z_near), _pose(-d)) for d in (0.15, 0.3)]
    past = PriorHistory(references=refs)
    off = compute_dense_prior(k, K, _pose(0.0), past)
    assert not (off.source == SOURCES["contour"]).any()
    on = compute_dense_prior(k, K, _pose(0.0), past, params=FusionParams(contour_fill=True))
    led = on.source == SOURCES["contour"]
    pillar = np.zeros((H, W), bool)
    pillar[24:96, 88:113] = True  # its interior (columns 85-115 at 2 m)
    assert (led & pillar).sum() > 0.8 * pillar.sum()
    np.testing.assert_allclose(on.depth_m[led & pillar], z_near, rtol=0.03)
    assert np.all(on.confidence[led] <= 0.5)  # error >= 6 %
