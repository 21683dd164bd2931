"""The camera-only frontend's distance from the last keyframe, from that keyframe's own points
(docs/frontend.md, round 12).

The essential matrix gives the rotation and the direction of the motion since the keyframe, not
its length. The keyframe's triangulated points (metric after the road-points check) seen again in
the current frame fix it: for a point ``X`` (keyframe camera) observed at the normalised pixel
``(x, y)``, the camera having moved by ``s`` along the unit direction ``d`` (keyframe camera),
``Y = R (X - s d) = a - s b`` (``a = R X``, ``b = R d``) projects to ``(x, y)``:
``a_x - s b_x = x (a_z - s b_z)`` and the same in ``y``, one linear equation each in ``s``
(the algebraic error, as the DLT's). A robust (Huber, iterated) least squares over the points
gives ``s``; the scale so stays the one of the points, step after step, instead of a road
measurement's per frame (biased low under a vehicle ahead on real KITTI: round 12).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mogs_node.geometry import check_array

__all__ = ["distance_from_points"]


def distance_from_points(
    xyz_kf: NDArray,
    xy_cur: NDArray,
    R_cur_kf: NDArray,
    dir_kf: NDArray,
    *,
    min_points: int = 10,
    huber: float = 2e-3,
    iterations: int = 5,
) -> tuple[float, float, int] | None:
    """Distance ``s`` moved along ``dir_kf`` [3] (keyframe camera; normalised here) since the
    keyframe from its points ``xyz_kf`` [N, 3] seen at normalised pixels ``xy_cur`` [N, 2] of the
    current camera (rotation ``R_cur_kf`` [3, 3]); the number of points used. ``huber``: the
    Huber threshold of the algebraic residual (normalised image units, ~1.5 px at f = 721).
    None with fewer than ``min_points`` points in front of both cameras or no constraint along
    the motion (points on its axis). Returned: ``s``, its 1-sigma (from the robust spread of the
    residuals) and the number of points."""
    X = check_array("xyz_kf", xyz_kf, shape=(None, 3)).astype(np.float64)
    xy = check_array("xy_cur", xy_cur, shape=(len(X), 2)).astype(np.float64)
    R = check_array("R_cur_kf", R_cur_kf, shape=(3, 3), finite=True).astype(np.float64)
    d = check_array("dir_kf", dir_kf, shape=(3,), finite=True).astype(np.float64)
    nd = float(np.linalg.norm(d))
    if nd < 1e-12:
        return None
    ok = np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(xy), axis=1) & (X[:, 2] > 0)
    a = X[ok] @ R.T
    ok_a = a[:, 2] > 0
    a, xy = a[ok_a], xy[ok][ok_a]
    if len(a) < min_points:
        return None
    b = R @ (d / nd)
    # rows: s * (b_x - x b_z) = a_x - x a_z, and the same in y
    A = np.concatenate([b[0] - xy[:, 0] * b[2], b[1] - xy[:, 1] * b[2]])
    y = np.concatenate([a[:, 0] - xy[:, 0] * a[:, 2], a[:, 1] - xy[:, 1] * a[:, 2]])
    # the algebraic residual is the image residual times the depth: divide it out
    z = np.concatenate([a[:, 2], a[:, 2]])
    A, y = A / z, y / z
    if float(A @ A) < 1e-12:
        return None
    informative = np.abs(A) >= 0.1 * np.max(np.abs(A))
    s = float(np.median(y[informative] / A[informative]))  # a robust start for the IRLS
    for _ in range(iterations):
        w = np.minimum(1.0, huber / np.maximum(np.abs(y - s * A), 1e-12))
        s = float((w * A) @ y / max(float((w * A) @ A), 1e-30))
    spread = 1.4826 * float(np.median(np.abs(y - s * A)))
    return s, spread / np.sqrt(max(float((w * A) @ A), 1e-30)), len(a)
