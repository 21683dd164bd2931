"""``mogs demo``: the whole pipeline on the embedded synthetic drive; outputs in ``runs/<ts>/``.

Runs ``launch/demo.yaml`` (player -> frontend -> segmentation + depth prior -> metrizer -> mapper,
and a report node) as separate processes, then prints where the outputs are and a summary line:
trajectories (TUM, KITTI), metrized depth per keyframe, the Gaussian map (PLY), renders and a
``report.md`` scored against the simulator's ground truth.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from mogs_node.commands.launch import add_keep_journal, add_run_options, parse_overrides
from mogs_node.eval.bench_docs import REPO_ROOT
from mogs_node.launch import Launcher, load_launch_file, run_dir_overrides


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--launch", default=str(REPO_ROOT / "launch" / "demo.yaml"), help="launch file"
    )
    parser.add_argument("--out", default=None, help="output folder (default runs/<timestamp>)")
    parser.add_argument("--frames", type=int, default=None, help="frames of the synthetic drive")
    add_run_options(parser, "give up after this many seconds (default 1200)", timeout_s=1200.0)
    add_keep_journal(parser)


def command(args: argparse.Namespace) -> int:
    out = Path(args.out or Path("runs") / time.strftime("%Y%m%d-%H%M%S")).resolve()
    out.mkdir(parents=True, exist_ok=True)
    base = load_launch_file(args.launch)
    # report, map, journal and mapper checkpoints in OUT: `mogs launch FILE --resume OUT` goes on
    overrides = run_dir_overrides(base, out, resume=False)
    if args.frames is not None:
        sim = dict(next(n for n in base.nodes if n.name == "player").params.get("sim", {}))
        sim["n_frames"] = args.frames
        overrides["player"] = {"sim": sim}
    for node, params in parse_overrides(args.set).items():  # --set wins
        overrides.setdefault(node, {}).update(params)
    launch = load_launch_file(args.launch, overrides=overrides)
    t0 = time.monotonic()
    code = Launcher(launch, keep_journal=args.keep_journal).run(timeout_s=args.timeout)
    dt = time.monotonic() - t0
    summary = out / "summary.json"
    if not summary.exists():
        print(
            f"demo ended (code {code}) after {dt:.0f} s without a report; see the log above. "
            f"Partial outputs in {out}"
        )
        return code or 1
    figures = json.loads(summary.read_text())
    parts = [
        f"{figures['keyframes']} keyframes ({figures['keyframes_with_depth']} metrized, "
        f"{figures['keyframes_mapped']} mapped)"
    ]
    if "depth" in figures:
        d = figures["depth"]
        parts.append(f"depth AbsRel {d['absrel']:.3f} at coverage {d['coverage']:.2f}")
    traj = figures.get("trajectory", {})
    if "ate_se3_rmse_m" in traj:
        parts.append(f"ATE {traj['ate_se3_rmse_m']:.2f} m over {traj['path_length_m']:.0f} m")
    if "mapper" in figures:
        parts.append(f"{figures['mapper'].get('n_gaussians', 0)} Gaussians")
    held = figures.get("map", {})
    if held.get("heldout_frames"):
        parts.append(
            f"held-out views {held['heldout_psnr_db']:.1f} dB PSNR, SSIM {held['heldout_ssim']:.2f}"
            f" ({held['heldout_frames']} frames)"
        )
    print(f"demo finished in {dt:.0f} s: " + ", ".join(parts))
    print(
        f"outputs in {out}: report.md, summary.json, trajectory_*.tum|kitti, map.ply, depth/, "
        "renders/ (the final map at held-out frames and keyframes), snapshots/"
    )
    return code
