"""Round 14: the re-observed points' contrast test (a textured point hidden behind a flat occluder)
and ``patch_match``'s contrast ratio."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.frontend.reobserve import reobserved_points
from mogs_node.frontend.track_points import (
    KeyframePoints,
    TrackPointsParams,
    patch_match,
)
from mogs_node.geometry import PinholeCamera, make_T

CAM = PinholeCamera(360.77, 361.73, 304.53, 86.41, 621, 188)


def _texture(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (188, 621)).astype(np.float32)


@settings(max_examples=40, deadline=None)
@given(
    gain=st.floats(1e-3, 1e3),
    offset=st.floats(-1e3, 1e3),
    radius=st.integers(1, 5),
    seed=st.integers(0, 1000),
)
def test_contrast_ratio_is_the_reference_spread_over_the_view_spread(gain, offset, radius, seed):
    # the view is the reference's texture times a gain plus an offset, at the same pixels: the
    # ZNCC is 1 whatever the gain (it cannot tell a faded copy), the contrast ratio is 1 / gain
    ref = _texture(seed)
    view = (gain * ref + offset).astype(np.float32)
    uv = np.array([[100.0, 50.0], [300.5, 90.25], [600.0, 150.0]])
    zncc, contrast = patch_match(ref, uv, view, uv, np.ones(3), radius)
    np.testing.assert_allclose(zncc, 1.0, atol=1e-3)
    np.testing.assert_allclose(contrast, 1.0 / gain, rtol=1e-3)


def test_flat_patches_give_zero_zncc_and_a_zero_or_infinite_contrast():
    tex, flat = _texture(1), np.full((188, 621), 80.0, np.float32)
    uv = np.array([[200.0, 90.0]])
    z, c = patch_match(tex, uv, flat, uv, np.ones(1), 3)  # the view's patch is flat
    assert z[0] == 0.0 and c[0] == np.inf
    z, c = patch_match(flat, uv, tex, uv, np.ones(1), 3)  # the reference's is flat
    assert z[0] == 0.0 and c[0] == 0.0
    z, c = patch_match(tex, np.zeros((0, 2)), tex, np.zeros((0, 2)), np.ones(0), 3)
    assert z.shape == c.shape == (0,)
    with pytest.raises(ShapeError, match="uv_view_px"):
        patch_match(tex, uv, tex, np.zeros((2, 2)), np.ones(1), 3)


def _points(uv: np.ndarray, z: float, ids: np.ndarray) -> KeyframePoints:
    n = len(uv)
    return KeyframePoints(
        ids.astype(np.int64),
        uv.astype(np.float32),
        CAM.backproject(uv, np.full(n, z)).astype(np.float32),
        np.tile(np.eye(3, dtype=np.float32) * 1e-4, (n, 1, 1)),
        np.full(n, 0.5, np.float32),
    )


def test_a_point_behind_a_faded_occluder_is_dropped_by_the_contrast_test_only():
    # the previous keyframe saw a textured wall at 12 m; the camera has not moved; in the new
    # keyframe an occluder covers u < 300 whose faint shading is the wall's texture at 5 % of its
    # contrast: the ZNCC still matches, so only the contrast test sees the point is hidden
    prev_img = _texture(3)
    cur_img = prev_img.copy()
    mean = prev_img[:, :300].mean()
    cur_img[:, :300] = mean + 0.05 * (prev_img[:, :300] - mean)
    u, v = np.meshgrid(np.arange(20.0, 600, 20), np.arange(20.0, 170, 20))
    uv = np.stack([u.ravel(), v.ravel()], 1)
    prev = _points(uv, 12.0, np.arange(len(uv)))
    fresh = KeyframePoints.empty()
    T = make_T(np.eye(3), np.zeros(3))
    base = TrackPointsParams(reproject_min_zncc=0.9, edge_radius_px=1e-3)
    recent = [(T, prev, prev_img)]
    hidden = np.flatnonzero(uv[:, 0] < 300 - 3)  # patches wholly on the occluder
    visible = np.flatnonzero(uv[:, 0] > 300 + 3)
    kept_off = reobserved_points(fresh, recent, T, CAM, cur_img, base)
    assert set(kept_off.ids.tolist()) >= set(hidden.tolist()) | set(visible.tolist())
    on = dataclasses.replace(base, reproject_min_contrast=0.5)
    kept = reobserved_points(fresh, recent, T, CAM, cur_img, on)
    assert set(kept.ids.tolist()) >= set(visible.tolist())
    assert not set(kept.ids.tolist()) & set(hidden.tolist())


def test_the_contrast_test_is_off_by_default_and_validated_as_a_share():
    assert TrackPointsParams().reproject_min_contrast == 0.0
    with pytest.raises(ConfigError, match="reproject_min_contrast"):
        TrackPointsParams(reproject_min_contrast=-0.1)
