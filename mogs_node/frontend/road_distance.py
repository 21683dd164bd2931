"""The road-plane distance between consecutive window frames, as a measurement for the window
(the metric scale a car's camera height gives, :func:`~.ground.estimate_ground_translation`).

One :class:`RoadDistance` per frontend keeps the previous window frame's grey image and the recent
ratios of measured to estimated distance, which gate measurements biased by a vehicle ahead.
"""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.frontend.estimator import VioEstimator
from mogs_node.frontend.ground import (
    GroundParams,
    estimate_ground_translation,
    road_normal_from_mount,
)
from mogs_node.geometry import se3_inverse

__all__ = ["RoadDistance"]


class RoadDistance:
    """Measures and adds the road distance of the newest window step (used from the next solve)."""

    def __init__(self, params: GroundParams, K: NDArray, T_imu_cam: NDArray) -> None:
        self.params = params
        self.K = K
        self.T_imu_cam = T_imu_cam
        self.road_normal = road_normal_from_mount(T_imu_cam)
        self.prev_gray: tuple[int, NDArray] | None = None  # (estimator seq, grey image)
        self.ratios: deque[float] = deque(maxlen=params.gate_window)

    def reset(self) -> None:
        self.prev_gray = None
        self.ratios.clear()

    def measure(self, estimator: VioEstimator, image: NDArray) -> str | None:
        """Measure between the previous and the newest window frame and add it to ``estimator``;
        the counter to count it under (``ground_measurements``, ``ground_rejected``,
        ``ground_gated``, ``ground_implausible``), None when there was nothing to measure."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        frames = estimator.frames
        prev, self.prev_gray = self.prev_gray, (frames[-1].seq, gray)
        if prev is None or len(frames) < 2 or frames[-2].seq != prev[0]:
            return None
        T_ic = self.T_imu_cam
        T_cur_prev = se3_inverse(estimator.pose(frames[-1].seq) @ T_ic) @ (
            estimator.pose(prev[0]) @ T_ic
        )
        t = T_cur_prev[:3, 3]
        gp = self.params
        dist = float(np.linalg.norm(t))
        if dist <= 0.05:  # below ~0.5 m/s the road moves too little in 0.1 s
            return None
        tau_guess = dist / gp.camera_height_m
        m = estimate_ground_translation(
            prev[1], gray, self.K, T_cur_prev[:3, :3], t, self.road_normal, tau_guess, gp
        )
        if m is None:
            return "ground_rejected"
        # A vehicle ahead or its shadow can bias a measurement for a few frames: one far from
        # the recent ratios to the window's own distance is not used (the ratio is kept, so a
        # lasting change of the window's scale is followed).
        ratio = m.distance_m / dist
        if not 1 / gp.max_ratio <= ratio <= gp.max_ratio:
            return "ground_implausible"  # not road (a near object in the lane): not kept either
        recent = self.ratios
        off = len(recent) < 5 or abs(ratio / float(np.median(recent)) - 1) > gp.gate_rel
        recent.append(ratio)
        if off:
            return "ground_gated"
        seq_prev, seq_cur = prev[0], frames[-1].seq
        if not estimator.add_ground_distance(
            seq_prev, seq_cur, m.distance_m, gp.relative_sigma * m.distance_m
        ):
            return "ground_rejected"
        return "ground_measurements"
