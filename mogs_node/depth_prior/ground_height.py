"""The camera's height above the ground, measured from the flow prior's metric depth.

A car's road-plane prior (:mod:`mogs_node.depth_prior.road`) needs the camera height. KITTI and the
sim publish it with the calibration; a folder recorded with a Kalibr-calibrated rig does not
(camchain.yaml has no such field), and a user should not have to measure it. With metric poses
(visual-inertial) the flow prior's depth is metric, so every pixel it triangulates gives the drop
``d = -up . X`` of its 3D point below the camera. The ground is the surface where many such drops
agree: the densest relative band of drops within a plausible height range. Box tops, bonnets and
kerbs lie 0.3-0.6 m below a car's camera and are left out by the range's lower bound; a
keyframe whose band holds too few pixels, or too small a share of the points below the camera (no
road seen: facing a wall or pillars), gives no measurement.

One keyframe's measurement is noisy (a few per cent: flow depth on a weakly textured road), so the
height used is the median of the measurements so far (:func:`ground_height_m`), kept by the
prior's sequence. Beyond the paper (docs/depth_prior.md, "Camera height from the flow depth").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "BAND_REL",
    "MIN_PIXELS",
    "MIN_SHARE",
    "MIN_VERIFIED",
    "fit_ground_height",
    "ground_height_m",
    "refine_ground_height",
]

BAND_REL = 0.04  # a surface: drops within +-4 % of the band's centre
MIN_PIXELS = 300  # pixels in the band for a measurement
MIN_SHARE = 0.08  # ... and this share of the pixels below the camera
MAX_TILT_DEG = 20.0  # a pixel counts when its surface normal is this close to "up"
NORMAL_STEP_PX = 3  # the normal from the 3D points this many pixels apart
MIN_CONFIDENCE = 0.3  # flow depth used (a predicted error below ~7 %)
MAX_DEPTH_M = 30.0  # far road: too little parallax for its depth to be of use
CANDIDATES = 160  # band centres tried, log-spaced over the height range
MIN_VERIFIED = 500  # road pixels the refined height must verify for a measurement
COARSE_STEPS = (-0.09, -0.06, -0.03, 0.0, 0.03, 0.06, 0.09)  # relative steps of the refinement
FINE_STEPS = (-0.02, -0.01, 0.01, 0.02)  # ... then around the best coarse one


def fit_ground_height(
    depth_m: NDArray[np.float32],
    confidence: NDArray[np.float32],
    rays_xy: NDArray[np.float32],
    up_cam: NDArray[np.float64],
    height_range_m: tuple[float, float],
) -> tuple[float, int] | None:
    """The ground's drop below the camera seen in one metric depth map: ``(height_m, pixels)``, or
    None when no band within ``height_range_m`` holds enough pixels.

    ``depth_m``, ``confidence``: ``[H, W]`` z-depth (0: none) and its confidence; ``rays_xy``:
    ``[2, H, W]`` the pixels' rays ``[x, y, 1]``; ``up_cam``: unit "up" in the camera frame.
    """
    lo, hi = float(height_range_m[0]), float(height_range_m[1])
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
        return None
    z = np.asarray(depth_m, np.float32)
    ok = (np.asarray(confidence) >= MIN_CONFIDENCE) & np.isfinite(z) & (z > 0) & (z < MAX_DEPTH_M)
    up = np.asarray(up_cam, np.float64)
    ok &= _level(z, rays_xy, ok, up)
    if not ok.any():
        return None
    x, y = rays_xy[0][ok], rays_xy[1][ok]
    drop = (-(up[0] * x + up[1] * y + up[2]) * z[ok]).astype(np.float64)
    below = drop[np.isfinite(drop) & (drop > 0.5 * lo)]
    if below.size < MIN_PIXELS:
        return None
    drops = np.sort(below)
    centres = np.geomspace(lo, hi, CANDIDATES)
    counts = np.searchsorted(drops, centres * (1 + BAND_REL), "right") - np.searchsorted(
        drops, centres * (1 - BAND_REL), "left"
    )
    best = int(np.argmax(counts))
    n = int(counts[best])
    if n < MIN_PIXELS or n < MIN_SHARE * drops.size:
        return None
    c = centres[best]
    band = drops[(drops >= c * (1 - BAND_REL)) & (drops <= c * (1 + BAND_REL))]
    return float(np.median(band)), n


def refine_ground_height(
    centre_m: float, verified_pixels: Callable[[float], int]
) -> tuple[float, int] | None:
    """The height near ``centre_m`` at which the road plane is verified on the most pixels
    (``verified_pixels(h)``: the road prior's flow and photometric tests against a reference at
    height ``h``, :func:`mogs_node.depth_prior.road.road_prior`): ``(height_m, pixels)``, None when
    fewer than ``MIN_VERIFIED`` pixels agree at the best height.

    The flow depth alone measures the ground to a few per cent (DIS smooths a weakly textured
    road); the plane's own tests peak within ~1-2 % of the height (on the demo's drive: within 3 %
    of the truth at every keyframe where the road is seen).
    """
    if not (np.isfinite(centre_m) and centre_m > 0):
        return None
    heights = [centre_m * (1.0 + r) for r in COARSE_STEPS]
    counts = [int(verified_pixels(h)) for h in heights]
    around = heights[int(np.argmax(counts))]
    heights += [around * (1.0 + r) for r in FINE_STEPS]
    counts += [int(verified_pixels(h)) for h in heights[len(COARSE_STEPS) :]]
    best = int(np.argmax(counts))  # the first of equals, coarse before fine
    return (float(heights[best]), counts[best]) if counts[best] >= MIN_VERIFIED else None


def _level(
    z: NDArray[np.float32], rays_xy: NDArray[np.float32], ok: NDArray[np.bool_], up: NDArray
) -> NDArray[np.bool_]:
    """Pixels whose surface (the normal of the 3D points ``NORMAL_STEP_PX`` to the right and
    below) is level: a wall or a pole facing the camera is not ground whatever its drop."""
    s = NORMAL_STEP_PX
    H, W = z.shape
    out = np.zeros((H, W), bool)
    if s >= H or s >= W:
        return out
    zz = np.where(ok, z, 0.0).astype(np.float64)
    P = np.stack([rays_xy[0] * zz, rays_xy[1] * zz, zz])  # [3, H, W]
    du = P[:, :-s, s:] - P[:, :-s, :-s]
    dv = P[:, s:, :-s] - P[:, :-s, :-s]
    n = np.cross(du, dv, axis=0)
    norm = np.linalg.norm(n, axis=0)
    cos = np.abs(np.tensordot(up, n, axes=1)) / np.maximum(norm, 1e-12)
    both = ok[:-s, :-s] & ok[:-s, s:] & ok[s:, :-s] & (norm > 0)
    out[:-s, :-s] = both & (cos >= np.cos(np.radians(MAX_TILT_DEG)))
    return out


def ground_height_m(heights_m: Sequence[float]) -> float:
    """The height used: the median of the keyframes' measurements (0: none yet, no road prior)."""
    h = np.asarray([v for v in heights_m if np.isfinite(v) and v > 0], np.float64)
    return float(np.median(h)) if h.size else 0.0
