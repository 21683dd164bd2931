"""Textureless regions filled from the depth of their outline (issue 16, session 15).

A uniform surface (the demo's grey pillars, a bonnet) gives the flow nothing to match inside, but
its outline and creases are image edges whose depth the epipolar search finds
(:mod:`mogs_node.depth_prior.edge_stereo`). Which region an edge's depth belongs to is decided
by occlusion: an edge moves with the nearer of the two surfaces it separates. So each edge
sample is given to the region on one side of it (looked up ``side_px`` along the image
gradient) when that side has no depth of its own or agrees with it (within ``side_agree``), and
the other side is farther by more than ``far_rel`` (the background behind an occluding
contour) or is another untextured region without depth (a crease between two faces). The regions are the
connected areas of near-zero image gradient (``flat_gradient``): the untextured surfaces
themselves, found without the segmentation.

A region takes the median of its samples' depths (a constant: a region's samples often lie on
one or two lines, along which a plane's slope is unknown) when at least ``min_samples`` of them
make it, at least ``min_inlier_share`` of those lie within ``inlier_rel`` of the median, and the
depth the region already has (the fused prior, any confidence; if at least ``min_known_share``
of it has one) agrees with the median within ``known_agree``. Its pixels without depth get it,
with a predicted relative error of ``max(min_rel_err, 1.4826 x the samples' MAD)``.

Measured on the demo loop: docs/depth_prior.md, "Outlines of textureless objects". Pure:
arrays in, arrays out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_prior.edge_stereo import EdgeStereoParams, edge_stereo_depth
from mogs_node.errors import ConfigError
from mogs_node.group_stats import group_medians

__all__ = [
    "ContourFillParams",
    "assign_to_regions",
    "contour_fill",
    "flat_regions",
    "near_flat",
    "outline_fill",
]

F32 = NDArray[np.float32]


@dataclass(frozen=True)
class ContourFillParams:
    """Parameters of :func:`contour_fill` (module docstring)."""

    flat_gradient: float = 2.0  # grey levels per pixel (0.7-px blur): untextured
    min_region_px: int = 100
    side_px: float = 6.0
    known_min_confidence: float = 0.1  # a side's depth counts from this prior confidence on
    side_agree: float = 0.10
    far_rel: float = 0.15
    min_samples: int = 10
    inlier_rel: float = 0.05
    min_inlier_share: float = 0.9
    known_agree: float = 0.25
    min_known_share: float = 0.05
    min_rel_err: float = 0.06
    replace_below: float = 0.3  # also the region's pixels below this confidence (0: holes)

    def __post_init__(self) -> None:
        if min(self.flat_gradient, self.side_px, self.inlier_rel, self.min_rel_err) <= 0:
            raise ConfigError(
                "contour: flat_gradient, side_px, inlier_rel and min_rel_err must be > 0"
            )
        if self.min_samples < 1 or self.min_region_px < 1:
            raise ConfigError("contour: min_samples and min_region_px must be >= 1")
        if not 0 <= self.min_inlier_share <= 1 or min(self.far_rel, self.known_agree) < 0:
            raise ConfigError("contour: need 0 <= min_inlier_share <= 1, far_rel, known_agree >= 0")


def _gradient(grey: NDArray[np.uint8]) -> tuple[F32, F32]:
    I = cv2.GaussianBlur(np.asarray(grey, np.float32), (0, 0), 0.7)
    return (
        cv2.Sobel(I, cv2.CV_32F, 1, 0, ksize=3) / 8.0,
        cv2.Sobel(I, cv2.CV_32F, 0, 1, ksize=3) / 8.0,
    )


def flat_regions(
    gx: F32, gy: F32, max_gradient: float, min_pixels: int
) -> tuple[NDArray[np.int32], int]:
    """4-connected regions of gradient magnitude below ``max_gradient`` with at least
    ``min_pixels`` pixels: ``(labels [H, W] (-1 elsewhere), number of labels)``."""
    flat = (np.hypot(gx, gy) < max_gradient).astype(np.uint8)
    n, cc = cv2.connectedComponents(flat, connectivity=4)
    big = np.bincount(cc.ravel(), minlength=n) >= min_pixels
    big[0] = False  # label 0: the non-flat pixels
    return np.where(flat.astype(bool) & big[cc], cc, -1).astype(np.int32), n


def near_flat(grey: NDArray[np.uint8], params: ContourFillParams) -> NDArray[np.bool_]:
    """Pixels within ``side_px + 1`` of an untextured region ``[H, W]``: the only edges whose
    depth the fill can use (the edge search need not look at the others)."""
    labels, _ = flat_regions(*_gradient(grey), params.flat_gradient, params.min_region_px)
    r = int(np.ceil(params.side_px)) + 1
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate((labels >= 0).astype(np.uint8), k) > 0


def assign_to_regions(
    v: NDArray[np.intp],
    u: NDArray[np.intp],
    z: F32,
    normal: NDArray[np.float64],
    labels: NDArray[np.int32],
    known: F32,
    params: ContourFillParams,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Edge samples given to the region on the occluding side (module docstring): ``(sample
    index, region label)`` pairs (a crease's sample goes to both sides)."""
    H, W = labels.shape
    out_i, out_l = [], []
    sides = []
    for sgn in (1.0, -1.0):
        su = np.clip(np.round(u + sgn * params.side_px * normal[:, 0]).astype(np.intp), 0, W - 1)
        sv = np.clip(np.round(v + sgn * params.side_px * normal[:, 1]).astype(np.intp), 0, H - 1)
        sides.append((labels[sv, su], known[sv, su]))
    for (lx, dx), (ly, dy) in ((sides[0], sides[1]), (sides[1], sides[0])):
        ok_x = (dx <= 0) | (np.abs(dx - z) <= params.side_agree * z)
        behind = (dy > 0) & (dy > (1.0 + params.far_rel) * z)
        # a crease separates two untextured faces: two regions (both sides in one region is a
        # gradient along the outline, e.g. a textured occluder's texture blurred over it)
        crease = (dx <= 0) & (dy <= 0) & (ly >= 0)
        take = np.flatnonzero(ok_x & (behind | crease) & (lx >= 0) & (lx != ly))
        out_i.append(take)
        out_l.append(lx[take])
    return np.concatenate(out_i), np.concatenate(out_l)


def contour_fill(
    grey: NDArray[np.uint8],
    edge_depth: F32,
    depth: F32,
    confidence: F32,
    params: ContourFillParams,
) -> tuple[F32, F32, dict[str, float]]:
    """Depth for the untextured regions of a keyframe from their outline (module docstring).

    ``grey`` ``[H, W]`` uint8; ``edge_depth`` ``[H, W]`` edge-stereo depth (0: none); ``depth`` /
    ``confidence`` the fused prior so far (0: none). Returns ``(fill_depth, fill_rel_err,
    stats)``: depth only at pixels without one in ``depth`` (0 elsewhere), error inf there.
    """
    H, W = depth.shape
    fill = np.zeros((H, W), np.float32)
    err = np.full((H, W), np.inf, np.float32)
    stats = {"contour_regions": 0.0, "contour_pixels": 0.0}
    gx, gy = _gradient(grey)
    labels, n = flat_regions(gx, gy, params.flat_gradient, params.min_region_px)
    # samples on an edge only (the side is looked up along the gradient, which a pixel without
    # one does not have)
    v, u = np.nonzero((edge_depth > 0) & (np.hypot(gx, gy) >= params.flat_gradient))
    if len(v) == 0 or n <= 1:
        return fill, err, stats
    z = edge_depth[v, u].astype(np.float64)
    g = np.stack([gx[v, u], gy[v, u]], 1).astype(np.float64)
    normal = g / (np.linalg.norm(g, axis=1, keepdims=True) + 1e-12)
    known = np.where(confidence >= params.known_min_confidence, depth, 0.0).astype(np.float32)
    idx, lab = assign_to_regions(v, u, z, normal, labels, known, params)
    if len(idx) == 0:
        return fill, err, stats
    lz = np.log(z[idx])
    cnt, med = group_medians(lab, lz, n)
    dev = np.abs(lz - med[lab])
    inl = np.bincount(lab, dev <= np.log1p(params.inlier_rel), minlength=n)[:n]
    _, mad = group_medians(lab, dev, n)
    ok = (cnt >= params.min_samples) & (inl >= params.min_inlier_share * np.maximum(cnt, 1))
    # the depth the region already has must agree (an edge given to the wrong side)
    flat = labels.ravel()
    has = (flat >= 0) & (depth.ravel() > 0)
    size = np.bincount(flat[flat >= 0], minlength=n)[:n]
    n_known = np.bincount(flat[has], minlength=n)[:n]
    _, known_med = group_medians(flat[has], np.log(depth.ravel()[has].astype(np.float64)), n)
    checked = n_known >= np.maximum(10, params.min_known_share * size)
    agree = ~checked | (np.abs(known_med - med) <= np.log1p(params.known_agree))
    ok &= agree & np.isfinite(med)
    weak = depth.ravel() <= 0
    if params.replace_below > 0:
        weak |= confidence.ravel() < params.replace_below
    target = (flat >= 0) & weak
    target &= ok[np.where(flat >= 0, flat, 0)]
    t = np.flatnonzero(target)
    fill.ravel()[t] = np.exp(med[flat[t]]).astype(np.float32)
    e = np.maximum(params.min_rel_err, 1.4826 * np.nan_to_num(mad, nan=np.inf))
    err.ravel()[t] = e[flat[t]].astype(np.float32)
    stats.update(contour_regions=float(ok.sum()), contour_pixels=float(len(t)))
    return fill, err, stats


def outline_fill(
    grey: NDArray[np.uint8],
    K: NDArray[np.float64],
    T_world_cam: NDArray[np.float64],
    references: Sequence[tuple[NDArray[np.uint8], NDArray[np.float64]]],
    depth: F32,
    confidence: F32,
    sky: NDArray[np.bool_],
    edge_params: EdgeStereoParams,
    params: ContourFillParams,
) -> tuple[F32, F32, dict[str, float]]:
    """The dense prior's ``contour`` source: the edges around untextured regions matched in the
    flow ``references`` (:func:`~mogs_node.depth_prior.edge_stereo.edge_stereo_depth`, sky
    excluded), then :func:`contour_fill` with them."""
    where = near_flat(grey, params) & ~sky
    edge, _ = edge_stereo_depth(grey, K, T_world_cam, references, edge_params, where=where)
    fill, err, stats = contour_fill(grey, edge, depth, confidence, params)
    fill[sky] = 0.0
    err[sky] = np.inf
    stats["edge_pixels"] = float(np.count_nonzero(edge))
    return fill, err, stats
