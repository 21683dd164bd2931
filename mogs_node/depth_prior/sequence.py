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

from mogs_node.depth_prior.dense_prior import (
    DensePrior,
    FusionParams,
    PriorHistory,
    compute_dense_prior,
)
from mogs_node.depth_prior.flow_prior import (
    FlowPriorParams,
    _grey,
    choose_far_field_reference,
    choose_references,
)
from mogs_node.depth_prior.road import RoadPriorParams
from mogs_node.geometry import check_array

__all__ = ["PriorSequence"]


GROUND_HEIGHTS_KEPT = 50  # camera-height measurements whose median is used
FRAMES_AHEAD = 32  # frames kept beyond flow.frame_references (add_frame)


@dataclass
class _Past:
    keyframe_id: int
    grey: NDArray[np.uint8]  # [H, W]
    T_world_cam: NDArray[np.float64]  # [4, 4]
    metrized: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None  # depth, confidence
    prior: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None  # its own prior
    stamp_ns: int = -1  # -1: unknown


@dataclass
class _Frame:
    """A non-keyframe frame kept as a possible flow reference."""

    stamp_ns: int
    grey: NDArray[np.uint8]  # [H, W]
    T_world_cam: NDArray[np.float64]  # [4, 4]


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
        # recent frames by stamp (flow.frame_references of them), keyframes' own frames included
        self.frames: dict[int, _Frame] = {}
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
            if self._K is not None:  # frames before the first keyframe are its references
                self.frames.clear()
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

    def add_frame(self, stamp_ns: int, image: NDArray[np.uint8], T_world_cam: NDArray) -> bool:
        """Keep a tracked frame (the keyframes' camera) as a possible flow reference of a later
        keyframe; False when off or its size does not match the keyframes'. A keyframe uses the
        latest ``flow.frame_references`` frames before its stamp; ``FRAMES_AHEAD`` more are kept,
        so that frames that arrive while a keyframe waits do not push its own ones out."""
        n = self.flow.frame_references
        if n <= 0:
            return False
        grey = _grey(image, "image")
        if self.history and self.history[-1].grey.shape != grey.shape:
            return False
        T = check_array("T_world_cam", T_world_cam, shape=(4, 4), finite=True)
        self.frames[int(stamp_ns)] = _Frame(int(stamp_ns), grey, np.array(T, np.float64))
        while len(self.frames) > n + FRAMES_AHEAD:
            self.frames.pop(min(self.frames))
        return True

    def forget_frames(self) -> None:
        """Drop the kept frames (a frontend reset: their poses are in another world)."""
        self.frames.clear()

    def _references(
        self, stamp_ns: int | None, T_world_cam: NDArray, past: list[_Past], shape: tuple
    ) -> tuple[
        list[tuple[NDArray, NDArray]], list[int], list[tuple[NDArray, NDArray]], tuple | None
    ]:
        """Flow references (grey, pose), their keyframe ids (-1: a frame), the road's extra
        references and the far-field reference (or None), chosen among the earlier keyframes and
        the kept frames before ``stamp_ns``."""
        pool = [(p.stamp_ns, p.grey, p.T_world_cam, p.keyframe_id) for p in past]
        if stamp_ns is not None and self.frames:
            seen = {p.stamp_ns for p in past}
            before = sorted(t for t in self.frames if t < stamp_ns)[-self.flow.frame_references :]
            pool += [
                (t, self.frames[t].grey, self.frames[t].T_world_cam, -1)
                for t in before
                if t not in seen and self.frames[t].grey.shape == shape
            ]
            pool.sort(key=lambda e: e[0])
        Th = np.array([e[2] for e in pool]) if pool else np.zeros((0, 4, 4))
        refs = choose_references(T_world_cam, Th, self.flow)
        road = self._road_references(refs)
        far = choose_far_field_reference(T_world_cam, Th, refs, self.flow)
        return (
            [(pool[j][1], pool[j][2]) for j in refs],
            [pool[j][3] for j in refs],
            [(pool[j][1], pool[j][2]) for j in road],
            None if far is None else (pool[far][1], pool[far][2]),
        )

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

    def _road_references(self, refs: list[int]) -> list[int]:
        """The references' pool entries (keyframes and kept frames, oldest first) before the
        nearest reference and not chosen already: the road they saw may have been hidden from
        the nearest one (``road.extra_references`` of them)."""
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
        self,
        keyframe_id: int,
        image: NDArray[np.uint8],
        K: NDArray,
        T_world_cam: NDArray,
        stamp_ns: int | None = None,
    ) -> tuple[DensePrior, list[int]]:
        """Prior of a new keyframe; returns it with the ids of the flow references used (-1: a
        kept frame, :meth:`add_frame`, used only with the keyframe's ``stamp_ns``)."""
        grey = _grey(image, "image")
        self._check_camera(K, grey.shape)
        past = list(self.history)
        references, ref_ids, road_refs, far_ref = self._references(
            stamp_ns, T_world_cam, past, grey.shape
        )
        earlier = [
            (p.metrized[0], p.metrized[1], p.T_world_cam, p.grey)
            for p in reversed(past)
            if p.metrized is not None
        ]
        last = past[-1] if past else None
        carried = None
        if last is not None and last.prior is not None:
            carried = (last.prior[0], last.prior[1], last.T_world_cam, last.grey)
        past_in = PriorHistory(
            references, earlier, carried, road_refs, self.ground_heights_m, far_ref
        )
        prior = compute_dense_prior(
            grey,
            K,
            T_world_cam,
            past_in,
            flow_params=self.flow,
            road_params=self.road,
            params=self.fusion,
        )
        fit = prior.stats.get("ground_height_fit_m", float("nan"))
        if np.isfinite(fit):
            self.ground_heights_m.append(fit)
        self.remember(keyframe_id, grey, K, T_world_cam)
        carry = prior.confidence if prior.carry_confidence is None else prior.carry_confidence
        self.history[-1].prior = (prior.depth_m, carry)
        self.history[-1].stamp_ns = -1 if stamp_ns is None else int(stamp_ns)
        return prior, ref_ids
