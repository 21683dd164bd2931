"""Flow depth prior: two-view triangulation against ray-cast ground truth, gating, helpers."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.depth_prior.flow_prior import (
    FlowPriorParams,
    choose_far_field_reference,
    choose_references,
    compute_flow_prior,
    detect_sky,
    fit_scale_huber,
    ground_depth_bound,
    triangulate_matches,
    two_view_depth,
)
from mogs_node.errors import ConfigError, ShapeError
from mogs_node.geometry import make_T, se3_inverse, so3_exp

sys.path.insert(0, str(Path(__file__).parents[1]))  # tests/: the helpers
from _two_view_scene import CAM, render  # noqa: E402

T0 = np.eye(4)
T1 = make_T(so3_exp(np.array([0.0, 0.02, 0.0])), np.array([0.1, 0.0, 0.8]))
T2 = make_T(so3_exp(np.array([0.0, 0.03, 0.0])), np.array([0.15, 0.0, 1.4]))


@pytest.fixture(scope="module")
def views():
    return {name: render(T) for name, T in (("0", T0), ("1", T1), ("2", T2))}


def _absrel(pred: np.ndarray, gt: np.ndarray, m: np.ndarray) -> np.ndarray:
    return np.abs(pred[m] - gt[m]) / gt[m]


def test_two_view_depth_matches_ground_truth(views) -> None:
    (i0, _), (i1, d1) = views["0"], views["1"]
    r = two_view_depth(i1, i0, CAM.K, se3_inverse(T0) @ T1)
    v = r.valid
    assert r.depth_m.dtype == np.float32 and r.confidence.dtype == np.float32
    assert np.all(r.depth_m[~v] == 0) and np.all((r.confidence >= 0) & (r.confidence <= 1))
    assert v.mean() > 0.5
    err = _absrel(r.depth_m, d1, v)
    assert np.median(err) < 0.02
    assert np.mean(err) < 0.04
    # The confidence ranks errors: confident pixels are more accurate than the rest.
    hi = v & (r.confidence > 0.7)
    lo = v & (r.confidence <= 0.7)
    assert hi.sum() > 1000 and lo.sum() > 100
    assert np.mean(_absrel(r.depth_m, d1, hi)) < np.mean(_absrel(r.depth_m, d1, lo))
    assert r.baseline_m == pytest.approx(np.linalg.norm(T1[:3, 3]))


def test_gates_hold_where_valid(views) -> None:
    (i0, _), (i1, _) = views["0"], views["1"]
    p = FlowPriorParams()
    r = two_view_depth(i1, i0, CAM.K, se3_inverse(T0) @ T1, p)
    v = r.valid
    assert np.all(r.parallax_deg[v] > p.min_parallax_deg)
    assert np.all(r.fb_error_px[v] < p.max_fb_error_px)
    assert np.all(r.epipolar_px[v] < p.max_epipolar_px)
    bound = ground_depth_bound(CAM.K, CAM.height, CAM.width, p)
    assert np.all(r.depth_m[v] <= bound[v])
    # Near the epipole (the focus of expansion) there is no parallax, so no depth.
    e = CAM.K @ (se3_inverse(T0) @ T1)[:3, 3]  # epipole of r in k for forward motion ~ centre
    u0, v0 = int(round(e[0] / e[2])), int(round(e[1] / e[2]))
    assert not v[v0 - 3 : v0 + 4, u0 - 3 : u0 + 4].any()


def test_no_motion_gives_no_depth(views) -> None:
    i0, _ = views["0"]
    r = two_view_depth(i0, i0, CAM.K, np.eye(4))
    assert not r.valid.any()


def test_wrong_pose_is_rejected_by_epipolar_gate(views) -> None:
    (i0, _), (i1, _) = views["0"], views["1"]
    good = two_view_depth(i1, i0, CAM.K, se3_inverse(T0) @ T1)
    wrong = make_T(so3_exp(np.array([0.03, 0.0, 0.0])), np.zeros(3)) @ se3_inverse(T0) @ T1
    bad = two_view_depth(i1, i0, CAM.K, wrong)
    assert bad.valid.mean() < 0.2 * good.valid.mean()


def test_ground_bound_contains_the_ground(views) -> None:
    _, d0 = views["0"]
    p = FlowPriorParams(ground_margin=1.0)
    bound = ground_depth_bound(CAM.K, CAM.height, CAM.width, p)
    assert np.all(d0 <= bound * (1 + 1e-6))
    # Rows below the horizon hit the road: the bound there equals h / ray_y exactly.
    row = CAM.height - 1
    ray_y = (row - CAM.cy_px) / CAM.fy_px
    np.testing.assert_allclose(bound[row], p.camera_height_m / ray_y, rtol=1e-5)
    assert np.all(bound[0] == p.max_depth_m)  # above the horizon only the far cap


def test_two_references_fused(views) -> None:
    (i0, _), (i1, _), (i2, d2) = views["0"], views["1"], views["2"]
    one = compute_flow_prior(i2, CAM.K, T2, [(i1, T1)], FlowPriorParams(sky_mask=False))
    two = compute_flow_prior(i2, CAM.K, T2, [(i1, T1), (i0, T0)], FlowPriorParams(sky_mask=False))
    assert two.stats["n_references"] == 2
    # A static scene: the two pairs agree almost everywhere both see it, so fusing adds coverage.
    assert two.stats["pair_disagreement_fraction"] < 0.02
    assert np.mean(two.confidence > 0) > np.mean(one.confidence > 0)
    kept = ~two.sky & (two.confidence > 0) & (one.confidence > 0)
    assert np.all(two.confidence[kept] >= one.confidence[kept])
    m = two.confidence > 0
    assert np.median(_absrel(two.depth_m, d2, m)) < 0.02
    empty = compute_flow_prior(i2, CAM.K, T2, [])
    assert not empty.depth_m.any() and not empty.confidence.any()


def test_choose_references_by_distance() -> None:
    z = np.array([0.0, 0.1, 0.25, 0.5, 0.8, 1.0, 1.1])
    hist = make_T(np.eye(3)[None].repeat(len(z), 0), np.stack([0 * z, 0 * z, z], -1))
    Tk = make_T(np.eye(3), np.array([0.0, 0.0, 1.2]))
    # distances 1.2, 1.1, 0.95, 0.7, 0.4, 0.2, 0.1 -> nearest >= 0.3 is index 4 (0.4 m);
    # the second is the one closest to 1.0 m among those >= 0.6 m: index 2 (0.95 m).
    assert choose_references(Tk, hist, FlowPriorParams()) == [4, 2]
    assert choose_references(Tk, hist, FlowPriorParams(far_baseline_m=0)) == [4]
    # a second reference further back than max_far_baseline_m is not taken
    near = FlowPriorParams(far_baseline_m=0.9, max_far_baseline_m=0.9)  # 0.95 m is too far
    assert choose_references(Tk, hist, near) == [4, 3]
    assert choose_references(
        Tk, hist, replace(near, far_baseline_m=0.5, max_far_baseline_m=0.65)
    ) == [4]
    with pytest.raises(ConfigError, match="max_far_baseline_m"):
        FlowPriorParams(far_baseline_m=1.0, max_far_baseline_m=0.5)
    assert choose_references(Tk, hist[-2:], FlowPriorParams()) == []  # standing still
    assert choose_references(Tk, np.zeros((0, 4, 4))) == []


def test_detect_sky() -> None:
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (CAM.height, CAM.width), dtype=np.uint8)
    img[:40] = 220  # flat bright band at the top, above the horizon (cy = 79.5)
    img[100:130, 10:60] = 230  # flat bright patch below the horizon: road glare, not sky
    sky = detect_sky(img, CAM.K, FlowPriorParams())
    assert sky[:35].mean() > 0.95
    assert not sky[45:].any()


@settings(max_examples=40, deadline=None)
@given(
    scale=st.floats(0.05, 20.0),
    outlier_frac=st.floats(0.0, 0.3),
    seed=st.integers(0, 2**31 - 1),
)
def test_fit_scale_huber_recovers_scale_despite_outliers(scale, outlier_frac, seed) -> None:
    rng = np.random.default_rng(seed)
    n = 400
    target = rng.uniform(2.0, 60.0, n)
    depth = target / scale * (1 + rng.normal(0, 0.01, n))
    k = int(outlier_frac * n)
    depth[:k] *= rng.uniform(2.0, 5.0, k)  # gross outliers, all biased the same way
    s = fit_scale_huber(depth, target, delta_rel=0.05)
    # One-sided outliers bias a Huber estimate by at most delta * k / (n - k) in log scale.
    bias = 0.05 * k / (n - k)
    assert abs(np.log(s / scale)) < bias + 0.005
    # Plain least squares on the same data would be far off whenever there are outliers.
    if k >= 40:
        s_ls = np.sum(depth * target) / np.sum(depth * depth)
        assert abs(np.log(s_ls / scale)) > 2 * (bias + 0.005)


def test_fit_scale_huber_degenerate_and_shapes() -> None:
    assert np.isnan(fit_scale_huber(np.zeros(5), np.ones(5)))
    with pytest.raises(ShapeError, match="target_m"):
        fit_scale_huber(np.ones(5), np.ones(4))


def test_bad_arguments(views) -> None:
    i0, _ = views["0"]
    with pytest.raises(ShapeError, match="image_r"):
        two_view_depth(i0, i0[:, :-1], CAM.K, np.eye(4))
    with pytest.raises(ShapeError, match="T_r_k"):
        two_view_depth(i0, i0, CAM.K, np.eye(3))
    with pytest.raises(ShapeError, match="image_k"):
        two_view_depth(i0.astype(np.float32), i0, CAM.K, np.eye(4))
    with pytest.raises(ConfigError, match="dis_preset"):
        FlowPriorParams(dis_preset="slow")


def _reference_triangulation(uv_k, uv_r, K, T_r_k) -> np.ndarray:
    """Slow reference: OpenCV DLT triangulation in float64, z-depth in k."""
    import cv2

    P_k = K @ np.eye(3, 4)
    P_r = K @ T_r_k[:3]
    X = cv2.triangulatePoints(P_k, P_r, uv_k.T.astype(np.float64), uv_r.T.astype(np.float64))
    return X[2] / X[3]


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    baseline=st.floats(0.2, 3.0),
    yaw=st.floats(-0.1, 0.1),
)
def test_triangulate_matches_exact_and_matches_reference(seed, baseline, yaw) -> None:
    rng = np.random.default_rng(seed)
    n = 300
    uv_k = np.c_[rng.uniform(0, CAM.width, n), rng.uniform(0, CAM.height, n)]
    depth = rng.uniform(2.0, 60.0, n)
    direction = rng.normal(size=3) * np.array([0.3, 0.1, 1.0])
    direction /= np.linalg.norm(direction)
    T_k_r = make_T(so3_exp(np.array([0.0, yaw, 0.0])), baseline * direction)
    T_r_k = se3_inverse(T_k_r)
    X_r = CAM.backproject(uv_k, depth) @ T_r_k[:3, :3].T + T_r_k[:3, 3]
    uv_r, front = CAM.project(X_r)
    d, z_r, par, epi = triangulate_matches(
        uv_k[:, 0], uv_k[:, 1], uv_r[:, 0], uv_r[:, 1], CAM.K, T_r_k
    )
    assert d.dtype == np.float32 and par.dtype == np.float32
    ok = front & (par > 0.5)  # enough parallax for float32 to resolve the depth
    if ok.sum() < 10:
        return
    np.testing.assert_allclose(d[ok], depth[ok], rtol=2e-3)
    np.testing.assert_allclose(z_r[ok], X_r[ok, 2], rtol=2e-3, atol=1e-3)
    assert np.all(epi[ok] < 0.05)
    ref = _reference_triangulation(uv_k[ok], uv_r[ok], CAM.K, T_r_k)
    np.testing.assert_allclose(d[ok], ref, rtol=2e-3)
    # A match pushed off its epipolar line by 3 px reports that distance.
    X_far = CAM.backproject(uv_k[ok][:1], depth[ok][:1] * 1.5) @ T_r_k[:3, :3].T + T_r_k[:3, 3]
    line_dir = uv_r[ok][0] - CAM.project(X_far)[0][0]  # along the epipolar line
    normal = np.array([-line_dir[1], line_dir[0]]) / np.linalg.norm(line_dir)
    moved = uv_r[ok][0] + 3.0 * normal
    *_, e = triangulate_matches(
        uv_k[ok][:1, 0], uv_k[ok][:1, 1], moved[None, 0], moved[None, 1], CAM.K, T_r_k
    )
    assert e[0] == pytest.approx(3.0, abs=0.05)


def test_motion_boundary_gate_removes_pixels_at_depth_edges(views) -> None:
    (i0, _), (i1, d1) = views["0"], views["1"]
    T = se3_inverse(T0) @ T1
    plain = two_view_depth(i1, i0, CAM.K, T)
    gated = two_view_depth(i1, i0, CAM.K, T, FlowPriorParams(max_flow_gradient=0.3))
    assert not np.any(gated.valid & ~plain.valid)  # the gate only removes pixels
    removed = plain.valid & ~gated.valid
    assert removed.sum() > 0
    # The removed pixels lie near depth discontinuities of the ground truth (facade/road edges).
    import cv2

    edge = np.abs(cv2.Laplacian(np.log(d1), cv2.CV_64F)) > 0.05
    near_edge = cv2.dilate(edge.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    assert near_edge[removed].mean() > near_edge[plain.valid].mean()


def test_choose_far_field_reference() -> None:
    """The entry nearest ``far_field_baseline_m`` back, beyond 1.5x every chosen reference and
    within ``max_far_field_baseline_m``; None when off, without references or without one."""
    z = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 4.6])
    hist = make_T(np.eye(3)[None].repeat(len(z), 0), np.stack([0 * z, 0 * z, z], -1))
    Tk = make_T(np.eye(3), np.array([0.0, 0.0, 5.0]))  # distances 5, 4, 3, 2, 1, 0.4
    on = FlowPriorParams(far_field_baseline_m=3.0)
    assert choose_far_field_reference(Tk, hist, [5, 4], on) == 2
    assert choose_far_field_reference(Tk, hist, [4], replace(on, far_field_baseline_m=4.4)) == 1
    # 1.5x the farthest chosen reference (2 m -> 3 m) rules out the nearer entries
    assert choose_far_field_reference(Tk, hist, [3], replace(on, far_field_baseline_m=2.0)) == 2
    assert choose_far_field_reference(Tk, hist, [5], replace(on, max_far_field_baseline_m=3.5)) == 2
    assert (
        choose_far_field_reference(Tk, hist, [2], replace(on, max_far_field_baseline_m=4.0)) is None
    )
    assert choose_far_field_reference(Tk, hist, [], on) is None
    assert choose_far_field_reference(Tk, hist, [5], FlowPriorParams()) is None  # off
    with pytest.raises(ConfigError, match="far_field"):
        FlowPriorParams(far_field_baseline_m=9.0, max_far_field_baseline_m=8.0)
    with pytest.raises(ConfigError, match="far_field"):
        FlowPriorParams(far_field_baseline_m=-1.0)


def test_far_field_reference_fills_only_where_the_nearest_pair_was_below_the_gate(views) -> None:
    """A near reference 0.4 m back leaves part of the scene below a 1 deg parallax gate
    (forward-backward consistent: the motion was measured); the far-field reference 1.4 m back
    gives it depth there, accurate, and changes nothing where the near pair had depth."""
    (i0, _), (i2, d2) = views["0"], views["2"]
    T_near = make_T(so3_exp(np.array([0.0, 0.03, 0.0])), np.array([0.15, 0.0, 1.0]))
    i_near, _ = render(T_near)
    p = FlowPriorParams(sky_mask=False, min_parallax_deg=1.0)
    near = compute_flow_prior(i2, CAM.K, T2, [(i_near, T_near)], p)
    both = compute_flow_prior(i2, CAM.K, T2, [(i_near, T_near)], p, far_field=(i0, T0))
    slow = np.isfinite(near.pairs[0].parallax_deg) & (near.pairs[0].parallax_deg <= 1.0)
    new = (both.confidence > 0) & (near.confidence == 0)
    assert new.mean() > 0.1 and not np.any(new & ~slow)
    had = near.confidence > 0
    assert had.mean() > 0.2
    np.testing.assert_array_equal(both.depth_m[had], near.depth_m[had])
    np.testing.assert_array_equal(both.confidence[had], near.confidence[had])
    assert both.stats["far_field_fraction"] == pytest.approx(new.mean())
    assert near.stats["far_field_fraction"] == 0.0
    assert np.median(_absrel(both.depth_m, d2, new)) < 0.03
