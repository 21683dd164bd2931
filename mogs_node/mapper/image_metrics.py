"""Image quality metrics for rendered views: PSNR and SSIM (Wang et al. 2004, 11x11 Gaussian, 1.5)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch.nn.functional import conv2d

from mogs_node.geometry import check_array

__all__ = ["psnr_db", "ssim", "ssim_torch"]


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


def ssim_torch(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Differentiable mean SSIM of ``pred`` vs ``target`` ([H, W, 3] tensors of one float dtype,
    values in [0, 1]; valid region of the 11x11 window, colour channels averaged): the structural
    term of the mapper's loss (3DGS eq. 7, ``L = (1 - l) L1 + l (1 - SSIM)``) and of :func:`ssim`.
    Images smaller than the window have no valid region: SSIM 1 (no structure to compare)."""
    if pred.shape[0] < 11 or pred.shape[1] < 11:
        return torch.ones((), dtype=pred.dtype, device=pred.device)
    p = pred.permute(2, 0, 1)[:, None]
    t = target.permute(2, 0, 1)[:, None]
    x = torch.arange(11, dtype=pred.dtype, device=pred.device) - 5
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    g = g / g.sum()
    gy, gx = g.view(1, 1, 11, 1), g.view(1, 1, 1, 11)  # separable: two 1D passes

    def blur(a: torch.Tensor) -> torch.Tensor:
        return conv2d(conv2d(a, gy), gx)

    mu_p, mu_t = blur(p), blur(t)
    s_pp = blur(p * p) - mu_p**2
    s_tt = blur(t * t) - mu_t**2
    s_pt = blur(p * t) - mu_p * mu_t
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu_p * mu_t + c1) * (2 * s_pt + c2)) / ((mu_p**2 + mu_t**2 + c1) * (s_pp + s_tt + c2))
    return m.mean()


def ssim(pred: np.ndarray | torch.Tensor, target: np.ndarray | torch.Tensor) -> float:
    """Mean SSIM over the image (valid region of the 11x11 window), colour channels averaged."""
    p = _as_float_image("pred", pred).clamp(0, 1)
    t = _as_float_image("target", target)
    return float(ssim_torch(p, t))
