"""Feature tracker: KLT tracks on procedurally textured images warped by known homographies."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.tracker import FeatureTracker, TrackerParams
from mogs_node.geometry import PinholeCamera, so3_exp

W, H = 320, 192
CAM = PinholeCamera(250.0, 250.0, 159.5, 95.5, W, H)


def texture(seed: int, size: int = 1024) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size), np.float32)
    for s in (3, 9, 27):
        n = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), s)
        img += n / n.std()
    img = (img - img.min()) / (img.max() - img.min())
    return (img * 255).astype(np.uint8)


def plane_view(
    tex: np.ndarray,
    R_cam_world: np.ndarray,
    t_cam_world: np.ndarray,
    depth_m: float = 5.0,
    px_per_m: float = 100.0,
) -> np.ndarray:
    """Image of a textured plane z = depth_m (world) seen by camera (R, t): exact homography."""
    s = tex.shape[0]
    # texture pixel (a, b) <-> world point ((a - s/2)/ppm, (b - s/2)/ppm, depth)
    A = np.array(
        [[1 / px_per_m, 0, -s / 2 / px_per_m], [0, 1 / px_per_m, -s / 2 / px_per_m], [0, 0, 1.0]]
    )
    M = np.column_stack(
        [R_cam_world[:, 0], R_cam_world[:, 1], R_cam_world[:, 2] * depth_m + t_cam_world]
    )
    Hm = CAM.K @ M @ A
    return cv2.warpPerspective(tex, Hm, (W, H), flags=cv2.INTER_LINEAR)


def test_tracks_kept_under_translation():
    tex = texture(0)
    tr = FeatureTracker(TrackerParams(max_features=120), CameraModel(CAM))
    ratios = []
    first_ids = None
    for i in range(10):
        img = plane_view(tex, np.eye(3), np.array([-0.04 * i, 0.01 * i, 0.0]))
        res = tr.track(img)
        if i == 0:
            first_ids = set(res.ids.tolist())
            assert len(res.ids) >= 80
        else:
            ratios.append(res.kept_ratio)
        assert np.all(np.isfinite(res.uv_px))
    assert min(ratios) >= 0.8
    # Tracked pixels follow the true motion: 0.04 m at 5 m with f=250 -> 2 px per frame in u.
    assert len(first_ids & set(res.ids.tolist())) >= 40


def test_track_positions_match_homography():
    tex = texture(1)
    tr = FeatureTracker(TrackerParams(), CameraModel(CAM))
    a = tr.track(plane_view(tex, np.eye(3), np.zeros(3)))
    b = tr.track(plane_view(tex, np.eye(3), np.array([0.1, 0.0, 0.0])))
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    assert len(common) > 50
    du = b.uv_px[ib] - a.uv_px[ia]
    np.testing.assert_allclose(np.median(du[:, 0]), 250 * 0.1 / 5.0, atol=0.1)
    assert np.percentile(np.abs(du[:, 0] - 5.0), 90) < 0.3
    assert np.all(b.track_len[ib] == 2)


def test_imu_prediction_enables_large_rotation():
    tex = texture(2)
    R = so3_exp(np.array([0.0, 0.12, 0.0]))  # ~30 px image shift per frame
    kept = {}
    for use_imu in (False, True):
        tr = FeatureTracker(TrackerParams(pyr_levels=1, win_size_px=11), CameraModel(CAM))
        tr.track(plane_view(tex, np.eye(3), np.zeros(3)))
        res = tr.track(plane_view(tex, R, np.zeros(3)), R_cur_prev_cam=R if use_imu else None)
        kept[use_imu] = res.n_tracked / res.n_prev
    assert kept[True] >= 0.8
    assert kept[True] > kept[False] + 0.3


def test_standstill_and_blank_images_no_nan():
    tex = texture(3)
    tr = FeatureTracker(TrackerParams(), CameraModel(CAM))
    img = plane_view(tex, np.eye(3), np.zeros(3))
    for _ in range(3):
        res = tr.track(img)
    assert res.kept_ratio == 1.0
    res = tr.track(np.zeros((H, W), np.uint8))
    assert res.n_tracked <= res.n_prev and np.all(np.isfinite(res.uv_px))
    res = tr.track(img)
    assert len(res.ids) > 50


def test_clahe_option_tracks_low_contrast():
    tex = (texture(4) // 16 + 100).astype(np.uint8)
    tr = FeatureTracker(TrackerParams(clahe=True), CameraModel(CAM))
    tr.track(plane_view(tex, np.eye(3), np.zeros(3)))
    res = tr.track(plane_view(tex, np.eye(3), np.array([0.05, 0, 0])))
    assert res.n_prev > 50 and res.kept_ratio >= 0.8


def test_bad_input_raises():
    tr = FeatureTracker(TrackerParams(), CameraModel(CAM))
    with pytest.raises(ShapeError, match="image"):
        tr.track(np.zeros((H + 1, W), np.uint8))
    with pytest.raises(ShapeError, match="image"):
        tr.track(np.zeros((H, W), np.float32))
    with pytest.raises(ConfigError):
        TrackerParams(max_features=2)
    with pytest.raises(ConfigError):
        CameraModel(CAM, "radtan", (0.1,))


@settings(max_examples=30, deadline=None)
@given(
    model=st.sampled_from(["radtan", "equidistant"]),
    k1=st.floats(-0.3, 0.3),
    k2=st.floats(-0.05, 0.05),
    seed=st.integers(0, 1000),
)
def test_undistort_distort_round_trip(model, k1, k2, seed):
    coeffs = (k1, k2, 1e-3, -1e-3) if model == "radtan" else (k1, k2, 0.01, -0.005)
    cam = CameraModel(CAM, model, coeffs)
    rng = np.random.default_rng(seed)
    uv = rng.uniform([40, 30], [W - 40, H - 30], size=(50, 2))
    raw = cam.distort_px(uv)
    np.testing.assert_allclose(cam.undistort_px(raw), uv, atol=1e-2)  # OpenCV's iterations
