"""``mogs demo``: run the demo launch graph and leave its outputs in ``runs/<timestamp>/``.

Until the pipeline nodes land (issue 8), the demo graph is the runtime's pass-through pipeline
(synthetic source -> relay -> recorder); the recorder's summary is the run's output.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from mogs_node.eval.report import REPO_ROOT
from mogs_node.launch import Launcher, load_launch_file


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--launch", default=str(REPO_ROOT / "launch" / "demo.yaml"), help="launch file"
    )
    parser.add_argument("--out", default=None, help="output folder (default runs/<timestamp>)")
    parser.add_argument(
        "--timeout", type=float, default=600.0, help="give up after this many seconds"
    )


def command(args: argparse.Namespace) -> int:
    out = Path(args.out or Path("runs") / time.strftime("%Y%m%d-%H%M%S")).resolve()
    out.mkdir(parents=True, exist_ok=True)
    summary = out / "recorder.json"
    launch = load_launch_file(args.launch, overrides={"recorder": {"summary_path": str(summary)}})
    t0 = time.monotonic()
    code = Launcher(launch).run(timeout_s=args.timeout)
    dt = time.monotonic() - t0
    if summary.exists():
        data = json.loads(summary.read_text())
        counts = ", ".join(f"{k}: {v}" for k, v in data["count"].items())
        lost = sum(t.get("lost", 0) for t in data["topics"].values())
        print(f"demo finished in {dt:.1f} s: received {counts}; lost {lost}. Outputs in {out}")
    else:
        print(f"demo ended (code {code}) without a summary; see the log above. Outputs in {out}")
        return code or 1
    return code
