"""Dense metric anchors: a second, metric depth map as extra weighted sparse points (issue 16).

A user with a learned relative-depth prior (Depth Anything) still has the frontend's metric
poses, so the weight-free flow prior (:mod:`mogs_node.depth_prior.flow_prior`: multi-view flow
triangulated with those poses) can run beside it. Its confident pixels are metric and far more
numerous than the frontend's points (about 1500 per demo keyframe at confidence >= 0.3, AbsRel
0.06 there, against 17-300 points), but noisier than the points. They enter the calibration of
the relative prior (global affine, Algorithm 1, CDR eqs. (6)-(11)) as extra sparse points:

- sub-sampled on a grid (one per ``stride`` x ``stride`` cell), confidence at least
  ``min_confidence``;
- only where the frontend has no point within ``gap_px`` (the points are more accurate, and
  where they are dense the anchors only add noise: demo LFM inputs, all anchors 0.083, anchors
  off the points' neighbourhood 0.079; docs/metrizer.md "Dense metric anchors");
- weighted ``weight * confidence`` (the frontend points' omega is ~0.03-0.4 on the demo).

Pure: arrays in, arrays out.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["anchor_points"]

F64 = NDArray[np.float64]


def anchor_points(
    depth_m: NDArray[np.floating],
    confidence: NDArray[np.floating],
    feature_uv_px: NDArray[np.floating],
    *,
    stride: int,
    min_confidence: float,
    gap_px: float,
    weight: float,
    depth_range_m: tuple[float, float],
) -> tuple[F64, F64, F64]:
    """Grid samples of a metric depth map ``depth_m`` ``[H, W]`` with ``confidence`` ``[H, W]``
    as sparse points: ``(uv [M, 2], z [M], w [M])``, pixel centres of the grid cells.

    A pixel is used when its depth is finite and in ``depth_range_m``, its confidence finite and
    at least ``min_confidence`` (> 0), and no pixel of ``feature_uv_px`` ``[N, 2]`` lies within
    ``gap_px`` of it (``gap_px <= 0``: no such test). ``w = weight * min(confidence, 1)``.
    """
    H, W = depth_m.shape
    s = max(int(stride), 1)
    vv, uu = np.mgrid[s // 2 : H : s, s // 2 : W : s]
    uu, vv = uu.ravel(), vv.ravel()
    z = np.asarray(depth_m, np.float64)[vv, uu]
    c = np.asarray(confidence, np.float64)[vv, uu]
    lo, hi = depth_range_m
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(z) & np.isfinite(c) & (z >= lo) & (z <= hi)
        ok &= c >= max(float(min_confidence), 1e-6)
    if gap_px > 0 and len(feature_uv_px) and ok.any():
        f = np.asarray(feature_uv_px, np.float64)
        f = f[np.all(np.isfinite(f), axis=1)]
        fu = np.round(f[:, 0]).astype(np.intp)
        fv = np.round(f[:, 1]).astype(np.intp)
        inside = (fu >= 0) & (fu < W) & (fv >= 0) & (fv < H)
        if inside.any():
            free = np.ones((H, W), np.uint8)
            free[fv[inside], fu[inside]] = 0
            dist = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            ok &= dist[vv, uu] > gap_px
    uv = np.stack([uu[ok], vv[ok]], axis=1).astype(np.float64)
    w = float(weight) * np.minimum(c[ok], 1.0)
    return uv, z[ok], w
