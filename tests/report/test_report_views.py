"""Final-map views of the run report (mogs_node/report/views.py): exact expectations."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ShapeError
from mogs_node.geometry import make_T, so3_exp
from mogs_node.mapper.gaussians import GaussianMap
from mogs_node.mapper.ply import read_gaussian_ply, write_gaussian_ply
from mogs_node.mapper.rasterizer import RasterParams
from mogs_node.report.views import (
    FIELDS,
    FrameStore,
    MapReplica,
    choose_heldout,
    depth_to_color,
    image_to_rgb,
    map_digest,
    render_map_view,
    score_view,
    side_by_side,
)

# A screen-space dilation small enough that a Gaussian's footprint ends before the next pixel:
# with sigma^2 = 0.01 + 0.05 px^2 a neighbour one pixel away has alpha 0.99 exp(-1 / 0.12)
# = 2.4e-4 < 1/255, so it is skipped and each pixel sees its own Gaussian only.
TIGHT = RasterParams(backend="torch", eps2d_px2=0.05)  # torch: the C++ backend's semantics
ALPHA_MAX = TIGHT.alpha_max


def _pixel_map(
    rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray
) -> dict[str, np.ndarray]:
    """One opaque isotropic Gaussian per pixel, at the pixel's back-projection, with a screen
    standard deviation of 0.1 px (world sigma = 0.1 depth / f)."""
    H, W = depth_m.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = depth_m.astype(np.float64)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    p_cam = np.stack([x, y, z], -1).reshape(-1, 3)
    p_world = p_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    n = H * W
    sigma = 0.1 * z.reshape(-1) / K[0, 0]
    return {
        "means": p_world.astype(np.float32),
        "quats_wxyz": np.tile(np.array([1.0, 0, 0, 0], np.float32), (n, 1)),
        "log_scales": np.repeat(np.log(sigma)[:, None], 3, 1).astype(np.float32),
        "opacity_logit": np.full(n, 12.0, np.float32),  # sigmoid > alpha_max: clamped
        "colors_rgb": rgb.reshape(-1, 3).astype(np.float32) / 255.0,
    }


def _scene(seed: int, H: int = 24, W: int = 32, depth_scale: float = 1.0):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    u = np.arange(W)[None, :]
    depth = (4.0 + 0.05 * u + 0.1 * np.arange(H)[:, None]) * depth_scale  # a tilted plane
    K = np.array([[30.0, 0, (W - 1) / 2 + 0.3], [0, 28.0, (H - 1) / 2 - 0.2], [0, 0, 1]])
    T = make_T(so3_exp(rng.normal(0, 0.5, 3)), rng.normal(0, 10.0, 3))
    return rgb, depth.astype(np.float64), K, T


def test_a_map_built_from_an_image_renders_it_back_within_the_construction_bound() -> None:
    rgb, depth, K, T = _scene(0)
    H, W = depth.shape
    bg = (0.2, 0.5, 0.9)
    arrays = _pixel_map(rgb, depth, K, T)
    out, d, alpha = render_map_view(arrays, T, K, W, H, background_rgb=bg, raster=TIGHT)
    # each pixel: its own Gaussian at alpha_max, then the background with T = 1 - alpha_max
    gt = rgb / 255.0
    expected = ALPHA_MAX * gt + (1 - ALPHA_MAX) * np.array(bg)
    np.testing.assert_allclose(out, expected, atol=1e-5)
    np.testing.assert_allclose(alpha, ALPHA_MAX, atol=1e-6)
    np.testing.assert_allclose(d, depth, rtol=1e-4)  # expected depth = the pixel's depth
    # the PSNR bound of the construction: error (1 - alpha_max) |bg - c| per channel
    mse_bound = float(np.mean(((1 - ALPHA_MAX) * (np.array(bg) - gt)) ** 2))
    bound_db = -10 * math.log10(mse_bound)
    psnr, s = score_view(rgb, out)
    assert psnr >= bound_db - 0.05 and bound_db > 40
    assert s > 0.99
    # the same map seen from a pose 0.5 m to the side is not the image: the test can fail
    T_off = T @ make_T(np.eye(3), np.array([0.5, 0.0, 0.0]))
    out2, _, _ = render_map_view(arrays, T_off, K, W, H, background_rgb=bg, raster=TIGHT)
    assert score_view(rgb, out2)[0] < 20


def test_render_back_with_the_default_rasterizer_settings() -> None:
    """Default dilation (0.3 px^2): a pixel also mixes in its neighbours, yet it sees its own
    Gaussian at alpha_max, so on an image of uniform 8 x 8 blocks the pixels whose neighbours
    within the footprint radius (alpha < 1/255 beyond) share their colour are exact up to
    (1 - alpha_max) |bg - c|, and every other pixel is a convex mix of its neighbours' colours."""
    rng = np.random.default_rng(1)
    H, W, B = 32, 48, 8
    blocks = rng.integers(0, 256, (H // B, W // B, 3), dtype=np.uint8)
    rgb = np.repeat(np.repeat(blocks, B, 0), B, 1)
    depth = np.full((H, W), 6.0)
    K = np.array([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])
    T = make_T(so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, -3.0]))
    torch_backend = RasterParams(backend="torch")  # default settings, no compilation
    out, _, _ = render_map_view(_pixel_map(rgb, depth, K, T), T, K, W, H, raster=torch_backend)
    sigma2 = 0.1**2 + RasterParams().eps2d_px2
    radius = math.sqrt(2 * sigma2 * math.log(ALPHA_MAX * 255))
    pos = np.arange(B)
    inner = (pos - radius > -0.5) & (pos + radius < B - 0.5)
    interior = np.tile(inner, H // B)[:, None] & np.tile(inner, W // B)[None, :]
    assert interior.sum() > 0
    gt = rgb / 255.0
    assert np.abs(out - gt)[interior].max() <= 1 - ALPHA_MAX + 1e-5
    # elsewhere bounded by the largest colour step between adjacent blocks (+ the background)
    step = max(
        np.abs(np.diff(blocks.astype(float), axis=0)).max(),
        np.abs(np.diff(blocks.astype(float), axis=1)).max(),
    )
    diag = np.abs(blocks[1:, 1:].astype(float) - blocks[:-1, :-1]).max()
    diag2 = np.abs(blocks[1:, :-1].astype(float) - blocks[:-1, 1:]).max()
    assert np.abs(out - gt).max() <= max(step, diag, diag2) / 255 + 1 - ALPHA_MAX + 1e-5


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), depth_scale=st.sampled_from([0.02, 1.0, 50.0, 3000.0]))
def test_render_back_holds_at_tiny_and_huge_scales(seed: int, depth_scale: float) -> None:
    rgb, depth, K, T = _scene(seed, H=12, W=16, depth_scale=depth_scale)
    T[:3, 3] *= depth_scale
    out, d, _ = render_map_view(_pixel_map(rgb, depth, K, T), T, K, 16, 12, raster=TIGHT)
    np.testing.assert_allclose(out, ALPHA_MAX * rgb / 255.0, atol=2e-5)
    np.testing.assert_allclose(d, depth, rtol=1e-3)


def test_an_empty_map_renders_the_background_with_no_depth() -> None:
    arrays = {k: np.zeros((0, w) if w else (0,), np.float32) for k, w in FIELDS.items()}
    rgb, d, a = render_map_view(
        arrays,
        np.eye(4),
        np.diag([10.0, 10.0, 1.0]),
        8,
        6,
        background_rgb=(0.5, 0.25, 1.0),
        raster=TIGHT,
    )
    np.testing.assert_array_equal(rgb, np.broadcast_to([0.5, 0.25, 1.0], (6, 8, 3)))
    assert not d.any() and not a.any()


def test_bad_inputs_name_what_is_wrong() -> None:
    rgb, depth, K, T = _scene(0, 4, 4)
    arrays = _pixel_map(rgb, depth, K, T)
    bad_T = T.copy()
    bad_T[0, 3] = np.nan
    with pytest.raises(ShapeError, match="T_world_cam"):
        render_map_view(arrays, bad_T, K, 4, 4)
    with pytest.raises(ShapeError, match="focal"):
        render_map_view(arrays, T, np.diag([0.0, 1.0, 1.0]), 4, 4)
    with pytest.raises(ShapeError, match="colors_rgb"):
        render_map_view({**arrays, "colors_rgb": arrays["colors_rgb"][:3]}, T, K, 4, 4)
    with pytest.raises(ShapeError, match="width/height"):
        render_map_view(arrays, T, K, 0, 4)
    with pytest.raises(ShapeError, match="render_rgb"):
        score_view(rgb, np.zeros((3, 4, 3)))


def _random_values(rng: np.random.Generator, n: int) -> dict[str, torch.Tensor]:
    return {
        "means": torch.as_tensor(rng.normal(size=(n, 3)), dtype=torch.float32),
        "quats_wxyz": torch.as_tensor(rng.normal(size=(n, 4)), dtype=torch.float32),
        "log_scales": torch.as_tensor(rng.normal(size=(n, 3)), dtype=torch.float32),
        "opacity_logit": torch.as_tensor(rng.normal(size=n), dtype=torch.float32),
        "colors": torch.as_tensor(rng.uniform(size=(n, 3)), dtype=torch.float32),
    }


def _apply(replica: MapReplica, m: GaussianMap) -> None:
    ch = m.drain_changes()
    replica.apply(
        ch.ids,
        ch.removed_ids,
        {
            "means": ch.means,
            "quats_wxyz": ch.quats_wxyz,
            "log_scales": ch.log_scales,
            "opacity_logit": ch.opacity_logit,
            "colors_rgb": ch.colors,
        },
    )


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), rounds=st.integers(1, 6))
def test_the_replica_equals_the_mappers_map_after_its_increments(seed: int, rounds: int) -> None:
    rng = np.random.default_rng(seed)
    m, replica = GaussianMap(), MapReplica()
    for k in range(rounds):
        m.add(_random_values(rng, int(rng.integers(0, 30))), birth_kf=k)
        if len(m):
            rows = torch.as_tensor(np.flatnonzero(rng.uniform(size=len(m)) < 0.5))
            if len(rows):
                grads = {kk: torch.randn_like(v[rows]) for kk, v in m.params.items()}
                m.adam_step(rows, grads, dict.fromkeys(m.params, 0.01))
            m.remove(torch.as_tensor(rng.uniform(size=len(m)) < 0.2))
        _apply(replica, m)
    np.testing.assert_array_equal(replica.ids, m.ids.numpy())
    for name, ours in zip(FIELDS, ("means", "quats_wxyz", "log_scales", "opacity_logit", "colors")):
        np.testing.assert_array_equal(replica.arrays[name], m.params[ours].numpy())
    assert replica.updates == rounds


def test_replica_rejects_malformed_updates() -> None:
    r = MapReplica()
    good = {k: np.zeros((2, w) if w else (2,), np.float32) for k, w in FIELDS.items()}
    with pytest.raises(ShapeError, match="twice"):
        r.apply(np.array([1, 1]), np.zeros(0, np.int64), good)
    with pytest.raises(ShapeError, match="log_scales"):
        r.apply(np.array([1, 2]), np.zeros(0, np.int64), {**good, "log_scales": np.zeros((2, 2))})
    with pytest.raises(ShapeError, match="missing 'means'"):
        r.apply(
            np.array([1, 2]), np.zeros(0, np.int64), {k: v for k, v in good.items() if k != "means"}
        )
    assert len(r) == 0 and r.updates == 0


def test_map_digest_of_a_replica_matches_its_ply(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    m, replica = GaussianMap(), MapReplica()
    m.add(_random_values(rng, 50), birth_kf=0)
    m.remove(torch.as_tensor(rng.uniform(size=50) < 0.3))
    _apply(replica, m)
    p = m.params
    write_gaussian_ply(
        tmp_path / "map.ply",
        p["means"].numpy(),
        p["quats_wxyz"].numpy(),
        p["log_scales"].numpy(),
        p["opacity_logit"].numpy(),
        p["colors"].numpy(),
    )
    ply = read_gaussian_ply(tmp_path / "map.ply")
    assert map_digest(ply["means"]) == map_digest(replica.arrays["means"])
    assert map_digest(ply["means"][::-1]) != map_digest(replica.arrays["means"])


def test_heldout_choice_is_deterministic_spread_and_excludes_keyframes() -> None:
    stamps = np.arange(100) * 10
    kfs = stamps[5::9]  # keyframes 50, 140, ..., 950
    got = choose_heldout(stamps[::-1], kfs, 10)  # order of the input does not matter
    cand = np.array([s for s in stamps if s not in set(kfs) and kfs[0] < s < kfs[-1]])
    idx = np.round(np.linspace(0, len(cand) - 1, 10)).astype(int)
    np.testing.assert_array_equal(got, cand[idx])
    assert got[0] == cand[0] and got[-1] == cand[-1]
    assert not np.isin(got, kfs).any()
    gaps = np.diff(np.searchsorted(cand, got))
    assert gaps.max() - gaps.min() <= 1  # evenly spread over the candidates
    np.testing.assert_array_equal(got, choose_heldout(stamps, kfs, 10))
    # fewer candidates than asked: all of them; none asked or no keyframe: none
    np.testing.assert_array_equal(choose_heldout(stamps[:20], kfs[:2], 50), stamps[6:14])
    assert len(choose_heldout(stamps, kfs, 0)) == 0
    assert len(choose_heldout(stamps, [], 10)) == 0
    assert len(choose_heldout(stamps, [], 10, within_keyframes=False)) == 10
    with pytest.raises(ShapeError, match="n: must be"):
        choose_heldout(stamps, kfs, -1)


def test_heldout_choice_is_even_in_distance_travelled() -> None:
    """20 frames standing still, then 1 m per frame: the standing frames count once."""
    i = np.arange(60)
    pos = np.stack([np.maximum(0, i - 20), np.zeros(60), np.zeros(60)], 1).astype(float)
    kfs = [5, 15, 30, 50, 58]
    got = choose_heldout(i[::-1], kfs, 10, positions_m=pos[::-1])
    # candidates 6..57 without keyframes, path length 37 m; targets 0, 4.1, ..., 37 m: the
    # first candidate at or after each
    np.testing.assert_array_equal(got, [6, 25, 29, 33, 37, 41, 45, 49, 53, 57])
    # the vehicle never moves: the first candidate, then the index spread fills the places
    still = choose_heldout(i, kfs, 10, positions_m=np.zeros((60, 3)))
    assert len(still) == 10 and still[0] == 6 and not np.isin(still, kfs).any()
    with pytest.raises(ShapeError, match="positions_m"):
        choose_heldout(i, kfs, 10, positions_m=np.zeros((59, 3)))


@settings(max_examples=60, deadline=None)
@given(
    n_frames=st.integers(0, 400),
    kf_every=st.integers(2, 30),
    n=st.integers(1, 40),
    seed=st.integers(0, 1000),
)
def test_heldout_choice_properties(n_frames: int, kf_every: int, n: int, seed: int) -> None:
    stamps = np.arange(n_frames, dtype=np.int64) * 7
    kfs = stamps[::kf_every]
    rng = np.random.default_rng(seed)
    steps = rng.uniform(0, 2, (n_frames, 3)) * (rng.uniform(size=(n_frames, 1)) < 0.5)
    for pos in (None, np.cumsum(steps, 0)):
        got = choose_heldout(stamps, kfs, n, positions_m=pos)
        inside = (stamps > kfs[0]) & (stamps < kfs[-1]) if len(kfs) else False
        n_cand = int(np.sum(~np.isin(stamps, kfs) & inside))
        assert len(got) == min(n, n_cand) and len(np.unique(got)) == len(got)
        assert not np.isin(got, kfs).any() and np.all(np.diff(got) > 0)
        if len(got):
            assert kfs[0] < got.min() and got.max() < kfs[-1]


@settings(max_examples=40, deadline=None)
@given(max_frames=st.integers(1, 40), n_images=st.integers(0, 500))
def test_frame_store_keeps_a_bounded_even_sample(max_frames: int, n_images: int) -> None:
    fs = FrameStore(max_frames)
    for i in range(n_images):
        fs.add(1000 + i, np.full((2, 2, 3), i % 256, np.uint8))
    kept = sorted(fs.images)
    assert len(kept) <= max_frames
    idx = np.array(kept, np.int64) - 1000
    assert np.all(idx % fs.stride == 0)  # every stride-th image, from the first one
    # nothing that qualifies is missing: the sample is every stride-th image seen
    assert len(kept) == (n_images + fs.stride - 1) // fs.stride
    assert n_images == 0 or kept[0] == 1000


def test_frame_store_rejects_a_zero_budget() -> None:
    with pytest.raises(ShapeError, match="max_frames"):
        FrameStore(0)


def test_image_encodings_to_rgb() -> None:
    bgr = np.zeros((2, 3, 3), np.uint8)
    bgr[..., 0] = 200  # blue
    np.testing.assert_array_equal(image_to_rgb(bgr, "bgr8")[..., 2], 200)
    np.testing.assert_array_equal(image_to_rgb(bgr, "rgb8"), bgr)
    mono = np.arange(6, dtype=np.uint8).reshape(2, 3)
    assert image_to_rgb(mono, "mono8").shape == (2, 3, 3)
    with pytest.raises(ShapeError, match="uint8"):
        image_to_rgb(bgr.astype(np.float32))


def test_side_by_side_holds_the_three_panels() -> None:
    rng = np.random.default_rng(2)
    gt = rng.integers(0, 256, (10, 12, 3), dtype=np.uint8)
    render = rng.uniform(size=(10, 12, 3)).astype(np.float32)
    depth = np.linspace(1, 50, 120).reshape(10, 12)
    depth[0, 0] = 0.0  # no depth: black
    pic = side_by_side(gt, render, depth, band_px=6, gap_px=2)
    assert pic.shape == (16, 3 * 12 + 4, 3) and pic.dtype == np.uint8
    np.testing.assert_array_equal(pic[6:, :12], gt)
    np.testing.assert_array_equal(pic[6:, 14:26], (render * 255 + 0.5).astype(np.uint8))
    np.testing.assert_array_equal(pic[6:, 28:40], depth_to_color(depth))
    assert not pic[6, 28].any()


@settings(max_examples=40, deadline=None)
@given(
    scale=st.floats(1e-4, 1e5),
    bad=st.sampled_from(["none", "nan", "inf", "zero", "negative", "all_bad"]),
)
def test_depth_colors_at_any_scale_and_with_invalid_pixels(scale: float, bad: str) -> None:
    d = np.linspace(1.0, 10.0, 30).reshape(5, 6) * scale
    if bad == "all_bad":
        d[:] = np.nan
    elif bad != "none":
        d[2, 3] = {"nan": np.nan, "inf": np.inf, "zero": 0.0, "negative": -1.0}[bad]
    c = depth_to_color(d)
    assert c.shape == (5, 6, 3) and c.dtype == np.uint8
    if bad == "all_bad":
        assert not c.any()
        return
    if bad not in ("none",):
        assert not c[2, 3].any()
    # near is warm (red), far is cool (blue) on turbo
    assert int(c[0, 0, 0]) > int(c[0, 0, 2]) and int(c[4, 5, 2]) > int(c[4, 5, 0])
