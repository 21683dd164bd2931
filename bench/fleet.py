"""Fleet batch against single runs: wall time of ``mogs batch`` over the sum of ``mogs launch``.

Writes N tiny sim drives (different seeds, ground truth in the bag), runs each alone with
``mogs launch launch/bag.yaml`` one after the other (the sum of their wall times: what a shell
loop costs), then the same drives as one batch on a local Ray, once per ``--cpus-per-drive``
value. Prints and writes (``--json``): ``sequential_s``, per value C ``batch_s_cpd<C>``,
``batch_over_sequential_cpd<C>`` and ``drives_complete_cpd<C>``, ``figures_equal_cpd<C>`` (drives
whose summary figures equal their single run's), ``prior_wait_timeouts_cpd<C>`` (keyframes whose
prior went without the previous keyframe's metrized depth), and ``batch_over_sequential`` (C = 1, the
default). The machine's load at start and end goes beside them: on a shared machine the times
are upper bounds. Section ``fleet`` of docs/benchmarks.md.

    python bench/fleet.py --drives 4 --json runs/bench_fleet.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

from mogs_node.eval.bench_docs import (
    REPO_ROOT,
    add_output_options,
    machine_line,
    update_markdown_section,
    write_json,
)
from mogs_node.fleet.batch import BatchOptions, run_batch
from mogs_node.fleet.drives import PATIENT_PLAYER, drive_id, write_sim_drives
from mogs_node.fleet.table import comparable_figures

LAUNCH = REPO_ROOT / "launch" / "bag.yaml"


def run_alone(drive: Path, run_dir: Path, timeout_s: float) -> float:
    """``mogs launch`` of one drive on its own bus; its wall time [s] (raises if it fails)."""
    sets = [f"{n}.{k}={v}" for n, p in PATIENT_PLAYER.items() for k, v in p.items()]
    argv = [sys.executable, "-m", "mogs_node.cli", "launch", str(LAUNCH)]
    for s in [f"player.path={drive}", *sets]:
        argv += ["--set", s]
    argv += ["--run-dir", str(run_dir), "--timeout", str(timeout_s)]
    bus_dir = Path(tempfile.gettempdir()) / f"mogs-bench-fleet-{uuid.uuid4().hex[:8]}"
    bus_dir.mkdir()
    run_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    with (run_dir / "launch.log").open("w") as log:
        rc = subprocess.run(
            argv,
            cwd=REPO_ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
            env={**os.environ, "MOGS_BUS_DIR": str(bus_dir)},
        ).returncode
    wall = time.monotonic() - t0
    if rc != 0:
        raise RuntimeError(f"mogs launch of {drive} failed ({rc}): see {run_dir / 'launch.log'}")
    return wall


def _summary(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def measure(args: argparse.Namespace) -> dict[str, float]:
    work = Path(args.out or tempfile.mkdtemp(prefix="mogs-bench-fleet-"))
    drives = write_sim_drives(
        work / "drives", list(range(1, args.drives + 1)), n_frames=args.frames
    )
    fig: dict[str, float] = {
        "drives": args.drives,
        "frames_per_drive": args.frames,
        "ray_num_cpus": args.num_cpus,
        "load_average_1min_start": os.getloadavg()[0],
    }
    walls = []
    for d in drives:
        walls.append(run_alone(d, work / "alone" / d.name, args.timeout))
        print(f"alone {d.name}: {walls[-1]:.1f} s", flush=True)
    fig["sequential_s"] = sum(walls)
    fig["single_drive_mean_s"] = sum(walls) / len(walls)
    write_json(args.json, fig)
    for cpd in args.cpus_per_drive:
        opts = BatchOptions(
            num_cpus=args.num_cpus,
            cpus_per_drive=cpd,
            timeout_s=args.timeout,
            overrides=PATIENT_PLAYER,
            resume=False,
        )
        out = work / f"batch_cpd{cpd:g}"
        t0 = time.monotonic()
        res = run_batch(LAUNCH, [str(d) for d in drives], out, opts, progress=sys.stderr)
        wall = time.monotonic() - t0  # Ray's start and stop included
        equal = sum(
            comparable_figures(_summary(out / drive_id(str(d))))
            == comparable_figures(_summary(work / "alone" / d.name))
            for d, r in zip(drives, res.rows)
            if r["status"] == "complete"
        )
        key = f"cpd{cpd:g}"
        fig[f"batch_s_{key}"] = wall
        fig[f"batch_over_sequential_{key}"] = wall / fig["sequential_s"]
        fig[f"drives_complete_{key}"] = sum(r["status"] == "complete" for r in res.rows)
        fig[f"figures_equal_{key}"] = equal
        fig[f"prior_wait_timeouts_{key}"] = sum(  # 0: no prior went without the metrized depth
            _summary(out / drive_id(str(d)))["nodes"]["prior"].get("metrized_wait_timeouts", 0)
            for d, r in zip(drives, res.rows)
            if r["status"] == "complete"
        )
        print(f"batch --cpus-per-drive {cpd:g}: {wall:.1f} s, {equal} drives equal", flush=True)
        write_json(args.json, fig)  # what is measured so far
    first = f"cpd{args.cpus_per_drive[0]:g}"
    fig["batch_over_sequential"] = fig[f"batch_over_sequential_{first}"]
    fig["load_average_1min_end"] = os.getloadavg()[0]
    return fig


def _markdown(fig: dict[str, float], args: argparse.Namespace) -> str:
    cpds = " ".join(f"{c:g}" for c in args.cpus_per_drive)
    lines = [
        "## Fleet: a batch of drives on Ray against single runs (`mogs batch`)",
        "",
        f"Command: `python bench/fleet.py --drives {args.drives} --frames {args.frames} "
        f"--num-cpus {args.num_cpus} --cpus-per-drive {cpds} --json ...`. Machine: "
        f"{machine_line()}; {os.cpu_count()} cores, shared with other work: load average "
        f"{fig['load_average_1min_start']:.1f} at the start, {fig['load_average_1min_end']:.1f} "
        "at the end, so the times are upper bounds and their ratios noisy.",
        "",
        f"{args.drives} sim drives (seeds 1..{args.drives}, {args.frames} frames at 621x188, "
        "ground truth in the bag) through `launch/bag.yaml`'s whole graph, with the player "
        "waiting for every node (`PATIENT_PLAYER`, mogs_node/fleet/drives.py). Sequential: each "
        "drive alone with `mogs launch`, one after the other (a shell loop). Batch: one Ray task "
        f"per drive on a local Ray with {args.num_cpus} CPUs, Ray's start and stop included.",
        "",
        "| run | wall [s] | over sequential | drives complete | figures equal to the single run |",
        "| --- | ---: | ---: | ---: | ---: |",
        f"| sequential (sum of {args.drives} single runs) | {fig['sequential_s']:.1f} | 1.00 | "
        f"{args.drives} | - |",
    ]
    for c in args.cpus_per_drive:
        k = f"cpd{c:g}"
        lines.append(
            f"| batch, `--cpus-per-drive {c:g}` | {fig[f'batch_s_{k}']:.1f} | "
            f"{fig[f'batch_over_sequential_{k}']:.2f} | {fig[f'drives_complete_{k}']:.0f} | "
            f"{fig[f'figures_equal_{k}']:.0f} |"
        )
    lines += [
        "",
        f"`batch_over_sequential` = {fig['batch_over_sequential']:.2f}. Mean single-drive wall "
        f"time {fig['single_drive_mean_s']:.1f} s.",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=4)
    ap.add_argument("--frames", type=int, default=30, help="frames per sim drive")
    ap.add_argument("--num-cpus", type=int, default=os.cpu_count() or 2, help="local Ray CPUs")
    ap.add_argument("--cpus-per-drive", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--timeout", type=float, default=3000.0, help="per drive [s]")
    ap.add_argument("--out", default=None, help="working folder (default: a temporary one)")
    add_output_options(ap)
    args = ap.parse_args(argv)
    if args.drives < 1:
        raise SystemExit("--drives: at least 1")
    fig = measure(args)
    for k, v in fig.items():
        print(f"{k}: {v:.4g}")
    write_json(args.json, fig)
    if not args.no_docs:
        update_markdown_section("fleet", _markdown(fig, args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
