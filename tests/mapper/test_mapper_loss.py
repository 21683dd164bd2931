"""Mapper loss terms (issue #17): differentiable SSIM (3DGS eq. 7) and the exposure gauge."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from test_mapper import H, K, W, plane_view

from mogs_node.errors import ConfigError
from mogs_node.geometry import make_T
from mogs_node.mapper.image_metrics import ssim, ssim_torch
from mogs_node.mapper.mapper import GaussianMapper, MapperParams


def _ssim_2d_reference(p: np.ndarray, t: np.ndarray) -> float:
    """Wang et al. 2004 with a full 11x11 window, written out per window (slow, float64)."""
    x = np.arange(11) - 5.0
    g = np.exp(-(x**2) / (2 * 1.5**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for ch in range(3):
        for y in range(p.shape[0] - 10):
            for x0 in range(p.shape[1] - 10):
                a, b = p[y : y + 11, x0 : x0 + 11, ch], t[y : y + 11, x0 : x0 + 11, ch]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = (w * a * a).sum() - ma**2, (w * b * b).sum() - mb**2
                cov = (w * a * b).sum() - ma * mb
                vals.append(
                    ((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
                )
    return float(np.mean(vals))


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**16), h=st.integers(11, 16), w=st.integers(11, 18))
def test_separable_ssim_equals_the_windowed_definition(seed: int, h: int, w: int) -> None:
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 1, (h, w, 3))
    p = np.clip(t + rng.normal(0, 0.1, t.shape), 0, 1)
    assert ssim(p, t) == pytest.approx(_ssim_2d_reference(p, t), abs=1e-12)
    assert ssim(t, t) == pytest.approx(1.0, abs=1e-12)


def test_ssim_torch_is_differentiable_and_small_images_count_as_identical() -> None:
    rng = np.random.default_rng(1)
    t = torch.as_tensor(rng.uniform(0, 1, (12, 13, 3)))
    p = (t + 0.05 * torch.as_tensor(rng.normal(size=t.shape))).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: ssim_torch(x, t), (p,))
    small = torch.rand(8, 20, 3, dtype=torch.float64)
    assert float(ssim_torch(small, 1 - small)) == 1.0


def test_lambda_ssim_out_of_range_is_rejected() -> None:
    with pytest.raises(ConfigError, match="lambda_ssim"):
        MapperParams(lambda_ssim=1.5)


def _two_keyframes(**kw) -> GaussianMapper:
    img, depth = plane_view()
    conf = np.ones_like(depth)
    m = GaussianMapper(MapperParams(n_random_past=0, **kw), K, W, H)
    m.add_keyframe(0, img, np.eye(4), depth, conf)
    m.optimize(6)
    # the second view is 30 % darker: its exposure has something to fit
    img1, _ = plane_view(seed=0)
    dark = (img1.astype(np.float32) * 0.7).astype(np.uint8)
    m.add_keyframe(1, dark, make_T(np.eye(3), np.array([0.3, 0.0, 0.0])), depth, conf)
    m.optimize(20)
    return m


def test_exposure_gauge_keeps_the_first_keyframe_at_identity() -> None:
    free = _two_keyframes(exposure_gauge=False)
    fixed = _two_keyframes(exposure_gauge=True)
    assert float(free.keyframes[0].exposure_ab.abs().max()) > 0  # drifts without the gauge
    assert torch.equal(fixed.keyframes[0].exposure_ab, torch.zeros(2, dtype=torch.float64))
    # the darker second keyframe gets a negative log-gain or offset relative to the first
    a1, b1 = (float(v) for v in fixed.keyframes[1].exposure_ab)
    assert a1 < 0 or b1 < 0


def test_ssim_term_trains_a_view_and_keeps_the_map_repeatable() -> None:
    runs = [_two_keyframes(lambda_ssim=0.2) for _ in range(2)]
    for name in runs[0].map.params:
        assert torch.equal(runs[0].map.params[name], runs[1].map.params[name])
    img, _ = plane_view()
    r = runs[0].render_view(np.eye(4)).color
    assert ssim(r, img) > 0.5
