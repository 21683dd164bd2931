"""Where the pipeline's depth error comes from: the demo's keyframes with one input swapped at a time.

The demo (``launch/demo.yaml``) metrizes each keyframe from three inputs produced upstream: the
frontend's sparse metric points, the weight-free flow prior (two-view DIS depth on the frontend's
keyframe poses) and the graph over-segmentation. The metrizer's own sim evaluation
(:mod:`mogs_node.eval.depth_sim`) instead feeds it ground-truth sparse points, the simulated LFM
prior and oracle masks. This module runs the demo's frontend in-process on the demo sequence,
then metrizes every keyframe with each combination of

- sparse points: ``frontend`` (the keyframe's tracked points) | ``gt`` (ground-truth depth at the
  same pixels, points on a depth edge dropped: there the pixel's truth may belong to the other
  surface, while the tracked point is one 3D point) | ``gt_corners`` (the metrizer eval's: ground
  truth at up to 500 Shi-Tomasi corners off depth edges: how much the number of points costs);
- prior: ``flow`` (the demo's flow prior on the frontend poses) | ``flow_gtpose`` (the same flow
  prior on ground-truth poses: references chosen and triangulated with the true motion) | ``lfm``
  (the simulated LFM of the metrizer eval, full confidence);
- masks: ``graph`` (the demo's segmentation parameters) | ``oracle`` (the sim's instance ids);

through exactly the node's interface (:func:`mogs_node.metrizer.node.metrizer_inputs` on the same
messages), and scores each with the run report's scorer
(:func:`mogs_node.report.collect.score_depth`): AbsRel pooled over pixels, coverage averaged over
keyframes. The parameters of every stage are read from the demo launch file, so the table follows
the demo. Pure apart from reading that file: arrays in, figures out.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from mogs_node import msgs
from mogs_node.errors import ConfigError
from mogs_node.geometry import PinholeCamera
from mogs_node.params import parse_group, parse_params

__all__ = [
    "MASKS",
    "PRIORS",
    "SPARSE",
    "StageKeyframe",
    "demo_params",
    "evaluate_stages",
    "graph_masks",
    "prepare_keyframes",
    "stage_inputs",
]

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]
SPARSE = ("frontend", "gt", "gt_corners")
PRIORS = ("flow", "flow_gtpose", "lfm")
MASKS = ("graph", "oracle")


@dataclass
class StageKeyframe:
    """One demo keyframe: what the frontend emitted and the simulator's truth at that frame."""

    keyframe: msgs.Keyframe  # as the frontend node publishes it
    frame_index: int
    T_world_cam_gt: np.ndarray  # [4, 4] sim world
    gt_depth_m: np.ndarray  # [H, W] f32, 0 where none (sky), as the player publishes it
    instance_id: np.ndarray  # [H, W] int32, -1 on sky


def demo_params(launch_file: str | Path | None = None) -> dict[str, dict[str, Any]]:
    """``{node name: params}`` of the demo launch file (default ``launch/demo.yaml``)."""
    path = Path(launch_file) if launch_file else REPO_ROOT / "launch" / "demo.yaml"
    spec = yaml.safe_load(path.read_text())
    return {n["name"]: dict(n.get("params") or {}) for n in spec["nodes"]}


def prepare_keyframes(
    params: dict[str, dict[str, Any]], *, seed: int | None = None
) -> tuple[list[StageKeyframe], dict[str, Any]]:
    """Run the demo's frontend on the demo sequence; return its keyframes with their truth.

    Images and IMU are streamed in the player's order (IMU first at equal stamps), every frame
    (the pipeline's flow control delivers every frame too).
    """
    from mogs_node.eval.frontend_runs import run_frontend
    from mogs_node.frontend.frontend import Frontend
    from mogs_node.frontend.node_config import FrontendNodeParams, keyframe_message
    from mogs_node.sim import SimConfig, make_sequence

    sim = dict(params["player"].get("sim", {}))
    if seed is not None:
        sim["seed"] = seed
    seq = make_sequence(parse_params(SimConfig, sim, where="player.sim"))
    from bridges.sources import camera_info_of, sequence_from_sim

    fnp = parse_params(FrontendNodeParams, params.get("frontend", {}), where="frontend")
    # the calibration the player publishes on /camera/info (the launch file may leave it out)
    fp, cam, T_imu_cam = fnp.build(info=camera_info_of(sequence_from_sim(seq)))
    if (cam.pinhole.width, cam.pinhole.height) != (seq.camera.width, seq.camera.height):
        raise ConfigError(
            f"frontend: intrinsics for {cam.pinhole.width}x{cam.pinhole.height}, sequence is "
            f"{seq.camera.width}x{seq.camera.height}"
        )
    frames = [seq.render(i) for i in range(seq.n_frames)]
    fe = Frontend(fp, cam, T_imu_cam)
    t0 = time.perf_counter()
    outs = run_frontend(
        fe,
        seq.stamps_ns,
        (f.rgb for f in frames),
        seq.imu_stamps_ns,
        seq.imu_gyro_rad_s,
        seq.imu_accel_m_s2,
    )
    index = {int(t): i for i, t in enumerate(seq.stamps_ns)}
    kfs = []
    for o in outs:
        kf = o.keyframe
        if kf is None:
            continue
        i = index[int(kf.stamp_ns)]
        f = frames[i]
        gt = np.where(np.isfinite(f.depth_m) & (f.depth_m > 0), f.depth_m, 0.0).astype(np.float32)
        msg = keyframe_message(kf, "world")
        kfs.append(StageKeyframe(msg, i, np.array(f.T_world_cam), gt, f.instance_id))
    info = {
        "frames": seq.n_frames,
        "estimated_frames": sum(o.T_world_cam is not None for o in outs),
        "keyframes": len(kfs),
        "frontend_s": time.perf_counter() - t0,
        "K_sim": seq.camera.K,
        # every tracked frame (stamp, image, pose) as the prior node receives them on
        # /camera/image and /frontend/odometry (its flow.frame_references)
        "tracked_frames": [
            (int(o.stamp_ns), frames[index[int(o.stamp_ns)]].rgb, np.array(o.T_world_cam))
            for o in outs
            if o.T_world_cam is not None and o.status == "tracking"
        ],
    }
    return kfs, info


def graph_masks(kfs: list[StageKeyframe], params: dict[str, dict[str, Any]]) -> list[msgs.Masks]:
    """The demo segmentation node's masks of each keyframe (its launch parameters)."""
    from mogs_node.segmentation.graph import GraphSegParams, segment_graph
    from mogs_node.segmentation.params import SegmentationParams

    seg = parse_params(SegmentationParams, params.get("segmentation", {}), where="segmentation")
    gp = parse_group(GraphSegParams, seg, "graph", "segmentation")
    return [
        msgs.Masks(
            stamp_ns=s.keyframe.stamp_ns,
            frame_id="world",
            keyframe_id=s.keyframe.keyframe_id,
            labels=np.asarray(segment_graph(s.keyframe.rgb(), gp), np.int32),
            backend="graph",
        )
        for s in kfs
    ]


def _flow_priors(kfs: list[StageKeyframe], prior: dict[str, Any], *, gt_pose: bool) -> list:
    """The prior node's dense prior per keyframe (flow, road plane, previous prior carried), its
    history kept as the node keeps it; without the metrizer in the loop (no metrized depth is
    warped in here: :mod:`mogs_node.eval.depth_prior_eval` runs that loop)."""
    from mogs_node.depth_prior.sequence import PriorSequence
    from mogs_node.eval.depth_prior_eval import prior_params

    seq = PriorSequence(*prior_params({"prior": prior}))
    out = []
    for s in kfs:
        T = s.T_world_cam_gt if gt_pose else s.keyframe.T_world_cam
        out.append(seq.next(s.keyframe.keyframe_id, s.keyframe.image, s.keyframe.K, T)[0])
    return out


def _with_points(
    kf: msgs.Keyframe, uv: np.ndarray, depth_m: np.ndarray, weight: np.ndarray
) -> msgs.Keyframe:
    """``kf`` with its sparse points replaced by ground-truth depth at pixels ``uv`` ``[N, 2]``."""
    H, W = depth_m.shape
    ui = np.clip(np.round(uv[:, 0]).astype(int), 0, W - 1)
    vi = np.clip(np.round(uv[:, 1]).astype(int), 0, H - 1)
    z = depth_m[vi, ui].astype(np.float64)
    xyz = PinholeCamera.from_K(kf.K, W, H).backproject(np.asarray(uv, np.float64), z)
    return replace(
        kf,
        feature_ids=np.arange(len(uv), dtype=np.int64),
        feature_uv_px=np.asarray(uv, np.float32).reshape(-1, 2),
        feature_xyz_cam_m=xyz.astype(np.float32).reshape(-1, 3),
        feature_weight=np.asarray(weight, np.float32),
    )


def stage_inputs(
    kfs: list[StageKeyframe], params: dict[str, dict[str, Any]], *, lfm_seed: int = 7
) -> dict[str, dict[str, list]]:
    """Per input kind and variant, one message per keyframe (``Keyframe``, ``DepthMap``,
    ``Masks``) in the form the metrizer node receives."""
    from mogs_node.eval.depth_sim import _depth_edge_free
    from mogs_node.segmentation.graph import GraphSegParams, segment_graph
    from mogs_node.segmentation.params import SegmentationParams
    from mogs_node.sim import LfmParams, simulated_lfm

    sparse: dict[str, list] = {"frontend": [s.keyframe for s in kfs], "gt": [], "gt_corners": []}
    for s in kfs:
        kf = s.keyframe
        H, W = s.gt_depth_m.shape
        edge_free = _depth_edge_free(np.where(s.gt_depth_m > 0, s.gt_depth_m, np.inf))
        uv = np.asarray(kf.feature_uv_px, np.float64)
        ui = np.clip(np.round(uv[:, 0]).astype(int), 0, W - 1)
        vi = np.clip(np.round(uv[:, 1]).astype(int), 0, H - 1)
        ok = (s.gt_depth_m[vi, ui] > 0) & edge_free[vi, ui]
        sparse["gt"].append(_with_points(kf, uv[ok], s.gt_depth_m, kf.feature_weight[ok]))
        grey = kf.image if kf.image.ndim == 2 else cv2.cvtColor(kf.image, cv2.COLOR_RGB2GRAY)
        pts = cv2.goodFeaturesToTrack(grey, 2000, 0.005, 5)
        uv = np.zeros((0, 2)) if pts is None else pts[:, 0, :].astype(np.float64)
        ui = np.clip(np.round(uv[:, 0]).astype(int), 0, W - 1)
        vi = np.clip(np.round(uv[:, 1]).astype(int), 0, H - 1)
        uv = uv[(s.gt_depth_m[vi, ui] > 0) & edge_free[vi, ui]][:500]  # strongest first
        sparse["gt_corners"].append(
            _with_points(kf, uv, s.gt_depth_m, np.ones(len(uv), np.float32))
        )
    prior_p = params.get("prior", {})
    if prior_p.get("backend", "flow") != "flow":
        raise ConfigError("prior.backend: the stage breakdown needs the demo's flow prior")

    def as_msg(s: StageKeyframe, depth, conf, kind: str, source: str) -> msgs.DepthMap:
        return msgs.DepthMap(
            stamp_ns=s.keyframe.stamp_ns,
            frame_id="world",
            keyframe_id=s.keyframe.keyframe_id,
            kind=kind,
            depth=np.ascontiguousarray(depth, np.float32),
            confidence=np.ascontiguousarray(conf, np.float32),
            source=source,
        )

    priors: dict[str, list] = {}
    for name, gt_pose in (("flow", False), ("flow_gtpose", True)):
        fps = _flow_priors(kfs, prior_p, gt_pose=gt_pose)
        priors[name] = [
            as_msg(s, p.depth_m, p.confidence, "metric", "flow")
            for s, p in zip(kfs, fps, strict=True)
        ]
    rng = np.random.default_rng(lfm_seed)
    priors["lfm"] = []
    for s in kfs:
        d = np.where(s.gt_depth_m > 0, s.gt_depth_m, np.inf).astype(np.float32)
        lfm = simulated_lfm(d, rng, LfmParams())
        priors["lfm"].append(as_msg(s, lfm, np.ones_like(lfm), "relative_inverse_depth", "lfm"))
    seg = parse_params(SegmentationParams, params.get("segmentation", {}), where="segmentation")
    gp = parse_group(GraphSegParams, seg, "graph", "segmentation")
    masks: dict[str, list] = {"graph": [], "oracle": []}
    for s in kfs:
        kf = s.keyframe
        rgb = kf.rgb()
        for name, labels in (("graph", segment_graph(rgb, gp)), ("oracle", s.instance_id)):
            masks[name].append(
                msgs.Masks(
                    stamp_ns=kf.stamp_ns,
                    frame_id="world",
                    keyframe_id=kf.keyframe_id,
                    labels=np.asarray(labels, np.int32),
                    backend=name,
                )
            )
    return {"sparse": sparse, "prior": priors, "masks": masks}


def _pool(scores: list) -> dict[str, float]:
    n = sum(s.count for s in scores)
    if n == 0:
        return {"absrel": float("nan"), "delta1": float("nan"), "coverage": 0.0, "keyframes": 0}
    return {
        "absrel": sum(s.sum_abs_rel for s in scores) / n,
        "delta1": sum(s.n_delta1 for s in scores) / n,
        "coverage": float(np.mean([s.coverage for s in scores])),
        "keyframes": len(scores),
    }


def evaluate_stages(
    kfs: list[StageKeyframe],
    inputs: dict[str, dict[str, list]],
    params: dict[str, dict[str, Any]],
    *,
    sparse: tuple[str, ...] = SPARSE,
    priors: tuple[str, ...] = PRIORS,
    masks: tuple[str, ...] = MASKS,
) -> dict[str, Any]:
    """Metrize every keyframe for each combination; figures keyed ``"sparse|prior|masks"``.

    Also scores the inputs themselves: each prior on its own (metric kinds only: where its
    confidence > 0) and the sparse points off depth edges (median relative error, scale against
    the truth; how many lie on a depth edge).
    """
    from mogs_node.eval.depth_prior_eval import metrizer_params as metrizer_params_of
    from mogs_node.eval.depth_sim import _depth_edge_free
    from mogs_node.metrizer.matching import MatchedKeyframe, metrizer_inputs
    from mogs_node.metrizer.pipeline import metrize
    from mogs_node.report.collect import score_depth

    metrizer_params, mode = metrizer_params_of(params)
    combos: dict[str, Any] = {}
    for sp, pr, mk in itertools.product(sparse, priors, masks):
        scores, per_kf = [], []
        t0 = time.perf_counter()
        for i, s in enumerate(kfs):
            entry = MatchedKeyframe(
                s.keyframe.keyframe_id,
                keyframe=inputs["sparse"][sp][i],
                masks=inputs["masks"][mk][i],
                prior=inputs["prior"][pr][i],
            )
            out = metrize(metrizer_inputs(entry), metrizer_params, mode)
            sc = score_depth(s.keyframe.keyframe_id, s.keyframe.stamp_ns, out.depth_m, s.gt_depth_m)
            scores.append(sc)
            per_kf.append((sc.absrel, sc.coverage))
        combos[f"{sp}|{pr}|{mk}"] = {
            **_pool(scores),
            "per_keyframe": per_kf,
            "seconds": time.perf_counter() - t0,
        }
        log.info("%s|%s|%s: %s", sp, pr, mk, _pool(scores))
    prior_alone = {}
    for pr in priors:
        ms = inputs["prior"][pr]
        if ms[0].kind != "metric":
            continue
        sc = [
            score_depth(
                s.keyframe.keyframe_id, 0, np.where(m.confidence > 0, m.depth, 0), s.gt_depth_m
            )
            for s, m in zip(kfs, ms, strict=True)
        ]
        prior_alone[pr] = {**_pool(sc), "per_keyframe": [(x.absrel, x.coverage) for x in sc]}
    sparse_err = []
    for s in kfs:
        kf = s.keyframe
        H, W = s.gt_depth_m.shape
        uv = np.round(np.asarray(kf.feature_uv_px, np.float64)).astype(int)
        ui, vi = np.clip(uv[:, 0], 0, W - 1), np.clip(uv[:, 1], 0, H - 1)
        g = s.gt_depth_m[vi, ui]
        z = np.asarray(kf.feature_xyz_cam_m[:, 2], np.float64)
        ok = (g > 0) & (z > 0)
        edge_free = _depth_edge_free(np.where(s.gt_depth_m > 0, s.gt_depth_m, np.inf))
        on_edge = int(np.sum(ok & ~edge_free[vi, ui]))
        ok &= edge_free[vi, ui]
        rel = np.abs(z[ok] - g[ok]) / g[ok]
        sparse_err.append(
            {
                "keyframe_id": kf.keyframe_id,
                "n": int(ok.sum()),
                "on_depth_edge": on_edge,
                "median_relerr": float(np.median(rel)) if rel.size else float("nan"),
                "scale": float(np.median(z[ok] / g[ok])) if rel.size else float("nan"),
            }
        )
    return {"combos": combos, "prior_alone": prior_alone, "sparse": sparse_err}
