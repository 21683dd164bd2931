"""A real-time source keeps its depth (issue 28): one drive at its recorded rate and as fast as
the pipeline accepts, side by side.

Makes (or reuses) a simulated KITTI-raw drive (``mogs sim --frames N --size WxH --static-start
2``) and plays it through ``launch/kitti.yaml`` in each mode:

- ``rate``: ``rate: 1.0`` as the launch file has it (the player's clock holds while 2 keyframes wait
  for the mapper, issue 23; frames the frontend cannot keep up with are superseded);
- ``fast``: ``fast: true``, every frame processed, the reference;
- ``live`` (optional): ``rate: 1.0`` with a clock that never holds (``max_keyframes_in_flight:
  0``), as a live camera: the frontend must shed keyframes itself.

Per mode, from the run's ``summary.json`` (the report node's own scoring): keyframes, keyframes
shed (by reason), keyframes metrized without masks or prior, depth AbsRel and coverage against the
drive's ground truth, ATE, held-out PSNR; and measured from the bus by this script: image ->
metrized depth latency (p50 / p95, the keyframe's image published by the player to its depth
published by the metrizer) and CPU per node (seconds of CPU over the run, and its mean share of
one core). The issue's acceptance figures are checked and printed.

Usage::

    python bench/realtime.py [--frames 200] [--size 1242x375] [--modes rate,fast] [--drive DIR]
                             [--out DIR] [--json [PATH]] [--no-docs]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import zmq

from mogs_node import msgs
from mogs_node.bus import Subscriber
from mogs_node.eval.bench_docs import REPO_ROOT, machine_line, update_markdown_section, write_json
from mogs_node.launch import Launcher, load_launch_file, run_dir_overrides

MODES = {
    "rate": {"rate": 1.0, "fast": False},
    "fast": {"fast": True},
    "live": {"rate": 1.0, "fast": False, "max_keyframes_in_flight": 0},
}
# the acceptance bounds at rate 1.0 against fast
ABSREL_RATIO_MAX = 1.15
COVERAGE_RATIO_MIN = 0.9
LATENCY_P95_MAX_MS = 3000.0


STAGES = (
    "frontend",
    "chain_busy",
    "segmentation",
    "prior",
    "metrizer",
)  # where a keyframe's latency goes


class BusProbe:
    """Wall-clock arrival of each image and of each keyframe's outputs along the chain, on the
    bus: the image (player), the keyframe (frontend), its masks and prior (workers) and its
    metrized depth (metrizer)."""

    TOPICS = (
        "/camera/image",
        "/frontend/keyframe",
        "/seg/masks",
        "/prior/depth",
        "/metrizer/depth",
    )
    SLOT = {"/frontend/keyframe": "keyframe", "/seg/masks": "masks", "/prior/depth": "prior"}

    def __init__(self, bus, ctx: zmq.Context) -> None:
        self.sub = Subscriber(bus, context=ctx)
        for t in self.TOPICS:
            self.sub.subscribe(t)
        self.image_s: dict[int, float] = {}  # stamp -> arrival
        self.keyframe_stamp: dict[int, int] = {}  # keyframe id -> stamp
        self.depth_s: dict[int, float] = {}  # keyframe id -> arrival
        self.slot_s: dict[str, dict[int, float]] = {s: {} for s in self.SLOT.values()}

    def poll(self, timeout_ms: int) -> None:
        env = self.sub.receive(timeout_ms=timeout_ms)
        if env is None:
            return
        now, m = time.monotonic(), env.msg
        if env.topic == "/camera/image":
            self.image_s.setdefault(int(m.stamp_ns), now)
            return
        if env.topic == "/frontend/keyframe" and isinstance(m, msgs.Keyframe):
            self.keyframe_stamp[int(m.keyframe_id)] = int(m.stamp_ns)
        if env.topic == "/metrizer/depth":
            self.depth_s.setdefault(int(m.keyframe_id), now)
        elif env.topic in self.SLOT:
            self.slot_s[self.SLOT[env.topic]].setdefault(int(m.keyframe_id), now)

    def _complete(self) -> list[int]:
        return [
            k for k, s in self.keyframe_stamp.items() if k in self.depth_s and s in self.image_s
        ]

    def latencies_ms(self) -> list[float]:
        return [
            1000.0 * (self.depth_s[k] - self.image_s[self.keyframe_stamp[k]])
            for k in self._complete()
        ]

    def stages_ms(self) -> dict[int, dict[str, float]]:
        """Per keyframe, the image -> depth latency split into stages [ms]: ``frontend`` (image
        -> keyframe published), ``chain_busy`` (keyframe -> the previous keyframe's depth: the
        queue; the prior waits for it), ``segmentation`` / ``prior`` (keyframe -> masks / prior:
        the worker's queue and compute), ``metrizer`` (the later of the two -> depth: its wait for
        the keyframe in order and its compute)."""
        out: dict[int, dict[str, float]] = {}
        kf_s, masks_s, prior_s = (self.slot_s[s] for s in ("keyframe", "masks", "prior"))
        for k in self._complete():
            if k not in kf_s or k not in masks_s or k not in prior_s:
                continue
            t_img, t_kf = self.image_s[self.keyframe_stamp[k]], kf_s[k]
            inputs = max(masks_s[k], prior_s[k])
            before = [j for j in self.keyframe_stamp if j < k]
            prev_done = self.depth_s.get(max(before), t_kf) if before else t_kf
            out[k] = {
                "chain_busy": 1000.0 * max(0.0, prev_done - t_kf),  # the previous one's depth
                "frontend": 1000.0 * (t_kf - t_img),
                "segmentation": 1000.0 * (masks_s[k] - t_kf),
                "prior": 1000.0 * (prior_s[k] - t_kf),
                "metrizer": 1000.0 * (self.depth_s[k] - inputs),
                "total": 1000.0 * (self.depth_s[k] - t_img),
            }
        return out

    def close(self) -> None:
        self.sub.close()


class CpuMeter:
    """CPU seconds (user + system) of every node process, sampled while it lives."""

    def __init__(self) -> None:
        self.cpu_s: dict[str, float] = {}  # node -> CPU s of its processes (respawns summed)
        self._last: dict[int, tuple[str, float]] = {}
        self._procs: dict[int, psutil.Process] = {}

    def sample(self, launcher: Launcher) -> None:
        for child in launcher.children:
            pid = child.proc.pid if child.proc is not None else None
            if pid is not None and pid not in self._procs:
                try:
                    self._procs[pid] = psutil.Process(pid)
                except psutil.NoSuchProcess:
                    continue
                self._last[pid] = (child.name, 0.0)
        for pid, p in list(self._procs.items()):
            try:
                t = p.cpu_times()
            except psutil.NoSuchProcess:
                del self._procs[pid]
                continue
            name, before = self._last[pid]
            self.cpu_s[name] = self.cpu_s.get(name, 0.0) + (t.user + t.system - before)
            self._last[pid] = (name, t.user + t.system)


def percentile(values: list[float], q: float) -> float:
    return round(float(np.percentile(values, q)), 1) if values else float("nan")


def make_drive(drive: Path, frames: int, size: str) -> None:
    """The simulated drive (KITTI raw layout with OXTS and ground-truth depth), once."""
    if (drive / "image_02" / "timestamps.txt").exists():
        return
    cmd = [sys.executable, "-m", "mogs_node.cli", "sim", "--out", str(drive)]
    cmd += ["--frames", str(frames), "--size", size, "--static-start", "2"]
    subprocess.run(cmd, check=True)


def run_mode(mode: str, drive: Path, out: Path, args: argparse.Namespace) -> dict[str, Any]:
    """One run of ``launch/kitti.yaml`` on ``drive`` in ``mode``; its figures."""
    path = REPO_ROOT / "launch" / "kitti.yaml"
    overrides: dict[str, dict] = {
        "player": {"path": str(drive), **MODES[mode]},
        "report": {"heldout_views": args.heldout_views, "max_keyframe_views": args.keyframe_views},
    }
    if args.end_s is not None:
        overrides["player"]["end_s"] = args.end_s
    if args.mapper_iters is not None:
        overrides["mapper"] = {"iters_per_keyframe": args.mapper_iters}
    base = load_launch_file(path, overrides=overrides)
    for node, params in run_dir_overrides(base, out, resume=False).items():
        overrides.setdefault(node, {}).update(params)
    launch = load_launch_file(path, overrides=overrides)
    ctx = zmq.Context()
    probe = BusProbe(launch.bus, ctx)
    meter = CpuMeter()
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "launch.log", "w") as log:
        launcher = Launcher(launch, out=log)
        runner = threading.Thread(
            target=launcher.run,
            kwargs={"install_signal_handlers": False, "timeout_s": args.timeout},
        )
        t0 = time.monotonic()
        runner.start()
        last = 0.0
        while runner.is_alive():
            probe.poll(100)
            if time.monotonic() - last >= 1.0:
                last = time.monotonic()
                meter.sample(launcher)
        runner.join()
    wall_s = time.monotonic() - t0
    probe.close()
    ctx.term()
    summary_path = out / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    figures = figures_of(summary, probe, meter, wall_s)
    write_json(out / "figures.json", figures)  # each run's own, as soon as it is done
    write_json(out / "stages.json", {str(k): v for k, v in probe.stages_ms().items()})
    return figures


def figures_of(
    summary: dict[str, Any], probe: BusProbe, meter: CpuMeter, wall_s: float
) -> dict[str, Any]:
    """The side-by-side figures of one run."""
    depth = summary.get("depth", {})
    traj = summary.get("trajectory", {})
    rt = summary.get("realtime", {})
    lat = probe.latencies_ms()
    stages = probe.stages_ms()
    span = max(probe.depth_s.values(), default=0.0) - min(probe.image_s.values(), default=0.0)
    return {
        "frames_seen": len(probe.image_s),
        "keyframes": summary.get("keyframes", len(probe.keyframe_stamp)),
        "keyframes_with_depth": summary.get("keyframes_with_depth", len(probe.depth_s)),
        "keyframes_mapped": summary.get("keyframes_mapped", 0),
        "keyframes_shed": rt.get("keyframes_shed", 0),
        "shed_reasons": rt.get("shed_reasons", {}),
        "metrized_without_inputs": rt.get("metrized_without_inputs", 0),
        "inputs_failed": rt.get("inputs_failed", 0),
        "inputs_stalled": rt.get("inputs_stalled", 0),
        "depth_absrel": depth.get("absrel", float("nan")),
        "depth_coverage": depth.get("coverage", float("nan")),
        "ate_se3_rmse_m": traj.get("ate_se3_rmse_m", float("nan")),
        "trajectory_error": traj.get("error", ""),
        "heldout_psnr_db": summary.get("map", {}).get("heldout_psnr_db", float("nan")),
        "latency_image_to_depth_ms_p50": percentile(lat, 50),
        "latency_image_to_depth_ms_p95": percentile(lat, 95),
        "latency_stages_ms_p50": {
            st: percentile([v[st] for v in stages.values()], 50) for st in STAGES
        },
        "latency_stages_ms_p95": {
            st: percentile([v[st] for v in stages.values()], 95) for st in STAGES
        },
        "drive_wall_s": round(span, 1),
        "wall_s": round(wall_s, 1),
        "cpu_s": {k: round(v, 1) for k, v in sorted(meter.cpu_s.items())},
        "cpu_share_of_one_core": {
            k: round(v / max(wall_s, 1e-9), 2) for k, v in sorted(meter.cpu_s.items())
        },
    }


def acceptance(res: dict[str, dict[str, Any]]) -> dict[str, bool]:
    """The issue's checks on the ``rate`` run against ``fast`` (those the modes run allow)."""
    checks: dict[str, bool] = {}
    for mode in ("rate", "live"):
        r = res.get(mode)
        if r is None:
            continue
        checks[f"{mode}.metrized_without_inputs == 0"] = r["metrized_without_inputs"] == 0
        checks[f"{mode}.latency_image_to_depth_ms_p95 <= 3000"] = (
            r["latency_image_to_depth_ms_p95"] <= LATENCY_P95_MAX_MS
        )
        checks[f"{mode}.trajectory scored"] = bool(
            not r["trajectory_error"] and np.isfinite(r["ate_se3_rmse_m"])
        )
        if "fast" in res:
            f = res["fast"]
            checks[f"{mode}.depth_absrel <= 1.15 x fast"] = (
                r["depth_absrel"] <= ABSREL_RATIO_MAX * f["depth_absrel"]
            )
            checks[f"{mode}.depth_coverage >= 0.9 x fast"] = (
                r["depth_coverage"] >= COVERAGE_RATIO_MIN * f["depth_coverage"]
            )
    return checks


ROWS = (
    ("keyframes (published / with depth / mapped)", "keyframes", "keyframes_with_depth"),
    ("keyframes shed whole", "keyframes_shed", None),
    ("metrized without masks or prior", "metrized_without_inputs", None),
    ("depth AbsRel / coverage", "depth_absrel", "depth_coverage"),
    ("ATE SE(3) [m]", "ate_se3_rmse_m", None),
    ("held-out PSNR [dB]", "heldout_psnr_db", None),
    ("latency image -> depth p50 / p95 [ms]", "latency_image_to_depth_ms_p50", None),
    ("wall time of the drive [s] (first image -> last depth)", "drive_wall_s", None),
)


def _cell(r: dict[str, Any], key: str, second: str | None) -> str:
    def fmt(v: Any) -> str:
        return f"{v:.3f}" if isinstance(v, float) else str(v)

    if key == "keyframes":
        return f"{r['keyframes']} / {r['keyframes_with_depth']} / {r['keyframes_mapped']}"
    if key == "latency_image_to_depth_ms_p50":
        return f"{r[key]:.0f} / {r['latency_image_to_depth_ms_p95']:.0f}"
    if key == "keyframes_shed" and r["shed_reasons"]:
        reasons = ", ".join(f"{k} {v}" for k, v in r["shed_reasons"].items())
        return f"{r[key]} ({reasons})"
    return fmt(r[key]) + (f" / {fmt(r[second])}" if second else "")


def table(res: dict[str, dict[str, Any]]) -> str:
    modes = list(res)
    lines = ["| figure | " + " | ".join(modes) + " |", "| --- |" + " ---: |" * len(modes)]
    for label, key, second in ROWS:
        lines.append(f"| {label} | " + " | ".join(_cell(res[m], key, second) for m in modes) + " |")
    for st in STAGES:  # where the latency goes (keyframes with every stage seen)

        def stage(r: dict[str, Any], st: str = st) -> str:
            p50, p95 = r.get("latency_stages_ms_p50", {}), r.get("latency_stages_ms_p95", {})
            return f"{p50.get(st, float('nan')):.0f} / {p95.get(st, float('nan')):.0f}"

        label = f"latency stage {st} p50 / p95 [ms]"
        lines.append(f"| {label} | " + " | ".join(stage(res[m]) for m in modes) + " |")
    nodes = sorted({n for m in modes for n in res[m]["cpu_s"]})
    for n in nodes:
        cells = [
            f"{res[m]['cpu_s'].get(n, 0.0):.0f} s ({res[m]['cpu_share_of_one_core'].get(n, 0.0)})"
            for m in modes
        ]
        lines.append(f"| CPU {n} [s (share of one core)] | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def docs_body(
    res: dict[str, dict[str, Any]], checks: dict[str, bool], args: argparse.Namespace, cmd: str
) -> str:
    """The ``realtime`` section of docs/benchmarks.md."""
    checks_md = "\n".join(f"- {'pass' if ok else 'FAIL'}: `{n}`" for n, ok in checks.items())
    live = ", `live` = `rate: 1.0` with a clock that never holds (a live camera)"
    return f"""## A real-time source keeps its depth (issue 28)

Command: `{cmd}`

Machine: {machine_line()}{"; load: " + args.load if args.load else ""}. The simulated drive
(`mogs sim --frames {args.frames} --size {args.size} --static-start 2`, KITTI raw layout with
OXTS) through `launch/kitti.yaml`: `rate` = `rate: 1.0` as the launch file has it, `fast` =
`fast: true`{live if "live" in res else ""}. Depth, ATE and held-out PSNR from the run's
`summary.json` (the report's own scoring); latency (a keyframe's image published -> its metrized
depth published) and CPU per node measured by the script from the bus and the processes. The
latency stages of a keyframe: `frontend` image -> keyframe published, `chain_busy` keyframe ->
the previous keyframe's depth (the queue: the prior waits for it), `segmentation` / `prior`
keyframe -> masks / prior (with the queue), `metrizer` the later of the two -> depth.

{table(res)}

{checks_md}
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--size", default="1242x375")
    ap.add_argument("--modes", default="rate,fast", help="comma-separated: rate, fast, live")
    ap.add_argument("--drive", default=None, help="the drive folder (made when missing)")
    ap.add_argument("--out", default="/tmp/mogs-bench-realtime", help="run folders go here")
    ap.add_argument("--timeout", type=float, default=3600.0, help="per run [s]")
    ap.add_argument("--end-s", type=float, default=None, help="play the drive up to this [s]")
    ap.add_argument(
        "--mapper-iters", type=int, default=None, help="mapper.iters_per_keyframe (a loaded box)"
    )
    ap.add_argument("--heldout-views", type=int, default=12, help="report.heldout_views")
    ap.add_argument("--keyframe-views", type=int, default=4, help="report.max_keyframe_views")
    ap.add_argument("--json", nargs="?", const="-", default=None, help="PATH, or stdout")
    ap.add_argument("--load", default="", help="say the machine's load for the record")
    ap.add_argument(
        "--from-json", default=None, help="no runs: the table and docs of a --json result"
    )
    ap.add_argument("--no-docs", action="store_true")
    args = ap.parse_args(argv)
    if args.keyframe_views < 1 or args.heldout_views < 0:
        ap.error("--keyframe-views >= 1 (the report renders at least one), --heldout-views >= 0")
    modes = [m for m in args.modes.split(",") if m]
    unknown = set(modes) - set(MODES)
    if unknown:
        ap.error(f"--modes: unknown {sorted(unknown)}; known {sorted(MODES)}")
    cmd = "python bench/realtime.py " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.from_json:  # the table and the docs section of a recorded result
        res = json.loads(Path(args.from_json).read_text())
        res.pop("checks", None)
        cmd = res.pop("command", cmd)
        res = {m: res[m] for m in MODES if m in res}  # rate, fast, live
    else:
        out = Path(args.out)
        drive = Path(args.drive) if args.drive else out / f"drive_{args.frames}_{args.size}"
        make_drive(drive, args.frames, args.size)
        res = {m: run_mode(m, drive, out / m, args) for m in modes}
    checks = acceptance(res)
    print(table(res))
    for name, ok in checks.items():
        print(f"{'PASS' if ok else 'FAIL'}  {name}")
    doc = {**res, "checks": checks, "command": cmd.strip()}
    if args.json == "-":
        print(json.dumps(doc, indent=2, sort_keys=True, default=float))
    else:
        write_json(args.json, doc)
    if not args.no_docs:
        update_markdown_section("realtime", docs_body(res, checks, args, cmd.strip()))
    return 0 if all(checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
