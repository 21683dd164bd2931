"""``mogs eval depth|traj|map``: run an evaluation and print / write its figures.

Dataset-specific work lives in ``mogs_node.eval``: ``depth_<dataset>.evaluate(args)``,
``frontend_runs.evaluate(args)`` and ``map.evaluate(args)`` each return the JSON-ready dict whose keys are
fixed by DESIGN.md section 7. Nothing under ``docs/`` is written unless ``--write-docs`` (the
standard run of each then replaces its section of ``docs/benchmarks.md``; ``eval map`` also
its plot), so that ``git status`` stays clean after any evaluation.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys

from mogs_node.errors import ConfigError
from mogs_node.eval.bench_docs import write_json

DEPTH_DATASETS = {
    "sim": "mogs_node.eval.depth_sim",
    "kitti78": "mogs_node.eval.depth_kitti78",
    "demo": "mogs_node.eval.depth_demo",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="what", metavar="WHAT", required=True)

    depth = sub.add_parser("depth", help="depth metrization ablation (AbsRel, RMSE, delta1)")
    depth.add_argument("--dataset", choices=sorted(DEPTH_DATASETS), default="sim")
    depth.add_argument(
        "--frames", type=int, default=None, help="number of keyframes (default per dataset)"
    )
    depth.add_argument("--seed", type=int, default=0)
    depth.add_argument(
        "--masks",
        choices=["oracle", "graph", "both"],
        default="both",
        help="instance masks on sim: ground truth, the graph segmenter, or both",
    )
    depth.add_argument("--size", default=None, help="WxH render size for sim (default per dataset)")
    depth.add_argument(
        "--data", default=None, help="dataset folder (kitti78: default ../shared/data/...)"
    )
    depth.add_argument(
        "--viz", default=None, metavar="DIR", help="write image|masks|prior|depth|error strips"
    )
    depth.add_argument(
        "--launch", default=None, help="demo: its launch file (default launch/demo.yaml)"
    )
    depth.add_argument(
        "--points",
        choices=["lidar", "tracks"],
        default="lidar",
        help="kitti78 sparse points: LiDAR at the tracked corners, or the system's own KLT "
        "tracks triangulated with the PnP poses (docs/frontend.md)",
    )
    depth.add_argument(
        "--json", default=None, metavar="PATH", help="also write the figures as JSON"
    )
    depth.set_defaults(_eval="depth")

    traj = sub.add_parser("traj", help="run the frontend on a sequence; ATE/RPE with evo")
    traj.add_argument("--dataset", choices=["sim", "oxts", "euroc"], default="sim")
    traj.add_argument("--seconds", type=float, default=None, help="sequence length (sim/oxts)")
    traj.add_argument("--seed", type=int, default=0)
    traj.add_argument("--data", default=None, help="dataset folder (default ../shared/data/...)")
    traj.add_argument(
        "--out", default=None, metavar="DIR", help="write TUM/KITTI trajectories here"
    )
    traj.add_argument(
        "--no-ground",
        action="store_true",
        help="sim/oxts: camera and IMU only, without the translation measured on the road at the "
        "camera's calibrated height (docs/frontend.md, round 5)",
    )
    traj.add_argument("--json", default=None, metavar="PATH", help="also write the figures as JSON")
    traj.set_defaults(_eval="traj")

    gmap = sub.add_parser(
        "map", help="Gaussian map quality and convergence for three initialisations"
    )
    gmap.add_argument("--dataset", choices=["sim"], default="sim")
    gmap.add_argument("--seed", type=int, default=0)
    gmap.add_argument("--iters", type=int, default=None, help="iteration budget")
    gmap.add_argument("--target-psnr", type=float, default=20.0)
    gmap.add_argument("--plot", default=None, metavar="PNG", help="Gaussians-vs-iterations plot")
    gmap.add_argument("--json", default=None, metavar="PATH", help="also write the figures as JSON")
    gmap.set_defaults(_eval="map")
    for p in (depth, traj, gmap):
        p.add_argument(
            "--write-docs",
            action="store_true",
            help="the standard run replaces its section of docs/benchmarks.md (default: no docs/)",
        )


def command(args: argparse.Namespace) -> int:
    if args._eval == "depth":
        module_name = DEPTH_DATASETS[args.dataset]
    elif args._eval == "traj":
        module_name = "mogs_node.eval.frontend_runs"
    else:
        module_name = "mogs_node.eval.map"
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        raise ConfigError(
            f"eval {args._eval} --dataset {args.dataset}: not available ({err})"
        ) from err
    figures = module.evaluate(args)
    json.dump(figures, sys.stdout, indent=2, default=float)
    sys.stdout.write("\n")
    write_json(args.json, figures)
    return 0
