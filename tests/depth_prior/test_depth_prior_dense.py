"""Dense weight-free prior: road plane, forward warp with z-buffer, fusion, sequence (issue 16)."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from mogs_node.depth_prior.dense_prior import (
    SOURCES,
    FusionParams,
    PriorHistory,
    compute_dense_prior,
    confidence_from_error,
    error_from_confidence,
    fuse_candidates,
)
from mogs_node.depth_prior.flow_prior import FlowPriorParams, two_view_depth
from mogs_node.depth_prior.road import (
    RoadPriorParams,
    road_prior,
    up_in_camera,
)
from mogs_node.depth_prior.sequence import PriorSequence
from mogs_node.depth_prior.warp import forward_warp_depth
from mogs_node.errors import ConfigError, ShapeError
from mogs_node.geometry import make_T, pixel_grid_xy, road_plane_depth, se3_inverse, so3_exp

sys.path.insert(0, str(Path(__file__).parents[1]))  # tests/: the helpers
from _two_view_scene import CAM, render  # noqa: E402

# The test scene's world is the first camera's frame (y down): "up" is -y.
ROAD = RoadPriorParams(up_world=(0.0, -1.0, 0.0))
FLOW = FlowPriorParams(far_baseline_m=0.0)
K = CAM.K
HW = (CAM.height, CAM.width)


@pytest.fixture(scope="module")
def views():
    T0 = np.eye(4)
    T1 = make_T(so3_exp(np.array([0.0, 0.01, 0.0])), np.array([0.05, 0.0, 0.8]))
    g0, d0 = render(T0)
    g1, d1 = render(T1)
    return (g0, d0, T0), (g1, d1, T1)


def _ground_truth_plane(depth_gt: np.ndarray, up_cam: np.ndarray, h: float) -> np.ndarray:
    """Pixels whose rendered depth is the ground's (the renderer samples the depth a quarter
    pixel off the pixel centre: 2 % tolerance)."""
    _, _, rays = pixel_grid_xy(K, *HW)
    z, _ = road_plane_depth(rays, up_cam, h)
    return np.isfinite(z) & (np.abs(z - depth_gt) <= 0.02 * depth_gt)


# ----------------------------------------------------------------------------------- road plane


@settings(max_examples=60, deadline=None)
@given(
    h=st.floats(1e-2, 1e3),
    pitch=st.floats(-0.3, 0.3),
    roll=st.floats(-0.3, 0.3),
)
def test_plane_depth_lies_on_the_plane(h: float, pitch: float, roll: float) -> None:
    up = so3_exp(np.array([pitch, 0.0, roll])) @ np.array([0.0, -1.0, 0.0])
    _, _, rays = pixel_grid_xy(K, *HW)
    z, sin_a = road_plane_depth(rays, up, h)
    below = np.isfinite(z)
    assert np.array_equal(below, sin_a > 0)
    X = z[below] * np.stack([rays[0][below], rays[1][below], np.ones(below.sum())])
    np.testing.assert_allclose(up @ X, -h, rtol=1e-4)
    assert np.all(z[below] > 0)


def test_up_in_camera_from_pose_and_fixed() -> None:
    R = so3_exp(np.array([0.1, -0.2, 0.3]))
    T = make_T(R, np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(up_in_camera(T, (0, 0, 2.0), (0, -1, 0)), R.T @ [0, 0, 1.0])
    np.testing.assert_allclose(up_in_camera(T, None, (0, -2.0, 0)), [0, -1.0, 0])
    with pytest.raises(ShapeError, match="T_world_cam"):
        up_in_camera(np.full((4, 4), np.nan), (0, 0, 1.0), (0, -1, 0))
    with pytest.raises(ConfigError, match="up_world"):
        RoadPriorParams(up_world=(0.0, 0.0, 0.0))


def test_road_plane_seen_from_two_poses_gives_the_plane_depth(views) -> None:
    (g0, _, T0), (g1, d1, T1) = views
    T_r_k = se3_inverse(T0) @ T1
    pair = two_view_depth(g1, g0, K, T_r_k, FLOW)
    up = up_in_camera(T1, ROAD.up_world, FLOW.ground_up_cam)
    _, _, rays = pixel_grid_xy(K, *HW)
    road = road_prior(g1, K, rays, up, 1.65, ROAD, (g0, T_r_k, pair.flow_px, pair.fb_error_px))
    truth = _ground_truth_plane(d1, up, 1.65)
    has = road.depth_m > 0
    assert has.sum() > 0.5 * (truth & (d1 < ROAD.max_depth_m)).sum()
    # on the ground the plane depth is the depth (up to the pose's tiny roll of the test scene)
    err = np.abs(road.depth_m[has & truth] - d1[has & truth]) / d1[has & truth]
    assert np.median(err) < 5e-3 and np.max(err) < 0.02
    # off the ground (facades reaching down below the horizon): little road, and only at the
    # foot of a facade, where its depth is within the test's resolution of the ground's
    off = has & ~truth
    assert off.sum() <= 0.05 * has.sum()
    assert np.all(np.abs(road.depth_m[off] - d1[off]) / d1[off] < 0.15)
    assert np.all(np.isinf(road.rel_err[~has])) and np.all(road.rel_err[has] > 0)


def test_road_without_reference_is_empty_unless_image_only(views) -> None:
    (g0, _, T0), _ = views
    up = up_in_camera(T0, ROAD.up_world, FLOW.ground_up_cam)
    _, _, rays = pixel_grid_xy(K, *HW)
    assert not road_prior(g0, K, rays, up, 1.65, ROAD).depth_m.any()
    p = RoadPriorParams(up_world=(0.0, -1.0, 0.0), image_only=True)
    road = road_prior(g0, K, rays, up, 1.65, p)
    assert road.depth_m.any()
    with pytest.raises(ConfigError, match="height"):
        road_prior(g0, K, rays, up, float("nan"), ROAD)


def test_wrong_height_is_rejected_by_the_flow(views) -> None:
    """The plane at twice the true height predicts other flow: verification rejects it."""
    (g0, _, T0), (g1, _, T1) = views
    T_r_k = se3_inverse(T0) @ T1
    pair = two_view_depth(g1, g0, K, T_r_k, FLOW)
    up = up_in_camera(T1, ROAD.up_world, FLOW.ground_up_cam)
    _, _, rays = pixel_grid_xy(K, *HW)
    ref = (g0, T_r_k, pair.flow_px, pair.fb_error_px)
    right = road_prior(g1, K, rays, up, 1.65, ROAD, ref)
    wrong = road_prior(g1, K, rays, up, 3.3, ROAD, ref)
    assert (wrong.depth_m > 0).sum() < 0.1 * (right.depth_m > 0).sum()


# ---------------------------------------------------------------------------------- forward warp


def test_warp_of_a_fronto_parallel_plane_gives_its_new_depth() -> None:
    d = np.full(HW, 10.0, np.float32)
    T_k_j = se3_inverse(make_T(np.eye(3), np.array([0.0, 0.0, 1.0])))  # k is 1 m ahead of j
    dk, ck = forward_warp_depth(d, None, K, T_k_j)
    hit = dk > 0
    assert hit.mean() > 0.95  # moving forward, the plane fills the view
    np.testing.assert_allclose(dk[hit], 9.0, rtol=1e-5)
    assert np.all(ck[hit] == 1.0) and np.all(ck[~hit] == 0.0)


def test_warp_of_known_depth_with_rotation_matches_rendering(views) -> None:
    (_, d0, T0), (_, d1, T1) = views
    dk, _ = forward_warp_depth(d0, None, K, se3_inverse(T1) @ T0)
    hit = dk > 0
    assert hit.mean() > 0.8
    rel = np.abs(dk[hit] - d1[hit]) / d1[hit]
    assert np.median(rel) < 5e-3  # off depth edges: exact up to the splat's half pixel
    assert np.mean(rel < 0.02) > 0.95


def test_zbuffer_keeps_the_occluder() -> None:
    H, W = HW
    d = np.full(HW, 20.0, np.float32)
    d[60:100, 200:260] = 5.0  # a near box in front of a far wall
    T_k_j = se3_inverse(make_T(np.eye(3), np.array([0.5, 0.0, 0.0])))  # k 0.5 m to the right
    dk, _ = forward_warp_depth(d, None, K, T_k_j)
    fx = K[0, 0]
    # the box moves left by fx * 0.5 / 5 = 30 px, the wall by 7.5 px: the box still hides it
    box = dk[65:95, 200 - 30 + 3 : 260 - 30 - 3]
    np.testing.assert_allclose(box, 5.0, rtol=1e-5)
    # right of the box the wall that was hidden behind it shows up: nothing known there
    gap = dk[65:95, 260 - 30 + 2 : 260 - 8 - 2]
    assert np.all(gap == 0.0)
    assert np.all(dk[(dk > 0)] <= 20.0 + 1e-4)
    assert fx * 0.5 / 5.0 == pytest.approx(30.0, rel=0.01)


def test_background_does_not_show_through_a_magnified_occluder() -> None:
    """Approaching a near box from 4 m to 1.6 m magnifies it 2.5x: its points land 2-3 px apart
    and the far wall's points, visible in the source around the box, land in the gaps. Every
    target pixel inside the box's new outline holds the box's depth or nothing."""
    d = np.full(HW, 40.0, np.float32)
    d[70:90, 230:270] = 4.0
    T_k_j = se3_inverse(make_T(np.eye(3), np.array([0.0, 0.0, 2.4])))
    dk, _ = forward_warp_depth(d, None, K, T_k_j)
    fx, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    u0, u1 = (np.array([230, 269]) - cx) * 2.5 + cx, (np.array([70, 89]) - cy) * 2.5 + cy
    inner = dk[int(u1[0]) + 2 : int(u1[1]) - 2, int(u0[0]) + 2 : int(u0[1]) - 2]
    assert inner.size > 1000
    assert np.all((inner == 0) | (np.abs(inner - 1.6) < 0.01))
    assert np.mean(inner > 0) > 0.9
    assert fx > 0
    # without the footprint test (occlusion_rel = inf) the wall leaks into the box
    leak, _ = forward_warp_depth(d, None, K, T_k_j, occlusion_rel=np.inf)
    inner_leak = leak[int(u1[0]) + 2 : int(u1[1]) - 2, int(u0[0]) + 2 : int(u0[1]) - 2]
    assert np.any(inner_leak > 30.0)


def test_carried_depth_contradicted_by_the_flow_is_dropped(views) -> None:
    """A carried depth twice the truth predicts matches the DIS flow does not find: rejected
    where the flow can tell; the true depth carried the same way passes the same test."""
    (g0, _, T0), (g1, d1, T1) = views
    conf = np.full(HW, 0.9, np.float32)
    kw = dict(flow_params=FLOW, road_params=RoadPriorParams(enabled=False))
    stats = {}
    for name, depth in (("true", d1), ("wrong", 2.0 * d1)):
        carried = (depth.astype(np.float32), conf, T1, g1)  # same pose and image: photo passes
        p = compute_dense_prior(g1, K, T1, PriorHistory([(g0, T0)], [carried]), **kw)
        stats[name] = p.stats["warp_flow_rejected"]
    assert stats["true"] < 0.05
    assert stats["wrong"] > 0.4
    off = compute_dense_prior(
        g1,
        K,
        T1,
        PriorHistory([(g0, T0)], [(2.0 * d1, conf, T1, g1)]),
        params=FusionParams(flow_check=False),
        **kw,
    )
    assert off.stats["warp_flow_rejected"] == 0.0


@settings(max_examples=40, deadline=None)
@given(
    bad=st.sampled_from([np.nan, np.inf, -np.inf, -1.0, 0.0]),
    frac=st.floats(0.0, 1.0),
    scale=st.floats(1e-2, 1e3),
    seed=st.integers(0, 1000),
)
def test_warp_ignores_bad_depth_and_scales(
    bad: float, frac: float, scale: float, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    d = np.full((40, 60), scale, np.float32)
    d[rng.random(d.shape) < frac] = bad
    Ks = np.array([[50.0, 0, 29.5], [0, 50.0, 19.5], [0, 0, 1]])
    dk, ck = forward_warp_depth(d, None, Ks, np.eye(4))  # zero motion: identity
    assert np.all(np.isfinite(dk)) and np.all(np.isfinite(ck))
    good = np.isfinite(d) & (d > 1e-3)
    np.testing.assert_allclose(dk[good], scale, rtol=1e-5)
    assert np.all(dk[dk > 0] == pytest.approx(scale, rel=1e-5))


def test_warp_rejects_bad_pose_and_shapes() -> None:
    d = np.ones(HW, np.float32)
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(ShapeError, match="T_k_j"):
        forward_warp_depth(d, None, K, T)
    with pytest.raises(ShapeError, match="value_j"):
        forward_warp_depth(d, np.ones((3, 3)), K, np.eye(4))
    with pytest.raises(ShapeError, match="depth_j_m"):
        forward_warp_depth(np.ones(5), None, K, np.eye(4))
    dk, _ = forward_warp_depth(np.zeros(HW), None, K, np.eye(4))  # nothing to warp
    assert not dk.any()


# ----------------------------------------------------------------------------------------- fusion


def test_fusion_exact_cases() -> None:
    p = FusionParams(agree_sigmas=2.0, conflict_ratio=2.0)
    d = np.array([[[10.0, 10.0, 10.0, 0.0]], [[10.4, 20.0, 20.0, 0.0]]], np.float32)
    e = np.array([[[0.05, 0.05, 0.05, np.inf]], [[0.1, 0.1, 0.3, np.inf]]], np.float32)
    fd, fe, lead = fuse_candidates(d, e, p)
    # agree (0.04 <= 2 * 0.15): inverse-variance mean, the leader's error
    w0, w1 = 1 / 0.05**2, 1 / 0.1**2
    assert fd[0, 0] == pytest.approx((w0 * 10 + w1 * 10.4) / (w0 + w1), rel=1e-5)
    assert fe[0, 0] == pytest.approx(0.05)
    # conflict (gap 1.0, e 0.1 <= 2 * 0.05): leader kept, error raised to the disagreement
    assert fd[0, 1] == pytest.approx(10.0) and fe[0, 1] == pytest.approx(1.0)
    # a much worse disagreeing candidate (gap 1.0 > 2 * 0.35, 0.3 > 2 * 0.05): outvoted
    assert fd[0, 2] == pytest.approx(10.0) and fe[0, 2] == pytest.approx(0.05)
    assert fd[0, 3] == 0 and np.isinf(fe[0, 3]) and lead[0, 3] == -1
    assert list(lead[0, :3]) == [0, 0, 0]


@settings(max_examples=60, deadline=None)
@given(
    S=st.integers(0, 4),
    seed=st.integers(0, 10_000),
    scale=st.floats(1e-2, 1e3),
    bad=st.sampled_from([np.nan, np.inf, -1.0, 0.0]),
)
def test_fusion_output_is_sane(S: int, seed: int, scale: float, bad: float) -> None:
    rng = np.random.default_rng(seed)
    d = (scale * rng.uniform(0.5, 2.0, (S, 8, 9))).astype(np.float32)
    e = rng.uniform(0.001, 1.0, (S, 8, 9)).astype(np.float32)
    d[rng.random(d.shape) < 0.3] = bad
    e[rng.random(e.shape) < 0.2] = np.inf
    fd, fe, lead = fuse_candidates(d, e, FusionParams())
    assert fd.shape == (8, 9) and np.all(np.isfinite(fd))
    none = ~np.isfinite(fe)
    assert np.array_equal(none, fd == 0) and np.array_equal(none, lead < 0)
    ok = np.isfinite(d) & (d > 0) & np.isfinite(e)
    if S:
        e_min = np.where(ok, e, np.inf).min(0)
        assert np.all(fe[~none] >= e_min[~none] - 1e-6)  # never more confident than the best
        lo = np.where(ok, d, np.inf).min(0)
        hi = np.where(ok, d, 0).max(0)
        assert np.all((fd[~none] >= lo[~none] * (1 - 1e-5)) & (fd[~none] <= hi[~none] * (1 + 1e-5)))


@settings(max_examples=50, deadline=None)
@given(e=st.floats(0.0, 1e3), ref=st.floats(1e-3, 1.0))
@example(e=0.0002, ref=1.0)  # found by CI: float32 confidence 1.0, error back 0
def test_confidence_and_error_are_inverse(e: float, ref: float) -> None:
    c = confidence_from_error(np.array([e]), ref)
    assert 0 <= c[0] <= 1
    if c[0] > 1e-6:
        # a float32 confidence 1 / (1 + (e / ref)^2) rounds to 1 below e ~ ref * sqrt(eps):
        # errors that small come back as 0 (within 5e-4 x ref)
        tol = max(1e-4, 5e-4 * ref)
        assert error_from_confidence(c, ref)[0] == pytest.approx(e, rel=1e-2, abs=tol)
    assert confidence_from_error(np.array([np.nan, np.inf]), ref).tolist() == [0.0, 0.0]
    assert np.isinf(error_from_confidence(np.array([0.0, np.nan]), ref)).all()


# ---------------------------------------------------------------------------- the dense prior


def test_dense_prior_fills_the_ground_and_is_metric(views) -> None:
    (g0, _, T0), (g1, d1, T1) = views
    flow_only = compute_dense_prior(
        g1,
        K,
        T1,
        PriorHistory([(g0, T0)]),
        flow_params=FLOW,
        road_params=RoadPriorParams(enabled=False),
    )
    dense = compute_dense_prior(
        g1, K, T1, PriorHistory([(g0, T0)]), flow_params=FLOW, road_params=ROAD
    )
    assert (dense.confidence > 0).mean() > (flow_only.confidence > 0).mean() + 0.02
    assert (dense.source == SOURCES["road"]).mean() > 0.05
    m = dense.confidence > 0
    rel = np.abs(dense.depth_m[m] - d1[m]) / d1[m]
    assert np.median(rel) < 0.02
    assert set(np.unique(dense.source[m])) <= {SOURCES["flow"], SOURCES["road"]}
    assert np.all(dense.depth_m[~m] == 0) and np.all(np.isinf(dense.rel_err[~m]))


def test_confidence_is_calibrated_on_the_two_view_scene(views) -> None:
    """Higher confidence, lower error: the top half of the pixels by confidence beats the rest."""
    (g0, _, T0), (g1, d1, T1) = views
    dense = compute_dense_prior(
        g1, K, T1, PriorHistory([(g0, T0)]), flow_params=FLOW, road_params=ROAD
    )
    m = dense.confidence > 0
    c, rel = dense.confidence[m], np.abs(dense.depth_m[m] - d1[m]) / d1[m]
    hi = c >= np.median(c)
    assert np.mean(rel[hi]) < np.mean(rel[~hi])


def test_zero_baseline_carries_earlier_depth(views) -> None:
    """Standing still: no flow reference, the earlier metrized depth is warped in (identity)."""
    (g0, d0, T0), _ = views
    conf = np.full(HW, 0.8, np.float32)
    p = compute_dense_prior(
        g0, K, T0, PriorHistory((), [(d0.astype(np.float32), conf, T0, g0)]), road_params=ROAD
    )
    m = p.confidence > 0
    assert m.mean() > 0.95
    np.testing.assert_allclose(p.depth_m[m], d0[m], rtol=1e-4)  # zero motion: the same depth
    assert np.all(p.source[m] == SOURCES["warp"])
    empty = compute_dense_prior(g0, K, T0, road_params=ROAD)
    assert not empty.confidence.any() and not empty.depth_m.any()


def test_warped_depth_through_an_unknown_occluder_is_dropped(views) -> None:
    """A wrong earlier depth whose image disagrees with the keyframe's is not carried."""
    (g0, d0, T0), _ = views
    g_other = (255 - g0).astype(np.uint8)  # the earlier view saw something else there
    conf = np.full(HW, 0.8, np.float32)
    p = compute_dense_prior(
        g0, K, T0, PriorHistory((), [(d0, conf, T0, g_other)]), road_params=ROAD
    )
    assert (p.confidence > 0).mean() < 0.5


@settings(max_examples=20, deadline=None)
@given(bad=st.sampled_from([np.nan, np.inf]), where=st.sampled_from(["pose", "earlier"]))
def test_dense_prior_rejects_non_finite_poses(views, bad: float, where: str) -> None:
    (g0, d0, T0), _ = views
    T = T0.copy()
    T[1, 3] = bad
    conf = np.ones(HW, np.float32)
    if where == "pose":
        with pytest.raises(ShapeError, match="T_world_cam_k"):
            compute_dense_prior(g0, K, T, PriorHistory((), [(d0, conf, T0)]))
    else:
        with pytest.raises(ShapeError, match=r"earlier_depth\[0\].T_world_cam"):
            compute_dense_prior(g0, K, T0, PriorHistory((), [(d0, conf, T)]))


def test_dense_prior_with_non_finite_earlier_depth_stays_finite(views) -> None:
    (g0, d0, T0), _ = views
    d = d0.astype(np.float32).copy()
    d[::3] = np.nan
    d[1::3] = np.inf
    c = np.full(HW, 0.5, np.float32)
    c[:, ::5] = np.nan
    p = compute_dense_prior(g0, K, T0, PriorHistory((), [(d, c, T0, g0)]), road_params=ROAD)
    assert np.all(np.isfinite(p.depth_m)) and np.all(np.isfinite(p.confidence))
    assert p.confidence.min() >= 0 and p.confidence.max() <= 1


def test_bad_fusion_params() -> None:
    with pytest.raises(ConfigError):
        FusionParams(rel_err_ref=0)
    with pytest.raises(ConfigError):
        FusionParams(carry_growth=0.5)
    with pytest.raises(ConfigError):
        RoadPriorParams(max_depth_m=-1)


# ----------------------------------------------------------------------------------- sequence


def test_sequence_standstill_keyframe_gets_the_metrized_depth(views) -> None:
    (g0, d0, T0), (g1, d1, T1) = views
    seq = PriorSequence(FLOW, ROAD)
    first, refs = seq.next(0, g0, K, T0)
    assert refs == [] and not first.confidence.any()
    assert seq.add_metrized(0, d0.astype(np.float32), np.full(HW, 0.9, np.float32))
    still, refs = seq.next(1, g0, K, T0)  # standing still: same pose, same image
    assert refs == []
    assert (still.confidence > 0).mean() > 0.95
    moving, refs = seq.next(2, g1, K, T1)
    assert refs in ([0], [1])  # the nearest earlier keyframe far enough (both at one place)
    m = moving.confidence > 0
    assert m.mean() > 0.8
    assert np.median(np.abs(moving.depth_m[m] - d1[m]) / d1[m]) < 0.02
    # metrized depth of another size, or of a keyframe long gone, is not kept
    assert not seq.add_metrized(1, np.ones((3, 3), np.float32), np.ones((3, 3), np.float32))
    assert seq.add_metrized(7, d0.astype(np.float32), np.ones(HW, np.float32))  # comes later
    seq.remember(7, g0, K, T0)
    assert seq.history[-1].metrized is not None


def test_sequence_first_keyframe_takes_a_frame_before_it_as_reference(views) -> None:
    """A keyframe without an earlier keyframe (the first after a standstill) gets its flow from
    the tracked frames before it (``flow.frame_references``); frames after it, or at its own
    stamp, are never references; with the option off nothing changes."""
    (g0, _, T0), (g1, d1, T1) = views
    on = replace(FLOW, frame_references=4)
    seq = PriorSequence(on, ROAD)
    assert seq.add_frame(100, g0, T0)
    assert seq.add_frame(300, g0, T0)  # after the keyframe: not a reference of it
    prior, refs = seq.next(0, g1, K, T1, stamp_ns=200)
    assert refs == [-1]
    m = prior.confidence > 0
    assert m.mean() > 0.5
    assert np.median(np.abs(prior.depth_m[m] - d1[m]) / d1[m]) < 0.02
    late = PriorSequence(on, ROAD)
    late.add_frame(300, g0, T0)
    prior, refs = late.next(0, g1, K, T1, stamp_ns=200)
    assert refs == [] and not prior.confidence.any()
    off = PriorSequence(FLOW, ROAD)
    assert not off.add_frame(100, g0, T0)
    assert off.next(0, g1, K, T1, stamp_ns=200)[1] == []
    with pytest.raises(ShapeError):
        seq.add_frame(400, g0, np.full((4, 4), np.nan))
    with pytest.raises(ConfigError):
        FlowPriorParams(frame_references=-1)
    with pytest.raises(ConfigError):
        FusionParams(carry_min_confidence=1.5)


def test_carry_min_confidence_drops_weak_carried_depth(views) -> None:
    """``fusion.carry_min_confidence``: carried prior pixels less confident than it are not
    carried; the others are, unchanged (standing still: the identity warp)."""
    (g0, d0, T0), _ = views
    conf = np.where(np.arange(HW[1])[None, :] < HW[1] // 2, 0.02, 0.6).astype(np.float32)
    conf = np.broadcast_to(conf, HW).copy()
    prev = (d0.astype(np.float32), conf, T0, g0)
    past = PriorHistory(previous_prior=prev)
    every = compute_dense_prior(g0, K, T0, past, road_params=ROAD)
    strong = compute_dense_prior(
        g0, K, T0, past, road_params=ROAD, params=FusionParams(carry_min_confidence=0.05)
    )
    left, right = np.s_[:, : HW[1] // 2 - 2], np.s_[:, HW[1] // 2 + 2 :]
    assert (every.confidence[left] > 0).mean() > 0.9
    assert not strong.confidence[left].any()
    assert (strong.confidence[right] > 0).mean() > 0.9
    m = strong.confidence > 0
    np.testing.assert_allclose(strong.depth_m[m], d0[m], rtol=1e-4)


def test_plane_depth_at_the_horizon_is_inf_with_sine_zero() -> None:
    # hypothesis found it: a ray 5.5e-10 below the horizon had a positive sine but no depth
    up = so3_exp(np.array([0.22609198612092135, 0.0, 0.06319843562286392])) @ np.array(
        [0.0, -1.0, 0.0]
    )
    _, _, rays = pixel_grid_xy(K, *HW)
    z, sin_a = road_plane_depth(rays, up, 1.0)
    assert np.array_equal(np.isfinite(z), sin_a > 0)
    assert np.all(sin_a[~np.isfinite(z)] <= 0)
