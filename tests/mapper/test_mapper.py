"""Mapper core: Gaussian map bookkeeping, window, optimisation, pruning, PLY (insertion:
test_mapper_insertion.py; image metrics: test_mapper_image_metrics.py; ``mogs eval map``: tests/eval)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.geometry import make_T, rotmat_from_rpy
from mogs_node.mapper.gaussians import PARAM_NAMES, GaussianMap
from mogs_node.mapper.insertion import InsertionParams, background_mask, sample_gaussians
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
