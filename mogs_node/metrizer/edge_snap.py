"""Depth edges of a blurred prior snapped to their object (issue 16, beyond the paper).

A learned relative-depth model blurs depth edges: across the boundary between a near object and
the background its inverse depth passes through intermediate values ("flying pixels"; the
simulated LFM blurs them with a 2-px Gaussian, :mod:`mogs_node.sim.lfm`). A per-object affine of
the prior keeps that ramp, so the pixels in the band are neither the object's depth nor the
background's: on the demo drive with the simulated LFM, the 22 % of pixels near a depth edge held
53 % of the error (mean AbsRel 0.18, against 0.04 elsewhere). The masks follow image edges, so
each such pixel takes the output of the nearest pixel of its own object outside the band: the
object's interior depth, extended to its border. Only near a boundary between objects: inside an
object a steep prior gradient is a slanted surface (the road near the horizon), not an edge
(sim frames: without that restriction up to 10 % worse on some, with it 5-27 % better on all).

Pure: arrays in, arrays out.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt

__all__ = ["near_object_boundary", "prior_edge_band", "snap_edges"]


def prior_edge_band(
    prior: NDArray[np.floating], confidence: NDArray[np.floating], rel: float, radius: int
) -> NDArray[np.bool_]:
    """``[H, W]`` pixels within ``radius`` px of a prior depth edge: relative gradient
    ``|grad x| / |x|`` (Sobel, per pixel) above ``rel``, where the prior has a value."""
    x = np.where(np.asarray(confidence) > 0, np.asarray(prior, np.float32), np.float32(0.0))
    x = np.nan_to_num(x.astype(np.float32, copy=False), nan=0.0, posinf=0.0, neginf=0.0)
    gx = cv2.Sobel(x, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(x, cv2.CV_32F, 0, 1, ksize=3)
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.hypot(gx, gy) / np.float32(8.0)
        edge = (g > rel * np.abs(x)) & (x != 0)
    if radius > 0:
        k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        edge = cv2.dilate(edge.astype(np.uint8), k) > 0
    return edge


def near_object_boundary(objects: NDArray[np.integer], radius: int) -> NDArray[np.bool_]:
    """``[H, W]`` pixels within ``radius`` px (square) of a pixel whose 4-neighbour belongs to
    another object."""
    o = objects
    bd = np.zeros(o.shape, bool)
    dx, dy = o[:, 1:] != o[:, :-1], o[1:] != o[:-1]
    bd[:, 1:] |= dx
    bd[:, :-1] |= dx
    bd[1:] |= dy
    bd[:-1] |= dy
    if radius > 0:
        k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        bd = cv2.dilate(bd.astype(np.uint8), k) > 0
    return bd


def snap_edges(
    depth: NDArray[np.float32],
    confidence: NDArray[np.float32],
    objects: NDArray[np.integer],
    band: NDArray[np.bool_],
) -> int:
    """In place: each pixel of ``band`` ``[H, W]`` with a depth takes the depth and confidence of
    the nearest pixel outside the band when that pixel belongs to the same object (``objects``
    ``[H, W]``) and has a depth. ``depth`` / ``confidence`` ``[H, W]``. Returns the pixels
    changed."""
    if not band.any() or band.all():
        return 0
    _, (iy, ix) = distance_transform_edt(band, return_indices=True)
    ok = band & (depth > 0)
    src_y, src_x = iy[ok], ix[ok]
    keep = (objects[src_y, src_x] == objects[ok]) & (depth[src_y, src_x] > 0)
    vy, vx = np.nonzero(ok)
    vy, vx, src_y, src_x = vy[keep], vx[keep], src_y[keep], src_x[keep]
    depth[vy, vx] = depth[src_y, src_x]
    confidence[vy, vx] = confidence[src_y, src_x]
    return int(len(vy))
