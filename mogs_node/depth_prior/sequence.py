"""The dense prior over a keyframe sequence: the history the prior node keeps, without the bus.

:class:`PriorSequence` holds the last ``history`` keyframes (grey image, pose) to choose flow
references from, and the metrized depth of those keyframes as it arrives (``/metrizer/depth`` in
the node; in order or late, whatever the pipeline delivers). :meth:`PriorSequence.next` computes
the prior of a new keyframe from them (:func:`~mogs_node.depth_prior.dense_prior.compute_dense_prior`)
and then remembers the keyframe. The node (:mod:`mogs_node.depth_prior.node`) and the evaluation
(:mod:`mogs_node.eval.depth_prior_eval`) share it, so both see the same references and sources.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mogs_node.depth_prior.dense_prior import DensePrior, FusionParams, compute_dense_prior
from mogs_node.depth_prior.flow_prior import FlowPriorParams, _grey, choose_references
from mogs_node.depth_prior.road import RoadPriorParams

__all__ = ["PriorSequence"]


GROUND_HEIGHTS_KEPT = 50  # camera-height measurements whose median is used


@dataclass
class _Past:
    keyframe_id: int
    grey: NDArray[np.uint8]  # [H, W]
    T_world_cam: NDArray[np.float64]  # [4, 4]
    metrized: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None  # depth, confidence
    prior: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None  # its own prior


class PriorSequence:
    """Keyframe history and metrized depths of one camera; priors in keyframe order."""

    def __init__(
        self,
        flow: FlowPriorParams | None = None,
        road: RoadPriorParams | None = None,
        fusion: FusionParams | None = None,
    ) -> None:
        self.flow = flow or FlowPriorParams()
        self.road = road or RoadPriorParams()
        self.fusion = fusion or FusionParams()
        self.history: deque[_Past] = deque(maxlen=self.flow.history)
        self._K: NDArray[np.float64] | None = None
        self._pending: dict[int, tuple[NDArray, NDArray]] = {}  # metrized before its keyframe
        # the keyframes' measurements of the camera height (road.auto_height), latest kept
        self.ground_heights_m: deque[float] = deque(maxlen=GROUND_HEIGHTS_KEPT)

    def _check_camera(self, K: NDArray[np.float64], shape: tuple[int, ...]) -> None:
        """Another camera or resolution makes the old keyframes unusable: forget them."""
        K = np.asarray(K, np.float64)
        if (
            self._K is None
            or not np.array_equal(self._K, K)
            or (self.history and self.history[-1].grey.shape != shape)
        ):
            self.history.clear()
            self._pending.clear()
            self._K = np.array(K)

    def remember(
        self, keyframe_id: int, image: NDArray[np.uint8], K: NDArray, T_world_cam: NDArray
    ):
        """Add a keyframe to the history without computing its prior (e.g. done before a restart)."""
        grey = _grey(image, "image")
        self._check_camera(K, grey.shape)
        past = _Past(int(keyframe_id), grey, np.array(T_world_cam, np.float64))
        past.metrized = self._pending.pop(int(keyframe_id), None)
        self.history.append(past)

    def add_metrized(self, keyframe_id: int, depth_m: NDArray, confidence: NDArray) -> bool:
        """Store the metrized depth of a keyframe; False if its size does not fit the history."""
        d = np.asarray(depth_m, np.float32)
        c = np.asarray(confidence, np.float32)
        if d.shape != c.shape or (self.history and d.shape != self.history[-1].grey.shape):
            return False
        for p in self.history:
            if p.keyframe_id == keyframe_id:
                p.metrized = (d, c)
                return True
        if self.history and keyframe_id < self.history[0].keyframe_id:
            return False  # too old to be of use
        self._pending[int(keyframe_id)] = (d, c)  # its keyframe has not come yet
        while len(self._pending) > self.flow.history:
            self._pending.pop(min(self._pending))
        return True

    def _road_references(self, past: list[_Past], refs: list[int]) -> list[int]:
        """The keyframe before the nearest reference, when far enough: the road it saw may have
        been hidden from the nearest one (``road.extra_references`` of them)."""
        out: list[int] = []
        if not refs:
            return out
        j = refs[0] - 1
        while j >= 0 and len(out) < self.road.extra_references:
            if j not in refs:
                out.append(j)
            j -= 1
        return out

    def next(
        self, keyframe_id: int, image: NDArray[np.uint8], K: NDArray, T_world_cam: NDArray
    ) -> tuple[DensePrior, list[int]]:
        """Prior of a new keyframe; returns it with the ids of the flow references used."""
        grey = _grey(image, "image")
        self._check_camera(K, grey.shape)
        past = list(self.history)
        Th = np.array([p.T_world_cam for p in past]) if past else np.zeros((0, 4, 4))
        refs = choose_references(T_world_cam, Th, self.flow)
        earlier = [
            (p.metrized[0], p.metrized[1], p.T_world_cam, p.grey)
            for p in reversed(past)
            if p.metrized is not None
        ]
        last = past[-1] if past else None
        carried = None
        if last is not None and last.prior is not None:
            carried = (last.prior[0], last.prior[1], last.T_world_cam, last.grey)
        prior = compute_dense_prior(
            grey,
            K,
            T_world_cam,
            [(past[j].grey, past[j].T_world_cam) for j in refs],
            earlier,
            carried,
            [(past[j].grey, past[j].T_world_cam) for j in self._road_references(past, refs)],
            flow_params=self.flow,
            road_params=self.road,
            params=self.fusion,
            ground_heights_m=self.ground_heights_m,
        )
        fit = prior.stats.get("ground_height_fit_m", float("nan"))
        if np.isfinite(fit):
            self.ground_heights_m.append(fit)
        self.remember(keyframe_id, grey, K, T_world_cam)
        self.history[-1].prior = (prior.depth_m, prior.confidence)
        return prior, [past[j].keyframe_id for j in refs]
