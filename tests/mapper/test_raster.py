"""CPU rasterizer: tile backends against the per-pixel reference, gradients, numerical stress."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.geometry import se3_exp
from mogs_node.mapper.composite import cpp_extension_available
from mogs_node.mapper.projection import se3_exp_torch
from mogs_node.mapper.rasterizer import GaussianTensors, RasterParams, render


def render_reference(scene, T, K, width, height, *, params=RasterParams(), **kw):  # noqa: B008
    """The slow per-pixel reference: :func:`render`'s ``"reference"`` backend."""
    return render(scene, T, K, width, height, params=replace(params, backend="reference"), **kw)


BACKENDS = [
    "torch",
    pytest.param(
        "cpp",
        marks=pytest.mark.skipif(
            not cpp_extension_available(), reason="C++ extension could not be compiled here"
        ),
    ),
]


def random_scene(n: int, seed: int, dtype=torch.float32, depth_m: float = 4.0) -> GaussianTensors:
    g = torch.Generator().manual_seed(seed)
    spread = torch.tensor([1.5, 0.8, 1.0], dtype=dtype)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * spread + torch.tensor(
        [0, 0, depth_m], dtype=dtype
    )
    return GaussianTensors(
        means=means,
        quats_wxyz=torch.randn(n, 4, generator=g, dtype=dtype),
        log_scales=torch.randn(n, 3, generator=g, dtype=dtype) * 0.4 - 1.6,
        opacity_logit=torch.randn(n, generator=g, dtype=dtype) * 2.0,
        colors=torch.rand(n, 3, generator=g, dtype=dtype),
    )


def pose(dtype=torch.float32) -> torch.Tensor:
    T = torch.as_tensor(se3_exp(np.array([0.1, -0.05, 0.2, 0.02, -0.03, 0.01])), dtype=dtype)
    return T


K_SMALL = (30.0, 30.0, 19.5, 11.5)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tile_backend_matches_per_pixel_reference(backend: str, seed: int) -> None:
    scene = random_scene(80, seed)
    bg = torch.tensor([0.1, 0.2, 0.3])
    params = RasterParams(backend=backend)
    ref = render_reference(scene, pose(), K_SMALL, 40, 24, background=bg, params=params)
    out = render(scene, pose(), K_SMALL, 40, 24, background=bg, params=params)
    assert float(ref.alpha.mean()) > 0.2  # the scene actually covers the image
    assert (out.color - ref.color).abs().max() < 1e-4
    assert (out.depth - ref.depth).abs().max() < 1e-4 * float(ref.depth.max())
    assert (out.alpha - ref.alpha).abs().max() < 1e-4
    assert torch.equal(out.counts, ref.counts)
    assert (out.weights - ref.weights).abs().max() < 1e-4 * max(1.0, float(ref.weights.max()))


@pytest.mark.parametrize("backend", BACKENDS)
def test_forward_weights_equal_colour_gradient_and_sum_to_alpha(backend: str) -> None:
    """The forward's per-Gaussian weight sum_p alpha_i T_i is d(sum of a colour channel) / d
    colour_i (what pruning used to get from a backward pass), and over all Gaussians it sums to
    the image's accumulated alpha; early-terminated pixels included (opaque scene)."""
    scene = random_scene(120, 7)
    scene.opacity_logit = scene.opacity_logit + 3.0
    colors = scene.colors.clone().requires_grad_()
    scene.colors = colors
    out = render(scene, pose(), K_SMALL, 40, 24, params=RasterParams(backend=backend))
    (g,) = torch.autograd.grad(out.color[..., 1].sum(), colors)
    assert float(out.weights.sum()) > 100.0
    assert torch.allclose(out.weights, g[:, 1], rtol=1e-4, atol=1e-5)
    alpha_sum = float(out.alpha.detach().sum())
    assert abs(float(out.weights.sum()) - alpha_sum) < 1e-3 * alpha_sum
    assert torch.equal(out.weights > 0, out.counts > 0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_tile_size_and_early_termination_do_not_change_result(backend: str) -> None:
    scene = random_scene(200, 5)
    scene.opacity_logit = scene.opacity_logit + 4.0  # opaque and large: pixels terminate early
    scene.log_scales = scene.log_scales + 1.0
    a = render(scene, pose(), K_SMALL, 40, 24, params=RasterParams(backend=backend, tile_px=16))
    b = render(scene, pose(), K_SMALL, 40, 24, params=RasterParams(backend=backend, tile_px=5))
    ref = render_reference(scene, pose(), K_SMALL, 40, 24)
    assert float((ref.alpha > 0.999).float().mean()) > 0.5
    assert (a.color - b.color).abs().max() < 1e-5
    assert (a.color - ref.color).abs().max() < 1e-4


def _loss_fn(render_fn, backend: str, K, W: int, H: int, T: torch.Tensor, weights: torch.Tensor):
    def loss(means, quats, log_scales, opacity_logit, colors, xi, bg):
        out = render_fn(
            GaussianTensors(means, quats, log_scales, opacity_logit, colors),
            T,
            K,
            W,
            H,
            background=bg,
            pose_tangent=xi,
            params=RasterParams(backend=backend),
        )
        stacked = torch.cat([out.color, out.depth[..., None], out.alpha[..., None]], -1)
        return (stacked * weights).sum()

    return loss


def _tiny_inputs(seed: int):
    scene = random_scene(10, seed, torch.float64)
    scene.log_scales = scene.log_scales * 0.5 + 0.4  # a few pixels wide at K_TINY
    xi = torch.zeros(6, dtype=torch.float64)
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    return [t.clone().requires_grad_() for t in (*scene.tensors(), xi, bg)]


K_TINY = (12.0, 12.0, 9.5, 6.5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_float64_tiny_scene(backend: str) -> None:
    inputs = _tiny_inputs(3)
    w = torch.rand(14, 20, 5, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    fn = _loss_fn(render, backend, K_TINY, 20, 14, pose(torch.float64), w)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_match_reference(backend: str) -> None:
    inputs = _tiny_inputs(7)
    w = torch.rand(14, 20, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    T = pose(torch.float64)
    g_ref = torch.autograd.grad(
        _loss_fn(render_reference, backend, K_TINY, 20, 14, T, w)(*inputs), inputs
    )
    g = torch.autograd.grad(_loss_fn(render, backend, K_TINY, 20, 14, T, w)(*inputs), inputs)
    assert all(float(a.abs().max()) > 0 for a in g_ref)  # every input really gets a gradient
    for a, b in zip(g, g_ref, strict=True):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-7)


@pytest.mark.skipif(not cpp_extension_available(), reason="C++ extension could not be compiled")
def test_cpp_gradients_are_bitwise_repeatable_with_several_threads() -> None:
    """Same inputs and thread count, same gradients to the last bit: a map is reproducible run to
    run (the backward used to hand tiles to threads dynamically, and the per-thread partial sums
    then differed in the last bits, which densification and pruning amplify)."""
    scene = random_scene(3000, 5)
    leaves = [t.requires_grad_() for t in scene.tensors()]
    threads = torch.get_num_threads()
    torch.set_num_threads(4)
    try:
        runs = []
        for _ in range(4):
            out = render(
                scene, pose(), (80.0, 80.0, 79.5, 47.5), 160, 96, params=RasterParams(backend="cpp")
            )
            loss = out.color.square().sum() + 0.1 * out.depth.sum()
            runs.append(torch.cat([g.flatten() for g in torch.autograd.grad(loss, leaves)]))
    finally:
        torch.set_num_threads(threads)
    assert float(runs[0].abs().max()) > 0
    for r in runs[1:]:
        assert torch.equal(r, runs[0])


@pytest.mark.skipif(not cpp_extension_available(), reason="C++ extension could not be compiled")
def test_cpp_results_do_not_depend_on_the_thread_count() -> None:
    """1, 2, 3 and 4 compositing threads (``RasterParams.threads``): the same image, counts,
    weights and gradients to the last bit (each tile-list entry's gradient has its own slot, added
    per Gaussian in list order), so the thread count is a speed setting, never a map change."""
    scene = random_scene(3000, 5)
    leaves = [t.requires_grad_() for t in scene.tensors()]
    runs = []
    for threads in (1, 2, 3, 4):
        prm = RasterParams(backend="cpp", threads=threads)
        out = render(scene, pose(), (80.0, 80.0, 79.5, 47.5), 160, 96, params=prm)
        loss = out.color.square().sum() + 0.1 * out.depth.sum()
        grads = torch.autograd.grad(loss, leaves)
        runs.append([out.color, out.depth, out.alpha, out.counts, out.weights, *grads])
    assert float(runs[0][5].abs().max()) > 0
    for r in runs[1:]:
        for a, b in zip(r, runs[0], strict=True):
            assert torch.equal(a, b)


@pytest.mark.skipif(not cpp_extension_available(), reason="C++ extension could not be compiled")
@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 300),
    seed=st.integers(0, 10_000),
    size=st.sampled_from([(1, 1), (17, 5), (40, 24), (161, 97)]),
    tile=st.sampled_from([1, 4, 16]),
    ties=st.booleans(),
)
def test_cpp_tile_binning_equals_the_torch_binning(n, seed, size, tile, ties) -> None:
    """The compiled binning (a counting sort by tile) gives exactly the torch path's lists: the
    same offsets and ids in the same depth order, ties in depth included (stable), Gaussians off
    screen, invalid, tiny or huge."""
    from mogs_node.mapper.projection import Projected, bin_tiles

    width, height = size
    g = torch.Generator().manual_seed(seed)
    uv = (torch.rand(n, 2, generator=g) * 1.4 - 0.2) * torch.tensor([width, height])
    ext = torch.rand(n, 2, generator=g) ** 3 * max(width, height) * 0.7
    depth = torch.rand(n, generator=g) * 10
    if ties:  # many equal depth keys: the order among them is the index order
        depth = torch.round(depth)
    valid = torch.rand(n, generator=g) > 0.2
    opacity = torch.full((n,), 0.5)
    proj = Projected(uv, torch.zeros(n, 3), depth, opacity, valid, ext)
    a = bin_tiles(proj, width, height, tile, cpp=True)
    b = bin_tiles(proj, width, height, tile, cpp=False)
    assert torch.equal(a.tile_offsets, b.tile_offsets)
    assert torch.equal(a.gauss_ids, b.gauss_ids)
    assert (a.tiles_x, a.tiles_y) == (b.tiles_x, b.tiles_y)
    if n:  # a NaN centre (never valid in a projection): the compiled path declines it
        from mogs_node.mapper.composite import load_cpp_extension

        uv[0, 0] = float("nan")
        valid[0] = True
        args = (depth.float(), valid, uv, ext, width, height, tile)
        assert load_cpp_extension().bin_tiles(*args) == []


def test_raster_threads_must_not_be_negative() -> None:
    with pytest.raises(ConfigError, match="threads"):
        RasterParams(threads=-1)


def test_pose_tangent_gradient_moves_image_like_a_pose_change() -> None:
    """d(render)/d(xi) . delta equals render(exp(delta) T) - render(T) to first order."""
    scene = random_scene(60, 4, torch.float64)
    T = pose(torch.float64)
    delta = torch.tensor([1.0, -2.0, 1.0, 2.0, 1.0, -1.0], dtype=torch.float64) * 1e-7
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    img = render(scene, T, K_SMALL, 40, 24, pose_tangent=xi).color.sum()
    (g,) = torch.autograd.grad(img, xi)
    plus = render(scene, se3_exp_torch(delta) @ T, K_SMALL, 40, 24).color.sum()
    minus = render(scene, se3_exp_torch(-delta) @ T, K_SMALL, 40, 24).color.sum()
    assert float(plus - minus) / 2 == pytest.approx(float(g @ delta), rel=1e-4)


def test_se3_exp_torch_matches_geometry() -> None:
    rng = np.random.default_rng(0)
    for xi in [rng.normal(size=6), np.zeros(6), np.array([1, 2, 3, 1e-9, 0, 0])]:
        np.testing.assert_allclose(
            se3_exp_torch(torch.as_tensor(xi)).numpy(), se3_exp(xi), atol=1e-12
        )


def _stress_scene() -> GaussianTensors:
    """Degenerate and extreme Gaussians mixed with ordinary ones."""
    n = 12
    scene = random_scene(n, 11)
    means = scene.means.clone()
    log_scales = scene.log_scales.clone()
    opacity = scene.opacity_logit.clone()
    means[0] = torch.tensor([0.0, 0.0, -2.0])  # behind the camera
    means[1] = torch.tensor([0.1, 0.0, 0.0])  # at the camera plane
    means[2] = torch.tensor([0.0, 0.0, 0.01])  # at the near plane
    means[3] = torch.tensor([0.0, 0.0, 1e-3])  # between camera and near plane
    means[4] = torch.tensor([1e3, 0.0, 1e6])  # huge depth
    means[5] = torch.tensor([0.0, 0.0, 1e9])
    log_scales[6] = torch.tensor([-40.0, -40.0, -40.0])  # degenerate point
    log_scales[7] = torch.tensor([3.0, -40.0, -40.0])  # needle
    log_scales[8] = torch.tensor([30.0, 30.0, -40.0])  # huge disc
    opacity[9] = -1e4  # zero opacity
    opacity[10] = 1e4  # fully opaque (alpha clamp)
    means[11] = torch.tensor([50.0, 0.0, 0.5])  # far outside the field of view, close
    log_scales[11] = torch.tensor([0.0, 0.0, 0.0])
    return GaussianTensors(means, scene.quats_wxyz, log_scales, opacity, scene.colors)


@pytest.mark.parametrize("backend", BACKENDS)
def test_numerical_stress_no_nan_or_inf(backend: str) -> None:
    scene = _stress_scene()
    leaves = [t.requires_grad_() for t in scene.tensors()]
    xi = torch.zeros(6, requires_grad=True)
    out = render(
        scene, torch.eye(4), K_SMALL, 40, 24, pose_tangent=xi, params=RasterParams(backend=backend)
    )
    for img in (out.color, out.depth, out.alpha):
        assert torch.isfinite(img).all()
    assert float(out.alpha.detach().max()) <= 1.0
    loss = out.color.sum() + out.depth.sum() * 1e-3 + out.alpha.sum()
    grads = torch.autograd.grad(loss, [*leaves, xi])
    for gr in grads:
        assert torch.isfinite(gr).all()
    assert int(out.counts[0]) == int(out.counts[1]) == int(out.counts[3]) == int(out.counts[9]) == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_opacity_map_renders_background(backend: str) -> None:
    scene = random_scene(30, 2)
    scene.opacity_logit = torch.full((30,), -1e4, requires_grad=True)
    bg = torch.tensor([0.3, 0.5, 0.7])
    out = render(
        scene, torch.eye(4), K_SMALL, 40, 24, background=bg, params=RasterParams(backend=backend)
    )
    assert torch.equal(out.color, bg.expand(24, 40, 3))
    assert float(out.alpha.detach().abs().max()) == 0.0
    (g,) = torch.autograd.grad(out.color.sum(), [scene.opacity_logit])
    assert torch.isfinite(g).all()


def test_empty_map_and_bad_arguments() -> None:
    empty = GaussianTensors(
        torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)
    )
    out = render(empty, torch.eye(4), K_SMALL, 40, 24)
    assert out.color.shape == (24, 40, 3) and float(out.alpha.max()) == 0.0
    bad = random_scene(5, 0)
    bad.colors = torch.zeros(4, 3)
    with pytest.raises(ShapeError, match="colors"):
        render(bad, torch.eye(4), K_SMALL, 40, 24)
    with pytest.raises(ShapeError, match="T_cam_world"):
        render(random_scene(5, 0), torch.eye(3), K_SMALL, 40, 24)
    with pytest.raises(ConfigError, match="backend"):
        RasterParams(backend="vulkan")


@settings(max_examples=8, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    log_scale_shift=st.floats(-3.0, 2.0),
    opacity_shift=st.floats(-4.0, 6.0),
    depth_m=st.floats(0.3, 500.0),
)
def test_property_tile_equals_reference_and_stays_finite(
    seed: int, log_scale_shift: float, opacity_shift: float, depth_m: float
) -> None:
    scene = random_scene(25, seed, depth_m=depth_m)
    scene.log_scales = scene.log_scales + log_scale_shift + float(np.log(depth_m / 4.0))
    scene.opacity_logit = scene.opacity_logit + opacity_shift
    ref = render_reference(scene, pose(), K_SMALL, 24, 16)
    out = render(scene, pose(), K_SMALL, 24, 16)
    assert torch.isfinite(out.color).all() and torch.isfinite(out.depth).all()
    assert (out.color - ref.color).abs().max() < 1e-4
    assert (out.alpha - ref.alpha).abs().max() < 1e-4
    assert torch.isfinite(out.weights).all() and bool((out.weights >= 0).all())
    assert (out.weights - ref.weights).abs().max() < 1e-4 * max(1.0, float(ref.weights.max()))


def test_auto_backend_falls_back_to_pytorch_without_extension(monkeypatch) -> None:
    from mogs_node.mapper import composite

    scene = random_scene(40, 3)
    want = render_reference(scene, pose(), K_SMALL, 40, 24)
    monkeypatch.setattr(composite, "_EXT", None)
    monkeypatch.setattr(composite, "_EXT_FAILED", True)  # as after a failed compilation
    assert not composite.cpp_extension_available()
    out = render(scene, pose(), K_SMALL, 40, 24, params=RasterParams(backend="cpp"))
    assert (out.color - want.color).abs().max() < 1e-4
