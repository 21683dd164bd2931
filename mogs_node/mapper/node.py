"""Mapper node: keyframes + metrized depth -> Gaussian map (DESIGN.md sections 1, 2).

Subscribes (reliable) to ``/frontend/keyframe`` and ``/metrizer/depth`` and pairs them by
``keyframe_id`` (:class:`~mogs_node.keyframe_join.KeyframeJoin`, pure); each complete pair goes to
the pure :class:`~mogs_node.mapper.mapper.GaussianMapper` (insertion + ``iters_per_keyframe`` window
iterations). After each keyframe it publishes ``/mapper/stats`` (:class:`~mogs_node.msgs.MapStats`),
``/mapper/render`` (the map rendered at the keyframe pose) and ``/mapper/gaussians``
(:class:`~mogs_node.msgs.GaussianUpdate`: only the Gaussians added or changed since the previous
message and the removed ids, never the whole map). On shutdown (and every ``ply_every_kf``
keyframes) the map is written to ``ply_path`` as a standard 3DGS PLY.

Long drives: regions the vehicle has left go to disk and come back when it returns
(:mod:`mogs_node.mapper.submaps`; ``offload_distance_m``), the PLY is streamed from them, and
checkpoints record which regions are on disk (their files live in ``checkpoint_dir/submaps``).
Each window iteration tells the node shell it advanced (:meth:`Node.progress`): a window step that
takes minutes is work, not a hang (issue 23).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mogs_node import msgs
from mogs_node.depth_kind import resample_metrized
from mogs_node.errors import ConfigError, ShapeError
from mogs_node.keyframe_join import KeyframeJoin
from mogs_node.mapper.checkpoint import (
    CHECKPOINT_NAME,
    CheckpointError,
    integrated_keyframe_ids,
    latest_checkpoint,
    load_checkpoint_with_extra,
    save_checkpoint,
)
from mogs_node.mapper.composite import load_cpp_extension
from mogs_node.mapper.insertion import InsertionParams
from mogs_node.mapper.mapper import GaussianMapper, MapperParams, resolve_device
from mogs_node.mapper.rasterizer import RasterParams
from mogs_node.mapper.submaps import SubmapError, SubmapParams, SubmapStore, write_map_ply
from mogs_node.node import CATCH_UP_ENV, Node

__all__ = ["MapperNode", "MapperNodeParams"]


@dataclass(frozen=True)
class MapperNodeParams:
    """Parameters of the mapper node (flat; the mapper core's are :class:`MapperParams`)."""

    iters_per_keyframe: int = (
        30  # window iterations after each keyframe (at most, see converge_rel)
    )
    iters_when_behind: int = -1  # iterations for a keyframe while more input waits (-1: never
    # fewer than iters_per_keyframe); the iterations saved are run when the input queue is empty
    idle_iters_per_tick: int = 2  # owed iterations run per idle timer tick (0: never run them)
    window_size: int = 8  # keyframes in the optimisation window
    n_random_past: int = 2  # random past keyframes among an iteration's candidate views
    train_downsample: int = 1  # optimise at 1/n of the image resolution
    insert_downsample: int = 1  # render the map for insertion at 1/n of the resolution
    converge_rel: float = 0.0  # end a keyframe's iterations once the newest view's L1 error
    # falls by less than this fraction per iteration of it (0: always iters_per_keyframe)
    min_iters: int = 4  # ... never before this many
    device: str = "cpu"  # cpu | cuda[:N]: where the map lives and is optimised (cuda: gsplat)
    lambda_depth: float = 0.1  # weight of the confidence-weighted depth loss
    exposure: bool = True  # per-keyframe affine exposure compensation
    exposure_gauge: bool = False  # ... except the first keyframe's (MapperParams.exposure_gauge)
    lambda_ssim: float = 0.0  # weight of the D-SSIM term of the photometric loss
    refine_lambda_ssim: float = 0.0  # ... in the final refinement
    refine_lambda_depth: float = (
        -1.0
    )  # depth-loss weight in the final refinement (-1: lambda_depth)
    refine_lr_scale: float = 1.0  # the final refinement's learning rates: this x the drive's ...
    refine_lr_final: float = 1.0  # ... decayed exponentially to this fraction of that at its end
    refine_poses: bool = False  # optimise window keyframe poses
    densify: bool = False  # gradient-based cloning
    background_depth_m: float = 0.0  # far-sphere Gaussians where the depth has none (0: off)
    insertion_confidence: float = -1.0  # the confidence insertion reads wherever there is depth
    # (-1: the source's own; InsertionParams.fixed_confidence)
    insertion_patch_px: int = 0  # object-guided insertion: flat Gaussians on planar depth
    # patches up to this size (0: off; InsertionParams.patch_px, docs/mapper.md)
    insertion_color_tol: float = 0.0  # also insert where the map draws the wrong colour: mean
    # |rendered - image| above this (0: off; InsertionParams.color_tol)
    insertion_disagree_color_tol: float = 0.0  # a depth disagreement inserts only where the
    # rendered colour is off by more than this (0: always; InsertionParams.disagree_color_tol)
    final_refine_iters: int = 0  # at the end of the drive: iterations over every keyframe
    final_refine_downsample: int = 1  # ... at 1/n of the resolution (GaussianMapper.refine)
    final_refine_chunk: int = 5  # refinement iterations per timer tick (heartbeats go on)
    final_refine_threads: int = 0  # torch threads for it (0: keep `threads`); after the drive
    # the other nodes are idle. The map is bitwise repeatable for a given thread count
    source_node: str = "player"  # its "stopped" diagnostics mark the end of the drive
    backend: str = "auto"  # rasterizer backend: auto | cpp | torch | gsplat
    threads: int = 0  # torch threads (0: torch's default)
    composite_threads: int = 0  # threads of the C++ compositing passes only (0: `threads`);
    # the map is bitwise the same for any count (docs/mapper.md "Speed, session 15")
    max_pending: int = 16  # keyframes waiting for their depth (or depth for its keyframe)
    publish_render: bool = True  # publish /mapper/render after each keyframe
    render_at_train_size: bool = False  # ... at the training resolution (train_downsample):
    # a snapshot for the report and viewer, off the drive's critical path (issue 17)
    ply_path: str = ""  # write the map here on shutdown ("" = never)
    ply_every_kf: int = 0  # also write it every n keyframes (0 = only on shutdown)
    checkpoint_dir: str = ""  # save the mapper state here (checkpoint.py; "" = never)
    checkpoint_every_keyframes: int = 5  # ... every n mapped keyframes and on shutdown
    resume: bool = False  # on start, load checkpoint_dir's checkpoint (if any) first
    submap_length_m: float = 50.0  # long drives: distance travelled per submap (submaps.py)
    offload_distance_m: float = 150.0  # a region left farther behind goes to disk (0: never)
    reload_distance_m: float = 100.0  # ... and comes back when the camera is this near again
    max_gaussians_in_ram: int = 0  # ... also regions beyond reload_distance_m, the farthest
    # first, while the map holds more Gaussians than this (0: no bound; submaps.py)
    submap_dir: str = ""  # offloaded regions ("": checkpoint_dir/submaps, else a temp folder)
    keyframe_topic: str = "/frontend/keyframe"  # input keyframes
    depth_topic: str = "/metrizer/depth"  # input metric depth
    stats_topic: str = "/mapper/stats"  # output statistics
    render_topic: str = "/mapper/render"  # output render
    gaussians_topic: str = "/mapper/gaussians"  # output incremental map updates

    def __post_init__(self) -> None:
        if (
            self.iters_per_keyframe < 0
            or self.max_pending < 1
            or self.threads < 0
            or self.composite_threads < 0
        ):
            raise ConfigError(
                "mapper: iters_per_keyframe >= 0, max_pending >= 1, threads, composite_threads >= 0"
            )
        if self.final_refine_threads < 0:
            raise ConfigError("mapper.final_refine_threads: must be >= 0")
        if self.iters_when_behind < -1 or self.idle_iters_per_tick < 0:
            raise ConfigError("mapper: iters_when_behind >= -1, idle_iters_per_tick >= 0")
        if self.checkpoint_every_keyframes < 1:
            raise ConfigError("mapper.checkpoint_every_keyframes: must be >= 1")
        if self.resume and not self.checkpoint_dir:
            raise ConfigError("mapper.resume: needs checkpoint_dir")
        self.submap_params()  # validates the submap settings

    def submap_params(self) -> SubmapParams:
        return SubmapParams(
            length_m=self.submap_length_m,
            offload_distance_m=self.offload_distance_m,
            reload_distance_m=self.reload_distance_m,
            max_gaussians_in_ram=self.max_gaussians_in_ram,
        )

    def submap_folder(self) -> Path | None:
        if self.submap_dir:
            return Path(self.submap_dir)
        return Path(self.checkpoint_dir) / "submaps" if self.checkpoint_dir else None

    def mapper_params(self) -> MapperParams:
        return MapperParams(
            raster=RasterParams(backend=self.backend, threads=self.composite_threads),
            window_size=self.window_size,
            n_random_past=self.n_random_past,
            train_downsample=self.train_downsample,
            insert_downsample=self.insert_downsample,
            converge_rel=self.converge_rel,
            min_iters=self.min_iters,
            device=self.device,
            lambda_depth=self.lambda_depth,
            exposure=self.exposure,
            exposure_gauge=self.exposure_gauge,
            lambda_ssim=self.lambda_ssim,
            refine_lambda_ssim=self.refine_lambda_ssim,
            refine_lambda_depth=self.refine_lambda_depth,
            refine_lr_scale=self.refine_lr_scale,
            refine_lr_final=self.refine_lr_final,
            refine_poses=self.refine_poses,
            densify=self.densify,
            insertion=InsertionParams(
                background_depth_m=self.background_depth_m,
                fixed_confidence=self.insertion_confidence,
                patch_px=self.insertion_patch_px,
                color_tol=self.insertion_color_tol,
                disagree_color_tol=self.insertion_disagree_color_tol,
            ),
        )


def _map_header(stamp_ns: int, keyframe_id: int) -> dict[str, Any]:
    """The header fields of a map message (stats, update): the keyframe it follows, in the world
    frame."""
    return {"stamp_ns": stamp_ns, "frame_id": "world", "keyframe_id": keyframe_id}


def depth_for_keyframe(
    depth: msgs.DepthMap, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Metric depth and confidence at the keyframe's size (nearest: `mogs_node.depth_kind`)."""
    if depth.kind != "metric":
        raise ShapeError(f"depth.kind: the mapper needs metric depth, got {depth.kind!r}")
    d, c = np.asarray(depth.depth, np.float32), np.asarray(depth.confidence, np.float32)
    return resample_metrized(d, c, width, height)


class MapperNode(Node):
    """Gaussian mapper process; see the module docstring."""

    Params = MapperNodeParams

    def setup(self) -> None:
        p: MapperNodeParams = self.params
        if p.threads:
            torch.set_num_threads(p.threads)
        resolve_device(p.device)  # a missing GPU fails here, with one clear ConfigError
        # keyframe + metrized depth by id; no time bound (a keyframe waits for its depth), the
        # oldest incomplete dropped beyond max_pending and counted (pair_* counters)
        self.pairs = KeyframeJoin(("depth",), max_pending=p.max_pending, release_partial=False)
        self.mapper: GaussianMapper | None = None
        self.integrated_keyframe_ids: set[int] = set()  # keyframes in the map (restart catch-up)
        self.submaps = SubmapStore(p.submap_params(), p.submap_folder())
        restarted = os.environ.get(CATCH_UP_ENV) == "1"  # respawned after a crash, or --resume
        ck = (
            latest_checkpoint(p.checkpoint_dir)
            if (p.resume or restarted) and p.checkpoint_dir
            else None
        )
        if ck is not None:
            try:
                self.mapper, extra = load_checkpoint_with_extra(ck, p.mapper_params())
                self._restore_submaps(self.mapper, extra.get("submaps"))
            except (CheckpointError, SubmapError) as err:
                self.mapper = None
                self.submaps = SubmapStore(p.submap_params(), p.submap_folder())
                # not a crash loop under respawn: keep the file for inspection and rebuild the
                # map from the journal (catch-up replays every keyframe when none is integrated)
                bad = ck.with_name(ck.name + ".corrupt")
                os.replace(ck, bad)
                self.counters["checkpoint_errors"] = 1
                self.log.error("unusable checkpoint moved to %s, map rebuilt: %s", bad, err)
            else:
                self.integrated_keyframe_ids = integrated_keyframe_ids(self.mapper)
                self.log.info(
                    "resumed from %s: %d keyframes", ck, len(self.integrated_keyframe_ids)
                )
        if p.backend in ("auto", "cpp") and p.device == "cpu":
            # compile (first run on a machine: ~40 s, minutes under load) before the first
            # keyframe, not inside its handler where heartbeats stop
            load_cpp_extension()
        self.counters.update(
            {"keyframes_mapped": 0, "keyframes_rejected": 0, "keyframes_behind": 0, "owed_iters": 0}
        )
        if p.iters_when_behind >= 0 and p.idle_iters_per_tick > 0:
            self.every(0.05, self._idle_optimize)
        self.refine_left = -1  # final refinement iterations still to run (-1: not started)
        self.last_stamp_ns = 0  # of the newest mapped keyframe
        # after the drive: the refinement (if any), then the final map and its stats marked
        # final, which a run report with wait_final_map waits for (with no refinement too)
        self.source_done = False
        self.subscribe("/diagnostics", self.on_diagnostics, msg_type=msgs.Diagnostics)
        self.every(0.2, self._final_refine)
        self.subscribe(
            p.keyframe_topic,
            self.on_keyframe,
            reliable=True,
            msg_type=msgs.Keyframe,
            idempotent=True,
        )
        self.subscribe(
            p.depth_topic, self.on_depth, reliable=True, msg_type=msgs.DepthMap, idempotent=True
        )
        # after a restart: every journaled keyframe not in the map (all of them without a
        # checkpoint: the map is rebuilt in the same order); /mapper/stats not sent twice
        self.catch_up((p.keyframe_topic, p.depth_topic), (p.stats_topic,))

    def _restore_submaps(self, mapper: GaussianMapper, state: dict[str, Any] | None) -> None:
        """The submap record of a checkpoint (None: one written before submaps existed)."""
        if state is not None:
            self.submaps.restore(state, mapper)
            return
        if mapper.offloaded_kfs:
            raise SubmapError("checkpoint: keyframes offloaded but no submap record")
        for kf in mapper.keyframes:
            self.submaps.add_keyframe(kf.index, kf.T_world_cam)

    def _should_stop(self) -> bool:
        """Polled before each window iteration: it advanced (liveness), and stop on request."""
        self.progress()
        return self.stopping

    def _integrated(self, keyframe_id: int) -> bool:
        return keyframe_id in getattr(self, "integrated_keyframe_ids", ())

    def iterations_for_next_keyframe(self) -> int:
        """``iters_per_keyframe``, or ``iters_when_behind`` while more input waits in the queue.

        A live drive does not wait for the mapper: keyframes it cannot map at full effort pile up
        in the reliable input queue (memory grows, the map lags behind). Behind, every keyframe is
        still inserted, with fewer iterations; the saved ones are owed and run when the queue is
        empty (:meth:`_idle_optimize`, to the keyframes trained least:
        :meth:`GaussianMapper.catch_up`), so the total optimisation is the same once it catches
        up; the final map waits for them.
        """
        p: MapperNodeParams = self.params
        if p.iters_when_behind < 0 or self.queue_depth == 0:
            return p.iters_per_keyframe
        return min(p.iters_when_behind, p.iters_per_keyframe)

    def _idle_optimize(self) -> None:
        if self.mapper is None or self.queue_depth or self.counters["owed_iters"] <= 0:
            return
        n = min(self.params.idle_iters_per_tick, self.counters["owed_iters"])
        self.mapper.catch_up(n, should_stop=self._should_stop)
        self.counters["owed_iters"] -= n

    def on_diagnostics(self, m: msgs.Diagnostics) -> None:
        if m.node == self.params.source_node and m.status == "stopped":
            self.source_done = True

    def _final_refine(self) -> None:
        """After the drive (the source stopped, every keyframe seen is mapped, nothing queued,
        the iterations owed from keyframes mapped while behind paid by :meth:`_idle_optimize`):
        ``final_refine_iters`` over every keyframe (:meth:`GaussianMapper.refine`), a chunk per
        tick; then the map update and a ``/mapper/stats`` marked ``final`` (the run report
        waits for it)."""
        p: MapperNodeParams = self.params
        m = self.mapper
        if (
            m is None
            or not m.keyframes
            or not self.source_done
            or self.queue_depth
            or len(self.pairs)
            or (self.counters["owed_iters"] > 0 and self.params.idle_iters_per_tick > 0)
        ):
            return
        if self.refine_left < 0:
            if self.refine_left == -2:  # done
                return
            self.refine_left = p.final_refine_iters
            if p.final_refine_threads > 0:
                torch.set_num_threads(p.final_refine_threads)
            self.log.info(
                "final refinement: %d iterations over %d keyframes, %d threads",
                self.refine_left,
                len(m.keyframes),
                torch.get_num_threads(),
            )
        n = min(p.final_refine_chunk, self.refine_left)
        st = (
            m.refine(
                n,
                p.final_refine_downsample,
                should_stop=lambda: self.stopping,
                total_iters=p.final_refine_iters,
            )
            if n > 0
            else m.stats()
        )
        self.refine_left -= n
        # on the heartbeat: a run report waiting for the final map sees the refinement advance
        self.counters["refine_left"] = max(self.refine_left, 0)
        if self.refine_left > 0:
            return
        self.refine_left = -2
        last = m.keyframes[-1]
        self.publish_update(last.keyframe_id, self.last_stamp_ns)
        self._publish_stats(
            self.last_stamp_ns, last.keyframe_id, st, {"final": 1.0, "pruned": st["n_pruned"]}
        )

    def _publish_stats(
        self, stamp_ns: int, keyframe_id: int, st: dict[str, Any], extra: dict[str, Any]
    ) -> None:
        """The map's statistics after a keyframe (``extra``: what that step adds)."""
        self.publish(
            self.params.stats_topic,
            msgs.MapStats(
                **_map_header(stamp_ns, keyframe_id),
                n_gaussians=int(st["n_gaussians"]) + self.submaps.gaussians_on_disk,
                n_keyframes=int(st["n_keyframes"]),
                iterations=int(st["iterations"]),
                loss=float(st["loss"]),
                psnr_db=float(st["psnr_db"]),
                extra=extra,
            ),
        )

    def on_keyframe(self, msg: msgs.Keyframe) -> None:
        if self._integrated(msg.keyframe_id):
            return
        self._pair("keyframe", msg)

    def on_depth(self, msg: msgs.DepthMap) -> None:
        if self._integrated(msg.keyframe_id):
            return
        self._pair("depth", msg)

    def _pair(self, slot: str, msg: msgs.Keyframe | msgs.DepthMap) -> None:
        for entry in self.pairs.add(slot, msg.keyframe_id, msg):
            self.process(entry.keyframe, entry.get("depth"))
        for k, v in self.pairs.counters.items():
            self.counters[f"pair_{k}"] = v

    def process(self, kf: msgs.Keyframe, depth: msgs.DepthMap) -> None:
        p: MapperNodeParams = self.params
        rgb = kf.rgb()
        H, W = rgb.shape[:2]
        if self.mapper is None:
            self.mapper = GaussianMapper(p.mapper_params(), kf.K, W, H)
        m = self.mapper
        if (m.width, m.height) != (W, H) or not np.allclose(kf.K, m.K_matrix):
            self.counters["keyframes_rejected"] += 1
            self.log.warning("keyframe %d: camera differs from the map's; skipped", kf.keyframe_id)
            return
        d, c = depth_for_keyframe(depth, W, H)
        t0, c0 = time.perf_counter(), time.process_time()
        position = np.asarray(kf.T_world_cam, np.float64)[:3, 3]
        self.submaps.reload_near(m, position)  # a region it returns to: its map first
        n_new = m.add_keyframe(kf.keyframe_id, rgb, kf.T_world_cam, d, c)
        self.submaps.add_keyframe(m.keyframes[-1].index, kf.T_world_cam)
        self.integrated_keyframe_ids.add(int(kf.keyframe_id))
        n_iters = self.iterations_for_next_keyframe()
        if n_iters < p.iters_per_keyframe:
            self.counters["keyframes_behind"] += 1
            self.counters["owed_iters"] += p.iters_per_keyframe - n_iters
        st = m.optimize(n_iters, should_stop=self._should_stop)
        map_ms = (time.perf_counter() - t0) * 1000  # reload + insertion + window iterations
        map_cpu_ms = (time.process_time() - c0) * 1000  # the same in CPU time (load-independent)
        self.counters["keyframes_mapped"] += 1
        self.last_stamp_ns = int(kf.stamp_ns)
        self._publish_stats(
            kf.stamp_ns,
            kf.keyframe_id,
            st,
            {
                "inserted": float(n_new),
                "pruned": st["n_pruned"],
                "window": st["window"],
                "map_ms": round(map_ms, 3),
                "map_cpu_ms": round(map_cpu_ms, 3),
                "gaussians_in_ram": float(len(m.map)),
                "gaussians_on_disk": float(self.submaps.gaussians_on_disk),
            },
        )
        if p.publish_render:
            K, size = (m.train_K, m.train_size) if p.render_at_train_size else (None, None)
            r = m.render_view(m.keyframe_pose(kf.keyframe_id), K=K, size=size)
            depth_m = (r.depth / r.alpha.clamp_min(1e-6)).where(r.alpha > 1e-3, torch.zeros(()))
            self.publish(
                p.render_topic,
                msgs.Render(
                    **kf.result_header(),
                    image=(r.color.cpu().numpy() * 255 + 0.5).astype(np.uint8),
                    depth=np.nan_to_num(depth_m.cpu().numpy()).astype(np.float32),
                ),
            )
        self.publish_update(kf.keyframe_id, kf.stamp_ns)
        self.submaps.offload_far(m, position)  # after the drain: offloaded rows are published
        self.counters.update(
            {
                "gaussians_in_ram": len(m.map),
                "gaussians_on_disk": self.submaps.gaussians_on_disk,
                "submaps_on_disk": len(self.submaps.offloaded),
                "submap_offloads": self.submaps.counters["offloads"],
                "submap_reloads": self.submaps.counters["reloads"],
                "submap_offloads_for_count": self.submaps.counters["offloads_for_count"],
            }
        )
        if (
            p.ply_path
            and p.ply_every_kf
            and self.counters["keyframes_mapped"] % p.ply_every_kf == 0
        ):
            write_map_ply(m, self.submaps, p.ply_path)
        if (
            p.checkpoint_dir
            and self.counters["keyframes_mapped"] % p.checkpoint_every_keyframes == 0
        ):
            self.save_checkpoint()

    def publish_update(self, keyframe_id: int, stamp_ns: int) -> None:
        """``/mapper/gaussians``: the Gaussians changed since the last update, removed ids."""
        ch = self.mapper.drain_changes()
        self.publish(
            self.params.gaussians_topic,
            msgs.GaussianUpdate(
                **_map_header(stamp_ns, keyframe_id),
                ids=ch.ids,
                means=ch.means,
                log_scales=ch.log_scales,
                quats_wxyz=ch.quats_wxyz,
                opacity_logit=ch.opacity_logit,
                colors_rgb=ch.colors,
                removed_ids=ch.removed_ids,
            ),
        )

    def save_checkpoint(self) -> None:
        """Write the mapper state to ``checkpoint_dir`` (atomically; nothing before a keyframe)."""
        p: MapperNodeParams = self.params
        if p.checkpoint_dir and self.mapper is not None:
            try:
                save_checkpoint(
                    self.mapper,
                    Path(p.checkpoint_dir) / CHECKPOINT_NAME,
                    extra={"submaps": self.submaps.state()},
                )
                self.submaps.pin()  # submap files no checkpoint refers to any more go
                self.counters["checkpoints_saved"] = self.counters.get("checkpoints_saved", 0) + 1
            except OSError:  # a full or read-only disk must not stop the mapping
                self.counters["checkpoint_errors"] = self.counters.get("checkpoint_errors", 0) + 1
                self.log.exception("checkpoint to %s failed", p.checkpoint_dir)

    def teardown(self) -> None:
        p: MapperNodeParams = self.params
        self.save_checkpoint()
        if p.ply_path and self.mapper is not None:
            n = write_map_ply(self.mapper, self.submaps, p.ply_path)
            self.log.info(
                "map written to %s (%d Gaussians, %d streamed from %d offloaded submaps)",
                p.ply_path,
                n,
                self.submaps.gaussians_on_disk,
                len(self.submaps.offloaded),
            )
        if not p.checkpoint_dir:
            self.submaps.close()


def with_params(params: MapperNodeParams, **kw: Any) -> MapperNodeParams:
    """A copy of ``params`` with fields replaced (convenience for launch code and tests)."""
    return replace(params, **kw)
