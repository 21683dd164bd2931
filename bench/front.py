"""Run time against error (issue 27): the whole pipeline at a grid of settings on the demo drive.

Every configuration runs ``launch/demo.yaml`` as real processes (the launcher of ``mogs
launch``; player in ``fast`` mode, so the drive is paced by the slowest node) with a preset
(``mogs_node/presets.py``) or one knob moved from ``balanced``. For each configuration:

- cost: CPU seconds per frame over every process of the run (broker and nodes), from the
  operating system's own accounting (psutil: user + system time of each process, sampled every
  0.25 s), from the first image to the final map; real-time factor (sequence duration / that
  span); peak RSS summed over the processes;
- errors, from the run's own report (``summary.json``): depth AbsRel and coverage of the metrized
  depth, ATE (SE(3) RMSE) as % of the path, held-out PSNR and SSIM of the final map;
- work that follows the scene: CPU per frame while the ground truth stands still against while
  it moves (``standstill_over_moving_cpu``), per node.

It writes JSON (``--json``, rewritten after every configuration: a stopped grid resumes where it
stopped, configurations already measured with the same settings are kept), the picture
(``--png``; cost on x, one panel per error, the non-dominated front, the presets and the peers'
published figures) and ``docs/benchmarks.md`` section ``front``.

Usage::

    python bench/front.py --jobs 2                         # the grid: what docs/front.json lacks
    python bench/front.py --quick --json /tmp/front.json   # short drive, the three presets
    python bench/front.py --fresh --jobs 2                 # all of it again (a stage changed)

``--quick`` runs the three presets on the first 40 frames (2 s standing, 2 s driving), two at a
time (``--jobs``): within 10 minutes on an idle 2-core machine.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from mogs_node import msgs
from mogs_node.bus import Subscriber
from mogs_node.eval.bench_docs import REPO_ROOT, machine_line, update_markdown_section, write_json
from mogs_node.launch import Launcher, load_launch_file, run_dir_overrides
from mogs_node.presets import FIGURES_PATH, PRESETS, balanced_value, deep_merge, role_of

if not __package__:  # run as a script (python bench/front.py): the repo root holds bench/
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.front_cpu import CpuSampler, cpu_between  # noqa: E402
from bench.front_plot import ERRORS, front_markdown, plot_front  # noqa: E402

# (role.param[.sub], values moved to): each alone from balanced (= launch/demo.yaml's own values,
# in brackets), the cheaper value first. The costly knobs of issue 27.
KNOBS: tuple[tuple[str, tuple[Any, ...]], ...] = (
    ("frontend.points.max_tracks", (500, 1500)),  # sparse points per keyframe [900]
    ("metrizer.cdr.irls_iters", (1, 6)),  # CDR IRLS iterations [3]
    ("metrizer.consensus.max_iters", (64, 384)),  # MSC hypotheses per model [192]
    ("metrizer.metrizer.sample_stride", (12, 3)),  # CDR data terms: every n-th pixel [6]
    ("prior.flow.dis_preset", ("fast",)),  # the prior's flow [medium]
    ("segmentation.graph.scale", (0.5,)),  # segmentation resolution [1.0]
    ("mapper.iters_per_keyframe", (4, 20)),  # [6]
    ("mapper.final_refine_iters", (0, 300)),  # after the drive, full resolution [800]
    ("mapper.train_downsample", (4, 1)),  # mapping image scale [2]
    ("mapper.window_size", (4, 10)),  # [6]
)
# the measured points, each with its commit: `python bench/front.py` measures what is missing
DEFAULT_JSON = REPO_ROOT / "docs" / "front.json"
QUICK_FRAMES = 40  # --quick: the 2 s standing start and 2 s of driving
STANDSTILL_SPEED_M_S = 0.05  # ground-truth speed below this: standing still
SAMPLE_PERIOD_S = 0.25


@dataclass(frozen=True)
class Config:
    name: str
    preset: str = "balanced"
    knob: tuple[str, Any] | None = None  # ("role.param[.sub]", value)

    def key(self) -> dict[str, Any]:
        """What the point measured: the preset, its table of overrides (a preset redefined is
        measured again) and the knob moved."""
        return {
            "preset": self.preset,
            "preset_table": PRESETS[self.preset],
            "knob": list(self.knob) if self.knob else None,
        }


def grid(quick: bool) -> list[Config]:
    """The presets first (a grid stopped early still places them), then each knob alone."""
    if quick:  # the longest first: run two at a time, the wall time is about quality's
        return [Config(p, preset=p) for p in ("quality", "balanced", "fast")]
    configs = [Config(p, preset=p) for p in ("balanced", "fast", "quality")]
    for i in range(max(len(v) for _, v in KNOBS)):  # every knob's first value (the cheaper) first
        configs += [Config(f"{p}={v[i]}", knob=(p, v[i])) for p, v in KNOBS if i < len(v)]
    return configs


def knob_overrides(launch, path: str, value: Any) -> dict[str, dict]:
    """``--set``-style overrides (node name -> top-level params) that move one knob: nested
    groups merged into the node's own values, every node of the role."""
    role, *keys = path.split(".")
    nested: Any = value
    for k in reversed(keys[1:]):
        nested = {k: nested}
    out: dict[str, dict] = {}
    for spec in launch.nodes:
        if role_of(spec.cls) == role:
            top = keys[0]
            if isinstance(nested, dict):
                merged = deep_merge({top: spec.params.get(top) or {}}, {top: nested})[top]
            else:
                merged = nested
            out[spec.name] = {top: merged}
    if not out:
        raise ValueError(f"knob {path}: no {role} node in the launch file")
    return out


def run_config(
    launch_path: Path, cfg: Config, frames: int, out: Path, timeout_s: float
) -> dict[str, Any]:
    """One configuration through the real pipeline: its cost and errors."""
    base = load_launch_file(launch_path, preset=cfg.preset)
    sim = dict(next(n for n in base.nodes if n.name == "player").params.get("sim", {}))
    sim["n_frames"] = frames
    frame_rate_hz = float(sim.get("frame_rate_hz", 10.0))
    overrides = run_dir_overrides(base, out, resume=False)
    overrides.setdefault("player", {})["sim"] = sim
    # the scorer renders only what the errors need: the held-out views (the same 12 as the
    # demo's report), one keyframe view, no pictures (minutes of wall time on a loaded machine
    # demo), and it waits for the final map as long as the configuration may take: the
    # refinement after the drive sends nothing for many minutes on a loaded machine
    overrides.setdefault("report", {}).update(
        max_keyframe_views=1, save_renders=False, save_snapshots=False, idle_timeout_s=timeout_s
    )
    if cfg.knob is not None:
        for node, params in knob_overrides(base, *cfg.knob).items():
            overrides.setdefault(node, {}).update(params)
    launch = load_launch_file(launch_path, overrides=overrides, preset=cfg.preset)

    ctx = zmq.Context()
    sub = Subscriber(launch.bus, context=ctx)
    for topic in ("/camera/image", "/groundtruth/pose", "/mapper/stats"):
        sub.subscribe(topic)
    log = open(out / "launch.log", "w")  # noqa: SIM115 - closed below
    launcher = Launcher(launch, out=log)
    result: dict[str, int] = {}
    runner = threading.Thread(
        target=lambda: result.setdefault(
            "rc", launcher.run(install_signal_handlers=False, timeout_s=timeout_s)
        )
    )
    sampler = CpuSampler(launcher)
    t_start = time.monotonic()
    runner.start()
    image_t: dict[int, float] = {}  # stamp -> arrival
    gt_pos: dict[int, np.ndarray] = {}  # stamp -> ground-truth camera position
    stats_t: list[float] = []
    inserted: list[int] = []  # Gaussians each mapped keyframe inserted (-1: not said)
    final_t: float | None = None
    last_sample = 0.0
    for now, env in sub.arrivals(runner.is_alive, timeout_ms=50):
        if env is not None:
            m = env.msg
            if env.topic == "/camera/image":
                image_t.setdefault(m.stamp_ns, now)
            elif env.topic == "/groundtruth/pose":
                gt_pos[m.stamp_ns] = np.asarray(m.T_world_cam)[:3, 3]
            elif isinstance(m, msgs.MapStats):
                if m.extra.get("final"):
                    final_t = now
                else:
                    stats_t.append(now)
                    inserted.append(int(m.extra.get("inserted", -1)))
        if now - last_sample >= SAMPLE_PERIOD_S:
            last_sample = now
            sampler.sample(now)
    runner.join()
    sampler.sample(time.monotonic())
    sub.close()
    ctx.term()
    log.close()
    wall_s = time.monotonic() - t_start
    summary = json.loads((out / "summary.json").read_text())
    point = {"name": cfg.name, **cfg.key(), "launch_rc": result.get("rc"), "wall_s": wall_s}
    if cfg.knob is not None:
        point["knob_balanced"] = balanced_value(base, cfg.knob[0])
    point.update(cost_figures(sampler, image_t, stats_t, final_t, frame_rate_hz))
    point.update(scene_figures(sampler, image_t, gt_pos, stats_t))
    point.update(error_figures(summary))
    point["inserted_per_keyframe"] = inserted
    # False: the report scored the map before the mapper's final one (a run cut short)
    point["final_map"] = final_t is not None
    # a respawned node (e.g. killed for memory) replays its inputs: CPU and errors not comparable
    point["respawns"] = sum(c.respawns for c in launcher.children)
    return point


def cost_figures(
    sampler: CpuSampler,
    image_t: dict[int, float],
    stats_t: list[float],
    final_t: float | None,
    frame_rate_hz: float,
) -> dict[str, Any]:
    """CPU per frame (all processes, first image -> final map), real-time factor, peak RSS."""
    if not image_t or not sampler.samples:
        return {"frames": len(image_t), "cpu_s_per_frame": float("nan")}
    first = min(image_t.values())
    last = max([*stats_t, final_t or 0.0, max(image_t.values())])
    by_node = cpu_between(sampler, first, last)
    span = max(last - first, 1e-9)
    return {
        "frames": len(image_t),
        "cpu_s_per_frame": round(sum(by_node.values()) / len(image_t), 4),
        "cpu_s_per_frame_by_node": {n: round(c / len(image_t), 4) for n, c in by_node.items()},
        "real_time_factor": round((len(image_t) / frame_rate_hz) / span, 4),
        "rss_peak_mib": round(sum(sampler.rss_mib.values()), 1),
        "rss_peak_mib_by_node": {n: round(v, 1) for n, v in sampler.rss_mib.items()},
    }


def scene_figures(
    sampler: CpuSampler,
    image_t: dict[int, float],
    gt_pos: dict[int, np.ndarray],
    stats_t: list[float],
) -> dict[str, Any]:
    """CPU per frame standing still vs moving (ground-truth speed at each image): standstill
    from the first image to the first moving one, moving from there to the last keyframe mapped
    (the refinement after the drive belongs to neither)."""
    stamps = sorted(s for s in image_t if s in gt_pos)
    if len(stamps) < 3:
        return {"standstill_over_moving_cpu": float("nan")}
    speeds = [0.0]
    for a, b in zip(stamps, stamps[1:], strict=False):
        speeds.append(float(np.linalg.norm(gt_pos[b] - gt_pos[a])) / ((b - a) * 1e-9))
    moving = [s for s, v in zip(stamps, speeds, strict=True) if v >= STANDSTILL_SPEED_M_S]
    if not moving or moving[0] == stamps[0]:
        return {"standstill_over_moving_cpu": float("nan")}
    n_still = sum(1 for s in stamps if s < moving[0])
    t0, t1 = image_t[stamps[0]], image_t[moving[0]]
    t2 = max([*stats_t, image_t[stamps[-1]]])
    still = cpu_between(sampler, t0, t1)
    move = cpu_between(sampler, t1, t2)
    n_move = len(stamps) - n_still
    still_pf = sum(still.values()) / n_still
    move_pf = sum(move.values()) / max(n_move, 1)
    return {
        "standstill_frames": n_still,
        "moving_frames": n_move,
        "standstill_cpu_s_per_frame": round(still_pf, 4),
        "moving_cpu_s_per_frame": round(move_pf, 4),
        "standstill_over_moving_cpu": round(still_pf / move_pf, 4) if move_pf > 0 else None,
        "standstill_cpu_s_per_frame_by_node": {n: round(c / n_still, 4) for n, c in still.items()},
        "moving_cpu_s_per_frame_by_node": {
            n: round(c / max(n_move, 1), 4) for n, c in move.items()
        },
    }


def error_figures(summary: dict[str, Any]) -> dict[str, Any]:
    """The errors of a run from its report's summary.json."""
    depth, traj, mp = (
        summary.get("depth", {}),
        summary.get("trajectory", {}),
        summary.get("map", {}),
    )
    path_m = traj.get("path_length_m") or float("nan")
    return {
        "keyframes": summary.get("keyframes"),
        "keyframes_mapped": summary.get("keyframes_mapped"),
        "depth_absrel": depth.get("absrel", float("nan")),
        "depth_coverage": depth.get("coverage", float("nan")),
        "ate_pct": 100.0 * traj.get("ate_se3_rmse_m", float("nan")) / path_m,
        "heldout_psnr_db": mp.get("heldout_psnr_db", float("nan")),
        "heldout_ssim": mp.get("heldout_ssim", float("nan")),
        "n_gaussians": mp.get("gaussians"),
    }


def dominates(q: dict[str, Any], p: dict[str, Any]) -> bool:
    """``q`` costs no more than ``p``, is no worse on any error and better on cost or one."""
    pairs = [(q["cpu_s_per_frame"], p["cpu_s_per_frame"], True)]
    pairs += [(q[e], p[e], low) for e, low in ERRORS.items()]
    if any(not np.isfinite(a) or not np.isfinite(b) for a, b, _ in pairs):
        return False
    no_worse = all((a <= b) if low else (a >= b) for a, b, low in pairs)
    better = any((a < b) if low else (a > b) for a, b, low in pairs)
    return no_worse and better


def analyse(points: list[dict[str, Any]]) -> dict[str, Any]:
    """The front (non-dominated points), the preset checks and the knob table."""
    by_name = {p["name"]: p for p in points}
    front = [p["name"] for p in points if not any(dominates(q, p) for q in points)]
    out: dict[str, Any] = {"front": front, "presets": {}, "preset_checks": {}}
    for name in PRESETS:
        if name in by_name:
            out["presets"][name] = name
            out["preset_checks"][f"{name}_dominated_by"] = [
                q["name"] for q in points if dominates(q, by_name[name])
            ]
    if {"fast", "quality"} <= by_name.keys():
        fast, qual = by_name["fast"], by_name["quality"]
        out["preset_checks"]["fast_over_quality_cpu"] = round(
            fast["cpu_s_per_frame"] / qual["cpu_s_per_frame"], 3
        )
        others = [by_name[n] for n in PRESETS if n in by_name and n != "quality"]
        # strictly: a tie with balanced is not "best"
        out["preset_checks"]["quality_best_absrel"] = qual["depth_absrel"] < min(
            p["depth_absrel"] for p in others
        )
        out["preset_checks"]["quality_best_heldout_psnr"] = qual["heldout_psnr_db"] > max(
            p["heldout_psnr_db"] for p in others
        )
    if "balanced" in by_name:
        b = by_name["balanced"]
        out["standstill_over_moving_cpu"] = b.get("standstill_over_moving_cpu")
        out["standstill_over_moving_cpu_without_source_and_report"] = pipeline_only_ratio(b)
        out["knobs"] = [
            {
                "knob": p["knob"][0],
                "balanced": p.get("knob_balanced"),
                "value": p["knob"][1],
                "d_cpu_s_per_frame": p["cpu_s_per_frame"] - b["cpu_s_per_frame"],
                **{f"d_{e}": p[e] - b[e] for e in ERRORS},
            }
            for p in points
            if p.get("knob")
        ]
    return out


def pipeline_only_ratio(point: dict[str, Any]) -> float | None:
    """Standing still over moving CPU per frame without the player (the sensor: a sim renderer
    or a file reader here, nothing on a car) and the report (the scorer)."""
    still = point.get("standstill_cpu_s_per_frame_by_node") or {}
    moving = point.get("moving_cpu_s_per_frame_by_node") or {}
    skip = {"player", "report"}
    m = sum(v for n, v in moving.items() if n not in skip)
    return round(sum(v for n, v in still.items() if n not in skip) / m, 4) if m > 0 else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--launch", default=str(REPO_ROOT / "launch" / "demo.yaml"))
    ap.add_argument(
        "--json",
        default=None,
        help=f"results, read back to resume a grid (default {DEFAULT_JSON.relative_to(REPO_ROOT)};"
        " --quick: none)",
    )
    ap.add_argument("--quick", action="store_true", help="short drive, the three presets")
    ap.add_argument("--frames", type=int, default=None, help=f"default 60 (quick: {QUICK_FRAMES})")
    ap.add_argument(
        "--only", action="append", default=[], help="run only these names, in this order"
    )
    ap.add_argument("--fresh", action="store_true", help="measure again what --json holds")
    ap.add_argument(
        "--merge",
        action="append",
        default=[],
        help="also take the points of this JSON (e.g. a grid run in parts); --json's win",
    )
    ap.add_argument("--redo", action="append", default=[], help="measure this name again")
    ap.add_argument(
        "--no-run", action="store_true", help="only the picture and docs from what --json holds"
    )
    ap.add_argument("--timeout", type=float, default=1800.0, help="per configuration [s]")
    ap.add_argument("--png", default=str(REPO_ROOT / "docs" / "front.png"))
    ap.add_argument("--no-docs", action="store_true")
    ap.add_argument("--load", default="", help="the machine's load, said in the docs")
    ap.add_argument("--quick-json", default=None, help="a --quick run's JSON, said in the docs")
    ap.add_argument(
        "--jobs", type=int, default=None, help="configurations at a time (default 1; quick: 2)"
    )
    args = ap.parse_args(argv)
    args.json = args.json or (None if args.quick else str(DEFAULT_JSON))
    frames = args.frames or (QUICK_FRAMES if args.quick else 60)
    args.jobs = args.jobs or (2 if args.quick else 1)
    configs = grid(args.quick)
    if args.only:  # in the order given
        by_name = {c.name: c for c in configs}
        configs = [by_name[n] for n in args.only if n in by_name]

    done: dict[str, dict[str, Any]] = {}
    sources = [*args.merge, *([args.json] if args.json and not args.fresh else [])]
    for src in sources:
        if Path(src).exists():
            for p in json.loads(Path(src).read_text()).get("points", []):
                if p.get("frames_requested", frames) == frames and valid(p):  # clean, not quick
                    done[p["name"]] = p
    demo = load_launch_file(Path(args.launch))
    for p in done.values():  # points measured before the bench recorded it
        if p.get("knob") and "knob_balanced" not in p:
            p["knob_balanced"] = balanced_value(demo, p["knob"][0])
    todo = [c for c in ([] if args.no_run else configs) if not measured(done, c, frames, args)]
    for c in configs:
        if c not in todo and not args.no_run:
            print(f"[front] {c.name}: measured already (resume)", flush=True)
    t_bench = time.monotonic()
    if args.jobs > 1 and len(todo) > 1:
        run_parallel(args, todo, frames, done)
    else:
        work = Path(tempfile.mkdtemp(prefix="mogs-front-"))
        for i, cfg in enumerate(todo):
            out = work / f"{i:02d}"
            out.mkdir()
            print(f"[front] {i + 1}/{len(todo)} {cfg.name} -> {out}", flush=True)
            t0 = time.process_time()
            point = run_config(Path(args.launch), cfg, frames, out, args.timeout)
            point.update(frames_requested=frames, commit=code_commit())
            point["bench_cpu_s"] = round(time.process_time() - t0, 1)
            print("[front] " + json.dumps({k: point.get(k) for k in SHOWN}), flush=True)
            if not valid(point):
                print(f"[front] {cfg.name}: not a clean run, left out: {out}", flush=True)
                continue
            done[cfg.name] = point
            write_results(args, done, frames)
    bench_wall_s = round(time.monotonic() - t_bench, 1) if todo else None
    results = write_results(args, done, frames, bench_wall_s)
    if not args.quick and not args.only and {"fast", "balanced", "quality"} <= done.keys():
        figs = {
            n: {k: results_point(results, n).get(k) for k in ("cpu_s_per_frame", *ERRORS)}
            for n in results["presets"]
        }
        figs["_measured"] = f"bench/front.py, {time.strftime('%Y-%m-%d')}"
        FIGURES_PATH.write_text(json.dumps(figs, indent=2) + "\n")
    if not args.no_docs:
        png = plot_front(results, Path(args.png))
        cmd = "python bench/front.py " + " ".join(argv if argv is not None else sys.argv[1:])
        body = front_markdown(results, cmd.strip(), machine_line(), args.load, png)
        update_markdown_section("front", body)
    return 0


SHOWN = ("name", "cpu_s_per_frame", "real_time_factor", *ERRORS, "standstill_over_moving_cpu")


def valid(point: dict[str, Any]) -> bool:
    """A clean run: it ended well, no node respawned, the report scored the final map."""
    return (
        point.get("launch_rc", 0) == 0
        and not point.get("respawns")
        and point.get("final_map", True)
    )


def measured(done: dict[str, dict[str, Any]], cfg: Config, frames: int, args) -> bool:
    """Whether ``done`` holds ``cfg`` measured with the same settings (resume)."""
    prev = done.get(cfg.name)
    return bool(
        prev
        and cfg.name not in args.redo
        and prev.get("frames_requested") == frames
        and valid(prev)
        and {k: prev.get(k) for k in cfg.key()} == json.loads(json.dumps(cfg.key()))
    )


def run_parallel(args, todo: list[Config], frames: int, done: dict[str, dict[str, Any]]) -> None:
    """``args.jobs`` configurations at a time, each in its own bench process with its own bus
    (``MOGS_BUS_DIR``): one run of the pipeline keeps about one core busy (its slowest node
    paces it), so two use both cores of a 2-core machine. CPU seconds are each process's own."""
    work = Path(tempfile.mkdtemp(prefix="mogs-front-"))
    queue = list(todo)
    running: dict[str, tuple[subprocess.Popen, Path]] = {}
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # ends the children below too
    try:
        _run_queue(args, queue, running, work, frames, done)
    finally:
        for proc, _ in running.values():
            proc.terminate()


def _run_queue(args, queue, running, work: Path, frames: int, done) -> None:
    while queue or running:
        while queue and len(running) < args.jobs:
            cfg = queue.pop(0)
            part = Path(tempfile.mkdtemp(prefix="c", dir=work))
            (part / "bus").mkdir()
            cmd = [sys.executable, str(Path(__file__).resolve()), "--only", cfg.name]
            cmd += ["--json", str(part / "point.json"), "--no-docs", "--frames", str(frames)]
            cmd += ["--launch", args.launch, "--timeout", str(args.timeout)]
            cmd += ["--quick"] if args.quick else []
            env = {**os.environ, "MOGS_BUS_DIR": str(part / "bus")}
            print(f"[front] start {cfg.name} -> {part}", flush=True)
            log = open(part / "bench.log", "w")  # noqa: SIM115 - the child owns it
            running[cfg.name] = (subprocess.Popen(cmd, env=env, stdout=log, stderr=log), part)
        time.sleep(1.0)
        for name, (proc, part) in list(running.items()):
            if proc.poll() is None:
                continue
            del running[name]
            pts = {}
            with contextlib.suppress(OSError, ValueError):
                pts = {
                    p["name"]: p for p in json.loads((part / "point.json").read_text())["points"]
                }
            if name not in pts:
                print(f"[front] {name} failed (rc {proc.returncode}): {part}/bench.log", flush=True)
                continue
            print("[front] " + json.dumps({k: pts[name].get(k) for k in SHOWN}), flush=True)
            if not valid(pts[name]):
                print(f"[front] {name}: not a clean run, left out: {part}/bench.log", flush=True)
                continue
            done[name] = pts[name]
            write_results(args, done, frames)


def code_commit() -> str:
    """The commit the point was measured on, ``+dirty`` when the code differs from it."""

    def git(*a: str) -> str:
        r = subprocess.run(["git", *a], cwd=REPO_ROOT, capture_output=True, text=True)
        return r.stdout.strip() if r.returncode == 0 else ""

    head = git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = git(
        "status",
        "--porcelain",
        "--",
        "mogs_node",
        "bridges",
        "launch",
        f":(exclude,glob)**/{FIGURES_PATH.name}",
    )
    return head + ("+dirty" if dirty else "")


def results_point(results: dict[str, Any], name: str) -> dict[str, Any]:
    return next(p for p in results["points"] if p["name"] == name)


def write_results(
    args, done: dict[str, dict[str, Any]], frames: int, bench_wall_s: float | None = None
) -> dict[str, Any]:
    points = list(done.values())
    frames = next((p["frames_requested"] for p in points), frames)
    results = {"frames": frames, "quick": args.quick, "points": points, **analyse(points)}
    if bench_wall_s is not None:  # this invocation's wall time (all its configurations)
        results["bench_wall_s"] = bench_wall_s
    if getattr(args, "quick_json", None) and Path(args.quick_json).exists():
        quick = json.loads(Path(args.quick_json).read_text())
        results["quick_wall_s"] = quick.get("bench_wall_s")
        results["quick_preset_checks"] = quick.get("preset_checks")
    write_json(args.json, results)
    return results


if __name__ == "__main__":
    sys.exit(main())
