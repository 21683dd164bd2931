"""Depth-prior worker node: ``/frontend/keyframe`` -> ``/prior/depth`` (DESIGN.md sections 1, 3).

Backends: ``flow`` (weight-free default: two-view DIS depth against earlier keyframes,
:mod:`mogs_node.depth_prior.flow_prior`; the node keeps the last ``history`` keyframes to choose
references by distance) or ``depth_anything`` (ONNX monocular depth,
:mod:`mogs_node.depth_prior.depth_anything_onnx`). The ONNX model is loaded in ``setup``: a
missing or malformed model stops the node at start-up with a ModelError, never a silent fallback.

The flow prior is metric when the keyframe poses are (``kind="metric"``); the ONNX prior has the
kind declared in its parameters. Every message carries a per-pixel confidence, 0 where no prior.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from mogs_node import msgs
from mogs_node.depth_prior.depth_anything_onnx import DepthAnythingOnnx, DepthAnythingParams
from mogs_node.depth_prior.flow_prior import (
    FlowPriorParams,
    choose_references,
    compute_flow_prior,
    fit_scale_huber,
)
from mogs_node.errors import ConfigError
from mogs_node.node import Node, parse_params

__all__ = ["DepthPriorNode", "DepthPriorParams"]

BACKENDS = ("flow", "depth_anything")


@dataclass(frozen=True)
class DepthPriorParams:
    """Parameters of the depth-prior worker."""

    backend: str = "flow"  # "flow" (weight-free) or "depth_anything" (ONNX file in `onnx`)
    flow: dict[str, Any] = field(default_factory=dict)  # FlowPriorParams fields
    onnx: dict[str, Any] = field(default_factory=dict)  # DepthAnythingParams fields (model_path)
    in_topic: str = "/frontend/keyframe"  # keyframes
    out_topic: str = "/prior/depth"  # priors, keyed by keyframe id

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(
                f"depth_prior.backend: expected one of {BACKENDS}, got {self.backend!r}"
            )


@dataclass
class _Past:
    keyframe_id: int
    grey: np.ndarray  # [H, W] uint8
    T_world_cam: np.ndarray  # [4, 4]


class DepthPriorNode(Node):
    """One prior per keyframe, in keyframe order (reliable topics)."""

    Params = DepthPriorParams

    def setup(self) -> None:
        p: DepthPriorParams = self.params
        self.flow_params = parse_params(FlowPriorParams, p.flow, where=f"{self.name}.flow")
        self.net: DepthAnythingOnnx | None = None
        if p.backend == "depth_anything":
            self.net = DepthAnythingOnnx(
                parse_params(DepthAnythingParams, p.onnx, where=f"{self.name}.onnx")
            )
        self.history: deque[_Past] = deque(maxlen=self.flow_params.history)
        self._K: np.ndarray | None = None
        self.subscribe(
            p.in_topic, self.on_keyframe, reliable=True, msg_type=msgs.Keyframe, idempotent=True
        )
        self.catch_up((p.in_topic,), (p.out_topic,))  # after a restart: the keyframes missed

    def on_keyframe(self, kf: msgs.Keyframe) -> None:
        if self.already_published(self.params.out_topic, kf.keyframe_id):
            if self.net is None:  # done before a restart: only a reference for the flow prior
                grey = self._grey(kf)
                self.history.append(_Past(kf.keyframe_id, grey, np.array(kf.T_world_cam)))
            return
        if self.net is not None:
            rgb = kf.rgb()
            out = self.net.infer(np.ascontiguousarray(rgb))
            depth, conf, kind, extra = out.value, out.confidence, out.kind, {}
        else:
            depth, conf, kind, extra = self._flow(kf)
        self.publish(
            self.params.out_topic,
            msgs.DepthMap(
                **kf.result_header(),
                kind=kind,
                depth=np.ascontiguousarray(depth, np.float32),
                confidence=np.ascontiguousarray(conf, np.float32),
                source=self.params.backend,
                object_labels=None,
                object_model=None,
            ),
        )
        self.log.debug("keyframe %d: prior %s", kf.keyframe_id, extra)

    def _grey(self, kf: msgs.Keyframe) -> np.ndarray:
        """The keyframe in grey; the history is reset when the camera changed."""
        grey = kf.image if kf.image.ndim == 2 else cv2.cvtColor(kf.image, cv2.COLOR_RGB2GRAY)
        if (
            self._K is None
            or not np.array_equal(self._K, kf.K)
            or (self.history and self.history[-1].grey.shape != grey.shape)
        ):
            self.history.clear()  # another camera or resolution: old keyframes are unusable
            self._K = np.array(kf.K)
        return np.ascontiguousarray(grey)

    def _flow(self, kf: msgs.Keyframe):
        grey = self._grey(kf)
        past = list(self.history)
        refs = choose_references(
            kf.T_world_cam,
            np.array([q.T_world_cam for q in past]) if past else np.zeros((0, 4, 4)),
            self.flow_params,
        )
        prior = compute_flow_prior(
            grey,
            kf.K,
            kf.T_world_cam,
            [(past[j].grey, past[j].T_world_cam) for j in refs],
            self.flow_params,
        )
        self.history.append(
            _Past(kf.keyframe_id, np.ascontiguousarray(grey), np.array(kf.T_world_cam))
        )
        extra = dict(prior.stats)
        extra["references"] = [past[j].keyframe_id for j in refs]
        if len(kf.feature_xyz_cam_m):  # diagnostic: robust scale of the prior vs sparse points
            uv = np.round(kf.feature_uv_px).astype(int)
            H, W = grey.shape
            ok = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
            d = prior.depth_m[uv[ok, 1], uv[ok, 0]]
            extra["scale_vs_features"] = fit_scale_huber(d, kf.feature_xyz_cam_m[ok, 2])
        return prior.depth_m, prior.confidence, "metric", extra
