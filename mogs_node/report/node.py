"""Run report node: writes a run's outputs and its scores against ground truth into a folder.

Outputs in ``out_dir``: ``trajectory_frames.tum`` / ``.kitti`` (odometry of every frame),
``trajectory_keyframes.tum`` / ``.kitti``, ``groundtruth.tum`` when ground truth was streamed,
``depth/kf_NNNNNN.npz`` (metric depth + confidence per keyframe), ``renders/`` (the final map
at held-out frames and keyframes: ground truth | render | depth pictures,
``heldout_<stamp_ns>.png`` and ``keyframe_NNNNNN.png``), ``snapshots/kf_NNNNNN_on_arrival.png``
(the mapper's ``/mapper/render`` of each keyframe, taken when the keyframe was mapped: the map of
that moment, not the final one), ``report.md`` and ``summary.json``.

The final map is the mapper's map rebuilt from its incremental ``/mapper/gaussians`` updates
(:class:`~mogs_node.report.views.MapReplica`): once the source node has stopped, every keyframe
has its metrized depth and reached the mapper, and the map update of the newest mapped keyframe has
arrived, the node renders that map at up to ``heldout_views`` non-keyframe frames with an odometry
pose (ground truth: their ``/camera/image``) and at the keyframes, scores PSNR / SSIM, writes the
pictures, and stops (also ``settle_s`` after its last input when no keyframe was made at all, or
after ``idle_timeout_s`` without input), so a launch file can end the run with
``exit_when: [report]``. Rendering runs a view at a time from the node's timer, so heartbeats go
on.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from mogs_node import msgs
from mogs_node.errors import ConfigError
from mogs_node.frontend.trajectory_io import write_kitti, write_tum
from mogs_node.mapper.composite import load_cpp_extension
from mogs_node.mapper.rasterizer import RasterParams
from mogs_node.node import Node
from mogs_node.report.collect import RunCollector, summarise, write_report
from mogs_node.report.views import (
    FrameStore,
    ViewScore,
    choose_heldout,
    image_to_rgb,
    map_digest,
    render_map_view,
    score_view,
    side_by_side,
)

__all__ = ["NOT_ESTIMATED", "RunReportNode", "RunReportParams"]

#: odometry statuses that acknowledge a frame without estimating its pose (frontend node)
NOT_ESTIMATED = frozenset(
    {"initializing", "reset", "rejected", "dropped", "no_calibration", "no_pose"}
)
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
    # issue 28: keyframes shed whole (frontend, by reason) and metrized without an input (metrizer)
    "keyframes_shed",
    "metrized_without_inputs",
    "match_failed_inputs",
    "match_stalled_inputs",
    # the prior node: keyframes whose wait for the previous one's metrized depth ran out
    "metrized_wait_timeouts",
    # the prior node: the camera height it measured (road.auto_height; 0: none yet)
    "ground_height_m",
)


@dataclass(frozen=True)
class RunReportParams:
    out_dir: str = "runs/latest"  # where the outputs go
    source_node: str = "player"  # the node whose stop marks the end of the input
    settle_s: float = 2.0  # after the source stopped and all keyframes are done, wait this long
    idle_timeout_s: float = 300.0  # stop after this long without any input once the source stopped
    save_depth: bool = True  # write depth/kf_*.npz
    save_renders: bool = True  # write the final map's pictures into renders/
    save_snapshots: bool = True  # write snapshots/kf_*_on_arrival.png (/mapper/render)
    title: str = "MOGS run"  # report title
    heldout_views: int = 12  # held-out (non-keyframe) frames rendered from the final map
    max_keyframe_views: int = 32  # keyframes rendered (an even sample beyond this many)
    max_stored_frames: int = 64  # camera images kept as held-out candidates (an even sample)
    render_backend: str = "auto"  # rasterizer backend of the final renders
    render_budget_s: float = 1.0  # rendering per timer tick before heartbeats get their turn
    threads: int = 0  # torch threads of the final renders (0: torch's default; 1 on shared
    # cores, where two OpenMP threads mostly wait for each other)
    image_topic: str = "/camera/image"  # ground truth of the held-out views
    gaussians_topic: str = "/mapper/gaussians"  # incremental map updates
    wait_final_map: bool = False  # the mapper refines after the drive (final_refine_iters):
    # render once its /mapper/stats marked final arrived

    def __post_init__(self) -> None:
        if self.threads < 0:
            raise ConfigError("report.threads: must be >= 0")
        if self.heldout_views < 0 or self.max_keyframe_views < 0 or self.max_stored_frames < 1:
            raise ConfigError(
                "report: heldout_views >= 0, max_keyframe_views >= 0, max_stored_frames >= 1"
            )


class RunReportNode(Node):
    Params = RunReportParams

    def setup(self) -> None:
        p: RunReportParams = self.params
        self.out = Path(p.out_dir)
        if p.threads:
            torch.set_num_threads(p.threads)
        (self.out / "depth").mkdir(parents=True, exist_ok=True)
        if p.render_backend in ("auto", "cpp"):
            # compile or load the rasterizer now (first run on a machine: a minute), not at the
            # end of the run inside a timer callback where heartbeats stop
            load_cpp_extension()
        self.c = RunCollector(need_final=p.wait_final_map)
        self.frames = FrameStore(p.max_stored_frames)  # held-out candidates (ground truth)
        self.kf_frames = FrameStore(p.max_keyframe_views)  # keyframe images by stamp
        self.camera: tuple[np.ndarray, int, int] | None = None  # K, width, height of the map
        self.view_jobs: list[tuple[str, int, int]] | None = None  # (kind, stamp, kf id) to render
        self.source_stopped_at: float | None = None
        self.last_input = time.monotonic()
        self.refine_left: dict[str, float] = {}  # per node: its final refinement's iterations left
        self.subscribe("/frontend/odometry", self.on_odometry, msg_type=msgs.Odometry)
        self.subscribe("/frontend/keyframe", self.on_keyframe, msg_type=msgs.Keyframe)
        self.subscribe("/metrizer/depth", self.on_depth, msg_type=msgs.DepthMap)
        self.subscribe("/mapper/stats", self.on_stats, msg_type=msgs.MapStats)
        self.subscribe("/mapper/render", self.on_render, reliable=False, msg_type=msgs.Render)
        self.subscribe(p.gaussians_topic, self.on_gaussians, msg_type=msgs.GaussianUpdate)
        # best effort, like every image topic; a deeper queue than 1: the report keeps them all
        self.subscribe(
            p.image_topic, self.on_image, reliable=False, msg_type=msgs.Image, queue_size=16
        )
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
        rgb = m.rgb()
        if self.camera is None:  # the mapper's camera: that of its first keyframe
            self.camera = (np.array(m.K), rgb.shape[1], rgb.shape[0])
        self.kf_frames.add(m.stamp_ns, rgb)

    def on_image(self, m: msgs.Image) -> None:
        self.frames.add(m.stamp_ns, image_to_rgb(m.data, m.encoding))

    def on_gaussians(self, m: msgs.GaussianUpdate) -> None:
        self._touch()
        self.c.final_map.apply_update(m)
        self.c.map_updated.add(m.keyframe_id)

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
        if m.extra.get("final"):
            self.c.final_seen = True
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
        if self.params.save_snapshots:
            (self.out / "snapshots").mkdir(exist_ok=True)
            cv2.imwrite(
                str(self.out / "snapshots" / f"kf_{m.keyframe_id:06d}_on_arrival.png"),
                m.image[..., ::-1],
            )

    def on_gt_pose(self, m: msgs.PoseStamped) -> None:
        self.c.gt_poses[m.stamp_ns] = np.array(m.T_world_cam)

    def on_gt_depth(self, m: msgs.DepthMap) -> None:
        self.c.add_gt_depth(m.stamp_ns, np.array(m.depth))

    def on_diagnostics(self, m: msgs.Diagnostics) -> None:
        left = m.counters.get("refine_left")
        if left is not None:  # the mapper's final refinement: while it advances the run is
            # not idle (a slow machine's refinement may outlast idle_timeout_s); a stuck one is
            if left < self.refine_left.get(m.node, float("inf")):
                self._touch()
            self.refine_left[m.node] = float(left)
        self.c.node_counters[m.node] = {
            k: float(v)
            for k, v in m.counters.items()
            if k in NODE_COUNTERS or k.startswith("keyframes_shed_")
        }
        fe = {k[9:]: float(v) for k, v in m.counters.items() if k.startswith("frontend_")}
        if len(fe) > 1:  # the frontend's own figures (not another node's one counter)
            self.c.frontend_figures = fe
        if (
            m.node == self.params.source_node
            and m.status == "stopped"
            and self.source_stopped_at is None
        ):
            self.source_stopped_at = time.monotonic()
            self.log.info("source %s finished; waiting for the pipeline to drain", m.node)

    def check_done(self) -> None:
        if self.view_jobs is not None:  # the run is over: render the final map
            self.render_views()
            return
        if self.source_stopped_at is None:
            return
        idle = time.monotonic() - self.last_input
        if self.c.complete and self.c.map_ready and idle >= self.params.settle_s:
            self.start_views()
        elif not self.c.keyframes and idle >= self.params.settle_s:
            # the input is over and the frontend made no keyframe at all (e.g. a stream without
            # IMU): nothing will reach the workers, so do not wait for idle_timeout_s
            self.log.warning("the source finished and no keyframe was made: reporting what came")
            self.request_stop()
        elif idle >= self.params.idle_timeout_s:
            self.log.warning("no input for %.0f s: writing an incomplete report", idle)
            self.start_views()

    def start_views(self) -> None:
        """Choose the views of the final map: held-out frames, then keyframes (by stamp)."""
        c, p = self.c, self.params
        kf_stamps = sorted(s for s, _ in c.keyframes.values())
        posed = [s for s in self.frames.images if s in c.odometry]
        xyz = np.array([c.odometry[s][:3, 3] for s in posed]).reshape(-1, 3)
        heldout = choose_heldout(posed, kf_stamps, p.heldout_views, positions_m=xyz)
        kf_id = {s: i for i, (s, _) in c.keyframes.items()}
        kfs = sorted(s for s in self.kf_frames.images if s in kf_id)
        self.view_jobs = [("heldout", int(s), -1) for s in heldout]
        self.view_jobs += [("keyframe", s, kf_id[s]) for s in kfs]
        if p.save_renders:
            (self.out / "renders").mkdir(exist_ok=True)
        self.log.info(
            "rendering the final map (%d Gaussians) at %d held-out frames and %d keyframes",
            len(c.final_map),
            len(heldout),
            len(kfs),
        )
        self.render_views()

    def render_views(self) -> None:
        """Render, score and picture views until ``render_budget_s`` is spent; stop when done."""
        t0 = time.monotonic()
        while self.view_jobs and time.monotonic() - t0 < self.params.render_budget_s:
            kind, stamp, kf_id = self.view_jobs.pop(0)
            try:
                self.c.view_scores.append(self.render_view(kind, stamp, kf_id))
            except Exception:  # a view that cannot be rendered is logged, the report goes on
                self.counters["render_errors"] = self.counters.get("render_errors", 0) + 1
                self.log.exception("rendering the %s view at %d failed", kind, stamp)
        if not self.view_jobs:
            self.request_stop()

    def render_view(self, kind: str, stamp_ns: int, keyframe_id: int) -> ViewScore:
        """The final map at one view: scores, and its picture in renders/."""
        p, c = self.params, self.c
        if self.camera is None or not len(c.final_map):
            raise ConfigError("no map or no camera to render with")
        K, W, H = self.camera
        if kind == "keyframe":
            gt, T = self.kf_frames.images[stamp_ns], c.keyframes[keyframe_id][1]
        else:
            gt, T = self.frames.images[stamp_ns], c.odometry[stamp_ns]
        if gt.shape[:2] != (H, W):
            raise ConfigError(f"image at {stamp_ns}: {gt.shape[1]}x{gt.shape[0]}, map {W}x{H}")
        rgb, depth_m, alpha = render_map_view(
            c.final_map.arrays, T, K, W, H, raster=RasterParams(backend=p.render_backend)
        )
        psnr, s = score_view(gt, rgb)
        png = ""
        if p.save_renders:
            name = f"keyframe_{keyframe_id:06d}" if kind == "keyframe" else f"heldout_{stamp_ns}"
            png = f"renders/{name}.png"
            title = f"keyframe {keyframe_id}" if kind == "keyframe" else "held-out frame"
            pic = side_by_side(
                gt,
                rgb,
                depth_m,
                (
                    f"ground truth: {title}, t = {stamp_ns / 1e9:.2f} s",
                    f"final map: PSNR {psnr:.2f} dB, SSIM {s:.3f}",
                    "rendered depth (near red, far blue)",
                ),
            )
            cv2.imwrite(str(self.out / png), pic[..., ::-1])
        coverage = float(np.mean(alpha >= 0.5))
        return ViewScore(kind, stamp_ns, keyframe_id, psnr, s, coverage, png)

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
        if len(c.final_map):
            figures["map"]["digest"] = map_digest(c.final_map.arrays["means"])
            if self.view_jobs:
                figures["map"]["views_not_rendered"] = len(self.view_jobs)
        (self.out / "summary.json").write_text(json.dumps(figures, indent=2, default=float) + "\n")
        line = write_report(self.out / "report.md", figures, title=self.params.title)
        self.log.info("run report: %s -> %s", line, self.out)
