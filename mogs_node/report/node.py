"""Run report node: writes a run's outputs and its scores against ground truth into a folder.

Outputs in ``out_dir``: ``trajectory_frames.tum`` / ``.kitti`` (odometry of every frame),
``trajectory_keyframes.tum`` / ``.kitti``, ``groundtruth.tum`` when ground truth was streamed,
``depth/kf_NNNNNN.npz`` (metric depth + confidence per keyframe), ``renders/kf_NNNNNN.png``,
``report.md`` and ``summary.json``. The node stops by itself once the source node has stopped and
every keyframe has its metrized depth and reached the mapper (or ``settle_s`` after its last input
when no keyframe was made at all, or after ``idle_timeout_s`` without input), so a launch file
can end the run with ``exit_when: [report]``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mogs_node import msgs
from mogs_node.frontend.trajectory_io import write_kitti, write_tum
from mogs_node.node import Node
from mogs_node.report.collect import RunCollector, summarise, write_report

__all__ = ["NOT_ESTIMATED", "RunReportNode", "RunReportParams"]

#: odometry statuses that acknowledge a frame without estimating its pose (frontend node)
NOT_ESTIMATED = frozenset({"initializing", "reset", "rejected", "dropped"})
#: node counters kept in summary.json: what each node received, dropped (best effort superseded)
#: and lost (reliable gaps); the player's frame counts
NODE_COUNTERS = (
    "received",
    "dropped",
    "lost",
    "handler_errors",
    "frames_published",
    "frames_total",
    "frames_unreadable",
    "ack_timeouts",
    "frontend_image_time_backwards",
)


@dataclass(frozen=True)
class RunReportParams:
    out_dir: str = "runs/latest"  # where the outputs go
    source_node: str = "player"  # the node whose stop marks the end of the input
    settle_s: float = 2.0  # after the source stopped and all keyframes are done, wait this long
    idle_timeout_s: float = 300.0  # stop after this long without any input once the source stopped
    save_depth: bool = True  # write depth/kf_*.npz
    save_renders: bool = True  # write renders/kf_*.png
    title: str = "MOGS run"  # report title


class RunReportNode(Node):
    Params = RunReportParams

    def setup(self) -> None:
        p: RunReportParams = self.params
        self.out = Path(p.out_dir)
        (self.out / "depth").mkdir(parents=True, exist_ok=True)
        (self.out / "renders").mkdir(parents=True, exist_ok=True)
        self.c = RunCollector()
        self.source_stopped_at: float | None = None
        self.last_input = time.monotonic()
        self.subscribe("/frontend/odometry", self.on_odometry, msg_type=msgs.Odometry)
        self.subscribe("/frontend/keyframe", self.on_keyframe, msg_type=msgs.Keyframe)
        self.subscribe("/metrizer/depth", self.on_depth, msg_type=msgs.DepthMap)
        self.subscribe("/mapper/stats", self.on_stats, msg_type=msgs.MapStats)
        self.subscribe("/mapper/render", self.on_render, reliable=False, msg_type=msgs.Render)
        self.subscribe("/groundtruth/pose", self.on_gt_pose, msg_type=msgs.PoseStamped)
        self.subscribe("/groundtruth/depth", self.on_gt_depth, msg_type=msgs.DepthMap)
        self.subscribe("/diagnostics", self.on_diagnostics, msg_type=msgs.Diagnostics)
        # after a restart / on --resume: everything the run produced so far, from the journal
        self.catch_up(
            (
                "/frontend/odometry",
                "/frontend/keyframe",
                "/metrizer/depth",
                "/mapper/stats",
                "/groundtruth/pose",
                "/groundtruth/depth",
            )
        )
        self.every(0.5, self.check_done)

    def _touch(self) -> None:
        self.last_input = time.monotonic()

    def on_odometry(self, m: msgs.Odometry) -> None:
        self._touch()
        self.c.acknowledged.add(m.stamp_ns)
        if m.status in NOT_ESTIMATED:  # an acknowledgement without an estimate: not scored
            self.c.unestimated_frames += 1
            return
        self.c.odometry[m.stamp_ns] = np.array(m.T_world_cam)

    def on_keyframe(self, m: msgs.Keyframe) -> None:
        self._touch()
        self.c.add_keyframe(m.keyframe_id, m.stamp_ns, m.T_world_cam)

    def on_depth(self, m: msgs.DepthMap) -> None:
        self._touch()
        self.c.add_depth(m.keyframe_id, np.array(m.depth), np.array(m.confidence))
        if self.params.save_depth:
            extra = (
                {}
                if m.object_labels is None
                else {"object_labels": m.object_labels, "object_model": m.object_model}
            )
            np.savez_compressed(
                self.out / "depth" / f"kf_{m.keyframe_id:06d}.npz",
                depth_m=m.depth,
                confidence=m.confidence,
                **extra,
            )

    def on_stats(self, m: msgs.MapStats) -> None:
        self._touch()
        self.c.mapped.add(m.keyframe_id)
        self.c.last_stats = {
            "keyframe_id": m.keyframe_id,
            "n_gaussians": m.n_gaussians,
            "n_keyframes": m.n_keyframes,
            "iterations": m.iterations,
            "loss": m.loss,
            "psnr_db": m.psnr_db,
            **m.extra,
        }

    def on_render(self, m: msgs.Render) -> None:
        if self.params.save_renders:
            cv2.imwrite(
                str(self.out / "renders" / f"kf_{m.keyframe_id:06d}.png"), m.image[..., ::-1]
            )

    def on_gt_pose(self, m: msgs.PoseStamped) -> None:
        self.c.gt_poses[m.stamp_ns] = np.array(m.T_world_cam)

    def on_gt_depth(self, m: msgs.DepthMap) -> None:
        self.c.add_gt_depth(m.stamp_ns, np.array(m.depth))

    def on_diagnostics(self, m: msgs.Diagnostics) -> None:
        self.c.node_counters[m.node] = {
            k: float(m.counters.get(k, 0.0)) for k in NODE_COUNTERS if k in m.counters
        }
        if (
            m.node == self.params.source_node
            and m.status == "stopped"
            and self.source_stopped_at is None
        ):
            self.source_stopped_at = time.monotonic()
            self.log.info("source %s finished; waiting for the pipeline to drain", m.node)

    def check_done(self) -> None:
        if self.source_stopped_at is None:
            return
        idle = time.monotonic() - self.last_input
        if self.c.complete and idle >= self.params.settle_s:
            self.request_stop()
        elif not self.c.keyframes and idle >= self.params.settle_s:
            # the input is over and the frontend made no keyframe at all (e.g. a stream without
            # IMU): nothing will reach the workers, so do not wait for idle_timeout_s
            self.log.warning("the source finished and no keyframe was made: reporting what came")
            self.request_stop()
        elif idle >= self.params.idle_timeout_s:
            self.log.warning("no input for %.0f s: writing an incomplete report", idle)
            self.request_stop()

    def teardown(self) -> None:
        c = self.c
        if c.odometry:
            stamps = np.array(sorted(c.odometry), np.int64)
            poses = np.stack([c.odometry[s] for s in stamps])
            write_tum(self.out / "trajectory_frames.tum", stamps, poses)
            write_kitti(self.out / "trajectory_frames.kitti", poses)
        if c.keyframes:
            ids = sorted(c.keyframes)
            write_tum(
                self.out / "trajectory_keyframes.tum",
                np.array([c.keyframes[i][0] for i in ids], np.int64),
                np.stack([c.keyframes[i][1] for i in ids]),
            )
            write_kitti(
                self.out / "trajectory_keyframes.kitti", np.stack([c.keyframes[i][1] for i in ids])
            )
        if c.gt_poses:
            stamps = np.array(sorted(c.gt_poses), np.int64)
            write_tum(
                self.out / "groundtruth.tum", stamps, np.stack([c.gt_poses[s] for s in stamps])
            )
        figures = summarise(c)
        (self.out / "summary.json").write_text(json.dumps(figures, indent=2, default=float) + "\n")
        line = write_report(self.out / "report.md", figures, title=self.params.title)
        self.log.info("run report: %s -> %s", line, self.out)
