"""Issue 23's "Must show" on the whole pipeline: a handheld walk with a camera-IMU time offset,
written as a rosbag2 and replayed through ``launch/bag.yaml`` with no calibration value typed.

    .venv/bin/python bench/handheld_bag.py [--frames 1200] [--offsets-ms 50 -30 0]
        [--contrast-ms 50] [--contrast-frames N] [--out DIR] [--json PATH] [--write-docs]

Per offset: ``mogs sim --motion handheld --time-offset-ms X --frames F --size 621x188 --format
rosbag2 --out DIR/walkF_X`` (skipped when that bag exists), then ``mogs launch launch/bag.yaml
--set player.path=DIR/walkF_X --run-dir DIR/runF_X_on``; for each ``--contrast-ms`` offset the same
with ``--set "frontend.time_offset={enabled: false}"`` (the launch value 0 used as it is). The figures
are read from each run's ``summary.json``: the offset in use at the end, whether ``platform: auto``
saw a walk, ATE (SE(3)-aligned, every frame with odometry) against the path, resets by reason,
keyframes per second, keyframes made / mapped, depth (AbsRel, coverage against the ground truth)
and the map's held-out PSNR; plus the launcher's CPU time. ``--write-docs`` replaces the
``handheld-bag`` section of ``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mogs_node.eval.bench_docs import machine_line, write_results  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def _mogs(*args: str, log: Path) -> tuple[int, float, float]:
    """``mogs ARGS`` with its output in ``log``: exit code, wall and CPU seconds (children). Its
    bus in a folder of its own (beside ``log``): another run of the same launch file elsewhere on
    the machine has the same endpoint names."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    env = dict(os.environ, MOGS_BUS_DIR=str(log.with_suffix(".bus")))
    with open(log, "w") as f:
        rc = subprocess.call(
            [sys.executable, "-m", "mogs_node.cli", *args], cwd=REPO, stdout=f, stderr=f, env=env
        )
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return rc, time.monotonic() - t0, cpu


def run_one(frames: int, offset_ms: float, estimation: bool, out: Path) -> dict:
    bag = out / f"walk{frames}_{offset_ms:g}"
    if not bag.exists():
        rc, _, _ = _mogs(
            "sim", "--motion", "handheld", "--time-offset-ms", f"{offset_ms:g}",
            "--frames", str(frames), "--size", "621x188", "--format", "rosbag2",
            "--out", str(bag), log=out / f"sim{frames}_{offset_ms:g}.log",
        )  # fmt: skip
        if rc != 0:
            raise SystemExit(f"mogs sim failed ({rc}): {out}/sim{frames}_{offset_ms:g}.log")
    run = out / f"run{frames}_{offset_ms:g}_{'on' if estimation else 'off'}"
    extra = [] if estimation else ["--set", "frontend.time_offset={enabled: false}"]
    rc, wall, cpu = _mogs(
        "launch", "launch/bag.yaml", "--set", f"player.path={bag}", "--run-dir", str(run),
        *extra, log=out / f"{run.name}.log",
    )  # fmt: skip
    row: dict = {"frames": frames, "true_ms": offset_ms, "estimation": estimation, "exit": rc}
    row.update(wall_s=wall, cpu_s=cpu, run_dir=str(run))
    summary = run / "summary.json"
    if summary.exists():
        row["summary"] = json.loads(summary.read_text())
    return row


def _cells(r: dict) -> list[str]:
    s = r.get("summary", {})
    fe, tr = s.get("frontend", {}), s.get("trajectory", {})
    d, m = s.get("depth", {}), s.get("map", {})
    ate = tr.get("ate_se3_rmse_m", float("nan"))
    path = tr.get("path_length_m", float("nan"))
    return [
        f"{r['true_ms']:g}",
        f"{r['frames']}",
        "on" if r["estimation"] else "off",
        f"{fe.get('time_offset_ms', float('nan')):.1f}",
        "yes" if fe.get("walk_detected") else "no",
        f"{ate:.2f}",
        f"{100 * ate / path:.2f} %" if path == path and path > 0 else "-",
        f"{tr.get('scale_error', float('nan')):.3f}",
        str(fe.get("resets") or 0),
        f"{fe.get('keyframes_per_s', float('nan')):.2f}",
        f"{s.get('keyframes', 0)} / {s.get('keyframes_mapped', 0)}",
        f"{d.get('absrel', float('nan')):.3f} / {d.get('coverage', float('nan')):.2f}",
        f"{m.get('heldout_psnr_db', float('nan')):.1f}",
        f"{r['cpu_s']:.0f} / {r['wall_s']:.0f}",
    ]


def markdown(rows: list[dict], args: argparse.Namespace) -> str:
    lines = [
        "The whole pipeline, `launch/bag.yaml` as it is (`platform: auto`; calibration from the "
        "bag), on `mogs sim --motion handheld --time-offset-ms X --frames F --size 621x188 "
        "--format rosbag2`. Command: `python bench/handheld_bag.py "
        + " ".join(a for a in sys.argv[1:] if a != "--write-docs")
        + " --write-docs`. ATE SE(3)-aligned over every frame with odometry (the report's); "
        "depth against the sim's ground truth; CPU = all processes of the run. "
        f"{machine_line()}; shared with other jobs (load {os.getloadavg()[0]:.1f} at the end): "
        "wall times are upper bounds.",
        "",
        "| true offset [ms] | frames | estimation | offset used [ms] | walk seen | ATE [m] | "
        "ATE / path | scale error | resets | keyframes/s | keyframes made / mapped | "
        "depth AbsRel / coverage | held-out PSNR [dB] | CPU / wall [s] |",
        "| ---: | ---: | --- | ---: | --- | ---: | ---: | ---: | --- | ---: | --- | --- | ---: "
        "| ---: |",
    ]
    lines += ["| " + " | ".join(_cells(r)) + " |" for r in rows]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1200)
    ap.add_argument("--offsets-ms", type=float, nargs="*", default=[50.0, -30.0, 0.0])
    ap.add_argument("--contrast-ms", type=float, nargs="*", default=[50.0])
    ap.add_argument("--contrast-frames", type=int, default=None, help="default: --frames")
    ap.add_argument("--out", default="/tmp/mogs-handheld-bag")
    ap.add_argument("--json", default=None)
    ap.add_argument("--write-docs", action="store_true")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plan = [(args.frames, o, True) for o in args.offsets_ms]
    plan += [(args.contrast_frames or args.frames, o, False) for o in args.contrast_ms]
    rows = []
    for frames, off, est in plan:
        r = run_one(frames, off, est, out)
        print(json.dumps({k: v for k, v in r.items() if k != "summary"}), _cells(r), flush=True)
        rows.append(r)
    write_results("handheld-bag", markdown(rows, args), {"runs": rows}, args.json, args.write_docs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
