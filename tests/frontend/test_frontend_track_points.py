"""Sparse keyframe points from the dense tracks: triangulation (DLT + Gauss-Newton), gates,
depth-edge tests, carry-forward at standstill (mogs_node/frontend/track_points.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.frontend import Frontend, FrontendParams
from mogs_node.frontend.reobserve import (
    carry_forward,
    merge_points,
    reobserved_points,
    reproject_points,
)
from mogs_node.frontend.track_points import (
    KeyframePoints,
    TrackHistory,
    TrackPointsParams,
    depth_edge_flags,
    epipole_cell_caps,
    gate_points,
    keyframe_points,
    patch_match,
    refine_points,
    triangulate_dlt,
    triangulate_on_ray,
    unsupported_depth_flags,
)
from mogs_node.frontend.tracker import FeatureTracker
from mogs_node.frontend.triangulation import RefineParams
from mogs_node.geometry import PinholeCamera, make_T, se3_inverse, so3_exp, transform_points

CAM = PinholeCamera(360.77, 361.73, 304.53, 86.41, 621, 188)


def _poses(n_views: int, step_m: float = 1.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """Camera poses in the reference (last view) frame: driving forward with a little sway."""
    rng = rng or np.random.default_rng(0)
    T = []
    for k in range(n_views):
        back = n_views - 1 - k
        R = so3_exp(rng.normal(0, 0.01, 3)) if k < n_views - 1 else np.eye(3)
        t = step_m * np.array([0.2 * np.sin(back), 0.05 * back, -back])
        T.append(make_T(R, t))
    return np.stack(T)


def _project(points_ref: np.ndarray, T_ref_cams: np.ndarray) -> np.ndarray:
    uv = np.full((len(points_ref), len(T_ref_cams), 2), np.nan)
    for f, T in enumerate(T_ref_cams):
        pc = transform_points(se3_inverse(T), points_ref)
        uv[:, f], front = CAM.project(pc)
        uv[~front, f] = np.nan
    return uv


def _scene(n: int, rng: np.random.Generator, z_range=(4.0, 40.0)) -> np.ndarray:
    z = rng.uniform(*z_range, n)
    uv = np.stack([rng.uniform(20, 600, n), rng.uniform(10, 178, n)], 1)
    return CAM.backproject(uv, z)


def test_noise_free_multi_view_points_are_recovered_exactly():
    rng = np.random.default_rng(1)
    X = _scene(200, rng)
    T = _poses(6, rng=rng)
    uv = _project(X, T)
    X0 = triangulate_dlt(uv, T, CAM)
    np.testing.assert_allclose(X0, X, rtol=1e-7)
    pts = refine_points(uv, T, CAM, X0 * 1.05)  # refinement from a 5 % wrong start
    np.testing.assert_allclose(pts.xyz_ref_m, X, rtol=1e-7)
    assert np.all(pts.reproj_max_px < 1e-6)
    assert np.all(pts.n_views == 6) and np.all(pts.in_front)
    params = TrackPointsParams()
    keep, omega = gate_points(pts, params)
    assert keep.mean() > 0.7 and np.all((omega[keep] > 0) & (omega[keep] <= 1))
    # what is dropped is dropped for its geometry: too little parallax or too uncertain a depth
    rel = pts.depth_sigma_m / pts.xyz_ref_m[:, 2]
    weak = (pts.parallax_deg < params.min_parallax_deg) | (rel > params.max_depth_rel_sigma)
    np.testing.assert_array_equal(keep, ~weak)


def test_noisy_points_have_percent_level_error_and_a_covariance_that_matches_it():
    rng = np.random.default_rng(2)
    X = _scene(400, rng, (5.0, 25.0))
    T = _poses(8, rng=rng)
    uv = _project(X, T) + rng.normal(0, 0.3, (400, 8, 2))
    pts = refine_points(uv, T, CAM, triangulate_dlt(uv, T, CAM), RefineParams(pixel_sigma_px=0.3))
    keep, _ = gate_points(pts, TrackPointsParams())
    rel = np.abs(pts.xyz_ref_m[keep, 2] - X[keep, 2]) / X[keep, 2]
    assert keep.mean() > 0.5
    assert np.median(rel) < 0.01
    # the depth sigma from the Jacobian describes the actual errors (normalised spread ~ 1)
    zscore = (pts.xyz_ref_m[keep, 2] - X[keep, 2]) / pts.depth_sigma_m[keep]
    assert 0.6 < np.std(zscore) < 1.6


def test_low_parallax_points_are_gated_out():
    rng = np.random.default_rng(3)
    near = _scene(50, rng, (5.0, 10.0))
    far = _scene(50, rng, (5000.0, 9000.0))  # 5 m of baseline: < 0.06 degrees
    T = _poses(6, rng=rng)
    X = np.concatenate([near, far])
    uv = _project(X, T)
    pts = refine_points(uv, T, CAM, triangulate_dlt(uv, T, CAM))
    keep, omega = gate_points(pts, TrackPointsParams(max_depth_m=1e5))
    assert keep[:50].mean() >= 0.9  # (a few near the epipole have too little parallax)
    assert not keep[50:].any() and np.all(omega[50:] == 0)
    assert np.all(pts.parallax_deg[50:] < 0.1)


def test_a_track_that_slides_along_an_occluding_edge_is_rejected_by_its_reprojection_error():
    rng = np.random.default_rng(4)
    X = _scene(20, rng, (8.0, 12.0))
    T = _poses(6, rng=rng)
    uv = _project(X, T)
    uv[:5, :3, 0] += np.array([6.0, 4.0, 2.0])  # a T-junction drifts along the edge
    pts = refine_points(uv, T, CAM, triangulate_dlt(uv, T, CAM))
    keep, _ = gate_points(pts, TrackPointsParams())
    assert not keep[:5].any() and keep[5:].mean() >= 0.8
    assert np.all(pts.reproj_max_px[:5] > 1.0)


def test_unsupported_depth_flags_drop_a_straddling_point_and_keep_both_sides():
    """Round 9: a wall at 10 m (u < 300) beside one at 20 m, points every 6 px, plus tracks on
    the contour that triangulated between the two (14 m): only those are dropped; points by
    the silhouette whose own side agrees, and a lone point, are kept."""
    u, v = np.meshgrid(np.arange(200, 400, 6.0), np.arange(40, 140, 6.0))
    uv = np.stack([u.ravel(), v.ravel()], 1)
    z = np.where(uv[:, 0] < 300, 10.0, 20.0)
    straddling = np.stack([np.full(5, 300.0), np.arange(43.0, 140.0, 24.0)], 1)
    lone = np.array([[600.0, 20.0]])
    uv_all = np.concatenate([uv, straddling, lone])
    z_all = np.concatenate([z, np.full(len(straddling), 14.0), [50.0]])
    flags = unsupported_depth_flags(uv_all, z_all, radius_px=8.0, rel_jump=0.05)
    np.testing.assert_array_equal(flags[: len(uv)], False)
    assert flags[len(uv) : -1].all() and not flags[-1]
    # the older rule drops both sides of the jump as well
    assert depth_edge_flags(uv_all, z_all, radius_px=8.0, rel_jump=0.05)[: len(uv)].sum() > 30
    assert not unsupported_depth_flags(uv[:1], z[:1], radius_px=8.0, rel_jump=0.05).any()
    with pytest.raises(ShapeError):
        unsupported_depth_flags(uv, z[:-1], radius_px=8.0, rel_jump=0.05)


def test_depth_edge_flags_mark_both_sides_of_a_depth_jump_only():
    # a fronto-parallel wall at 10 m (u < 300) next to one at 20 m (u >= 300), points every 6 px
    u, v = np.meshgrid(np.arange(200, 400, 6.0), np.arange(40, 140, 6.0))
    uv = np.stack([u.ravel(), v.ravel()], 1)
    z = np.where(uv[:, 0] < 300, 10.0, 20.0)
    flags = depth_edge_flags(uv, z, radius_px=8.0, rel_jump=0.1)
    near_edge = np.abs(uv[:, 0] - 299) <= 8
    assert flags[near_edge & (uv[:, 0] < 300)].all() and flags[near_edge & (uv[:, 0] >= 300)].all()
    np.testing.assert_array_equal(flags[~near_edge], False)
    # a smooth slope (3 % between neighbours) is no edge
    assert not depth_edge_flags(uv, 10.0 * 1.03 ** (uv[:, 0] / 6), radius_px=8, rel_jump=0.1).any()


def test_patch_check_rejects_a_patch_across_a_depth_edge():
    rng = np.random.default_rng(5)
    fg = rng.integers(0, 255, (188, 621)).astype(np.uint8)
    bg = rng.integers(0, 255, (188, 621)).astype(np.uint8)
    # reference: foreground texture left of u = 300; the other view: foreground moved 6 px left,
    # background moved 1 px left (a depth edge between them)
    ref = np.where(np.arange(621)[None] < 300, fg, bg)
    view = np.where(np.arange(621)[None] < 294, np.roll(fg, -6, 1), np.roll(bg, -1, 1))
    uv_ref = np.array([[250.0, 90.0], [299.0, 90.0], [300.0, 60.0]])
    uv_view = uv_ref - [6.0, 0.0]  # all tracked with the foreground's motion
    z = patch_match(ref, uv_ref, view, uv_view, np.ones(3), 3)[0]
    assert z[0] > 0.99
    assert z[1] < 0.8 and z[2] < 0.8


def _points(uv: np.ndarray, z: np.ndarray, ids: np.ndarray) -> KeyframePoints:
    return KeyframePoints(
        ids.astype(np.int64),
        uv.astype(np.float32),
        CAM.backproject(uv, z).astype(np.float32),
        np.tile(np.eye(3, dtype=np.float32) * 1e-4, (len(uv), 1, 1)),
        np.full(len(uv), 0.5, np.float32),
    )


def test_reprojected_points_keep_what_is_still_seen_and_drop_what_is_covered():
    rng = np.random.default_rng(11)
    prev_img = rng.integers(0, 255, (188, 621)).astype(np.uint8)
    u, v = np.meshgrid(np.arange(20.0, 600, 15), np.arange(20.0, 170, 15))
    uv = np.stack([u.ravel(), v.ravel()], 1)
    prev = _points(uv, np.full(len(uv), 12.0), np.arange(len(uv)))
    # the camera moved sideways (the wall at 12 m shifts 2 px to the right in the new image);
    # an occluder now covers u < 200 of the new image
    step_m = 2.0 * 12.0 / CAM.fx_px
    T_cur_prev = make_T(np.eye(3), np.array([step_m, 0.0, 0.0]))
    xyz = transform_points(T_cur_prev, prev.xyz_cam_m.astype(np.float64))
    new_uv, _ = CAM.project(xyz)
    shift = float(np.median(new_uv[:, 0] - uv[:, 0]))
    np.testing.assert_allclose(new_uv[:, 0] - uv[:, 0], 2.0, atol=1e-4)
    cur_img = np.roll(prev_img, 2, axis=1)
    cur_img[:, :200] = rng.integers(0, 255, (188, 200)).astype(np.uint8)
    out = reproject_points(prev, T_cur_prev, CAM, prev_img, cur_img, radius_px=3, min_zncc=0.9)
    kept_u = prev.uv_px[np.searchsorted(prev.ids, out.ids), 0]
    assert np.all(kept_u + shift >= 200 - 4)  # nothing under the occluder
    assert np.sum(uv[:, 0] + shift > 205) - len(out) <= 2  # (nearly) all the rest kept
    np.testing.assert_allclose(out.xyz_cam_m, xyz[out.ids].astype(np.float32), atol=1e-5)
    np.testing.assert_allclose(out.uv_px, new_uv[out.ids], atol=1e-3)
    # a wrong relative pose (the points land 6 px off their texture) keeps nothing
    T_bad = make_T(np.eye(3), np.array([4 * step_m, 0.0, 0.0]))
    bad = reproject_points(prev, T_bad, CAM, prev_img, cur_img, radius_px=3, min_zncc=0.9)
    assert len(bad) <= 2


def test_merge_adds_only_new_separate_and_depth_consistent_points():
    fresh = _points(np.array([[100.0, 50], [200, 50], [300, 50]]), np.full(3, 10.0), np.arange(3))
    old = _points(
        np.array([[100.0, 90], [202, 51], [400, 50], [305, 52], [500, 120]]),
        np.array([9.0, 10.0, 10.0, 30.0, 20.0]),
        np.array([0, 10, 11, 12, 13]),  # id 0: the same track as a fresh point
    )
    p = TrackPointsParams()
    out = merge_points(fresh, old, min_distance_px=5.0, params=p)
    # id 10 lies 2 px from a fresh point; id 12 sits 5.8 px from a fresh point at a third of its
    # depth (a depth edge); ids 11 and 13 are added
    np.testing.assert_array_equal(out.ids, [0, 1, 2, 11, 13])
    np.testing.assert_array_equal(out.xyz_cam_m[:3], fresh.xyz_cam_m)
    assert merge_points(fresh, KeyframePoints.empty(), min_distance_px=5.0, params=p) is fresh
    empty = merge_points(KeyframePoints.empty(), old, min_distance_px=5.0, params=p)
    np.testing.assert_array_equal(empty.ids, old.ids)  # nothing fresh to clash with


def test_carry_forward_moves_points_into_the_new_camera_exactly():
    rng = np.random.default_rng(6)
    X = _scene(100, rng)
    prev = KeyframePoints(
        np.arange(100),
        CAM.project(X)[0].astype(np.float32),
        X.astype(np.float32),
        np.tile(np.eye(3, dtype=np.float32) * 0.01, (100, 1, 1)),
        np.full(100, 0.5, np.float32),
    )
    T_cur_prev = make_T(so3_exp(np.array([0.0, 0.02, 0.0])), np.array([0.0, 0.0, -0.3]))
    cur = carry_forward(prev, T_cur_prev, CAM)
    assert cur.carried and len(cur) >= 90
    np.testing.assert_allclose(
        cur.xyz_cam_m, transform_points(T_cur_prev, X[cur.ids]).astype(np.float32), rtol=1e-6
    )
    np.testing.assert_allclose(cur.uv_px, CAM.project(cur.xyz_cam_m.astype(float))[0], atol=1e-3)
    same = carry_forward(prev, np.eye(4), CAM)
    np.testing.assert_allclose(same.xyz_cam_m, prev.xyz_cam_m)


def test_history_and_keyframe_points_on_exact_tracks():
    rng = np.random.default_rng(7)
    X_world = _scene(300, rng, (5.0, 30.0))  # world = the last camera's frame
    T = _poses(8, rng=rng)
    uv = _project(X_world, T)
    hist = TrackHistory(10)
    for f in range(8):
        seen = np.flatnonzero(np.isfinite(uv[:, f, 0]))
        order = rng.permutation(len(seen))  # any order of ids
        hist.add(1000 + f, seen[order], uv[seen[order], f])
        hist.set_pose(1000 + f, T[f])
    # random points, no surfaces: the neighbour-depth test is off (a tiny radius)
    pts = keyframe_points(hist, CAM, TrackPointsParams(min_patch_zncc=-1.0, edge_radius_px=1e-3))
    assert len(pts) > 150
    np.testing.assert_allclose(pts.xyz_cam_m, X_world[pts.ids], rtol=1e-4)
    np.testing.assert_allclose(pts.uv_px, uv[pts.ids, -1], atol=1e-3)
    # every view (no thinning of the older frames): the same exact points
    every = keyframe_points(
        hist, CAM, TrackPointsParams(min_patch_zncc=-1.0, edge_radius_px=1e-3, view_stride=1)
    )
    np.testing.assert_allclose(every.xyz_cam_m, X_world[every.ids], rtol=1e-4)
    with pytest.raises(ConfigError):
        TrackPointsParams(view_stride=0)
    with pytest.raises(ConfigError, match="edge_rule"):
        TrackPointsParams(edge_rule="neither")
    # a newest frame without a pose gives nothing (yet)
    hist.add(2000, np.arange(5), np.zeros((5, 2)))
    assert len(keyframe_points(hist, CAM, TrackPointsParams())) == 0


def test_bucketing_caps_every_cell_and_spreads_tracks():
    from mogs_node.sim import SimConfig, make_sequence

    seq = make_sequence(SimConfig(seed=0, n_frames=1, width=621, height=188))
    params = TrackPointsParams()
    tp = params.tracker()
    tr = FeatureTracker(tp, CameraModel(seq.camera)).track(seq.render(0).rgb)
    cx = np.minimum((tr.uv_raw_px[:, 0] * tp.bucket_cols / 621).astype(int), tp.bucket_cols - 1)
    cy = np.minimum((tr.uv_raw_px[:, 1] * tp.bucket_rows / 188).astype(int), tp.bucket_rows - 1)
    counts = np.bincount(cy * tp.bucket_cols + cx, minlength=tp.bucket_cols * tp.bucket_rows)
    assert counts.max() <= tp.bucket_cap
    assert len(tr.ids) > 300
    assert np.count_nonzero(counts) >= 0.6 * len(counts)  # sky and blank road excepted


def test_params_are_validated_and_bad_shapes_are_named():
    with pytest.raises(ConfigError):
        TrackPointsParams(min_views=1)
    with pytest.raises(ConfigError):
        TrackPointsParams(min_depth_m=5.0, max_depth_m=1.0)
    with pytest.raises(ShapeError, match="T_ref_cams"):
        triangulate_dlt(np.zeros((3, 4, 2)), np.tile(np.eye(4), (3, 1, 1)), CAM)
    with pytest.raises(ShapeError, match="uv_px"):
        triangulate_dlt(np.zeros((3, 4)), np.tile(np.eye(4), (4, 1, 1)), CAM)


def test_a_keyframe_with_too_few_fresh_points_carries_the_previous_ones():
    fe = Frontend(FrontendParams(), CameraModel(CAM), np.eye(4))
    rng = np.random.default_rng(8)
    X = _scene(60, rng)
    prev = KeyframePoints(
        np.arange(60),
        CAM.project(X)[0].astype(np.float32),
        X.astype(np.float32),
        np.zeros((60, 3, 3), np.float32),
        np.ones(60, np.float32),
    )
    T_prev = make_T(np.eye(3), np.array([1.0, 2.0, 3.0]))
    fe._last_points = (T_prev, prev)
    T_now = make_T(np.eye(3), np.array([1.0, 2.0, 3.1]))  # 10 cm on: no fresh points
    pts = fe._keyframe_points(T_now)
    assert pts.carried and len(pts) > 50
    np.testing.assert_allclose(pts.xyz_cam_m[:, 2], X[pts.ids, 2] - 0.1, atol=1e-5)
    # moving on (1 m): occluders may have moved over the old points, nothing is carried
    fe._last_points = (T_prev, prev)
    assert len(fe._keyframe_points(make_T(np.eye(3), np.array([1.0, 2.0, 4.0])))) == 0


finite = st.floats(-1e6, 1e6, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(
    n_views=st.integers(2, 6),
    depth_m=st.floats(1e-2, 1e4),
    step_m=st.floats(0.0, 5.0),
    nan_share=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**16),
)
def test_triangulation_is_finite_or_omitted_at_the_edges(n_views, depth_m, step_m, nan_share, seed):
    """2 views, tiny and huge depths, no baseline at all, NaN pixels: never an exception, never a
    non-finite point through the gates, and gated points are in front with positive weight."""
    rng = np.random.default_rng(seed)
    uv_kf = np.stack([rng.uniform(0, 621, 30), rng.uniform(0, 188, 30)], 1)
    X = CAM.backproject(uv_kf, np.full(30, depth_m) * rng.uniform(0.5, 2.0, 30))
    T = _poses(n_views, step_m=step_m, rng=rng)
    uv = _project(X, T)
    uv[rng.random(uv.shape[:2]) < nan_share] = np.nan
    X0 = triangulate_dlt(uv, T, CAM)
    pts = refine_points(uv, T, CAM, X0)
    keep, omega = gate_points(pts, dataclasses.replace(TrackPointsParams(), min_views=2))
    assert np.all(np.isfinite(pts.xyz_ref_m[keep])) and np.all(pts.xyz_ref_m[keep, 2] > 0)
    assert np.all(np.isfinite(omega)) and np.all((omega[keep] > 0) & (omega[keep] <= 1))
    assert np.all(omega[~keep] == 0)
    if step_m == 0.0:  # no baseline: nothing can be triangulated
        assert not keep.any()
    flags = depth_edge_flags(uv_kf[keep], pts.xyz_ref_m[keep, 2], radius_px=8.0, rel_jump=0.1)
    assert flags.shape == (keep.sum(),)


def test_dense_tracker_options_are_validated_and_track_without_the_backward_pass():
    from mogs_node.frontend.tracker import TrackerParams
    from mogs_node.sim import SimConfig, make_sequence

    for bad in ({"bucket_cap": -1}, {"klt_max_iter": 0}, {"top_up_every": 0}, {"top_up_below": 0}):
        with pytest.raises(ConfigError):
            TrackerParams(**bad)
    seq = make_sequence(SimConfig(seed=0, n_frames=3, width=621, height=188))
    tr = FeatureTracker(TrackPointsParams(top_up_every=2).tracker(), CameraModel(seq.camera))
    first = tr.track(seq.render(0).rgb)
    second = tr.track(seq.render(1).rgb)
    assert second.n_tracked >= 0.7 * len(first.ids)  # 1 m of driving between the frames
    kept = np.isin(first.ids, second.ids)
    assert np.all(np.isfinite(second.uv_px)) and kept.sum() == len(second.ids) <= second.n_tracked
    # new corners come every 2nd frame only: frame 1 has none, frame 2 has some
    assert second.ids.max() <= first.ids.max()
    third = tr.track(seq.render(2).rgb)
    assert third.ids.max() > first.ids.max()


def test_linear_triangulation_along_the_keyframe_ray_matches_the_dlt():
    """Round 13: the start of the refinement from the keyframe's ray (one unknown, closed form)
    gives the DLT's exact points on exact tracks, and after the Gauss-Newton refinement the same
    gated points on noisy ones."""
    rng = np.random.default_rng(21)
    X = _scene(300, rng, (4.0, 40.0))
    T = _poses(7, rng=rng)
    uv = _project(X, T)
    np.testing.assert_allclose(triangulate_on_ray(uv, T, CAM), X, rtol=1e-7)
    noisy = uv + rng.normal(0, 0.3, uv.shape)
    params = RefineParams(iterations=1, pixel_sigma_px=0.5)
    a = refine_points(noisy, T, CAM, triangulate_dlt(noisy, T, CAM), params)
    b = refine_points(noisy, T, CAM, triangulate_on_ray(noisy, T, CAM), params)
    keep_a, _ = gate_points(a, TrackPointsParams())
    keep_b, _ = gate_points(b, TrackPointsParams())
    assert keep_a.sum() > 150 and (keep_a != keep_b).sum() <= 2
    both = keep_a & keep_b
    np.testing.assert_allclose(b.xyz_ref_m[both], a.xyz_ref_m[both], rtol=2e-3)
    # no keyframe observation, or no other view: NaN; a point behind the cameras: NaN
    no_ref, alone = uv[:3].copy(), uv[3:6].copy()
    no_ref[:, -1] = np.nan
    alone[:, :-1] = np.nan
    behind = uv[6:9].copy()
    behind[:, :-1] = 2 * behind[:, -1:] - behind[:, :-1]  # the flow reversed: X behind
    out = triangulate_on_ray(np.concatenate([no_ref, alone, behind]), T, CAM)
    assert np.all(np.isnan(out))
    with pytest.raises(ValueError, match="identity"):
        triangulate_on_ray(uv, T[::-1], CAM)  # the last view is not the reference camera


@settings(max_examples=60, deadline=None)
@given(
    depth_m=st.floats(1e-2, 1e3),
    step_m=st.floats(0.0, 5.0),
    nan_share=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**16),
)
def test_linear_triangulation_along_the_ray_is_finite_in_front_or_nan(
    depth_m, step_m, nan_share, seed
):
    rng = np.random.default_rng(seed)
    uv_kf = np.stack([rng.uniform(0, 621, 30), rng.uniform(0, 188, 30)], 1)
    X = CAM.backproject(uv_kf, np.full(30, depth_m) * rng.uniform(0.5, 2.0, 30))
    T = _poses(5, step_m=step_m, rng=rng)
    uv = _project(X, T)
    uv[rng.random(uv.shape[:2]) < nan_share] = np.nan
    out = triangulate_on_ray(uv, T, CAM)
    finite = np.all(np.isfinite(out), axis=1)
    assert np.all(np.isnan(out[~finite]))
    assert np.all(out[finite, 2] > 0)
    if step_m == 0.0:
        assert not finite.any()  # no baseline: no point


@settings(max_examples=60, deadline=None)
@given(scale=st.floats(1e-6, 1e6), seed=st.integers(0, 2**16))
def test_inverse_of_3x3_stacks_matches_lapack(scale, seed):
    from mogs_node.frontend.triangulation import _inv3

    rng = np.random.default_rng(seed)
    A = rng.normal(size=(50, 3, 3))
    A = scale * (A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3))  # well-conditioned, any scale
    np.testing.assert_allclose(_inv3(A) @ A, np.broadcast_to(np.eye(3), A.shape), atol=1e-6)
    singular = np.zeros((1, 3, 3))
    assert not np.all(np.isfinite(_inv3(singular)))


def test_reobserved_points_in_one_pass_match_merging_keyframe_by_keyframe():
    """Round 13: two recent keyframes' points joining the fresh ones in one pass give what
    reproject_points + merge_points per keyframe give (newest first), where every track has
    one copy; a track in both keyframes joins with the newest keyframe's copy."""
    rng = np.random.default_rng(31)
    img = rng.integers(0, 255, (188, 621)).astype(np.uint8)
    p = TrackPointsParams(min_distance_px=4, reproject_min_zncc=0.9)
    u, v = np.meshgrid(np.arange(20.0, 600, 10), np.arange(20.0, 170, 10))
    uv = np.stack([u.ravel(), v.ravel()], 1)
    n = len(uv)
    z = np.where(uv[:, 0] < 300, 12.0, 30.0)  # two walls: a depth edge at u = 300
    fresh = _points(uv[::3], z[::3], np.arange(0, n, 3))
    older = _points(uv[1::3], z[1::3], np.arange(1, n, 3))
    newer = _points(uv[2::3], z[2::3], np.arange(2, n, 3))
    T = np.eye(4)  # the camera did not move: every patch matches
    recent = [(T, older, img), (T, newer, img)]
    one = reobserved_points(fresh, recent, T, CAM, img, p)
    seq = fresh
    for T_prev, prev, image_prev in reversed(recent):
        old = reproject_points(prev, T_prev, CAM, image_prev, img, radius_px=3, min_zncc=0.9)
        seq = merge_points(seq, old, min_distance_px=p.min_distance_px, params=p)
    assert len(one) > len(fresh)
    np.testing.assert_array_equal(np.sort(one.ids), np.sort(seq.ids))
    np.testing.assert_array_equal(one.ids[: len(fresh)], fresh.ids)
    # the same track in both keyframes, 8 px apart: the newer keyframe's copy joins
    dup_new = _points(np.array([[400.0, 100.0]]), np.array([30.0]), np.array([999]))
    dup_old = _points(np.array([[408.0, 100.0]]), np.array([30.0]), np.array([999]))
    out = reobserved_points(
        KeyframePoints.empty(), [(T, dup_old, img), (T, dup_new, img)], T, CAM, img, p
    )
    np.testing.assert_array_equal(out.ids, [999])
    np.testing.assert_allclose(out.uv_px, [[400.0, 100.0]])
    assert reobserved_points(fresh, [], T, CAM, img, p) is fresh


def test_epipole_cell_caps_thin_the_focus_of_expansion_only_when_driving_forward():
    p = TrackPointsParams(max_tracks=1600, epipole_radius_deg=10.0, epipole_cap_share=0.25)
    cap = p.bucket_cap()
    caps = epipole_cell_caps(CAM, np.array([0.0, 0.0, 10.0]), p)
    assert caps.shape == (p.bucket_rows, p.bucket_cols)
    low = caps < cap
    # straight ahead: the cells around the principal point (304, 86) and no others
    rows, cols = np.nonzero(low)
    assert set(cols.tolist()) <= {6, 7, 8, 9} and set(rows.tolist()) <= {1, 2, 3}
    assert low[2, 7] and low[2, 8] and np.all(caps[low] == int(np.ceil(0.25 * cap)))
    # turning right: the thinned cells move right; any speed gives the same caps
    turned = epipole_cell_caps(CAM, np.array([np.tan(np.radians(20.0)), 0.0, 1.0]), p)
    assert np.nonzero(turned < cap)[1].min() > cols.max()
    np.testing.assert_array_equal(epipole_cell_caps(CAM, np.array([0.0, 0.0, 0.01]), p), caps)
    # standing, reversing, sideways, NaN, or switched off: no caps
    for v in ([0.0, 0.0, 0.0], [0.0, 0.0, -5.0], [5.0, 0.0, 1.0], [np.nan, 0.0, 1.0]):
        assert epipole_cell_caps(CAM, np.array(v), p) is None
    off = dataclasses.replace(p, epipole_radius_deg=0.0)
    assert epipole_cell_caps(CAM, np.array([0.0, 0.0, 10.0]), off) is None
    with pytest.raises(ConfigError):
        TrackPointsParams(epipole_cap_share=1.5)


def test_tracker_cell_caps_prune_to_the_longest_tracks_and_limit_new_corners():
    from mogs_node.sim import SimConfig, make_sequence

    seq = make_sequence(SimConfig(seed=0, n_frames=3, width=621, height=188))
    p = TrackPointsParams(max_tracks=1600, min_distance_px=3)
    tp = p.tracker()
    caps = np.full((tp.bucket_rows, tp.bucket_cols), tp.bucket_cap)
    caps[:, :8] = 3  # the left half: at most 3 tracks per cell
    tr = FeatureTracker(tp, CameraModel(seq.camera))
    first = tr.track(seq.render(0).rgb)
    second = tr.track(seq.render(1).rgb, None, caps)

    def cells(res):
        cx = np.minimum((res.uv_raw_px[:, 0] * tp.bucket_cols / 621).astype(int), 15)
        cy = np.minimum((res.uv_raw_px[:, 1] * tp.bucket_rows / 188).astype(int), 4)
        return np.bincount(cy * tp.bucket_cols + cx, minlength=80).reshape(5, 16)

    assert cells(first)[:, :8].max() > 3
    assert cells(second)[:, :8].max() <= 3 and cells(second)[:, 8:].max() > 3
    # the tracks kept in a capped cell are old ones (longest first), not new corners
    left = second.uv_raw_px[:, 0] < 8 * 621 / 16
    assert np.all(second.track_len[left] == 2)
    with pytest.raises(ShapeError, match="cell_caps"):
        tr.track(seq.render(2).rgb, None, caps[:, :4])
