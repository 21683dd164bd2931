"""Mapper core: Gaussian map bookkeeping, insertion, window, optimisation, PLY."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from plyfile import PlyData

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.geometry import make_T, rotmat_from_rpy
from mogs_node.mapper.gaussians import PARAM_NAMES, GaussianMap
from mogs_node.mapper.insertion import (
    InsertionParams,
    _stride_map,
    background_mask,
    flat_image_mask,
    insertion_mask,
    planar_mask,
    random_depth,
    sample_gaussians,
)
from mogs_node.mapper.mapper import GaussianMapper, MapperParams, export_ply
from mogs_node.mapper.ply import PLY_PROPERTIES, read_gaussian_ply, write_gaussian_ply
from mogs_node.mapper.window import overlap_coefficient, update_window

W, H = 64, 32
K = np.array([[40.0, 0, 31.5], [0, 40.0, 15.5], [0, 0, 1]])


def plane_view(depth_m: float = 5.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A textured fronto-parallel wall: smooth random colours (uint8) and constant depth."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0, 1, size=(H // 8 + 1, W // 8 + 1, 3))
    yy, xx = np.mgrid[0:H, 0:W] / 8.0
    y0, x0 = yy.astype(int), xx.astype(int)
    fy, fx = (yy - y0)[..., None], (xx - x0)[..., None]
    img = (
        coarse[y0, x0] * (1 - fx) * (1 - fy)
        + coarse[y0, x0 + 1] * fx * (1 - fy)
        + coarse[y0 + 1, x0] * (1 - fx) * fy
        + coarse[y0 + 1, x0 + 1] * fx * fy
    )
    return (img * 255).astype(np.uint8), np.full((H, W), depth_m, np.float32)


def random_values(n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g),
        "quats_wxyz": torch.randn(n, 4, generator=g),
        "log_scales": torch.randn(n, 3, generator=g),
        "opacity_logit": torch.randn(n, generator=g),
        "colors": torch.rand(n, 3, generator=g),
    }


def test_gaussian_map_ids_changes_and_sparse_adam() -> None:
    m = GaussianMap()
    ids_a = m.add(random_values(5), birth_kf=0)
    ids_b = m.add(random_values(3, 1), birth_kf=1)
    assert ids_a.tolist() == [0, 1, 2, 3, 4] and ids_b.tolist() == [5, 6, 7]
    first = m.drain_changes()
    assert first.ids.tolist() == list(range(8)) and len(first.removed_ids) == 0
    np.testing.assert_array_equal(first.means[5:], random_values(3, 1)["means"].numpy())
    assert len(m.drain_changes().ids) == 0  # nothing changed since
    before = {k: v.clone() for k, v in m.params.items()}
    rows = torch.tensor([1, 6])
    m.adam_step(
        rows,
        {k: torch.ones_like(m.params[k][rows]) for k in PARAM_NAMES},
        {k: 0.1 for k in PARAM_NAMES},
    )
    moved = (m.params["means"] != before["means"]).any(1)
    assert moved.tolist() == [False, True, False, False, False, False, True, False]
    # first Adam step moves by exactly lr * sign(grad)
    torch.testing.assert_close(
        before["means"][rows] - m.params["means"][rows], torch.full((2, 3), 0.1)
    )
    m.remove(torch.tensor([True, False, False, False, False, False, True, False]))
    ch = m.drain_changes()
    assert ch.removed_ids.tolist() == [0, 6] and ch.ids.tolist() == [1]
    assert m.ids.tolist() == [1, 2, 3, 4, 5, 7]
    with pytest.raises(ShapeError, match="colors"):
        m.add({**random_values(2), "colors": torch.zeros(3, 3)}, birth_kf=2)


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


def test_window_keeps_newest_and_drops_least_overlapping() -> None:
    assert overlap_coefficient(np.array([1, 2, 3]), np.array([2, 3, 4, 5])) == pytest.approx(2 / 3)
    vis = {
        0: np.arange(0, 100),
        1: np.arange(50, 150),
        2: np.arange(90, 190),
        3: np.arange(95, 200),
    }
    win, dropped = update_window([2, 1, 0], 3, vis, size=2, overlap_min=0.05)
    assert win == [3, 2] and set(dropped) == {0, 1}
    win, dropped = update_window([], 0, vis, size=3, overlap_min=0.3)
    assert win == [0] and dropped == []


def test_ply_roundtrip_standard_layout(tmp_path) -> None:
    v = random_values(7)
    colors = v["colors"].numpy()
    path = write_gaussian_ply(
        tmp_path / "m.ply",
        v["means"].numpy(),
        v["quats_wxyz"].numpy(),
        v["log_scales"].numpy(),
        v["opacity_logit"].numpy(),
        colors,
    )
    ply = PlyData.read(str(path))
    assert ply["vertex"].data.dtype.names == PLY_PROPERTIES
    assert ply["vertex"].count == 7 and not ply.text
    back = read_gaussian_ply(path)
    np.testing.assert_allclose(back["means"], v["means"].numpy())
    np.testing.assert_allclose(back["quats_wxyz"], v["quats_wxyz"].numpy())
    np.testing.assert_allclose(back["colors_rgb"], colors, atol=1e-6)
    np.testing.assert_allclose(
        np.asarray(ply["vertex"]["f_dc_0"]), (colors[:, 0] - 0.5) / 0.28209479177387814, rtol=1e-6
    )


def _mapper(**kw) -> GaussianMapper:
    return GaussianMapper(MapperParams(**kw), K, W, H)


def test_mapper_fits_a_view_and_does_not_reinsert_explained_parts(tmp_path) -> None:
    img, depth = plane_view()
    conf = np.ones_like(depth)
    # stride 4 (confidence doubling only; the planar rule is tested above): 128 Gaussians
    m = _mapper(n_random_past=0, insertion=InsertionParams(planar_tol=0.0))
    n0 = m.add_keyframe(10, img, np.eye(4), depth, conf)
    assert n0 == len(m.map) > 0
    psnr_0 = m.optimize(1)["psnr_db"]
    stats = m.optimize(40)
    assert stats["psnr_db"] > psnr_0 + 3.0
    assert stats["iterations"] == 41
    r = m.render_view(np.eye(4))
    assert float(r.alpha.mean()) > 0.95
    # the same view again is explained: (almost) nothing new
    n1 = m.add_keyframe(11, img, np.eye(4), depth, conf)
    assert n1 < 0.05 * n0  # a few border pixels (coarse stride: 128 Gaussians in all)
    # a view that looks further right explains its left part only
    T_right = make_T(np.eye(3), np.array([1.5, 0.0, 0.0]))
    img2, _ = plane_view(seed=0)
    n2 = m.add_keyframe(12, img2, T_right, depth, conf)
    assert 0 < n2 < 0.6 * n0
    export_ply(m, str(tmp_path / "map.ply"))
    assert len(read_gaussian_ply(tmp_path / "map.ply")["means"]) == len(m.map)


def test_background_mask_is_pixels_without_depth_that_the_map_leaves_transparent() -> None:
    depth = np.full((4, 5), 10.0, np.float32)
    depth[0, :] = 0.0  # sky: no depth
    depth[1, 0] = np.nan
    depth[1, 1] = 0.05  # below min_depth_m: no usable depth either
    alpha = np.zeros((4, 5), np.float32)
    alpha[0, 3:] = 0.95  # the map already draws these sky pixels
    off = InsertionParams()
    assert not background_mask(depth, alpha, off).any()  # 0: off by default
    p = InsertionParams(background_depth_m=200.0)
    want = np.zeros((4, 5), bool)
    want[0, :3] = True
    want[1, :2] = True
    np.testing.assert_array_equal(background_mask(depth, alpha, p), want)
    empty_map = np.zeros((4, 5), bool)
    empty_map[0, :] = True
    empty_map[1, :2] = True
    np.testing.assert_array_equal(background_mask(depth, None, p), empty_map)
    with pytest.raises(ConfigError, match="background_depth_m"):
        InsertionParams(background_depth_m=0.05)


def test_mapper_fills_pixels_without_depth_with_a_far_sphere() -> None:
    img, depth = plane_view(depth_m=5.0)
    depth[: H // 4] = 0.0  # the top quarter has no depth (sky)
    conf = np.ones_like(depth)
    T = make_T(np.eye(3), np.array([0.2, -0.1, 0.3]))
    ins = InsertionParams(planar_tol=0.0, background_depth_m=100.0)
    m = _mapper(n_random_past=0, insertion=ins)
    m.add_keyframe(0, img, T, depth, conf)
    means = m.map.params["means"].numpy()
    dist = np.linalg.norm(means - T[:3, 3], axis=1)
    far = dist > 50.0
    # far Gaussians sit on the rays of the sky pixels at 100 m depth (camera z), at the coarsest
    # stride: 8 px from the depth octaves, capped at 0.15 f = 6 px (footprint cap)
    z = (means[far] - T[:3, 3])[:, 2]
    np.testing.assert_allclose(z, 100.0, rtol=1e-5)
    v = 40.0 * (means[far] - T[:3, 3])[:, 1] / z + 15.5
    assert np.all(v < H // 4) and far.sum() == len(range(0, H // 4, 6)) * len(range(0, W, 6))
    assert np.all(dist[~far] < 10.0)
    sky_alpha = float(m.render_view(T).alpha[:2].mean())
    assert sky_alpha > 0.6  # the sky is drawn, not the black background
    # without the option only the wall's Gaussians spill over the top rows
    m0 = _mapper(n_random_past=0, insertion=InsertionParams(planar_tol=0.0))
    m0.add_keyframe(0, img, T, depth, conf)
    assert float(m0.render_view(T).alpha[:2].mean()) < 0.3
    # a second keyframe at the same pose: the sky is mostly explained, few new far Gaussians
    n_before = int(far.sum())
    m.optimize(10)
    m.add_keyframe(1, img, T, depth, conf)
    dist = np.linalg.norm(m.map.params["means"].numpy() - T[:3, 3], axis=1)
    assert int((dist > 50.0).sum()) - n_before < 0.25 * n_before


def _full_res_l1(m: GaussianMapper) -> list[float]:
    out = []
    for kf in m.keyframes:
        r = m.render_view(kf.T_world_cam, kf.exposure_ab).color
        out.append(float((r - kf.image_f32).abs().mean()))
    return out


def test_final_refinement_visits_every_keyframe_and_sharpens_at_full_resolution() -> None:
    img, depth = plane_view()
    conf = np.ones_like(depth)
    m = _mapper(n_random_past=0, train_downsample=2, window_size=1)
    T1 = make_T(np.eye(3), np.array([0.5, 0.0, 0.0]))
    m.add_keyframe(0, img, np.eye(4), depth, conf)
    m.optimize(10)
    img1, _ = plane_view(seed=0)
    m.add_keyframe(1, img1, T1, depth, conf)
    m.optimize(10)  # window 1: keyframe 0 is no longer trained here
    before = _full_res_l1(m)
    it0 = m.iterations
    m.refine(30, downsample=1)
    assert m.iterations == it0 + 30
    after = _full_res_l1(m)
    assert all(a < b for a, b in zip(after, before, strict=True)), (before, after)
    # round-robin over the keyframes: 30 iterations on 2 keyframes end where they started
    assert m._refine_next == 0
    m.refine(1)
    assert m._refine_next == 1
    with pytest.raises(ConfigError, match="downsample"):
        m.refine(1, downsample=0)
    # the keyframe's half-resolution targets stay cached; other factors are made on the fly
    kf = m.keyframes[0]
    assert kf.targets(2)[0].shape == (H // 2, W // 2, 3)
    assert kf.targets(4)[0].shape == (H // 4, W // 4, 3)
    assert kf.targets(2)[0].shape == (H // 2, W // 2, 3)


def test_final_refinement_decays_its_learning_rates_over_the_whole_refinement() -> None:
    """refine_lr_scale x the drive's rates at the start, decayed exponentially to refine_lr_final
    of that at the end of ``total_iters``, also when the node runs it in chunks; the depth weight
    is refine_lambda_depth's."""
    img, depth = plane_view()
    m = _mapper(n_random_past=0, refine_lr_scale=4.0, refine_lr_final=0.25, refine_lambda_depth=0.0)
    m.add_keyframe(0, img, np.eye(4), depth, np.ones_like(depth))
    seen: list[tuple[float, float | None]] = []
    step = m._train_step
    m._train_step = lambda i, f, lrs, **kw: (  # type: ignore[method-assign]
        seen.append((lrs["means"] / m.params.lr_means_m, kw["depth_w"])) or step(i, f, lrs, **kw)
    )
    m.refine(2, total_iters=4)
    m.refine(2, total_iters=4)
    gains = [g for g, _ in seen]
    np.testing.assert_allclose(gains, [4.0 * 0.25 ** (k / 4) for k in range(4)], rtol=1e-12)
    assert {w for _, w in seen} == {0.0}
    for bad in ({"refine_lr_scale": 0.0}, {"refine_lr_final": -1.0}, {"refine_lambda_depth": 2}):
        with pytest.raises(ConfigError, match="refine_"):
            MapperParams(**bad)


def test_mapper_optimises_only_what_the_window_sees() -> None:
    img, depth = plane_view()
    m = _mapper(n_random_past=0, window_size=1)
    m.add_keyframe(0, img, np.eye(4), depth, np.ones_like(depth))
    m.optimize(2)
    # a second keyframe looking the other way: its window does not see keyframe 0's Gaussians
    T_back = make_T(rotmat_from_rpy(0.0, np.pi, 0.0), np.zeros(3))
    m.add_keyframe(1, img, T_back, depth, np.ones_like(depth))
    m.drain_changes()
    old_rows = m.map.birth_kf == 0
    before = m.map.params["means"][old_rows].clone()
    m.optimize(3)
    assert torch.equal(m.map.params["means"][old_rows], before)
    changed = set(m.drain_changes().ids.tolist())
    assert changed and changed.isdisjoint(set(m.map.ids[old_rows].tolist()))


def test_mapper_prunes_transparent_gaussians_and_reports_removals() -> None:
    img, depth = plane_view()
    m = _mapper(n_random_past=0)
    m.add_keyframe(0, img, np.eye(4), depth, np.ones_like(depth))
    m.map.params["opacity_logit"][:10] = -20.0
    m.drain_changes()
    m.optimize(1)
    ch = m.drain_changes()
    assert len(ch.removed_ids) >= 10 and set(range(10)) <= set(ch.removed_ids.tolist())
    assert m.stats()["n_pruned"] >= 10


def test_mapper_prunes_redundant_gaussians_hidden_behind_a_wall() -> None:
    img, depth = plane_view()
    m = _mapper(n_random_past=0, prune_contrib_px=1.0)
    m.add_keyframe(0, img, np.eye(4), depth, np.ones_like(depth))
    m.map.params["opacity_logit"][:] = 8.0  # an opaque wall at 5 m
    n_wall = len(m.map)
    hidden = {k: v[:5].clone() for k, v in m.map.params.items()}
    hidden["means"][:, 2] = 9.0  # behind the wall, same pixels
    m.map.add(hidden, birth_kf=0)
    hidden_ids = set(m.map.ids[n_wall:].tolist())
    # the forward pass's blending weights: the wall draws, the hidden ones do not
    r = m.render_view(np.eye(4))
    assert float(r.weights[:n_wall].sum()) > 0.9 * H * W and float(r.weights[n_wall:].max()) < 0.1
    # unknown until the keyframe is rendered after their insertion: not judged
    _, judged = m._contribution([0])
    assert not bool(judged[n_wall:].any())
    # Gaussians born at the newest keyframe are not judged yet
    m.optimize(1)  # renders keyframe 0: its weight record now covers them
    contrib, judged = m._contribution([0])
    hid = torch.as_tensor([i in hidden_ids for i in m.map.ids.tolist()])
    assert int(hid.sum()) == 5 and bool(judged[hid].all()) and float(contrib[hid].max()) < 0.1
    assert float(contrib[~hid].sum()) > 0.9 * H * W
    assert hidden_ids <= set(m.map.ids.tolist())
    m.add_keyframe(1, img, np.eye(4), depth, np.ones_like(depth))
    m.optimize(1)
    assert hidden_ids.isdisjoint(set(m.map.ids.tolist()))
    # what is pruned was not drawn: the wall still covers the view
    assert float(m.render_view(np.eye(4)).alpha.mean()) > 0.95


def test_mapper_rejects_bad_inputs() -> None:
    img, depth = plane_view()
    m = _mapper()
    with pytest.raises(ShapeError, match="depth_m"):
        m.add_keyframe(0, img, np.eye(4), depth[:-1], np.ones_like(depth))
    with pytest.raises(ShapeError, match="T_world_cam"):
        m.add_keyframe(0, img, np.full((4, 4), np.nan), depth, np.ones_like(depth))
    with pytest.raises(ConfigError):
        MapperParams(window_size=0)
    with pytest.raises(ConfigError, match="planar_tol"):
        InsertionParams(planar_tol=-0.1)
    with pytest.raises(ConfigError, match="max_footprint_rad"):
        InsertionParams(max_footprint_rad=0.0)


def test_footprint_cap_keeps_coarse_gaussians_below_the_size_pruning() -> None:
    # a short focal length (20 px): uncapped, the confident planar stride 8 would be a 0.4 rad
    # footprint, twice the mapper's size pruning (sigma > 0.2 x distance): all would be removed
    img, depth = plane_view()
    K20 = np.array([[20.0, 0, 31.5], [0, 20.0, 15.5], [0, 0, 1]])
    conf = np.ones_like(depth)
    g = sample_gaussians(img, depth, conf, np.ones((H, W), bool), K20, np.eye(4), InsertionParams())
    sigma = np.exp(g["log_scales"].numpy())
    np.testing.assert_allclose(sigma, 3 * 5.0 / 20.0, rtol=1e-5)  # int(0.15 x 20) = 3 px
    m = GaussianMapper(MapperParams(n_random_past=0), K20, W, H)
    n = m.add_keyframe(0, img, np.eye(4), depth, conf)
    m.optimize(1)
    assert n == len(g["means"]) and len(m.map) == n


def test_psnr_and_ssim_known_values() -> None:
    from mogs_node.mapper.image_metrics import psnr_db, ssim

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (20, 30, 3))
    assert ssim(img, img) == pytest.approx(1.0)
    assert psnr_db(0.9 * img + 0.1, 0.9 * img) == pytest.approx(20.0)
    assert psnr_db(np.full((4, 4, 3), 0.5), np.full((4, 4, 3), 0.6)) == pytest.approx(20.0)
    noisy = np.clip(img + rng.normal(0, 0.2, img.shape), 0, 1)
    assert 0.0 < ssim(noisy, img) < 0.9
    assert psnr_db((img * 255).astype(np.uint8), img) > 40.0


def test_map_eval_ratios_bound_when_random_never_reaches_target() -> None:
    from mogs_node.eval.map import _ratios

    inits = {
        "mogs": {"iters_to_target": 60, "gaussians_at_target": 900, "gaussians_at_budget": 1000},
        "random": {
            "iters_to_target": None,
            "gaussians_at_target": None,
            "gaussians_at_budget": 500,
        },
    }
    r = _ratios(inits, budget=300)
    assert r["iters_ratio_mogs_vs_random"] == pytest.approx(0.2) and r["iters_ratio_is_upper_bound"]
    assert r["gaussians_ratio_mogs_vs_random"] is None
    assert r["gaussians_at_budget_ratio_mogs_vs_random"] == pytest.approx(2.0)
    assert r["gaussians_ratio_mogs_target_vs_random_budget"] == pytest.approx(1.8)
    inits["random"]["iters_to_target"] = 120
    inits["random"]["gaussians_at_target"] = 1800
    r = _ratios(inits, budget=300)
    assert (
        r["iters_ratio_mogs_vs_random"] == pytest.approx(0.5)
        and not r["iters_ratio_is_upper_bound"]
    )
    assert r["gaussians_ratio_mogs_vs_random"] == pytest.approx(0.5)


def test_map_eval_overrides_parse_into_one_policy_for_every_init() -> None:
    from mogs_node.eval.map import _parse_override, overrides_from

    pairs = [_parse_override(s) for s in ("densify=true", "insertion.color_tol=0.1")]
    o = overrides_from(pairs + [_parse_override("densify_grad_px=6e-6")])
    assert o["densify"] is True and o["densify_grad_px"] == pytest.approx(6e-6)
    assert o["insertion"] == InsertionParams(color_tol=0.1)
    with pytest.raises(ConfigError, match="no_such"):
        overrides_from([("no_such", 1)])
    with pytest.raises(ConfigError, match="raster"):
        overrides_from([("raster", 1)])


def _drive_behind(m: GaussianMapper, n_kf: int) -> None:
    """``n_kf`` keyframes along a wall, each mapped with no iteration (the node behind its input
    with ``iters_when_behind: 0``, as launch/kitti.yaml): insertion only, no pruning."""
    for i in range(n_kf):
        img, depth = plane_view(seed=i)
        T = make_T(np.eye(3), np.array([3.0 * i, 0.0, 0.0]))
        m.add_keyframe(i, img, T, depth, np.ones_like(depth))
        m.optimize(0)


def test_keyframes_mapped_behind_keep_their_gaussians_until_they_are_optimised() -> None:
    """Keyframes mapped while behind leave the window before any pruning runs: their Gaussians
    were seen (by the keyframe that inserted them) but never optimised. The next round must not
    prune them as unsupported or redundant (on the KITTI launch this emptied the map: 475k of
    545k Gaussians pruned, held-out 7.7 dB); the owed iterations then go to them."""
    m = _mapper(window_size=3, insertion=InsertionParams(planar_tol=0.0))
    _drive_behind(m, 10)
    n = len(m.map)
    assert m.window == [9, 8, 7] and int(m.map.steps.max()) == 0
    assert bool((m.map.n_obs >= 1).all())  # the inserting keyframe's observation is recorded
    m.optimize(2)  # one window round: the first pruning since the drive began
    assert m.n_pruned == 0 and len(m.map) == n
    # the owed iterations (the node's idle time) go to the keyframes trained least
    m.catch_up(20)
    iters = [kf.iterations for kf in m.keyframes]
    assert sum(iters) == 22 and min(iters) == 2  # the window round gave 2 of them theirs
    never_drawn = int((m.map.steps == 0).sum())
    assert never_drawn < 0.05 * len(m.map)
    # optimised now, the same rules apply to them as to any Gaussian: nothing transparent stays
    assert float(torch.sigmoid(m.map.params["opacity_logit"]).min()) >= m.params.prune_opacity
