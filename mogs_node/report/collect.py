"""Pure collection and scoring of a run's outputs (no bus, no files but :func:`write_run`).

:class:`RunCollector` keeps what the run report needs: estimated poses per frame and per keyframe,
ground-truth poses and depth by time stamp, metrized depth per keyframe (scored on arrival, so that
memory stays bounded), mapper statistics, the last render. :func:`summarise` turns it into the
figures of ``report.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mogs_node.eval.metrics import depth_metrics
from mogs_node.report.views import MapReplica, ViewScore

__all__ = ["DepthScore", "RunCollector", "summarise", "summarise_views", "write_report"]


@dataclass
class DepthScore:
    keyframe_id: int
    stamp_ns: int
    coverage: float  # share of ground-truth pixels that received a metric depth
    absrel: float
    rmse: float
    delta1: float
    sum_abs_rel: float  # for pooled (pixel-weighted) metrics
    sum_sq: float
    n_delta1: int
    count: int


@dataclass
class RunCollector:
    """Accumulates a run's outputs; match keys are keyframe ids and time stamps."""

    odometry: dict[int, np.ndarray] = field(default_factory=dict)  # stamp_ns -> T_world_cam
    keyframes: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)  # id -> (stamp, T)
    gt_poses: dict[int, np.ndarray] = field(default_factory=dict)  # stamp_ns -> T_world_cam
    gt_depth: dict[int, np.ndarray] = field(default_factory=dict)  # stamp_ns -> depth_m
    depth_done: set[int] = field(default_factory=set)  # keyframe ids with a metrized depth
    depth_scores: list[DepthScore] = field(default_factory=list)
    pending_depth: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    mapped: set[int] = field(default_factory=set)  # keyframe ids the mapper reported
    unestimated_frames: int = 0  # odometry acknowledgements without a pose (initialising, ...)
    acknowledged: set[int] = field(default_factory=set)  # stamps with any odometry message
    node_counters: dict[str, dict[str, float]] = field(default_factory=dict)  # last per node
    frontend_figures: dict[str, float] = field(default_factory=dict)  # its last frontend_* values
    last_stats: dict[str, Any] = field(default_factory=dict)
    final_map: MapReplica = field(default_factory=MapReplica)  # from /mapper/gaussians
    map_updated: set[int] = field(default_factory=set)  # keyframe ids of the map updates
    view_scores: list[ViewScore] = field(default_factory=list)  # final map, rendered at the end
    need_final: bool = False  # the mapper refines the map after the drive: wait for that update
    final_seen: bool = False  # the mapper's /mapper/stats marked final arrived

    def add_depth(self, keyframe_id: int, depth_m: np.ndarray, confidence: np.ndarray) -> None:
        self.depth_done.add(keyframe_id)
        self.pending_depth[keyframe_id] = (depth_m, confidence)
        self._score_pending()

    def add_gt_depth(self, stamp_ns: int, depth_m: np.ndarray) -> None:
        self.gt_depth[stamp_ns] = depth_m
        self._score_pending()

    def add_keyframe(self, keyframe_id: int, stamp_ns: int, T_world_cam: np.ndarray) -> None:
        self.keyframes[keyframe_id] = (stamp_ns, np.array(T_world_cam))
        self._score_pending()

    def _score_pending(self) -> None:
        for kf_id in list(self.pending_depth):
            if kf_id not in self.keyframes:
                continue
            stamp = self.keyframes[kf_id][0]
            gt = self.gt_depth.pop(stamp, None)
            if gt is None:
                continue
            depth, _ = self.pending_depth.pop(kf_id)
            self.depth_scores.append(score_depth(kf_id, stamp, depth, gt))

    @property
    def complete(self) -> bool:
        """Every keyframe seen has its metrized depth and reached the mapper."""
        ids = set(self.keyframes)
        return bool(ids) and ids <= self.depth_done and ids <= self.mapped

    @property
    def map_ready(self) -> bool:
        """The map update of the newest mapped keyframe arrived (the mapper publishes its stats,
        then its update, in order on reliable topics: so every earlier update arrived too)."""
        if self.need_final and not self.final_seen:
            return False  # the final update precedes the final stats on the mapper's socket
        return bool(self.mapped) and max(self.mapped) in self.map_updated


def score_depth(
    keyframe_id: int, stamp_ns: int, depth_m: np.ndarray, gt_m: np.ndarray
) -> DepthScore:
    """Depth metrics of one keyframe on ground-truth pixels that received a depth."""
    gt = np.asarray(gt_m, np.float64)
    pred = np.asarray(depth_m, np.float64)
    if gt.shape != pred.shape:  # ground truth at another resolution: compare at the prediction's
        import cv2

        gt = cv2.resize(gt, (pred.shape[1], pred.shape[0]), interpolation=cv2.INTER_NEAREST)
    has_gt = np.isfinite(gt) & (gt > 0)
    m = has_gt & np.isfinite(pred) & (pred > 0)
    res = depth_metrics(pred, gt, m)
    p, g = pred[m], gt[m]
    return DepthScore(
        keyframe_id=keyframe_id,
        stamp_ns=stamp_ns,
        coverage=float(m.sum() / max(1, has_gt.sum())),
        absrel=res["absrel"],
        rmse=res["rmse"],
        delta1=res["delta1"],
        sum_abs_rel=float(np.sum(np.abs(p - g) / g)) if p.size else 0.0,
        sum_sq=float(np.sum((p - g) ** 2)) if p.size else 0.0,
        n_delta1=int(np.sum(np.maximum(p / g, g / p) < 1.25)) if p.size else 0,
        count=int(m.sum()),
    )


def summarise(c: RunCollector) -> dict[str, Any]:
    """Figures of a run: depth pooled over keyframes, trajectory (evo), mapper statistics."""
    out: dict[str, Any] = {
        "keyframes": len(c.keyframes),
        "keyframes_with_depth": len(set(c.keyframes) & c.depth_done),
        "keyframes_mapped": len(set(c.keyframes) & c.mapped),
        "frames_with_odometry": len(c.odometry),
        "frames_without_estimate": c.unestimated_frames,
        "frames_acknowledged": len(c.acknowledged),
    }
    n = sum(s.count for s in c.depth_scores)
    if n:
        out["depth"] = {
            "keyframes_scored": len(c.depth_scores),
            "absrel": sum(s.sum_abs_rel for s in c.depth_scores) / n,
            "rmse": math.sqrt(sum(s.sum_sq for s in c.depth_scores) / n),
            "delta1": sum(s.n_delta1 for s in c.depth_scores) / n,
            "coverage": float(np.mean([s.coverage for s in c.depth_scores])),
            # the worst keyframe the mapper got (issue 16: none may be left mostly empty)
            "min_keyframe_coverage": float(
                min(s.coverage for s in c.depth_scores if s.keyframe_id in c.mapped)
                if any(s.keyframe_id in c.mapped for s in c.depth_scores)
                else min(s.coverage for s in c.depth_scores)
            ),
        }
    stamps = sorted(s for s in c.odometry if s in c.gt_poses)
    if len(stamps) >= 3:
        from mogs_node.eval.traj import trajectory_metrics

        est = np.stack([c.odometry[s] for s in stamps])
        ref = np.stack([c.gt_poses[s] for s in stamps])
        try:
            out["trajectory"] = trajectory_metrics(np.array(stamps, np.int64), est, ref)
        except Exception as err:  # evo raises on degenerate trajectories; report, do not crash
            out["trajectory"] = {"error": str(err)}
    if c.last_stats:
        out["mapper"] = dict(c.last_stats)
    if c.view_scores or len(c.final_map):
        out["map"] = {
            "gaussians": len(c.final_map),
            "updates": c.final_map.updates,
            **summarise_views(c.view_scores),
        }
    if c.frontend_figures:  # time offset, resets by reason, keyframe rate (issue 23)
        f = c.frontend_figures
        out["frontend"] = {
            "time_offset_ms": f.get("time_offset_ms", 0.0),
            "keyframes_per_s": f.get("keyframes_per_s", 0.0),
            "walk_detected": bool(f.get("platform_walk_detected", 0.0)),  # platform: auto
            "resets": {k[7:]: int(v) for k, v in f.items() if k.startswith("resets_") and v},
            "init_rejected": {
                k[14:]: int(v) for k, v in f.items() if k.startswith("init_rejected_")
            },
        }
    if c.node_counters:  # what each node dropped (best effort) or lost (reliable gaps)
        out["nodes"] = {n: dict(v) for n, v in sorted(c.node_counters.items())}
        out["realtime"] = realtime_figures(c.node_counters)
    return out


def realtime_figures(node_counters: dict[str, dict[str, float]]) -> dict[str, Any]:
    """Issue 28: keyframes shed whole (by reason) and keyframes metrized without their masks or
    prior (a failed or silent worker), summed over the nodes that count them."""
    total: dict[str, float] = {}
    for counters in node_counters.values():
        for k, v in counters.items():
            total[k] = total.get(k, 0.0) + v
    return {
        "keyframes_shed": int(total.get("keyframes_shed", 0)),
        "shed_reasons": {
            k[len("keyframes_shed_") :]: int(v)
            for k, v in sorted(total.items())
            if k.startswith("keyframes_shed_") and v
        },
        "metrized_without_inputs": int(total.get("metrized_without_inputs", 0)),
        "inputs_failed": int(total.get("match_failed_inputs", 0)),
        "inputs_stalled": int(total.get("match_stalled_inputs", 0)),
    }


def summarise_views(scores: list[ViewScore]) -> dict[str, Any]:
    """Mean PSNR [dB] / SSIM / coverage of the final map's held-out and keyframe views (means
    over views, as 3DGS papers report them) and every view's figures."""
    out: dict[str, Any] = {"exposure": "none"}
    for kind, prefix in (("heldout", "heldout"), ("keyframe", "keyframe")):
        v = [s for s in scores if s.kind == kind]
        out[f"{prefix}_frames"] = len(v)
        if v:
            out[f"{prefix}_psnr_db"] = float(np.mean([s.psnr_db for s in v]))
            out[f"{prefix}_ssim"] = float(np.mean([s.ssim for s in v]))
            out[f"{prefix}_coverage"] = float(np.mean([s.coverage for s in v]))
    out["views"] = [
        {
            "kind": s.kind,
            "stamp_ns": s.stamp_ns,
            "keyframe_id": s.keyframe_id,
            "psnr_db": s.psnr_db,
            "ssim": s.ssim,
            "coverage": s.coverage,
            "png": s.png,
        }
        for s in scores
    ]
    return out


def _map_lines(m: dict[str, Any]) -> list[str]:
    """report.md section of the final map: the table of scores, then every picture."""
    lines = [
        "",
        "## Final map, rendered at held-out frames and keyframes",
        "",
        f"The map as the mapper left it ({m['gaussians']} Gaussians, rebuilt from its "
        f"{m['updates']} `/mapper/gaussians` updates), rendered after the run at the frontend's "
        "pose of each view, without exposure compensation, and scored against the camera image. "
        "Held-out frames are frames that were not keyframes, spread evenly between the first "
        "and the last keyframe. Pictures: ground truth | render | rendered depth (inverse depth, "
        "turbo: near red, far blue; black = nothing rendered).",
        "",
        "| views | frames | PSNR [dB] | SSIM | coverage |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for kind, name in (("heldout", "held-out frames"), ("keyframe", "keyframes")):
        n = m.get(f"{kind}_frames", 0)
        if n:
            lines.append(
                f"| {name} | {n} | {m[f'{kind}_psnr_db']:.2f} | {m[f'{kind}_ssim']:.3f} | "
                f"{m[f'{kind}_coverage']:.3f} |"
            )
        else:
            lines.append(f"| {name} | 0 | - | - | - |")
    for kind, name in (("heldout", "Held-out frames"), ("keyframe", "Keyframes")):
        views = [v for v in m.get("views", []) if v["kind"] == kind]
        if not views:
            continue
        lines += ["", f"### {name}", ""]
        for v in views:
            label = f"t = {v['stamp_ns'] / 1e9:.2f} s"
            if v["keyframe_id"] >= 0:
                label = f"keyframe {v['keyframe_id']}, " + label
            lines.append(
                f"{label}: PSNR {v['psnr_db']:.2f} dB, SSIM {v['ssim']:.3f}, coverage "
                f"{v['coverage']:.2f}"
            )
            if v["png"]:
                lines += ["", f"![{label}]({v['png']})", ""]
    return lines


def write_report(path: Path, figures: dict[str, Any], *, title: str = "MOGS run") -> str:
    """Write ``report.md``; returns the one-line summary."""
    lines = [f"# {title}", ""]
    lines.append(
        f"Keyframes: {figures['keyframes']} (metrized depth: {figures['keyframes_with_depth']}, "
        f"reached the mapper: {figures['keyframes_mapped']}); frames with an odometry estimate: "
        f"{figures['frames_with_odometry']} (plus {figures.get('frames_without_estimate', 0)} "
        "acknowledged while initialising or rejected)."
    )
    rt = figures.get("realtime")
    if rt:
        lines.append(
            f"Keyframes shed whole: {rt['keyframes_shed']} "
            f"({', '.join(f'{k} {v}' for k, v in rt['shed_reasons'].items()) or 'none'}); "
            f"metrized without masks or prior: {rt['metrized_without_inputs']} "
            f"({rt['inputs_failed']} failed, {rt['inputs_stalled']} silent worker)."
        )
    summary = [f"{figures['keyframes']} keyframes"]
    if "depth" in figures:
        d = figures["depth"]
        lines += [
            "",
            "## Depth (metrized, against ground truth)",
            "",
            "| AbsRel | RMSE [m] | delta1 | coverage | keyframes |",
            "| ---: | ---: | ---: | ---: | ---: |",
            f"| {d['absrel']:.4f} | {d['rmse']:.3f} | {d['delta1']:.4f} | {d['coverage']:.3f} | {d['keyframes_scored']} |",
        ]
        summary.append(f"depth AbsRel {d['absrel']:.3f}")
    if "trajectory" in figures:
        t = figures["trajectory"]
        lines += ["", "## Trajectory (frontend odometry against ground truth, evo)", ""]
        if "frontend" in figures:
            fe = figures["frontend"]
            lines += [
                f"Camera-IMU time offset {fe['time_offset_ms']:.1f} ms, "
                f"{fe['keyframes_per_s']:.2f} keyframes/s, resets {fe['resets'] or 'none'}.",
                "",
            ]
        if "error" in t:
            lines.append(f"Not scored: {t['error']}")
        else:
            lines += [
                "| path [m] | ATE SE(3) [m] | ATE Sim(3) [m] | scale error | RPE [m] | RPE [deg] |",
                "| ---: | ---: | ---: | ---: | ---: | ---: |",
                f"| {t['path_length_m']:.1f} | {t['ate_se3_rmse_m']:.3f} | {t['ate_sim3_rmse_m']:.3f} | "
                f"{t['scale_error']:.3f} | {t['rpe_trans_m']:.3f} | {t['rpe_rot_deg']:.3f} |",
            ]
            summary.append(f"ATE {t['ate_se3_rmse_m']:.2f} m over {t['path_length_m']:.0f} m")
    if "mapper" in figures:
        m = figures["mapper"]
        lines += [
            "",
            "## Gaussian map",
            "",
            "| Gaussians | iterations | last training PSNR [dB] (mapper window) |",
            "| ---: | ---: | ---: |",
            f"| {m.get('n_gaussians', 0)} | {m.get('iterations', 0)} | {m.get('psnr_db', float('nan')):.2f} |",
        ]
        summary.append(
            f"{m.get('n_gaussians', 0)} Gaussians, PSNR {m.get('psnr_db', float('nan')):.1f} dB"
        )
    if "map" in figures:
        m = figures["map"]
        lines += _map_lines(m)
        if m.get("heldout_frames"):
            summary.append(
                f"held-out PSNR {m['heldout_psnr_db']:.1f} dB, SSIM {m['heldout_ssim']:.3f} "
                f"({m['heldout_frames']} frames)"
            )
    path.write_text("\n".join(lines) + "\n")
    return "; ".join(summary)
