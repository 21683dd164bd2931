"""Mapper insertion (``insertion.py``): which pixels get new Gaussians (unexplained, disagreeing,
untextured, planar), how they are sampled from the depth and how large they are."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_mapper import H, K, W, plane_view

from mogs_node.errors import ShapeError
from mogs_node.geometry import make_T, rotmat_from_rpy
from mogs_node.mapper.insertion import (
    InsertionParams,
    _stride_map,
    flat_image_mask,
    insertion_mask,
    planar_mask,
    random_depth,
    sample_gaussians,
)


def test_insertion_mask_explained_unexplained_and_disagreeing() -> None:
    p = InsertionParams(depth_rel_tol=0.2)
    d = np.full((4, 4), 10.0, np.float32)
    d[0, 0] = 0.0  # no depth here
    c = np.ones_like(d)
    assert insertion_mask(d, c, None, None, p).sum() == 15
    alpha = np.ones_like(d)
    agree = d.copy()
    assert insertion_mask(d, c, alpha, agree, p).sum() == 0
    alpha[1, 1] = 0.2  # low rendered opacity
    agree[2, 2] = 13.0  # depth disagreement (30 % > depth_rel_tol = 20 % at confidence 1)
    m = insertion_mask(d, c, alpha, agree, p)
    assert m.sum() == 2 and m[1, 1] and m[2, 2]
    c[2, 2] = 0.5  # the tolerance is relative and widens as 1 / confidence: 0.2 / 0.5 = 40 %
    assert insertion_mask(d, c, alpha, agree, p).sum() == 1
    agree[2, 2] = 15.0  # 50 % behind: disagrees even at confidence 0.5
    assert insertion_mask(d, c, alpha, agree, p).sum() == 2
    c[2, 2] = 0.0  # confidence 0 (random depth) never disagrees
    agree[2, 2] = 1e4
    assert insertion_mask(d, c, alpha, agree, p).sum() == 1
    agree[2, 2] = 5.0  # a map surface in front of the new depth is left to optimisation
    c[2, 2] = 1.0
    assert insertion_mask(d, c, alpha, agree, p).sum() == 1
    agree[2, 2] = 13.0
    assert (
        insertion_mask(d, np.ones_like(d), alpha, agree, InsertionParams(check_depth=False)).sum()
        == 1
    )


def test_insertion_mask_colour_disagreement_is_opt_in() -> None:
    d = np.full((3, 3), 10.0, np.float32)
    c = np.ones_like(d)
    alpha, rdepth = np.ones_like(d), d.copy()  # covered, depth agrees
    img = np.full((3, 3, 3), 0.5, np.float32)
    rendered = img.copy()
    rendered[1, 2] = [0.5, 0.5, 0.9]  # mean |diff| over channels 0.4 / 3 = 0.133
    rendered[0, 0] = [0.55, 0.5, 0.5]  # 0.017: within tolerance
    assert insertion_mask(d, c, alpha, rdepth, InsertionParams(), rendered, img).sum() == 0
    m = insertion_mask(d, c, alpha, rdepth, InsertionParams(color_tol=0.1), rendered, img)
    assert m.sum() == 1 and m[1, 2]
    assert (
        insertion_mask(d, c, alpha, rdepth, InsertionParams(color_tol=0.15), rendered, img).sum()
        == 0
    )
    with pytest.raises(ShapeError, match="rendered_rgb"):
        insertion_mask(d, c, alpha, rdepth, InsertionParams(color_tol=0.1), rendered[:2], img)


def test_sample_gaussians_backprojects_to_their_pixels_with_footprint_scale() -> None:
    img, depth = plane_view(8.0)
    depth[:, W // 2 :] = 60.0  # far half: coarser stride
    T_world_cam = make_T(rotmat_from_rpy(0.1, -0.2, 0.3), np.array([1.0, 2.0, -3.0]))
    p = InsertionParams(stride_px=2, far_depth_m=25.0, coarse_conf=0.7, max_footprint_rad=1.0)
    conf = np.full_like(depth, 0.5)  # below coarse_conf: base stride
    g = sample_gaussians(img, depth, conf, np.ones((H, W), bool), K, T_world_cam, p)
    means = g["means"].numpy().astype(np.float64)
    p_cam = (means - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    u = K[0, 0] * p_cam[:, 0] / p_cam[:, 2] + K[0, 2]
    v = K[1, 1] * p_cam[:, 1] / p_cam[:, 2] + K[1, 2]
    np.testing.assert_allclose(u, np.round(u), atol=1e-3)
    np.testing.assert_allclose(v, np.round(v), atol=1e-3)
    ui, vi = np.round(u).astype(int), np.round(v).astype(int)
    np.testing.assert_allclose(p_cam[:, 2], depth[vi, ui], rtol=1e-5)
    np.testing.assert_allclose(g["colors"].numpy(), img[vi, ui] / 255.0, atol=1e-6)
    near, far = ui < W // 2, ui >= W // 2
    assert near.sum() == (H // 2) * (W // 4)  # stride 2 on the near half
    assert far.sum() == (H // 8) * (W // 16)  # 60 m: two octaves beyond 25 m -> stride 8
    sigma = np.exp(g["log_scales"].numpy()[:, 0])
    np.testing.assert_allclose(sigma[near], 2 * 8.0 / 40.0, rtol=1e-5)
    np.testing.assert_allclose(sigma[far], 8 * 60.0 / 40.0, rtol=1e-5)
    # the default footprint cap, 0.15 rad x f = 6 px here, limits the far stride
    g = sample_gaussians(img, depth, conf, np.ones((H, W), bool), K, T_world_cam, InsertionParams())
    sigma = np.exp(g["log_scales"].numpy()[:, 0])
    z = (g["means"].numpy() - T_world_cam[:3, 3]) @ T_world_cam[:3, :3][:, 2]
    np.testing.assert_allclose(sigma[z > 30], 6 * 60.0 / 40.0, rtol=1e-4)
    r = random_depth((H, W), 1.0, 50.0, seed=3)
    assert r.shape == (H, W) and r.min() >= 1.0 and r.max() <= 50.0


def test_confident_depth_gets_fewer_larger_gaussians() -> None:
    _, depth = plane_view(8.0)
    checker = ((np.arange(H)[:, None] // 2 + np.arange(W)[None, :] // 2) % 2).astype(np.uint8)
    textured = np.repeat(60 + 120 * checker[..., None], 3, -1)  # 2 px checkerboard
    flat = np.full_like(textured, 120)
    flat[:, :, 0] += (np.arange(W) * 0.5).astype(np.uint8)  # a gentle ramp: 0.5 / 3 grey/px
    # a bumpy (non-planar) surface at the same distance: only the confidence doubling applies
    vv, uu = np.mgrid[0:H, 0:W]
    bumpy = (8.0 * (1 + 0.05 * np.sin(uu * 1.3) * np.cos(vv * 0.9))).astype(np.float32)
    p = InsertionParams(stride_px=2, coarse_conf=0.7, max_stride_px=8, max_footprint_rad=1.0)
    mask = np.ones((H, W), bool)
    n = {}
    cases = (("plane", flat, depth), ("bumpy", flat, bumpy), ("textured plane", textured, depth))
    for surface, img, d in cases:
        for conf in (0.0, 0.69, 0.7, 1.0):
            g = sample_gaussians(img, d, np.full_like(d, conf), mask, K, np.eye(4), p)
            n[surface, conf] = len(g["means"])
            stride = 2 if conf < 0.7 else (8 if surface == "plane" else 4)
            assert n[surface, conf] == (H // stride) * (W // stride)
            sigma = np.exp(g["log_scales"].numpy())
            z = g["means"].numpy()[:, 2:3]
            np.testing.assert_allclose(
                sigma, np.broadcast_to(stride * z / 40.0, sigma.shape), rtol=1e-5
            )
    # the covered area per view is the same: n * sigma^2 is constant
    assert n["bumpy", 0.0] == 4 * n["bumpy", 1.0] == 16 * n["plane", 1.0]
    # without the planar rule (or without the image test) the planes get the confidence
    # doubling only (or both the planar one)
    for q, img, stride in (
        (replace(p, planar_tol=0.0), flat, 4),
        (replace(p, planar_gain=1.0), flat, 4),
        (replace(p, planar_max_grad=0.0), textured, 8),
    ):
        g = sample_gaussians(img, depth, np.ones_like(depth), mask, K, np.eye(4), q)
        assert len(g["means"]) == (H // stride) * (W // stride)


def test_flat_image_mask_thresholds_the_windowed_grey_gradient() -> None:
    img = np.full((H, W, 3), 100, np.uint8)
    img[:, 30:] = 130  # an edge: central differences of 15 grey/px at columns 29 and 30
    fm = flat_image_mask(img, 8.0, 5)
    assert not fm[:, 27:33].any() and fm[:, :27].all() and fm[:, 33:].all()
    assert flat_image_mask(img, 15.5, 5).all() and flat_image_mask(img, 15.0, 1).sum() == H * (
        W - 2
    )


def _plane_depth(normal: np.ndarray, dist: float) -> np.ndarray:
    """Depth [H, W] of the plane ``normal . X = dist`` seen by the camera ``K`` at the origin."""
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1)
    return dist / (rays @ normal)


@settings(max_examples=40, deadline=None)
@given(
    nx=st.floats(-0.4, 0.4),
    ny=st.floats(-0.4, 0.4),
    dist=st.floats(0.05, 5e4),
)
def test_planar_mask_accepts_any_plane_in_view(nx: float, ny: float, dist: float) -> None:
    depth = _plane_depth(np.array([nx, ny, 1.0]), dist).astype(np.float32)
    assert np.all(depth > 0)
    assert planar_mask(depth, 0.01, 5).all()


def test_planar_mask_rejects_steps_noise_and_missing_depth() -> None:
    depth = _plane_depth(np.array([0.1, -0.2, 1.0]), 6.0)
    stepped = depth.copy()
    stepped[:, 40:] *= 1.3  # a depth step between columns 39 and 40
    pm = planar_mask(stepped, 0.01, 5)
    # the second difference is non-zero at columns 39 and 40; the 5 px window widens that by 2
    assert not pm[:, 37:43].any() and pm[:, :37].all() and pm[:, 43:].all()
    noisy = depth * (1 + 0.01 * np.random.default_rng(0).standard_normal(depth.shape))
    assert not planar_mask(noisy, 0.01, 5).any()  # 1 % depth noise is not a plane
    holes = depth.copy()
    holes[10, 10], holes[20, 50], holes[5, 30] = 0.0, np.nan, np.inf
    pm = planar_mask(holes, 0.01, 1)
    for v, u in ((10, 10), (20, 50), (5, 30)):  # the pixel and its 4 neighbours are not planar
        assert not pm[v, u] and not pm[v - 1, u] and not pm[v + 1, u]
        assert not pm[v, u - 1] and not pm[v, u + 1]
    assert pm.sum() == H * W - 15
    assert not planar_mask(np.random.default_rng(1).uniform(1, 50, (H, W)), 0.01, 5).any()


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    special=st.sampled_from([0.0, np.nan, np.inf, 1e-30, 1e30, -5.0]),
)
def test_stride_map_stays_in_bounds_and_planar_rule_only_coarsens_confident(
    seed: int, special: float
) -> None:
    rng = np.random.default_rng(seed)
    depth = rng.choice([_plane_depth(np.array([0.0, 0.1, 1.0]), 10.0), rng.uniform(1, 80, (H, W))])
    depth = depth.astype(np.float64)
    depth[rng.random((H, W)) < 0.1] = special
    conf = rng.choice([0.0, 0.3, 0.7, 1.0], size=(H, W))
    p = InsertionParams(stride_px=2, max_stride_px=8)
    img = rng.choice([np.full((H, W, 3), 90), rng.integers(0, 256, (H, W, 3))]).astype(np.uint8)
    s = _stride_map(depth, conf, p, img if seed % 2 else None)
    s_flat = _stride_map(depth, conf, replace(p, planar_tol=0.0))
    assert np.isin(s, [2, 4, 8]).all() and np.isin(s_flat, [2, 4, 8]).all()
    assert (s >= s_flat).all()
    np.testing.assert_array_equal(s[conf < 0.7], s_flat[conf < 0.7])
