"""Paper Table II in the live pipeline: the demo drive with the mapper initialised three ways.

The demo drive (``launch/demo.yaml``: player -> frontend -> segmentation + depth prior ->
metrizer -> mapper -> report) runs three times, with the same mapper policy and budget
(``iters_per_keyframe`` after each keyframe); only the depth the mapper receives differs:

- ``mogs``: the metrizer's depth (``mode: full``, MSC + CDR);
- ``prior_global``: the globally aligned prior (metrizer ``mode: no_msc_cdr``);
- ``random``: uniform random depth in [1, 50] m with confidence 0
  (:func:`mogs_node.mapper.insertion.random_depth`, as ``mogs eval map``) on the pixels where the
  metrizer's depth has a value (``same_pixels``: the comparison is about the depth values; where
  no source has depth, the sky, the mapper's far sphere takes the pixel for every init alike),
  published per keyframe by :class:`RandomDepthNode` in place of the metrizer's output (which
  still runs, so that every run costs the same upstream).

**Table II's figures** (``inits.<init>.iters_to_target``, ``gaussians_at_target``): how fast a
map initialised from each depth converges, per keyframe, iteration by iteration: each run keeps
its journal, and :mod:`bench.table2_convergence` replays it through the mapper core (the live
map, byte for byte) and, after each keyframe's insertion, optimises a copy of the map with the
mapper's own loop, scoring the held-out view next to the keyframe after every iteration; the
median over the keyframes of the iterations to the target (20 dB when every init's median gets
there; ``--target-db auto``: else the highest common one), the Gaussians in the map then.
``psnr_at_budget_db`` / ``ssim_at_budget``: the run report's means over its held-out frames at the
end of the drive (``map.heldout_psnr_db`` / ``map.heldout_ssim``, docs/report.md).

The first definition (session 11) stays under ``inits.<init>.fixed_view``: this script listens on
the run's bus, rebuilds the map from ``/mapper/gaussians`` (:class:`MapReplica`) and after every
map update scores candidate held-out frames (every ``--candidate-step``-th frame from
``--candidates-from`` on that is not a keyframe; ground truth from the sim, pose from the
frontend); the fixed view is the earliest candidate every init reaches the target at, and
``iters_to_target`` there the cumulative iteration count at the first update reaching it. It
measured mostly *when* a view ahead of the car entered the map, in steps of
``iters_per_keyframe`` (docs/benchmarks.md ``pipeline-table2``).

Usage::

    python bench/pipeline_table2.py [--frames 60] [--view-frame N] [--json PATH] [--no-docs]
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import sys
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
import zmq

if not __package__:  # run as a script (python bench/pipeline_table2.py): the repo root holds bench/
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench import table2_convergence as convergence  # noqa: E402
from bench.table2_random import RANDOM_TOPIC  # noqa: E402
from mogs_node import msgs
from mogs_node.bus import Subscriber
from mogs_node.commands.launch import parse_overrides
from mogs_node.eval.bench_docs import REPO_ROOT, machine_line, update_markdown_section, write_json
from mogs_node.launch import Launcher, load_launch_file
from mogs_node.mapper.insertion import InsertionParams
from mogs_node.mapper.insertion import _stride_map as stride_map
from mogs_node.mapper.rasterizer import RasterParams
from mogs_node.node import parse_params
from mogs_node.report.node import NOT_ESTIMATED
from mogs_node.report.views import MapReplica, render_map_view, score_view
from mogs_node.sim import SimConfig, make_sequence

INITS = ("mogs", "prior_global", "random")


def launch_dict(
    init: str, frames: int, out: Path, overrides: dict[str, dict[str, Any]] | None = None
) -> dict[str, Any]:
    """The demo launch file, set up for one initialisation, outputs in ``out``; ``overrides``
    (node -> params, ``--set``) apply to every initialisation alike."""
    launch = yaml.safe_load((REPO_ROOT / "launch" / "demo.yaml").read_text())
    launch["name"] = f"table2-{uuid.uuid4().hex[:8]}"
    nodes = {n["name"]: n for n in launch["nodes"]}
    overrides = dict(overrides or {})
    randomizer = overrides.pop("randomizer", {})  # RandomDepthParams (the random run's node)
    for node, params in overrides.items():
        nodes[node].setdefault("params", {}).update(params)
    nodes["player"]["params"]["sim"]["n_frames"] = frames
    nodes["report"]["params"]["out_dir"] = str(out)
    nodes["report"]["params"]["idle_timeout_s"] = 1200.0
    nodes["mapper"]["params"]["ply_path"] = str(out / "map.ply")
    nodes["mapper"]["heartbeat_timeout_s"] = 0.0  # a window round may be slow on loaded cores
    nodes["metrizer"]["params"]["mode"] = "no_msc_cdr" if init == "prior_global" else "full"
    if init == "random":
        nodes["mapper"]["params"]["depth_topic"] = RANDOM_TOPIC
        path = os.pathsep.join(p for p in (str(REPO_ROOT), os.environ.get("PYTHONPATH")) if p)
        launch["nodes"].append(
            {
                "name": "randomizer",
                "class": "bench.table2_random:RandomDepthNode",
                "env": {"PYTHONPATH": path},  # bench/ is importable from the repository root
                "params": dict(randomizer),
            }
        )
        nodes["player"]["params"]["wait_for_nodes"].append("randomizer")
    return launch


@dataclass
class HeldOutViews:
    """Follows the run on the bus and scores the map at candidate held-out frames.

    Candidates: frame indices ``candidates`` that turn out not to be keyframes. Their
    ground-truth images come from the sim itself (``gt_images``, index -> RGB: the same
    deterministic renderer the player uses), not from the best-effort ``/camera/image`` topic, so a
    dropped message cannot change which view is scored. Their poses are the frontend's odometry
    (the map's frame, as the run report's held-out views). After every map update each candidate
    whose pose is known and which is known not to be a keyframe is rendered and scored.
    """

    gt_images: dict[int, np.ndarray]  # frame index -> RGB uint8
    raster: RasterParams = field(default_factory=RasterParams)  # rasterizer settings of the view
    replica: MapReplica = field(default_factory=MapReplica)
    frame_stamps: list[int] = field(default_factory=list)  # every frame, from its odometry
    poses: dict[int, np.ndarray] = field(default_factory=dict)  # stamp -> T_world_cam
    kf_stamps: set[int] = field(default_factory=set)
    camera: tuple[np.ndarray, int, int] | None = None
    iterations: int = 0
    t0: float | None = None
    curves: dict[int, list[dict[str, float]]] = field(default_factory=dict)  # index -> scores
    keyframe_indices: set[int] = field(default_factory=set)  # candidates that were keyframes
    inserted: int = 0  # Gaussians inserted / pruned over the run (/mapper/stats extra)
    pruned: int = 0
    depth_stats: list[dict[str, float]] = field(default_factory=list)  # per depth map received

    def on(self, topic: str, m: Any, now: float) -> None:
        if topic == "/frontend/odometry":  # reliable: one per frame, estimated or not
            self.t0 = now if self.t0 is None else self.t0
            self.frame_stamps.append(m.stamp_ns)
            if m.status not in NOT_ESTIMATED:
                self.poses[m.stamp_ns] = np.array(m.T_world_cam)
        elif topic == "/frontend/keyframe":
            self.kf_stamps.add(m.stamp_ns)
            if self.camera is None:
                self.camera = (np.array(m.K), m.image.shape[1], m.image.shape[0])
        elif topic == "/mapper/stats":
            self.iterations = int(m.iterations)
            if m.extra.get("final"):
                if self.curves:  # the refined map's update came just before its stats
                    for c in self.curves.values():
                        if c:
                            c[-1]["iterations"] = self.iterations
            else:
                self.inserted += int(m.extra.get("inserted", 0))
            self.pruned = int(m.extra.get("pruned", self.pruned))  # the mapper's running total
        elif topic == "/mapper/gaussians":
            self.replica.apply_update(m)
            self._evaluate(now)
        elif isinstance(m, msgs.DepthMap):  # the depth the mapper gets
            self.depth_stats.append(depth_statistics(m.depth, m.confidence))

    def _scoreable(self, index: int) -> int | None:
        """The stamp of candidate ``index`` once it has a pose and is known not to be a keyframe
        (two later frames have a pose: its keyframe decision has been published)."""
        frames = sorted(self.frame_stamps)
        if index >= len(frames) or self.camera is None:
            return None
        s = frames[index]
        if s in self.kf_stamps:
            self.keyframe_indices.add(index)
            return None
        if s not in self.poses or sum(t > s for t in self.poses) < 2:
            return None
        return s

    def _evaluate(self, now: float) -> None:
        for index, gt in self.gt_images.items():
            s = self._scoreable(index)
            if s is None:
                continue
            K, W, H = self.camera
            rgb, _, _ = render_map_view(
                self.replica.arrays, self.poses[s], K, W, H, raster=self.raster
            )
            psnr, ssim = score_view(gt, rgb)
            self.curves.setdefault(index, []).append(
                {
                    "iterations": self.iterations,
                    "wall_s": round(now - (now if self.t0 is None else self.t0), 2),
                    "n_gaussians": len(self.replica),
                    "fixed_view_psnr_db": psnr,
                    "fixed_view_ssim": ssim,
                }
            )

    def view_figures(self, index: int | None, target_db: float) -> dict[str, Any]:
        """Table II's figures at held-out frame ``index`` (None: no view)."""
        curve = self.curves.get(index, []) if index is not None else []
        hit = next((c for c in curve if c["fixed_view_psnr_db"] >= target_db), None)
        last = curve[-1] if curve else {}
        return {
            "view_frame": index,
            "iters_to_target": None if hit is None else hit["iterations"],
            "wall_s_to_target": None if hit is None else hit["wall_s"],
            "gaussians_at_target": None if hit is None else hit["n_gaussians"],
            "fixed_view_psnr_at_budget_db": last.get("fixed_view_psnr_db"),
            "iterations_budget": self.iterations,
            "gaussians_at_budget": len(self.replica),
            "gaussians_inserted": self.inserted,
            "gaussians_pruned": self.pruned,
            "curve": {k: [c[k] for c in curve] for k in (last or {})},
        }


def depth_statistics(
    depth_m: np.ndarray, confidence: np.ndarray, params: InsertionParams | None = None
) -> dict[str, float]:
    """What the insertion policy makes of one depth map (``depth_m``/``confidence`` [H, W]):
    the fraction of pixels with depth, of those the fraction at or above the coarse-stride
    confidence, their median depth, and ``gaussians_per_px``: Gaussians per pixel that the policy
    samples where the map explains nothing (1 / stride^2 over the pixels with depth; stride from
    :func:`mogs_node.mapper.insertion.stride_map`, the same for every initialisation)."""
    p = params or InsertionParams()
    d = np.asarray(depth_m, np.float32)
    c = np.asarray(confidence, np.float32)
    ok = np.isfinite(d) & (d >= p.min_depth_m)
    if not ok.any():
        return {"valid": 0.0, "confident": 0.0, "median_depth_m": 0.0, "gaussians_per_px": 0.0}
    stride = stride_map(np.where(ok, d, 0.0), c, p)[ok].astype(np.float64)
    return {
        "valid": round(float(ok.mean()), 4),
        "confident": round(float((c[ok] >= p.coarse_conf).mean()), 4),
        "median_depth_m": round(float(np.median(d[ok])), 3),
        "gaussians_per_px": round(float(np.mean(1.0 / stride**2)), 6),
    }


def reached(curves: dict[int, list[dict[str, float]]], target_db: float) -> set[int]:
    """Candidate frames whose held-out view reaches ``target_db`` at some map update."""
    return {i for i, c in curves.items() if any(x["fixed_view_psnr_db"] >= target_db for x in c)}


def choose_view(views: dict[str, HeldOutViews], target_db: float) -> int | None:
    """The fixed held-out view: the earliest candidate frame that every initialisation's map
    reaches ``target_db`` at (the same rule for all: none is favoured; a view no run reaches
    gives no ratio). None when there is no such frame. A run that scored no candidate at all
    (e.g. an older run merged in) has no say."""
    scored = [reached(v.curves, target_db) for v in views.values() if v.curves]
    common = set.intersection(*scored) if scored else set()
    return min(common) if common else None


def common_target(
    views: dict[str, HeldOutViews], cap_db: float, step_db: float = 0.5, floor_db: float = 10.0
) -> float | None:
    """``--target-db auto``: the highest of ``cap_db``, ``cap_db - step_db``, ... (down to
    ``floor_db``) that some candidate view reaches under every initialisation within the budget,
    so that the fixed view and the ratios are defined (issue 17: random depth reached 20 dB at no
    candidate). The same rule for all; None when not even ``floor_db`` is common."""
    t = cap_db
    while t >= floor_db:
        if choose_view(views, t) is not None:
            return t
        t = round(t - step_db, 6)
    return None


def sim_images(
    frames: int, indices: list[int], sim_set: dict[str, Any] | None = None
) -> dict[int, np.ndarray]:
    """Ground-truth RGB of the demo drive's frames ``indices`` (the player's sim, re-rendered;
    ``sim_set``: a ``--set player.sim=...`` override, e.g. another seed)."""
    demo = yaml.safe_load((REPO_ROOT / "launch" / "demo.yaml").read_text())
    player = next(n for n in demo["nodes"] if n["name"] == "player")
    sim = {**player["params"]["sim"], **(sim_set or {}), "n_frames": frames}
    seq = make_sequence(parse_params(SimConfig, sim, where="sim"))
    return {i: seq.render(i).rgb for i in indices}


TOPICS = ("/frontend/odometry", "/frontend/keyframe", "/mapper/stats")


def run_init(
    init: str, args: argparse.Namespace, root: Path, gt_images: dict[int, np.ndarray]
) -> tuple[dict[str, Any], HeldOutViews]:
    """One run of the demo drive with initialisation ``init``: its run-level figures and the
    scores of its candidate held-out views."""
    out = root / init
    out.mkdir(parents=True, exist_ok=True)
    path = out / "launch.yaml"
    path.write_text(yaml.safe_dump(launch_dict(init, args.frames, out, args.overrides)))
    launch = load_launch_file(path)
    ctx = zmq.Context()
    sub = Subscriber(launch.bus, context=ctx)
    depth_topic = RANDOM_TOPIC if init == "random" else "/metrizer/depth"
    for t in (*TOPICS, "/mapper/gaussians", depth_topic):
        sub.subscribe(t, reliable=True)
    views = HeldOutViews(gt_images)
    log = open(out / "launch.log", "w")  # noqa: SIM115 (the journal stays: it is replayed)
    launcher = Launcher(launch, out=log, grace_s=30.0, keep_journal=True)
    runner = threading.Thread(
        target=launcher.run, kwargs={"install_signal_handlers": False, "timeout_s": args.timeout}
    )
    t_start = time.monotonic()
    # a receiving thread stamps each message on arrival; scoring the views (renders) runs here
    # and may lag behind on a loaded machine without shifting the wall times it records
    inbox: queue.Queue[tuple[Any, float] | None] = queue.Queue()

    def receive() -> None:
        while runner.is_alive():
            env = sub.receive(timeout_ms=100)
            if env is not None:
                inbox.put((env, time.monotonic()))
        while (env := sub.receive(timeout_ms=200)) is not None:  # what is still queued
            inbox.put((env, time.monotonic()))
        inbox.put(None)

    runner.start()
    receiver = threading.Thread(target=receive, daemon=True)
    receiver.start()
    while (item := inbox.get()) is not None:
        views.on(item[0].topic, item[0].msg, item[1])
    runner.join()
    receiver.join()
    # what the bench itself missed (a slow consumer): the views depend on every map update
    bus_stats = {t: st.as_dict() for t, st in sub.stats.items()}
    sub.close()
    ctx.term()
    fig: dict[str, Any] = {"wall_s": round(time.monotonic() - t_start, 1)}
    fig["bench_missed"] = {
        t: {k: v for k, v in st.items() if k in ("lost", "dropped", "shm_missed") and v}
        for t, st in bus_stats.items()
    }
    fig["frames_with_odometry"] = len(views.frame_stamps)
    # the depth the mapper got, as the insertion policy sees it: medians over the keyframes
    fig["depth_to_mapper"] = {
        k: round(float(np.median([d[k] for d in views.depth_stats])), 4)
        for k in (views.depth_stats[0] if views.depth_stats else {})
    }
    summary = out / "summary.json"
    m = json.loads(summary.read_text()).get("map", {}) if summary.exists() else {}
    fig["psnr_at_budget_db"] = m.get("heldout_psnr_db")
    fig["ssim_at_budget"] = m.get("heldout_ssim")
    fig["heldout_frames"] = m.get("heldout_frames", 0)
    fig["run_dir"] = str(out)
    return fig, views


def ratios(inits: dict[str, Any]) -> dict[str, float | None]:
    """MOGS against random (iterations and Gaussians at the target) and PSNR against the prior."""

    def div(a: float | None, b: float | None) -> float | None:
        return None if a is None or b in (None, 0) else round(a / b, 3)

    mo, pg, ra = (inits.get(k, {}) for k in INITS)
    return {
        "iters_to_target_mogs_over_random": div(
            mo.get("iters_to_target"), ra.get("iters_to_target")
        ),
        "gaussians_at_target_mogs_over_random": div(
            mo.get("gaussians_at_target"), ra.get("gaussians_at_target")
        ),
        "psnr_at_budget_mogs_minus_prior_global_db": None
        if mo.get("psnr_at_budget_db") is None or pg.get("psnr_at_budget_db") is None
        else round(mo["psnr_at_budget_db"] - pg["psnr_at_budget_db"], 3),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=60, help="frames of the synthetic drive")
    ap.add_argument(
        "--view-frame", type=int, default=None, help="fixed held-out frame (default: chosen)"
    )
    ap.add_argument(
        "--candidates-from",
        type=int,
        default=40,
        help="first candidate frame (the demo drives off at frame 20: views in its first 2 s of "
        "driving are near-copies of the static start's keyframes)",
    )
    ap.add_argument("--candidate-step", type=int, default=2, help="frames between candidates")
    ap.add_argument(
        "--target-db",
        default="20",
        help="dB, or auto: the highest of 20, 19.5, ... that a candidate reaches under every init",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NODE.PARAM=VALUE",
        help="for every init alike, e.g. mapper.final_refine_iters=0 (the budget: the drive)",
    )
    ap.add_argument(
        "--inits", default=",".join(INITS), help="comma-separated subset of " + ", ".join(INITS)
    )
    ap.add_argument("--timeout", type=float, default=2400.0, help="per run")
    ap.add_argument("--json", default=None)
    ap.add_argument("--no-docs", action="store_true")
    ap.add_argument("--notes", default=None, metavar="FILE", help="text for the docs section")
    ap.add_argument(
        "--merge",
        nargs="+",
        default=None,
        metavar="JSON",
        help="no new runs: the runs in these JSON files (e.g. one init each, run side by side)",
    )
    ap.add_argument(
        "--docs-from",
        default=None,
        metavar="JSON",
        help="write the table and plot from a finished run's JSON (no new runs)",
    )
    args = ap.parse_args(argv)
    args.auto_target = args.target_db == "auto"
    args.target_db = 20.0 if args.auto_target else float(args.target_db)
    args.overrides = parse_overrides(args.set)
    if args.docs_from:
        res = json.loads(Path(args.docs_from).read_text())
        write_docs(args, res, res["command"])
        return 0
    if args.merge:
        runs, ipk = runs_from_json(args.merge)
        cmd = "python bench/pipeline_table2.py " + " ".join(
            argv if argv is not None else sys.argv[1:]
        )
        res = assemble(runs, args, cmd.strip(), ipk)
        convs = {}
        for path in args.merge:
            convs.update(
                {
                    k: r["convergence"]
                    for k, r in json.loads(Path(path).read_text())["inits"].items()
                }
            )
        convergence.apply(res, convs, args.auto_target)
        write_json(args.json, res)
        if not args.no_docs:
            write_docs(args, res, res["command"])
        return 0
    inits = [k.strip() for k in args.inits.split(",") if k.strip()]
    if not set(inits) <= set(INITS) or not 0 <= args.candidates_from < args.frames:
        ap.error(f"--inits: a subset of {INITS}; --candidates-from: in [0, --frames)")
    if args.view_frame is not None and not 0 <= args.view_frame < args.frames:
        ap.error("--view-frame: in [0, --frames)")
    candidates = list(range(args.candidates_from, args.frames, args.candidate_step))
    if args.view_frame is not None and args.view_frame not in candidates:
        candidates.append(args.view_frame)
    gt_images = sim_images(args.frames, candidates, args.overrides.get("player", {}).get("sim"))
    root = Path(tempfile.mkdtemp(prefix="mogs-bench-table2-"))
    demo = yaml.safe_load((REPO_ROOT / "launch" / "demo.yaml").read_text())
    mapper = next(n for n in demo["nodes"] if n["name"] == "mapper")
    runs: dict[str, tuple[dict[str, Any], HeldOutViews]] = {}
    for init in inits:
        print(f"[table2] {init} ...", flush=True)
        runs[init] = run_init(init, args, root, gt_images)
        r, v = runs[init]
        print(
            f"[table2] {init}: held-out PSNR at budget {r['psnr_at_budget_db']} "
            f"(SSIM {r['ssim_at_budget']}), candidates reaching the target "
            f"{sorted(reached(v.curves, args.target_db))} of {sorted(v.curves)}, {r['wall_s']} s",
            flush=True,
        )
    cmd = "python bench/pipeline_table2.py " + " ".join(argv if argv is not None else sys.argv[1:])
    res = assemble(runs, args, cmd.strip(), mapper["params"].get("iters_per_keyframe"))
    convs = {}
    for init, (r, _) in runs.items():  # the per-keyframe convergence: the run's journal replayed
        run = Path(r["run_dir"])
        convs[init] = convergence.measure(
            run / "journal" / "journal.log", run / "launch.yaml", init
        )
    convergence.apply(res, convs, args.auto_target)
    write_json(args.json, res)
    if not args.no_docs:
        write_docs(args, res, res["command"])
    return 0


def assemble(
    runs: dict[str, tuple[dict[str, Any], HeldOutViews]],
    args: argparse.Namespace,
    cmd: str,
    iters_per_keyframe: int | None,
) -> dict[str, Any]:
    """The results of the runs of every init: the fixed view (chosen across them), each init's
    figures there and at the budget, the ratios."""
    views = {k: v for k, (_, v) in runs.items()}
    if getattr(args, "auto_target", False):
        t = common_target(views, args.target_db)
        args.target_db = t if t is not None else args.target_db
        print(f"[table2] target (auto): {args.target_db:g} dB", flush=True)
    view = args.view_frame if args.view_frame is not None else choose_view(views, args.target_db)
    scored = set.union(*(set(v.curves) for v in views.values())) if views else set()
    res: dict[str, Any] = {
        "target_psnr_db": args.target_db,
        "frames": args.frames,
        "view_frame": view,
        "candidates_scored": len(scored),
        "iters_per_keyframe": iters_per_keyframe,
        "command": cmd,
        "args": {
            k: getattr(args, k)
            for k in ("frames", "view_frame", "candidates_from", "candidate_step", "target_db")
        },
        "target_rule": "auto" if getattr(args, "auto_target", False) else "given",
        "overrides": getattr(args, "overrides", {}),
        "inits": {},
    }
    for init, (r, v) in runs.items():
        res["inits"][init] = {
            **v.view_figures(view, args.target_db),
            **r,
            "candidates_reached": sorted(reached(v.curves, args.target_db)),
            # every candidate's scores after each update (runs of one init each can be merged)
            "candidate_curves": {
                str(i): {k: [c[k] for c in v.curves[i]] for k in v.curves[i][0]}
                for i in sorted(v.curves)
            },
        }
    res["ratios"] = ratios(res["inits"])
    for init, r in res["inits"].items():
        print(
            f"[table2] {init} at frame {view}: iterations to target {r['iters_to_target']}, "
            f"Gaussians at target {r['gaussians_at_target']}"
        )
    for k, v in res["ratios"].items():
        print(f"{k:45s} {v}")
    return res


AT_BUDGET = ("iterations_budget", "gaussians_at_budget", "gaussians_inserted", "gaussians_pruned")


def runs_from_json(paths: list[str]) -> tuple[dict[str, tuple[dict[str, Any], HeldOutViews]], int]:
    """The runs saved in the JSON of earlier invocations (one init each, say, run side by side):
    their run-level figures and their candidates' curves, and the iterations per keyframe."""
    runs: dict[str, tuple[dict[str, Any], HeldOutViews]] = {}
    ipk = None
    for path in paths:
        saved = json.loads(Path(path).read_text())
        ipk = saved.get("iters_per_keyframe", ipk)
        for init, r in saved["inits"].items():
            v = HeldOutViews({})
            v.curves = {
                int(i): [dict(zip(c, vals, strict=True)) for vals in zip(*c.values(), strict=True)]
                for i, c in r["candidate_curves"].items()
            }
            v.iterations, v.inserted, v.pruned = (
                r["iterations_budget"],
                r["gaussians_inserted"],
                r["gaussians_pruned"],
            )
            keep = set(r) - set(v.view_figures(None, 0.0)) - {"candidates_reached"}
            runs[init] = ({k: r[k] for k in keep} | {k: r[k] for k in AT_BUDGET}, v)
    return runs, ipk


def write_docs(args: argparse.Namespace, res: dict[str, Any], cmd: str) -> None:
    """The plot and the ``pipeline-table2`` section of docs/benchmarks.md."""
    convergence.plot(res, REPO_ROOT / "docs" / "pipeline_table2.png")
    notes = Path(args.notes).read_text() if args.notes else ""
    section = convergence.markdown(cmd.strip(), res, machine_line(), notes)
    update_markdown_section("pipeline-table2", section)


if __name__ == "__main__":
    sys.exit(main())
