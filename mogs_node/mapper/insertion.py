"""Gaussian insertion from a keyframe's dense depth (MonoGS keyframe initialisation, MOGS depth).

Where the current map does not explain the new view -- its rendered opacity is low, or its
rendered surface lies behind the new depth by more than a tolerance relative to the depth and
inversely proportional to its confidence -- pixels are sampled on a grid whose stride adapts to
depth and confidence, back-projected to 3D, and each becomes an isotropic Gaussian whose scale is
the sampled pixel footprint (``stride * depth / f``) and whose colour is the image colour there.

One policy for every depth source, a function of (depth, confidence) only: confident metric depth
pins a surface, so one Gaussian covers a larger footprint (coarser stride, larger initial scale)
and disagreements with the map count at a tight tolerance; confident depth that is also locally
planar (the MOGS shape consensus fits planes per object) is coarsened once more, since a plane
needs the fewest Gaussians (paper section III-D: accurate metric geometry, fewer Gaussians);
unconfident depth is sampled finely (more depth hypotheses for the optimisation to keep or prune)
and its disagreements count only at a loose tolerance, not at all at confidence 0. With
``patch_px > 0`` (object-guided insertion, :mod:`insertion_patches`) square patches of the mask
whose depth is a plane and whose colour is flat first become one flat, surface-aligned Gaussian
each, read from the depth map alone. Depth sources for the paper's Table II comparison:
the MOGS metrized depth, the globally aligned prior (``no_msc_cdr``) and random depth
(:func:`random_depth`, which carries no information: confidence 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.geometry import check_array, pixel_to_normalized, transform_points
from mogs_node.mapper.insertion_patches import surface_patches

__all__ = [
    "InsertionParams",
    "background_mask",
    "flat_image_mask",
    "insertion_confidence",
    "insertion_mask",
    "planar_mask",
    "random_depth",
    "sample_gaussians",
]


@dataclass(frozen=True)
class InsertionParams:
    """Where and how densely to insert Gaussians."""

    stride_px: int = 2  # base sampling stride (pixels) for near depth
    far_depth_m: float = 25.0  # beyond this depth the stride doubles (and again at 2x, 4x ...)
    max_stride_px: int = 8  # the stride never exceeds this
    coarse_conf: float = 0.7  # at/above this confidence the stride doubles (larger footprint)
    planar_gain: float = 2.0  # ... and grows by this factor where also planar (1: off) ...
    planar_tol: float = 0.01  # ... i.e. the relative curvature of the inverse depth,
    # max(|d2(1/d)/du2|, |d2(1/d)/dv2|) * d per px^2, is below this (0: off)
    planar_window_px: int = 5  # planar means: below planar_tol everywhere in this square window
    planar_max_grad: float = 8.0  # ... and the image is flat there too: grey-level gradient
    # (central difference, 0-255 scale, per px) below this everywhere in the window (0: no test)
    alpha_explained: float = 0.9  # pixels with rendered alpha above this may be explained ...
    depth_rel_tol: float = 0.2  # ... unless (rendered - new) / new depth > depth_rel_tol / conf
    check_depth: bool = True  # use the depth disagreement test at all (ablation switch)
    disagree_color_tol: float = 0.0  # a depth disagreement counts only where the rendered colour
    # is also off, mean |rendered - image| > this (0: always): the map draws the view right there
    color_tol: float = 0.0  # also unexplained where mean |rendered - image| colour > this (0: off)
    max_footprint_rad: float = 0.15  # and never exceeds this angle (stride / f): footprints stay
    # below the mapper's size pruning (sigma > 0.2 x distance) even for short focal lengths
    scale_factor: float = 1.0  # initial sigma = scale_factor * stride * depth / f (MonoGS: NN dist)
    opacity_init: float = 0.5  # initial opacity (MonoGS: 0.5)
    min_depth_m: float = 0.1  # pixels with depth below this (or 0 = no value) are not used
    background_depth_m: float = 0.0  # pixels without depth that the map leaves transparent get
    # Gaussians on a far sphere at this distance (sky, far background; 0: off)
    patch_px: int = 0  # object-guided insertion (insertion_patches.py): the largest square
    # patch (px) that one flat, surface-aligned Gaussian may cover where the depth is a plane
    # over it; halved down to patch_min_px (0: off, pixel-grid sampling only)
    patch_min_px: int = 4  # the smallest such patch
    patch_rel_tol: float = 0.02  # planar: RMS residual of the plane fit in 1/z below this x 1/z
    patch_max_color_std: float = 3.0  # ... and grey-level std over the patch (0-255) at most
    # this (0: no colour test): a textured patch needs fine Gaussians for its colour
    patch_sigma_frac: float = 1.0  # in-plane sigma = this x the patch's back-projected edge
    # (1: the grid's rule, sigma = the sample spacing; 0.5 leaves alpha < alpha_explained between
    # patches at opacity_init 0.5, and the next keyframe inserts there again)
    patch_thickness: float = 0.1  # sigma along the normal = this x the in-plane sigma
    fixed_confidence: float = -1.0  # the confidence the insertion rules read for every pixel
    # with depth, whatever the source says (-1: the source's own): one treatment for every depth
    # source (Table II); the optimisation's depth loss still weights by the source's confidence

    def __post_init__(self) -> None:
        if self.stride_px < 1 or self.max_stride_px < self.stride_px:
            raise ConfigError("InsertionParams: need 1 <= stride_px <= max_stride_px")
        if not 0 < self.opacity_init < 1:
            raise ConfigError("InsertionParams.opacity_init: must be in (0, 1)")
        if not self.max_footprint_rad > 0:
            raise ConfigError("InsertionParams.max_footprint_rad: must be > 0")
        if self.planar_tol < 0 or self.planar_window_px < 1 or not self.planar_gain >= 1:
            raise ConfigError(
                "InsertionParams: need planar_tol >= 0, planar_window_px >= 1, planar_gain >= 1"
            )
        if self.planar_max_grad < 0:
            raise ConfigError("InsertionParams.planar_max_grad: must be >= 0")
        if not (self.background_depth_m == 0 or self.background_depth_m > self.min_depth_m):
            raise ConfigError("InsertionParams.background_depth_m: 0 (off) or > min_depth_m")
        if self.patch_px < 0 or (self.patch_px and self.patch_min_px < 2):
            raise ConfigError("InsertionParams: need patch_px >= 0 and patch_min_px >= 2")
        if not (self.patch_rel_tol >= 0 and self.patch_max_color_std >= 0):
            raise ConfigError("InsertionParams: need patch_rel_tol, patch_max_color_std >= 0")
        if not (self.patch_sigma_frac > 0 and self.patch_thickness > 0):
            raise ConfigError("InsertionParams: need patch_sigma_frac, patch_thickness > 0")
        if not (self.fixed_confidence == -1.0 or 0 <= self.fixed_confidence <= 1):
            raise ConfigError("InsertionParams.fixed_confidence: -1 (the source's) or in [0, 1]")


def insertion_confidence(
    depth_m: np.ndarray, confidence: np.ndarray, params: InsertionParams
) -> np.ndarray:
    """The confidence ``[H, W]`` the insertion rules read: the source's ``confidence`` [H, W], or
    with ``fixed_confidence >= 0`` that value wherever ``depth_m`` [H, W] is usable (0 elsewhere).
    A fixed value gives every depth source the same treatment (docs/mapper.md "Live Table II: one
    confidence for every source"): the rules then differ between sources only by the depth."""
    if params.fixed_confidence < 0:
        return confidence
    usable = np.isfinite(depth_m) & (depth_m >= params.min_depth_m)
    return np.where(usable, np.float32(params.fixed_confidence), np.float32(0.0))


def random_depth(shape: tuple[int, int], d_min_m: float, d_max_m: float, seed: int) -> np.ndarray:
    """Baseline initial depth: uniform random in ``[d_min_m, d_max_m]`` per pixel, f32 [H, W]."""
    rng = np.random.default_rng(seed)
    return rng.uniform(d_min_m, d_max_m, size=shape).astype(np.float32)


def insertion_mask(
    depth_m: np.ndarray,
    confidence: np.ndarray,
    rendered_alpha: np.ndarray | None,
    rendered_depth_m: np.ndarray | None,
    params: InsertionParams,
    rendered_rgb: np.ndarray | None = None,
    image_rgb: np.ndarray | None = None,
) -> np.ndarray:
    """Pixels ``[H, W]`` bool where the map does not explain the view and depth is usable.

    ``depth_m`` [H, W] (0 = no value), ``confidence`` [H, W] in [0, 1]; ``rendered_alpha`` [H, W]
    and ``rendered_depth_m`` [H, W] (expected depth, alpha-normalised) of the current map, or
    ``None`` for an empty map. A pixel is unexplained when ``alpha < alpha_explained`` or when
    ``rendered - depth > depth_rel_tol * depth / confidence`` (relative tolerance, widening as the
    confidence falls; confidence 0 never disagrees). With ``params.color_tol > 0`` and
    ``rendered_rgb``/``image_rgb`` [H, W, 3] in [0, 1] given, a pixel whose rendered colour differs
    from the image by more than ``color_tol`` (mean over channels) is unexplained as well: the map
    covers it but draws the wrong thing there (3DGS/MonoGS add Gaussians there by densification).
    """
    d = check_array("depth_m", depth_m, shape=(None, None), dtype=np.floating)
    c = check_array("confidence", confidence, shape=d.shape, dtype=np.floating)
    c = insertion_confidence(d, c, params)
    usable = np.isfinite(d) & (d >= params.min_depth_m)
    if rendered_alpha is None:
        return usable
    a = check_array("rendered_alpha", rendered_alpha, shape=d.shape, dtype=np.floating)
    rd = check_array("rendered_depth_m", rendered_depth_m, shape=d.shape, dtype=np.floating)
    unexplained = a < params.alpha_explained
    err = None  # mean |rendered - image| colour error per pixel
    wanted = params.color_tol > 0 or params.disagree_color_tol > 0
    if wanted and rendered_rgb is not None and image_rgb is not None:
        rc = check_array("rendered_rgb", rendered_rgb, shape=(*d.shape, 3), dtype=np.floating)
        ic = check_array("image_rgb", image_rgb, shape=(*d.shape, 3), dtype=np.floating)
        err = np.abs(rc - ic).mean(-1)
    if params.color_tol > 0 and err is not None:
        unexplained = unexplained | (err > params.color_tol)
    if not params.check_depth:
        return usable & unexplained
    # only a surface *in front of* what the map renders is missing: Gaussians inserted behind the
    # map's surface would be hidden in this view (a wrong surface in front is left to optimisation
    # and pruning)
    disagree = (c > 0) & (
        (rd - d) * np.maximum(c, 1e-6) > params.depth_rel_tol * np.maximum(d, 1e-6)
    )
    if params.disagree_color_tol > 0 and err is not None:
        # the map draws the right colour there: its surface is pulled to the depth by the depth
        # loss; new Gaussians would double it (pruned as redundant later)
        disagree &= err > params.disagree_color_tol
    return usable & (unexplained | disagree)


def background_mask(
    depth_m: np.ndarray, rendered_alpha: np.ndarray | None, params: InsertionParams
) -> np.ndarray:
    """Pixels ``[H, W]`` bool that get far-sphere Gaussians: no usable depth (``depth_m`` [H, W]
    below ``min_depth_m`` or non-finite) and the map transparent there (``rendered_alpha`` [H, W]
    below ``alpha_explained``; ``None``: an empty map). All False when ``background_depth_m`` is 0.

    The metrized depth has no value on sky and on whatever the prior could not measure; without
    Gaussians there the render shows the black background, and the optimiser drags nearby
    Gaussians into the hole (floaters, dark blobs in the sky). Gaussians at a distance beyond any
    measured surface fill such holes without occluding anything the depth later pins (outdoor
    3DGS systems model the sky as a far sphere or environment map for the same reason).
    """
    d = check_array("depth_m", depth_m, shape=(None, None), dtype=np.floating)
    if params.background_depth_m <= 0:
        return np.zeros(d.shape, bool)
    nodepth = ~(np.isfinite(d) & (d >= params.min_depth_m))
    if rendered_alpha is None:
        return nodepth
    a = check_array("rendered_alpha", rendered_alpha, shape=d.shape, dtype=np.floating)
    return nodepth & (a < params.alpha_explained)


def planar_mask(depth_m: np.ndarray, tol: float, window_px: int) -> np.ndarray:
    """Pixels ``[H, W]`` bool whose depth is locally planar.

    A plane is linear in inverse depth over the image (``1/z = a u + b v + c``), so its second
    differences of ``w = 1/d`` vanish; the relative curvature ``max(|w[u-1] - 2 w + w[u+1]|,
    |w[v-1] - 2 w + w[v+1]|) / w`` (per px^2; scale-free: the same for a plane at any distance)
    must stay below ``tol`` everywhere in the ``window_px`` square around the pixel. 1 % depth noise
    alone gives ~0.025, so noisy or random depth is never planar; pixels without depth (<= 0 or
    non-finite) and their neighbours are not planar. Image borders use the direction available.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    ok = np.isfinite(d) & (d > 0)
    w = np.where(ok, 1.0 / np.where(ok, d, 1.0), np.nan)
    curv = np.zeros_like(w)
    if w.shape[1] >= 3:
        curv[:, 1:-1] = np.abs(w[:, :-2] - 2.0 * w[:, 1:-1] + w[:, 2:])
    if w.shape[0] >= 3:
        curv[1:-1, :] = np.maximum(curv[1:-1, :], np.abs(w[:-2, :] - 2.0 * w[1:-1, :] + w[2:, :]))
    with np.errstate(invalid="ignore"):
        rel = curv / w
    bad = ~np.isfinite(rel)
    bad[:, 1:] |= ~ok[:, :-1]  # a missing neighbour: the curvature there is unknown
    bad[:, :-1] |= ~ok[:, 1:]
    bad[1:, :] |= ~ok[:-1, :]
    bad[:-1, :] |= ~ok[1:, :]
    rel = np.where(bad, np.inf, rel)
    return _window_max(rel, window_px) < tol


def _window_max(x: np.ndarray, window_px: int) -> np.ndarray:
    """Maximum over the ``window_px`` square around each pixel (separable, edges replicate)."""
    r = window_px // 2
    if r > 0:
        p = np.pad(x, ((0, 0), (r, r)), mode="edge")
        x = np.lib.stride_tricks.sliding_window_view(p, 2 * r + 1, axis=1).max(-1)
        p = np.pad(x, ((r, r), (0, 0)), mode="edge")
        x = np.lib.stride_tricks.sliding_window_view(p, 2 * r + 1, axis=0).max(-1)
    return x


def flat_image_mask(image_rgb: np.ndarray, max_grad: float, window_px: int) -> np.ndarray:
    """Pixels ``[H, W]`` bool where the image is flat: the grey level's central-difference
    gradient (0-255 scale, per px, the larger of the two directions) stays below ``max_grad``
    everywhere in the ``window_px`` square. A textured plane still needs fine Gaussians for its
    colour; only a plane that is flat in geometry and colour is fully described by few."""
    g = np.asarray(image_rgb, dtype=np.float64).mean(-1)
    grad = np.zeros_like(g)
    if g.shape[1] >= 3:
        grad[:, 1:-1] = np.abs(g[:, 2:] - g[:, :-2]) / 2
    if g.shape[0] >= 3:
        grad[1:-1, :] = np.maximum(grad[1:-1, :], np.abs(g[2:, :] - g[:-2, :]) / 2)
    return _window_max(grad, window_px) < max_grad


def _stride_map(
    depth_m: np.ndarray,
    confidence: np.ndarray,
    p: InsertionParams,
    image_rgb: np.ndarray | None = None,
) -> np.ndarray:
    """Per-pixel stride: ``stride_px`` doubled per octave beyond ``far_depth_m``, once more where
    the depth is confident (``confidence >= coarse_conf``: the surface is known, one Gaussian
    covers a larger footprint), and by ``planar_gain`` where it is confident and locally planar
    (:func:`planar_mask`: a plane needs the fewest Gaussians) and, with ``image_rgb`` [H, W, 3]
    given and ``planar_max_grad > 0``, also flat in colour (:func:`flat_image_mask`); at most
    ``max_stride_px``. ``depth_m`` [H, W] may hold 0 / non-finite values (no depth: base stride,
    never planar)."""
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, 0.0)
    octaves = np.floor(np.log2(np.maximum(d, 1e-6) / p.far_depth_m) + 1.0)
    confident = confidence >= p.coarse_conf
    s = p.stride_px * np.power(2.0, np.clip(octaves, 0, 8) + confident)
    if p.planar_tol > 0 and p.planar_gain > 1:
        planar = confident & planar_mask(d, p.planar_tol, p.planar_window_px)
        if image_rgb is not None and p.planar_max_grad > 0:
            planar &= flat_image_mask(image_rgb, p.planar_max_grad, p.planar_window_px)
        s = np.where(planar, np.round(s * p.planar_gain), s)
    return np.minimum(s, p.max_stride_px).astype(np.int64)


def sample_gaussians(
    image_rgb: np.ndarray,
    depth_m: np.ndarray,
    confidence: np.ndarray,
    mask: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: InsertionParams,
    offset: int = 0,
) -> dict[str, torch.Tensor]:
    """New Gaussians (``PARAM_NAMES`` -> tensors) at the grid-sampled pixels of ``mask``.

    ``image_rgb`` [H, W, 3] uint8, ``depth_m``/``confidence`` [H, W], ``mask`` [H, W] bool,
    ``K`` [3, 3], ``T_world_cam`` [4, 4]. The stride (:func:`_stride_map`) is capped at
    ``max_footprint_rad * f`` pixels. A pixel (u, v) with stride s is sampled when
    ``u % s == v % s == (offset % s)``, so strides nest (coarser grids are subsets of finer ones).
    ``offset`` shifts the grid between keyframes so that successive insertions interleave.
    """
    img = check_array("image_rgb", image_rgb, shape=(None, None, 3), dtype=np.uint8)
    H, W = img.shape[:2]
    d = check_array("depth_m", depth_m, shape=(H, W), dtype=np.floating).astype(np.float64)
    c = check_array("confidence", confidence, shape=(H, W), dtype=np.floating)
    m = check_array("mask", mask, shape=(H, W), dtype=np.bool_)
    K = check_array("K", K, shape=(3, 3), finite=True)
    T = check_array("T_world_cam", T_world_cam, shape=(4, 4), finite=True)
    if not np.all(np.isfinite(d[m])):
        raise ShapeError("depth_m: non-finite depth inside mask")
    c = insertion_confidence(d, c, params)
    patches = None
    if params.patch_px > 0:  # flat Gaussians on planar patches; the grid samples the rest
        patches = surface_patches(
            img,
            d,
            m,
            K,
            T,
            patch_px=params.patch_px,
            min_patch_px=params.patch_min_px,
            rel_tol=params.patch_rel_tol,
            max_color_std=params.patch_max_color_std,
            sigma_frac=params.patch_sigma_frac,
            thickness=params.patch_thickness,
            max_footprint_rad=params.max_footprint_rad,
        )
        m = m & ~patches.covered
    s = _stride_map(d, c, params, img)  # planarity from the whole depth map, not only the mask
    f = math.sqrt(K[0, 0] * K[1, 1])
    s = np.minimum(s, max(params.stride_px, int(params.max_footprint_rad * f)))
    vv, uu = np.mgrid[0:H, 0:W]
    pick = m & (uu % s == offset % s) & (vv % s == offset % s)
    v, u = np.nonzero(pick)
    z = d[v, u]
    x_n, y_n = pixel_to_normalized(K, u, v)
    p_world = transform_points(T, np.stack([x_n * z, y_n * z, z], -1))
    sigma = params.scale_factor * s[v, u] * z / f
    quats = np.zeros((len(z), 4))
    quats[:, 0] = 1
    scales = np.log(sigma)[:, None].repeat(3, 1)
    colors = img[v, u].astype(np.float32) / 255.0
    if patches is not None:
        p_world = np.concatenate([patches.means_world, p_world])
        quats = np.concatenate([patches.quats_wxyz, quats])
        scales = np.concatenate([np.log(patches.scales_m), scales])
        colors = np.concatenate([patches.colors_rgb, colors])
    logit = math.log(params.opacity_init / (1 - params.opacity_init))
    return {
        "means": torch.as_tensor(p_world, dtype=torch.float32),
        "quats_wxyz": torch.as_tensor(quats, dtype=torch.float32),
        "log_scales": torch.as_tensor(scales, dtype=torch.float32),
        "opacity_logit": torch.full((len(p_world),), logit, dtype=torch.float32),
        "colors": torch.as_tensor(colors),
    }
