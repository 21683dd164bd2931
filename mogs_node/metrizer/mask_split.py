"""Masks split along the prior's depth jumps (issue 16, a departure from the paper; off).

An image segmenter follows colour, not depth: a graph-segmentation mask can hold a pole and the
facade behind it, or a car and the road under it. The per-object calibration (one affine of the
prior per object, eqs. 6-8) then spans a depth edge and fits neither side. The relative prior
itself shows where depth jumps, even blurred: its inverse depth is affine in the pixels on any
plane (Laplacian 0, however slanted), not across a jump. Each mask is cut along that band into
4-connected pieces; the band's pixels (and pieces smaller than ``min_px``) go back to the
nearest piece of their own mask, so every pixel keeps a label and no piece crosses a mask
border. Paper III-B only merges under-supported masks, it never splits. Measured not to pay on
the demo drives (docs/metrizer.md "Masks split along the prior's depth jumps").

Pure: arrays in, arrays out.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt

from mogs_node.depth_kind import DepthKind
from mogs_node.metrizer.edge_snap import near_object_boundary

__all__ = ["jump_band", "split_masks"]


def jump_band(
    prior: NDArray[np.floating],
    confidence: NDArray[np.floating],
    prior_kind: str,
    rel: float,
    radius: int,
) -> NDArray[np.bool_]:
    """``[H, W]`` pixels within ``radius`` px of a depth jump of the prior: where the Laplacian of
    its inverse depth ``q``, relative to ``q``, exceeds ``rel``. A plane's inverse depth is affine
    in the pixel coordinates (its Laplacian is 0, however slanted: the road to the horizon), a
    depth edge, blurred or not, is not."""
    x = np.asarray(prior, np.float64)
    ok = (np.asarray(confidence) > 0) & np.isfinite(x)
    if prior_kind == DepthKind.RELATIVE_INVERSE_DEPTH:
        q = np.where(ok, x, 0.0)
    else:
        ok &= x > 0
        q = np.where(ok, 1.0 / np.where(ok, x, 1.0), 0.0)
    # a plane continues linearly past the image border (odd reflection): no kink there
    qp = np.pad(q, 3, mode="reflect", reflect_type="odd").astype(np.float32)
    # a 1-px Gaussian first: per-pixel noise (1 % on the simulated LFM) is not a jump
    lap = np.abs(cv2.Laplacian(cv2.GaussianBlur(qp, (5, 5), 1.0), cv2.CV_32F, ksize=1))[3:-3, 3:-3]
    with np.errstate(invalid="ignore", divide="ignore"):
        edge = (lap > rel * np.abs(q)) & ok
    # a pixel beside a pixel without prior is no evidence (its Laplacian sees the 0)
    edge &= cv2.erode(ok.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    if radius > 0:
        k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        edge = cv2.dilate(edge.astype(np.uint8), k) > 0
    return edge


def _grow_within_masks(
    out: NDArray[np.int64], lab: NDArray[np.integer], H: int, W: int, rounds: int
) -> None:
    """In place: pixels of a mask without a piece (``out < 0``) take the piece of a 4-neighbour
    of the same mask, ``rounds`` times (a geodesic reach: the nearest piece in the plane can lie
    in another mask across a thin one)."""
    o, lb = out.reshape(H, W), lab.reshape(H, W)
    for _ in range(rounds):
        todo = (o < 0) & (lb >= 0)
        if not todo.any():
            return
        new = o.copy()
        for sl_to, sl_from in (
            ((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
            ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
            ((slice(1, None), slice(None)), (slice(None, -1), slice(None))),
            ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
        ):
            take = todo[sl_to] & (new[sl_to] < 0) & (o[sl_from] >= 0) & (lb[sl_from] == lb[sl_to])
            new[sl_to][take] = o[sl_from][take]
        if np.array_equal(new, o):
            return
        o[...] = new


def split_masks(
    labels: NDArray[np.integer], band: NDArray[np.bool_], min_px: int, reach: int
) -> NDArray[np.int32]:
    """Instance labels ``[H, W]`` (``-1`` = no mask, kept) with each mask cut along ``band``
    ``[H, W]`` (the prior's depth jumps, :func:`jump_band`).

    A piece is a 4-connected component of a mask outside the band with at least ``min_px``
    pixels; every other pixel of the mask joins the nearest piece of the same mask (in the plane,
    else through the mask within ``reach`` px, else the mask's largest piece; a mask with no
    piece keeps one label). Returns compact labels ``0..M'-1`` and ``-1``.
    """
    lab = np.asarray(labels)
    H, W = lab.shape
    masked = lab >= 0
    band = band & masked
    if not band.any():
        return lab.astype(np.int32, copy=True)
    free = masked & ~band & ~near_object_boundary(lab, 0)
    n, cc = cv2.connectedComponents(free.astype(np.uint8), connectivity=4)
    size = np.bincount(cc.ravel(), minlength=n)
    big = size >= max(1, min_px)
    big[0] = False  # component 0: the pixels not free
    seed = big[cc]
    out = np.full(H * W, -1, np.int64)
    out[seed.ravel()] = cc.ravel()[seed.ravel()]
    lab_f = lab.ravel()
    if seed.any():
        _, (iy, ix) = distance_transform_edt(~seed, return_indices=True)
        src = (iy * W + ix).ravel()
        rest = masked.ravel() & ~seed.ravel()
        same = rest & (lab_f[src] == lab_f)
        out[same] = out[src[same]]
        _grow_within_masks(out, lab_f, H, W, rounds=reach)
    # pixels whose nearest piece belongs to another mask: the mask's largest piece (or, without a
    # piece, the whole mask as one label, offset past the component ids)
    left = masked.ravel() & (out < 0)
    if left.any():
        mx = int(lab_f.max())
        best = np.full(mx + 1, -1, np.int64)
        have = seed.ravel()
        if have.any():
            key = lab_f[have]
            comp = cc.ravel()[have]
            order = np.lexsort((-size[comp], key))
            first = np.concatenate([[True], key[order][1:] != key[order][:-1]])
            best[key[order][first]] = comp[order][first]
        fb = best[lab_f[left]]
        fb = np.where(fb >= 0, fb, n + lab_f[left])
        out[left] = fb
    _, inv = np.unique(out, return_inverse=True)
    res = inv.reshape(H, W).astype(np.int32) - (1 if (out < 0).any() else 0)
    return res
