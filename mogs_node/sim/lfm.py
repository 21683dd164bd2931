"""A simulated learned-foundation-model (LFM) depth prior, for controlled experiments only.

It turns ground-truth depth into what a monocular network such as Depth Anything V2 gives: relative
inverse depth that is locally consistent but has an unknown per-frame affine map, a smooth
low-frequency distortion, soft depth edges and noise. It is built from ground truth, so it must
never be reachable from the product's depth prior (``mogs_node.depth_prior`` does not import it).

Model, for valid pixels with inverse depth ``q = 1 / depth``::

    q_w   = q * exp(warp(u, v))                        warp: sum of random low-frequency cosines
    q_b   = blur(q_w) near depth edges, q_w elsewhere  Gaussian, edge_blur_px
    out   = scale * q_b (1 + noise) + shift      scale ~ logU(scale_range), shift ~ U(shift_range)

Sky (``depth`` inf or 0) has ``q = 0`` and so ends at about ``shift`` (small).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_dilation, gaussian_filter

from mogs_node.errors import ConfigError
from mogs_node.geometry import check_array

__all__ = ["LfmParams", "simulated_lfm", "simulated_lfm_with_truth"]


@dataclass(frozen=True)
class LfmParams:
    """Distortions of the simulated LFM; the defaults resemble a good relative-depth network."""

    scale_range: tuple[float, float] = (
        0.5,
        20.0,
    )  # log-uniform per-frame scale of inverse depth (m)
    shift_range: tuple[float, float] = (0.0, 0.02)  # uniform per-frame shift (1/m after scaling)
    warp_amplitude: float = 0.08  # std of the log-multiplicative low-frequency warp
    warp_components: int = 4  # number of random cosine waves in the warp
    warp_max_cycles: float = 1.5  # highest warp frequency, in cycles per image width
    edge_blur_px: float = 2.0  # Gaussian sigma used at depth edges (0: no blur)
    edge_threshold: float = 0.1  # relative inverse-depth jump that counts as an edge
    noise_std: float = 0.01  # relative (multiplicative) Gaussian noise per pixel
    max_depth_m: float = 1000.0  # depths beyond (and sky) are treated as q = 0


def simulated_lfm_with_truth(
    depth_m: np.ndarray, rng: np.random.Generator, params: LfmParams | None = None
) -> tuple[np.ndarray, dict[str, float]]:
    """Like :func:`simulated_lfm`, also returning the true ``{"scale", "shift"}`` of the frame."""
    p = params or LfmParams()
    d = check_array("depth_m", depth_m, shape=(None, None), dtype=np.floating)
    if p.scale_range[0] <= 0 or p.scale_range[1] < p.scale_range[0]:
        raise ConfigError(f"scale_range: invalid {p.scale_range}")
    H, W = d.shape
    valid = np.isfinite(d) & (d > 0) & (d < p.max_depth_m)
    q = np.where(valid, 1.0 / np.where(valid, d, 1.0), 0.0)
    # low-frequency warp
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    warp = np.zeros((H, W))
    for _ in range(max(p.warp_components, 0)):
        f = rng.uniform(0.2, p.warp_max_cycles) / W
        ang = rng.uniform(0, 2 * np.pi)
        warp += np.cos(
            2 * np.pi * f * (np.cos(ang) * uu + np.sin(ang) * vv) + rng.uniform(0, 2 * np.pi)
        )
    if p.warp_components > 0:
        warp *= p.warp_amplitude / np.sqrt(p.warp_components / 2.0)
    qw = q * np.exp(warp)
    # blur at depth edges
    if p.edge_blur_px > 0:
        qb = gaussian_filter(qw, p.edge_blur_px)
        gy, gx = np.gradient(qw)
        rel = np.hypot(gx, gy) / np.maximum(qw, 1e-6)
        edges = binary_dilation(
            rel > p.edge_threshold, iterations=max(int(round(2 * p.edge_blur_px)), 1)
        )
        qw = np.where(edges, qb, qw)
    scale = float(np.exp(rng.uniform(np.log(p.scale_range[0]), np.log(p.scale_range[1]))))
    shift = float(rng.uniform(*p.shift_range))
    out = scale * qw * (1.0 + p.noise_std * rng.standard_normal((H, W))) + shift
    out = np.maximum(out, 0.0).astype(np.float32)
    return out, {"scale": scale, "shift": shift}


def simulated_lfm(
    depth_m: np.ndarray, rng: np.random.Generator, params: LfmParams | None = None
) -> np.ndarray:
    """Relative inverse depth f32 ``[H, W]`` from ground-truth z-depth ``depth_m`` f32 ``[H, W]``.

    ``depth_m`` may hold ``inf`` (sky) or 0 (no value); both map to about ``shift``. See the module
    docstring for the model and :class:`LfmParams` for the parameters. Always finite, ``>= 0``.
    """
    return simulated_lfm_with_truth(depth_m, rng, params)[0]
