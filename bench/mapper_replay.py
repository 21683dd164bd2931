"""Benchmark: the mapper core replayed on a recorded run (its journal), CPU time and map quality.

Feeds the keyframes and metrized depth a pipeline run recorded (``runs/<ts>/journal/journal.log``
of ``make demo``) to the pure :class:`~mogs_node.mapper.mapper.GaussianMapper` exactly as the
mapper node does (``add_keyframe`` then ``optimize(iters_per_keyframe)``, parameters from the
launch file's mapper section), one process, no bus. Measures per keyframe the CPU time (process
time, all threads: meaningful on a shared machine) of insertion and of optimisation, and at the
end renders the final map at

- every keyframe (with its exposure), and
- the held-out frames: camera images that were not keyframes, at the frontend's odometry pose
  (``/frontend/odometry``), exposure of the nearest keyframe,

scoring PSNR and SSIM (:mod:`mogs_node.mapper.image_metrics`). ``--profile`` prints the cProfile
table (cumulative) of the whole replay.

    .venv/bin/python bench/mapper_replay.py runs/<ts>/journal/journal.log --json /tmp/replay.json

Refinement trials: replay the drive once and keep its online map (``--save-online``), then refine
that map under other settings without replaying (``--from-online``, same ``--set`` overrides)::

    mapper_replay.py JOURNAL --threads 1 --save-online /tmp/online.ckpt --refine-step 100
    mapper_replay.py JOURNAL --threads 1 --from-online /tmp/online.ckpt --refine-step 100 \
        --set refine_lr_scale=3 --set refine_lr_final=0.1
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mogs_node import msgs
from mogs_node.eval.bench_docs import REPO_ROOT, write_json
from mogs_node.journal.store import JournalStore
from mogs_node.launch import load_launch_file
from mogs_node.mapper.checkpoint import load_checkpoint, save_checkpoint
from mogs_node.mapper.image_metrics import psnr_db, ssim
from mogs_node.mapper.mapper import GaussianMapper, MapperParams, export_ply
from mogs_node.mapper.node import MapperNodeParams, depth_for_keyframe
from mogs_node.report.views import choose_heldout


def read_journal(path: Path) -> dict[str, list[Any]]:
    """Decoded messages of the topics the replay needs, in arrival order."""
    # a copy: opening a journal a node still writes would truncate its unfinished last record
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "journal.log"
        shutil.copyfile(path, copy)
        store = JournalStore(copy, fresh=False)
        topics = ("/frontend/keyframe", "/metrizer/depth", "/camera/image", "/frontend/odometry")
        out: dict[str, list[Any]] = {t: [] for t in topics}
        for i in store.select(topics):
            env = msgs.decode(store.read(i))
            out[env.topic].append(env.msg)
        store.close()
    return out


def mapper_params(launch: str, overrides: dict[str, Any]) -> MapperNodeParams:
    spec = next(n for n in load_launch_file(launch).nodes if n.name == "mapper")
    kw = {k: v for k, v in spec.params.items() if k in MapperNodeParams.__dataclass_fields__}
    kw.update(overrides)
    kw.pop("ply_path", None)
    return MapperNodeParams(**kw)


def core_params(p: MapperNodeParams, core: dict[str, Any]) -> MapperParams:
    """The node's core parameters with ``core`` overrides: ``name`` or ``insertion.name``."""
    mp = p.mapper_params()
    ins = {k.split(".", 1)[1]: v for k, v in core.items() if k.startswith("insertion.")}
    top = {k: v for k, v in core.items() if not k.startswith("insertion.")}
    return replace(mp, insertion=replace(mp.insertion, **ins), **top)


def replay(
    data: dict[str, list[Any]],
    p: MapperNodeParams,
    max_keyframes: int = 0,
    core: dict[str, Any] | None = None,
    behind: bool = False,
    after_insert: Callable[[GaussianMapper], None] | None = None,
) -> tuple[GaussianMapper, list[dict[str, float]]]:
    """Map every keyframe in order (the first ``max_keyframes``, 0: all); returns the mapper and
    per-keyframe CPU times (printed as they come). ``behind``: as a node that was behind its input
    the whole drive with ``iters_when_behind: 0`` (launch/kitti.yaml on a busy machine): every
    keyframe only inserted, then the owed ``iters_per_keyframe`` per keyframe run as its idle
    timer runs them, ``idle_iters_per_tick`` at a time (:meth:`GaussianMapper.catch_up`).
    ``after_insert(mapper)`` runs after each keyframe's insertion, before its iterations (it must
    leave the mapper as it found it: bench/table2_convergence.py works on a copy)."""
    depth = {d.keyframe_id: d for d in data["/metrizer/depth"]}
    mapper: GaussianMapper | None = None
    per_kf = []
    for kf in data["/frontend/keyframe"]:
        if kf.keyframe_id not in depth or (max_keyframes and len(per_kf) >= max_keyframes):
            continue
        rgb = kf.rgb()
        H, W = rgb.shape[:2]
        if mapper is None:
            mapper = GaussianMapper(core_params(p, core or {}), kf.K, W, H)
        d, c = depth_for_keyframe(depth[kf.keyframe_id], W, H)
        c0 = time.process_time()
        n_new = mapper.add_keyframe(kf.keyframe_id, rgb, kf.T_world_cam, d, c)
        c1 = time.process_time()
        if after_insert is not None:
            after_insert(mapper)
            c1 = time.process_time()
        st = mapper.optimize(0 if behind else p.iters_per_keyframe)
        c2 = time.process_time()
        k = {
            "keyframe_id": kf.keyframe_id,
            "insert_cpu_s": c1 - c0,
            "optimize_cpu_s": c2 - c1,
            "inserted": n_new,
            "gaussians": st["n_gaussians"],
            "iterations": st["iterations"],
        }
        per_kf.append(k)
        print(
            f"kf {k['keyframe_id']:4d}: insert {k['insert_cpu_s']:.2f} s, optimise "
            f"{k['optimize_cpu_s']:.2f} s CPU, +{k['inserted']} -> {int(k['gaussians'])} "
            f"Gaussians, {int(k['iterations'])} iterations",
            flush=True,
        )
    if mapper is None:
        raise SystemExit("the journal holds no keyframe with its metrized depth")
    owed = p.iters_per_keyframe * len(per_kf) if behind else 0
    while owed > 0:  # the node's idle timer once the input queue is empty
        n = min(max(p.idle_iters_per_tick, 1), owed)
        mapper.catch_up(n)
        owed -= n
    if behind:
        print(f"owed iterations run: {mapper.iterations}, {len(mapper.map)} Gaussians", flush=True)
    return mapper, per_kf


def _camera_rgb(m: Any) -> np.ndarray:
    img = m.data if m.data.ndim == 3 else np.repeat(m.data[..., None], 3, 2)
    return img[..., ::-1] if m.encoding.lower().startswith("bgr") else img


def score(mapper: GaussianMapper, data: dict[str, list[Any]]) -> dict[str, float]:
    """PSNR/SSIM of the final map at the keyframes and at held-out (non-keyframe) frames:

    - ``keyframe_*`` / ``heldout_*``: with the keyframes' exposure (the nearest keyframe's for a
      held-out frame), every non-keyframe frame inside the mapped part of the drive;
    - ``report_*``: as the run report scores it (``docs/report.md``): no exposure, the
      ``heldout_views`` (12) held-out frames :func:`choose_heldout` picks."""
    kf_stamps = {kf.stamp_ns for kf in data["/frontend/keyframe"]}
    last = max(kf.keyframe_id for kf in mapper.keyframes)
    t_end = next(kf.stamp_ns for kf in data["/frontend/keyframe"] if kf.keyframe_id == last)
    odo = {o.stamp_ns: o.T_world_cam for o in data["/frontend/odometry"]}
    kf_psnr, kf_ssim, kr_psnr, kr_ssim = [], [], [], []
    for kf in mapper.keyframes:
        gt = kf.image_f32.numpy()
        r = mapper.render_view(kf.T_world_cam, kf.exposure_ab).color.numpy()
        kf_psnr.append(psnr_db(r, gt))
        kf_ssim.append(ssim(r, gt))
        r = mapper.render_view(kf.T_world_cam).color.numpy()
        kr_psnr.append(psnr_db(r, gt))
        kr_ssim.append(ssim(r, gt))
    # frames after the first keyframe (the map exists) with an odometry pose, not keyframes
    t0 = min(kf_stamps)
    held = [m for m in data["/camera/image"] if m.stamp_ns in odo and m.stamp_ns not in kf_stamps]
    held = [m for m in held if t0 < m.stamp_ns < t_end]  # inside the mapped part of the drive
    mapped = {k.keyframe_id for k in mapper.keyframes}
    kfs = [kf for kf in data["/frontend/keyframe"] if kf.keyframe_id in mapped]
    stamps = np.array([kf.stamp_ns for kf in kfs])
    by_stamp = {kf.stamp_ns: kf.keyframe_id for kf in kfs}
    ho_psnr, ho_ssim = [], []
    for m in held:
        nearest = by_stamp[int(stamps[np.argmin(np.abs(stamps - m.stamp_ns))])]
        ab = next(k.exposure_ab for k in mapper.keyframes if k.keyframe_id == nearest)
        r = mapper.render_view(odo[m.stamp_ns], ab).color.numpy()
        gt = _camera_rgb(m).astype(np.float32) / 255.0
        ho_psnr.append(psnr_db(r, gt))
        ho_ssim.append(ssim(r, gt))
    images = {m.stamp_ns: m for m in data["/camera/image"] if m.stamp_ns in odo}
    posed = sorted(images)
    xyz = np.array([odo[s][:3, 3] for s in posed]).reshape(-1, 3)
    chosen = choose_heldout(posed, sorted(stamps), 12, positions_m=xyz)
    rep_psnr, rep_ssim = [], []
    for s in chosen:
        r = mapper.render_view(odo[int(s)]).color.numpy()
        gt = _camera_rgb(images[int(s)]).astype(np.float32) / 255.0
        rep_psnr.append(psnr_db(r, gt))
        rep_ssim.append(ssim(r, gt))
    nan = float("nan")
    return {
        "keyframe_psnr_db": float(np.mean(kf_psnr)),
        "keyframe_ssim": float(np.mean(kf_ssim)),
        "heldout_psnr_db": float(np.mean(ho_psnr)) if ho_psnr else nan,
        "heldout_ssim": float(np.mean(ho_ssim)) if ho_ssim else nan,
        "heldout_frames": len(ho_psnr),
        "report_keyframe_psnr_db": float(np.mean(kr_psnr)),
        "report_keyframe_ssim": float(np.mean(kr_ssim)),
        "report_heldout_psnr_db": float(np.mean(rep_psnr)) if rep_psnr else nan,
        "report_heldout_ssim": float(np.mean(rep_ssim)) if rep_ssim else nan,
        "report_heldout_frames": len(rep_psnr),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("journal", help="runs/<ts>/journal/journal.log of a pipeline run")
    ap.add_argument("--launch", default=str(REPO_ROOT / "launch" / "demo.yaml"))
    ap.add_argument("--set", action="append", default=[], help="mapper param=JSON value")
    ap.add_argument(
        "--core",
        action="append",
        default=[],
        help="MapperParams field=JSON value (insertion.FIELD for InsertionParams)",
    )
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--max-keyframes", type=int, default=0, help="map only the first n (0: all)")
    ap.add_argument(
        "--behind",
        action="store_true",
        help="every keyframe inserted with no iteration, the owed ones run after (kitti.yaml)",
    )
    ap.add_argument(
        "--save-online", default=None, help="save the online map (before refining) as a checkpoint"
    )
    ap.add_argument(
        "--from-online",
        default=None,
        help="start from such a checkpoint instead of replaying the drive (refinement trials)",
    )
    ap.add_argument("--profile", action="store_true", help="print the cProfile table")
    ap.add_argument("--json", default=None)
    ap.add_argument("--ply", default=None, help="also write the final map here (3DGS PLY)")
    ap.add_argument(
        "--refine-step",
        type=int,
        default=0,
        help="score the map every n refinement iterations (0: only at the end)",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    overrides = {}
    for kv in args.set:
        k, v = kv.split("=", 1)
        overrides[k] = json.loads(v)
    p = mapper_params(args.launch, overrides)
    core = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.core)}
    data = read_journal(Path(args.journal))
    prof = cProfile.Profile() if args.profile else None
    c0 = time.process_time()
    if prof:
        prof.enable()
    if args.from_online:  # the saved online map under this run's parameters
        mapper = load_checkpoint(args.from_online, params=core_params(p, core))
        per_kf = [{"insert_cpu_s": 0.0, "optimize_cpu_s": 0.0} for _ in mapper.keyframes]
    else:
        mapper, per_kf = replay(data, p, args.max_keyframes, core, behind=args.behind)
    if prof:
        prof.disable()
    cpu_total = time.process_time() - c0
    if args.save_online:
        save_checkpoint(mapper, args.save_online)
    refine: dict[str, float] = {}
    if p.final_refine_iters > 0:  # the end of the drive: the node's final refinement
        q0 = score(mapper, data)
        curve = []  # (iterations, report held-out PSNR, SSIM, refinement CPU s so far)
        cpu_refine, done = 0.0, 0
        step = args.refine_step or p.final_refine_iters
        while done < p.final_refine_iters:
            n = min(step, p.final_refine_iters - done)
            c1 = time.process_time()
            chunk = max(p.final_refine_chunk, 1)  # as the node runs it: pruning after each chunk
            for k in range(0, n, chunk):
                mapper.refine(
                    min(chunk, n - k), p.final_refine_downsample, total_iters=p.final_refine_iters
                )
            cpu_refine += time.process_time() - c1
            done += n
            if done < p.final_refine_iters:
                qi = score(mapper, data)
                curve.append([done, qi["report_heldout_psnr_db"], qi["report_heldout_ssim"]])
                curve[-1].append(cpu_refine)
                print(
                    f"refined {done}: report held-out {qi['report_heldout_psnr_db']:.2f} dB, "
                    f"{qi['report_heldout_ssim']:.3f}, {cpu_refine:.1f} s CPU",
                    flush=True,
                )
        refine = {
            "refine_cpu_s": cpu_refine,
            "refine_curve": curve,
            **{f"before_refine_{k}": v for k, v in q0.items()},
        }
        print(f"final refinement: {refine['refine_cpu_s']:.2f} s CPU", flush=True)
    if args.ply:
        export_ply(mapper, args.ply)
    q = score(mapper, data)
    per = [k["insert_cpu_s"] + k["optimize_cpu_s"] for k in per_kf]
    figures = {
        "keyframes": len(per_kf),
        "iterations": int(mapper.iterations),
        "gaussians": len(mapper.map),
        "pruned": int(mapper.n_pruned),
        "mapper_cpu_s_per_keyframe_mean": cpu_total / len(per_kf),
        "mapper_cpu_s_per_keyframe_median": statistics.median(per),
        "insert_cpu_s_per_keyframe_mean": statistics.mean(k["insert_cpu_s"] for k in per_kf),
        "optimize_cpu_s_per_keyframe_mean": statistics.mean(k["optimize_cpu_s"] for k in per_kf),
        **q,
        **refine,
        "params": {k: getattr(p, k) for k in MapperNodeParams.__dataclass_fields__},
    }
    for k, v in figures.items():
        if k not in ("params", "refine_curve"):
            print(f"{k}: {v:.4g}" if isinstance(v, float) else f"{k}: {v}")
    if prof:
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("cumulative").print_stats(35)
        print(s.getvalue())
    if args.json:
        write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
