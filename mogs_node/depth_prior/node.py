"""Depth-prior worker node: ``/frontend/keyframe`` -> ``/prior/depth`` (DESIGN.md sections 1, 3).

Backends: ``flow`` (weight-free default: the dense prior of
:mod:`mogs_node.depth_prior.dense_prior`: DIS flow depth against earlier keyframes, the road
plane at the camera height, and earlier keyframes' metrized depth from ``/metrizer/depth``
warped in, fused by confidence; the node keeps the last ``history`` keyframes and their metrized
depth in a :class:`~mogs_node.depth_prior.sequence.PriorSequence`; a keyframe waits for the
previous keyframe's metrized depth, so that its prior does not depend on timing: see
``metrized_wait_s``) or ``depth_anything`` (ONNX monocular depth,
:mod:`mogs_node.depth_prior.depth_anything_onnx`). The ONNX model is loaded in ``setup``: a
missing or malformed model stops the node at start-up with a ModelError, never a silent fallback.

The flow prior is metric when the keyframe poses are (``kind="metric"``; the road plane and the
metrized depth are metric too); the ONNX prior has the kind declared in its parameters. Every message carries a per-pixel confidence, 0 where no prior.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from mogs_node import msgs
from mogs_node.depth_kind import resample_metrized
from mogs_node.depth_prior.dense_prior import FusionParams
from mogs_node.depth_prior.depth_anything_onnx import DepthAnythingOnnx, DepthAnythingParams
from mogs_node.depth_prior.flow_prior import FlowPriorParams, fit_scale_huber
from mogs_node.depth_prior.road import RoadPriorParams
from mogs_node.depth_prior.sequence import PriorSequence
from mogs_node.errors import ConfigError
from mogs_node.geometry import PinholeCamera
from mogs_node.heartbeat import DIAGNOSTICS_TOPIC, other_node_busy
from mogs_node.keyframe_chain import failed_prior
from mogs_node.node import Node, parse_params
from mogs_node.worker_budget import ScaleBudget, ScaleBudgetParams

__all__ = ["DepthPriorNode", "DepthPriorParams"]

SIM_LFM_QUEUE = 64  # sim_lfm: ground-truth depths kept, keyframes waiting for theirs
FRAME_QUEUE = 32  # flow.frame_references: frames / poses queued and waiting for their pair
BACKENDS = ("flow", "depth_anything", "sim_lfm")


@dataclass(frozen=True)
class DepthPriorParams:
    """Parameters of the depth-prior worker."""

    backend: str = "flow"  # "flow" (weight-free) or "depth_anything" (ONNX file in `onnx`)
    flow: dict[str, Any] = field(default_factory=dict)  # FlowPriorParams fields
    road: dict[str, Any] = field(default_factory=dict)  # RoadPriorParams fields
    fusion: dict[str, Any] = field(default_factory=dict)  # FusionParams fields
    onnx: dict[str, Any] = field(default_factory=dict)  # DepthAnythingParams fields (model_path)
    # evaluation only (launch/demo_lfm.yaml): the simulated LFM made from the player's ground
    # truth; {"seed": int, "lfm": LfmParams fields}
    sim_lfm: dict[str, Any] = field(default_factory=dict)
    gt_depth_topic: str = "/groundtruth/depth"  # the sim_lfm backend's ground truth
    in_topic: str = "/frontend/keyframe"  # keyframes
    out_topic: str = "/prior/depth"  # priors, keyed by keyframe id
    metrized_topic: str = "/metrizer/depth"  # metrized depth of earlier keyframes ("" = off)
    # flow.frame_references > 0: the tracked frames between keyframes (image + the frontend's
    # pose of that frame, paired by stamp) are flow references too
    image_topic: str = "/camera/image"
    odometry_topic: str = "/frontend/odometry"
    camera_info_topic: str = "/camera/info"  # the source's camera height above the road, used
    # for flow.camera_height_m unless the launch file sets it ("" = off)
    metrized_wait_s: float = 5.0  # a keyframe waits for the previous one's metrized depth
    # (0: never) until no other node has said it is busy for this long: the prior then does not
    # depend on which arrived first or on the machine's load, so the same drive gives the same
    # prior on every run; a metrizer that will not answer (dead, failed) is given up on
    # the flow prior's image scale from a time budget per keyframe (ScaleBudgetParams fields,
    # mogs_node/worker_budget.py; budget_s 0 = off, full scale): the prior is published at that
    # scale (the metrizer resizes it to the keyframe's)
    scale_budget: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not math.isfinite(self.metrized_wait_s) or self.metrized_wait_s < 0:
            raise ConfigError(
                f"depth_prior.metrized_wait_s: must be >= 0, got {self.metrized_wait_s}"
            )
        if self.backend not in BACKENDS:
            raise ConfigError(
                f"depth_prior.backend: expected one of {BACKENDS}, got {self.backend!r}"
            )


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
        self._lfm = None
        if p.backend == "sim_lfm":
            self._setup_sim_lfm()
            return
        self.budget = ScaleBudget(
            parse_params(ScaleBudgetParams, p.scale_budget, where=f"{self.name}.scale_budget")
        )
        self.sequence = PriorSequence(
            self.flow_params,
            parse_params(RoadPriorParams, p.road, where=f"{self.name}.road"),
            parse_params(FusionParams, p.fusion, where=f"{self.name}.fusion"),
        )
        self.subscribe(
            p.in_topic, self.on_keyframe, reliable=True, msg_type=msgs.Keyframe, idempotent=True
        )
        inputs: tuple[str, ...] = (p.in_topic,)
        if p.camera_info_topic:
            self.subscribe(
                p.camera_info_topic, self.on_camera_info, reliable=True, msg_type=msgs.CameraInfo
            )
            inputs = (p.camera_info_topic, *inputs)
        if p.metrized_topic and self.net is None:
            self.subscribe(
                p.metrized_topic, self.on_metrized, reliable=True, msg_type=msgs.DepthMap
            )
            inputs += (p.metrized_topic,)
        # frames waiting for their pose (stamp -> image) and poses for their image (-> pose)
        self._frame_images: dict[int, msgs.Image] = {}
        self._frame_poses: dict[int, np.ndarray] = {}
        if self.flow_params.frame_references > 0 and p.image_topic and p.odometry_topic:
            # best effort with a queue: a busy node never holds the drive back, and frames that
            # come while it computes a prior stay queued (PriorSequence keeps enough of them)
            kw = {"reliable": False, "queue_size": FRAME_QUEUE}
            self.subscribe(p.image_topic, self.on_image, msg_type=msgs.Image, **kw)
            self.subscribe(p.odometry_topic, self.on_odometry, msg_type=msgs.Odometry, **kw)
        # keyframes held back (in order) until the previous keyframe's metrized depth is in
        self._waiting: deque[tuple[msgs.Keyframe, float]] = deque()
        self._waits_timed_out = 0
        self._busy_seen_s = -math.inf  # when another node last said it is busy
        if p.metrized_topic and self.net is None and p.metrized_wait_s > 0:
            self.counters["metrized_wait_timeouts"] = 0
            self.every(0.05, self._on_wait_timer)
            # the wait runs only while no other node says it is busy: a loaded pipeline that
            # works is waited for (as the player's acknowledgement timeout, bridges/player.py)
            self.subscribe(DIAGNOSTICS_TOPIC, self.on_heartbeat, reliable=False, queue_size=64)
        self.catch_up(inputs, (p.out_topic,))  # after a restart: the keyframes missed

    def _setup_sim_lfm(self) -> None:
        """Evaluation backend: keyframes wait (in order, at most ``SIM_LFM_QUEUE``) for the
        ground-truth depth at their stamp; no history, no metrized feedback."""
        from mogs_node.sim import LfmParams

        p: DepthPriorParams = self.params
        cfg = dict(p.sim_lfm)
        unknown = set(cfg) - {"seed", "lfm"}
        if unknown:
            raise ConfigError(f"{self.name}.sim_lfm: unknown parameter(s) {sorted(unknown)}")
        lfm = parse_params(LfmParams, cfg.get("lfm", {}), where=f"{self.name}.sim_lfm.lfm")
        self._lfm = (int(cfg.get("seed", 7)), lfm)
        self._gt: dict[int, np.ndarray] = {}
        self._lfm_waiting: deque[msgs.Keyframe] = deque()
        self.subscribe(p.gt_depth_topic, self.on_gt_depth, msg_type=msgs.DepthMap)
        self.subscribe(
            p.in_topic, self.on_keyframe, reliable=True, msg_type=msgs.Keyframe, idempotent=True
        )

    def on_gt_depth(self, msg: msgs.DepthMap) -> None:
        """Keep the latest ground-truth depths by stamp; release the keyframes waiting for one."""
        self._gt[int(msg.stamp_ns)] = np.asarray(msg.depth)
        while len(self._gt) > SIM_LFM_QUEUE:
            self._gt.pop(min(self._gt))
        while self._lfm_waiting and int(self._lfm_waiting[0].stamp_ns) in self._gt:
            self._process(self._lfm_waiting.popleft())

    def on_camera_info(self, msg: msgs.CameraInfo) -> None:
        """The camera height of the source's calibration (finite: known), unless typed (a typed
        0 with ``road.auto_height`` means "measure it", so a known height is taken instead)."""
        h = float(msg.camera_height_m)
        typed = self.params.flow.get("camera_height_m")
        if typed is not None and (float(typed) > 0 or not self.sequence.road.auto_height):
            return
        if not np.isfinite(h) or h <= 0:
            return
        if h != self.flow_params.camera_height_m:
            self.log.info("camera %.3f m above the road (from %s)", h, msg.source or "camera info")
            self.flow_params = self.sequence.flow = replace(self.flow_params, camera_height_m=h)

    def on_image(self, msg: msgs.Image) -> None:
        """A frame: kept as a flow reference once its tracked pose is in."""
        self._frame_images[int(msg.stamp_ns)] = msg
        self._pair_frames()

    def on_odometry(self, msg: msgs.Odometry) -> None:
        """The frontend's pose of a frame; only tracked frames (not initialising, not reset). A
        reset starts a new world: the frames kept so far are in the old one."""
        if msg.status == "reset":
            self.sequence.forget_frames()
            self._frame_poses.clear()
        if msg.status == "tracking":
            self._frame_poses[int(msg.stamp_ns)] = np.asarray(msg.T_world_cam, np.float64)
            self._pair_frames()

    def _pair_frames(self) -> None:
        """Give the sequence every frame with both its image and its pose, at the prior's scale."""
        for stamp in sorted(set(self._frame_images) & set(self._frame_poses)):
            image, _ = self._at_budget_scale(self._frame_images.pop(stamp).rgb_or_mono())
            self.sequence.add_frame(stamp, image, self._frame_poses.pop(stamp))
        for waiting in (self._frame_images, self._frame_poses):  # never paired: the oldest go
            while len(waiting) > FRAME_QUEUE:
                waiting.pop(min(waiting))

    def on_metrized(self, msg: msgs.DepthMap) -> None:
        """Keep an earlier keyframe's metric depth to warp into later keyframes."""
        if msg.kind != "metric":
            self.log.warning(
                "%s: kind %r is not metric, ignored", self.params.metrized_topic, msg.kind
            )
            return
        depth, conf = msg.depth, msg.confidence
        hist, scale = self.sequence.history, self.budget.scale
        H, W = depth.shape[:2]
        size = hist[-1].grey.shape[::-1] if hist else (round(W * scale), round(H * scale))
        if scale < 1.0:  # the prior works smaller
            depth, conf = resample_metrized(depth, conf, *size)
        if not self.sequence.add_metrized(msg.keyframe_id, depth, conf):
            self.log.debug("metrized depth of keyframe %d not kept", msg.keyframe_id)
        self._release_waiting()

    def on_keyframe(self, kf: msgs.Keyframe) -> None:
        p: DepthPriorParams = self.params
        if self._lfm is not None:
            if int(kf.stamp_ns) in self._gt and not self._lfm_waiting:
                self._process(kf)
                return
            self._lfm_waiting.append(kf)
            if len(self._lfm_waiting) > SIM_LFM_QUEUE:
                dropped = self._lfm_waiting.popleft()
                self.counters["sim_lfm_no_truth"] = self.counters.get("sim_lfm_no_truth", 0) + 1
                self.log.warning(
                    "keyframe %d: no ground-truth depth came, no prior", dropped.keyframe_id
                )
            return
        if p.metrized_topic and self.net is None and p.metrized_wait_s > 0:
            self._waiting.append((kf, time.monotonic()))
            self._release_waiting()
        else:
            self._process(kf)

    def on_heartbeat(self, msg: msgs.Message) -> None:
        """Another node busy in a handler (``busy_s`` > 0, mogs_node/heartbeat.py): the
        pipeline works, so a keyframe's wait for the metrized depth goes on."""
        if other_node_busy(msg, self.name):
            self._busy_seen_s = time.monotonic()

    def _on_wait_timer(self) -> None:
        if self.queue_depth == 0:  # heartbeats read but not handled yet may extend the wait
            self._release_waiting()

    def _release_waiting(self) -> None:
        """Compute the held-back keyframes, in order, whose predecessor's metrized depth is in
        (or whose wait is over: no other node said it was busy for ``metrized_wait_s`` since the
        keyframe came; the prior then goes without it, and the wait is counted)."""
        while self._waiting:
            kf, t_in = self._waiting[0]
            last = self.sequence.history[-1] if self.sequence.history else None
            if last is not None and last.metrized is None:
                since = max(t_in, self._busy_seen_s)
                if time.monotonic() - since < self.params.metrized_wait_s:
                    return
                self._waits_timed_out += 1
                self.counters["metrized_wait_timeouts"] = self._waits_timed_out
            self._waiting.popleft()
            self._process(kf)

    def _process(self, kf: msgs.Keyframe) -> None:
        if self.already_published(self.params.out_topic, kf.keyframe_id) and self.net is not None:
            return  # done before a restart; the learned prior keeps no state
        try:
            self._compute_and_publish(kf)
        except Exception as err:  # the metrizer must not wait for a prior that never comes
            self.publish(self.params.out_topic, failed_prior(kf, err))
            raise  # logged and counted by the node shell (handler_errors)

    def _compute_and_publish(self, kf: msgs.Keyframe) -> None:
        # the flow prior recomputes a keyframe done before a restart (publish() suppresses the
        # duplicate): the carried prior and warped depth of the next keyframes depend on it
        if self._lfm is not None:
            from mogs_node.depth_prior.sim_lfm import lfm_from_truth

            seed, lfm = self._lfm
            depth, conf = lfm_from_truth(
                self._gt[int(kf.stamp_ns)], kf.keyframe_id, seed=seed, lfm=lfm
            )
            kind, extra = "relative_inverse_depth", {}
        elif self.net is not None:
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

    def _at_budget_scale(
        self, image: np.ndarray, K: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """``image`` (and its ``K``) at the time budget's scale (worker_budget.py): keyframes
        and the frames kept as their flow references are resized alike."""
        scale = self.budget.scale
        if scale >= 1.0:
            return image, K
        H, W = image.shape[:2]
        size = (round(W * scale), round(H * scale))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        return image, None if K is None else PinholeCamera.from_K(K, W, H).scaled(*size).K

    def _flow(self, kf: msgs.Keyframe):
        scale = self.budget.scale
        image, K = self._at_budget_scale(kf.image, kf.K)
        t0 = time.monotonic()
        prior, refs = self.sequence.next(kf.keyframe_id, image, K, kf.T_world_cam, kf.stamp_ns)
        if self.budget.observe(time.monotonic() - t0) != scale:
            self.log.info(
                "keyframe %d: prior %.0f ms at scale %.2f (budget %.0f ms): next at scale %.2f",
                kf.keyframe_id,
                1000.0 * (time.monotonic() - t0),
                scale,
                1000.0 * self.budget.params.budget_s,
                self.budget.scale,
            )
        self.counters["prior_scale"] = scale
        h = prior.stats.get("ground_height_m", 0.0)
        if h > 0 and self.counters.get("ground_height_m", 0.0) <= 0:
            self.log.info(
                "keyframe %d: camera %.3f m above the ground (measured)", kf.keyframe_id, h
            )
        if "ground_height_m" in prior.stats:  # road.auto_height: in the diagnostics and report
            self.counters["ground_height_m"] = round(h, 4)
        extra: dict[str, Any] = dict(prior.stats)
        extra["references"] = refs
        if len(kf.feature_xyz_cam_m):  # diagnostic: robust scale of the prior vs sparse points
            uv = np.round(kf.feature_uv_px * scale).astype(int)
            H, W = prior.depth_m.shape
            ok = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
            d = prior.depth_m[uv[ok, 1], uv[ok, 0]]
            extra["scale_vs_features"] = fit_scale_huber(d, kf.feature_xyz_cam_m[ok, 2])
        return prior.depth_m, prior.confidence, "metric", extra
