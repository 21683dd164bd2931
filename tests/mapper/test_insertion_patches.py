"""Object-guided insertion (``insertion_patches.py``): one flat Gaussian per planar depth patch,
fine pixel-grid Gaussians elsewhere, the same rule for every depth source (docs/mapper.md)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError
from mogs_node.geometry import quat_wxyz_to_rotmat
from mogs_node.mapper.insertion import InsertionParams, sample_gaussians
from mogs_node.mapper.insertion_patches import plane_patches, surface_patches

H, W = 64, 96
F_PX = 80.0
K = np.array([[F_PX, 0, W / 2], [0, F_PX, H / 2], [0, 0, 1]])
GREY = np.full((H, W, 3), 120, np.uint8)
PATCH = dict(
    patch_px=16,
    min_patch_px=4,
    rel_tol=0.01,
    max_color_std=0.0,
    sigma_frac=0.5,
    thickness=0.1,
    max_footprint_rad=0.5,
)


def plane_depth(normal_cam: np.ndarray, offset_m: float) -> np.ndarray:
    """z-depth [H, W] of the plane ``n . X = offset_m`` (camera frame) along each pixel's ray."""
    vv, uu = np.mgrid[0:H, 0:W]
    x, y = (uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1]
    n = normal_cam / np.linalg.norm(normal_cam)
    return offset_m / (n[0] * x + n[1] * y + n[2])


def covariances(R: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    return R @ (sigmas[:, :, None] ** 2 * np.swapaxes(R, 1, 2))


def test_a_plane_is_one_flat_gaussian_per_largest_patch_on_the_plane_and_aligned() -> None:
    n = np.array([0.2, -0.5, 1.0])
    n /= np.linalg.norm(n)
    d = plane_depth(n, 6.0)
    assert d.min() > 0
    g = surface_patches(GREY, d, np.ones((H, W), bool), K, np.eye(4), **PATCH)
    assert len(g.means_world) == (H // 16) * (W // 16)  # every whole 16 px tile, nothing finer
    assert g.covered.all()
    np.testing.assert_allclose(g.means_world @ n, 6.0, rtol=1e-9)
    R = quat_wxyz_to_rotmat(g.quats_wxyz)
    thin = g.scales_m.argmin(1)
    axis = R[np.arange(len(R)), :, thin]
    np.testing.assert_allclose(np.abs(axis @ n), 1.0, atol=1e-9)
    in_plane = np.sort(g.scales_m, 1)[:, 1:]
    s_mean_lo = in_plane.min(1)
    assert np.all(g.scales_m.min(1) <= 0.1 * in_plane.max(1) + 1e-12)
    assert np.all(g.scales_m.min(1) >= 0.1 * s_mean_lo - 1e-12)
    np.testing.assert_allclose(g.colors_rgb, 120 / 255.0, rtol=1e-6)


def test_a_fronto_parallel_patch_has_the_pixel_footprint_as_its_in_plane_sigma() -> None:
    d = np.full((H, W), 4.0)
    g = surface_patches(GREY, d, np.ones((H, W), bool), K, np.eye(4), **PATCH)
    sigma = 0.5 * 16 * 4.0 / F_PX  # sigma_frac x the back-projected edge
    want = np.diag([sigma**2, sigma**2, (0.1 * sigma) ** 2])
    cov = covariances(quat_wxyz_to_rotmat(g.quats_wxyz), g.scales_m)
    np.testing.assert_allclose(cov, np.broadcast_to(want, cov.shape), atol=1e-12)


def test_the_pose_moves_the_gaussians_into_the_world() -> None:
    d = np.full((H, W), 4.0)
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    T[:3, 3] = [1.0, 2.0, 3.0]
    cam = surface_patches(GREY, d, np.ones((H, W), bool), K, np.eye(4), **PATCH)
    world = surface_patches(GREY, d, np.ones((H, W), bool), K, T, **PATCH)
    np.testing.assert_allclose(world.means_world, cam.means_world @ T[:3, :3].T + T[:3, 3])
    c_cam = covariances(quat_wxyz_to_rotmat(cam.quats_wxyz), cam.scales_m)
    c_world = covariances(quat_wxyz_to_rotmat(world.quats_wxyz), world.scales_m)
    np.testing.assert_allclose(c_world, T[:3, :3] @ c_cam @ T[:3, :3].T, atol=1e-12)


def test_random_depth_gets_no_patch_and_the_same_gaussians_as_without_the_policy() -> None:
    rng = np.random.default_rng(1)
    d = rng.uniform(1.0, 50.0, (H, W)).astype(np.float32)
    c = np.zeros((H, W), np.float32)
    mask = np.ones((H, W), bool)
    g = surface_patches(GREY, d, mask, K, np.eye(4), **PATCH)
    assert len(g.means_world) == 0 and not g.covered.any()
    a = sample_gaussians(GREY, d, c, mask, K, np.eye(4), InsertionParams(patch_px=16))
    b = sample_gaussians(GREY, d, c, mask, K, np.eye(4), InsertionParams())
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_a_depth_step_keeps_its_tiles_fine_and_patches_the_planes_on_either_side() -> None:
    d = np.full((H, W), 5.0)
    d[:, 40:] = 9.0  # step at column 40: inside the 16 px tile 32-47, the 8 px tile 40-47 is flat
    g = surface_patches(GREY, d, np.ones((H, W), bool), K, np.eye(4), **PATCH)
    assert g.covered[:, :40].all() and g.covered[:, 40:].all()  # 8 px tiles close the gap
    p16 = plane_patches(d, np.ones((H, W), bool), GREY, 16)
    assert np.isinf(p16.rel_rms[p16.u0 == 32]).sum() == 0  # complete ...
    assert np.all(p16.rel_rms[p16.u0 == 32] > 0.01)  # ... but not a plane: refused at 16 px
    d[:, 36:] = 9.0  # now inside the 8 px tile 32-39: its pixels stay with the grid (4 px min)
    g = surface_patches(GREY, d, np.ones((H, W), bool), K, np.eye(4), **PATCH)
    assert g.covered[:, 32:36].all()  # 4 px tiles
    assert len(g.means_world) > (H // 16) * (W // 16)


def test_only_whole_tiles_of_the_mask_with_depth_become_patches() -> None:
    d = np.full((H, W), 5.0)
    mask = np.zeros((H, W), bool)
    mask[:, :20] = True  # 16 px tile 0-15 whole, 16-19 only part of the next tile
    d[0, 0] = np.nan  # the top-left 4 px tile loses a pixel
    g = surface_patches(GREY, d, mask, K, np.eye(4), **PATCH)
    assert not g.covered[:, 20:].any()
    assert not g.covered[0:4, 0:4].any()
    assert g.covered[4:, 0:20].all() and g.covered[0:4, 4:20].all()
    assert np.all(np.isfinite(g.means_world))


def test_a_textured_patch_stays_fine_under_the_colour_test() -> None:
    rng = np.random.default_rng(2)
    img = GREY.copy()
    img[:16, :16] = rng.integers(0, 255, (16, 16, 3), dtype=np.uint8)
    d = np.full((H, W), 5.0)
    g = surface_patches(img, d, np.ones((H, W), bool), K, np.eye(4), **PATCH)
    assert g.covered[:16, :16].all()
    g = surface_patches(
        img, d, np.ones((H, W), bool), K, np.eye(4), **{**PATCH, "max_color_std": 10.0}
    )
    assert not g.covered[:16, :16].any() and g.covered[16:, :].all()


def test_a_grazing_plane_beyond_the_footprint_limit_is_not_a_patch() -> None:
    """A road seen almost edge-on: a patch's back-projected edge grows without bound towards the
    horizon; patches longer than ``max_footprint_rad`` x distance are refused (fine grid)."""
    d = plane_depth(np.array([0.0, -1.0, 0.02]), 1.5)
    d = np.where(d > 0, d, 0.0)  # the sky above the horizon: no depth
    cover = []
    for limit in (0.5, 0.1, 0.05):
        g = surface_patches(
            GREY, d, np.ones((H, W), bool), K, np.eye(4), **{**PATCH, "max_footprint_rad": limit}
        )
        cover.append(g.covered.mean())
        assert not (g.covered & (d <= 0)).any()
    assert cover[0] > cover[1] > cover[2] == 0.0


def test_sample_gaussians_joins_patches_and_the_grid_without_double_cover() -> None:
    d = np.full((H, W), 5.0, np.float32)
    d[:, 48:] = np.random.default_rng(3).uniform(1, 50, (H, W - 48))
    c = np.zeros((H, W), np.float32)
    mask = np.ones((H, W), bool)
    p = InsertionParams(patch_px=16, patch_min_px=8, max_footprint_rad=0.5)
    out = sample_gaussians(GREY, d, c, mask, K, np.eye(4), p)
    patches = (H // 16) * (48 // 16)
    grid = sample_gaussians(
        GREY, d, c, mask & (np.arange(W) >= 48)[None, :], K, np.eye(4), InsertionParams()
    )
    assert len(out["means"]) == patches + len(grid["means"])
    assert all(len(v) == len(out["means"]) for v in out.values())
    assert bool(torch.isfinite(out["log_scales"]).all())


@pytest.mark.parametrize(
    "bad",
    [
        {"patch_px": -1},
        {"patch_px": 16, "patch_min_px": 1},
        {"patch_rel_tol": -0.1},
        {"patch_max_color_std": -1.0},
        {"patch_sigma_frac": 0.0},
        {"patch_thickness": 0.0},
    ],
)
def test_bad_patch_settings_are_one_config_error(bad: dict) -> None:
    with pytest.raises(ConfigError, match="patch"):
        InsertionParams(**bad)


@settings(max_examples=40, deadline=None)
@given(
    tilt=st.tuples(st.floats(-0.6, 0.6), st.floats(-0.6, 0.6)),
    offset_m=st.floats(1e-2, 1e4),
    holes=st.integers(0, 30),
    seed=st.integers(0, 2**16),
)
def test_any_plane_at_any_scale_gives_finite_gaussians_on_it(
    tilt: tuple[float, float], offset_m: float, holes: int, seed: int
) -> None:
    """Planes from 1 cm to 10 km, with NaN / inf / 0 holes: every Gaussian is finite, lies on
    the plane, and no accepted patch holds a hole."""
    n = np.array([tilt[0], tilt[1], 1.0])
    n /= np.linalg.norm(n)
    d = plane_depth(n, offset_m)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, H * W, holes)
    d.ravel()[idx] = rng.choice([np.nan, np.inf, 0.0, -1.0], holes)
    g = surface_patches(GREY, d, np.ones((H, W), bool), K, np.eye(4), **PATCH)
    assert np.all(np.isfinite(g.means_world)) and np.all(np.isfinite(g.scales_m))
    assert np.all(g.scales_m > 0) and np.all(np.isfinite(g.quats_wxyz))
    np.testing.assert_allclose(g.means_world @ n, offset_m, rtol=1e-6)
    bad = ~(np.isfinite(d) & (d > 0))
    assert not (g.covered & bad).any()


def test_the_mapper_node_param_switches_the_policy_on_for_the_core() -> None:
    from mogs_node.mapper.node import MapperNodeParams

    assert MapperNodeParams().mapper_params().insertion.patch_px == 0  # the demo: off
    assert MapperNodeParams(insertion_patch_px=32).mapper_params().insertion.patch_px == 32
