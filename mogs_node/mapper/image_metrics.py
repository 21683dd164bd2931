"""Image quality metrics for rendered views: PSNR and SSIM (Wang et al. 2004, 11x11 Gaussian, 1.5)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch.nn.functional import conv2d

from mogs_node.geometry import check_array

__all__ = ["psnr_db", "ssim"]


def _as_float_image(name: str, img: np.ndarray | torch.Tensor) -> torch.Tensor:
    a = img.detach().cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
    a = check_array(name, a, shape=(None, None, 3))
    if a.dtype == np.uint8:
        a = a.astype(np.float64) / 255.0
    return torch.as_tensor(a, dtype=torch.float64)


def psnr_db(pred: np.ndarray | torch.Tensor, target: np.ndarray | torch.Tensor) -> float:
    """PSNR in dB of ``pred`` vs ``target`` ([H, W, 3], uint8 or float in [0, 1])."""
    p, t = _as_float_image("pred", pred), _as_float_image("target", target)
    mse = float(((p.clamp(0, 1) - t) ** 2).mean())
    return -10.0 * math.log10(max(mse, 1e-12))


def ssim(pred: np.ndarray | torch.Tensor, target: np.ndarray | torch.Tensor) -> float:
    """Mean SSIM over the image (valid region of the 11x11 window), colour channels averaged."""
    p = _as_float_image("pred", pred).clamp(0, 1).permute(2, 0, 1)[:, None]
    t = _as_float_image("target", target).permute(2, 0, 1)[:, None]
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    g = g / g.sum()
    w = (g[:, None] * g[None, :])[None, None]
    mu_p, mu_t = conv2d(p, w), conv2d(t, w)
    s_pp = conv2d(p * p, w) - mu_p**2
    s_tt = conv2d(t * t, w) - mu_t**2
    s_pt = conv2d(p * t, w) - mu_p * mu_t
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu_p * mu_t + c1) * (2 * s_pt + c2)) / ((mu_p**2 + mu_t**2 + c1) * (s_pp + s_tt + c2))
    return float(m.mean())
