"""``mogs batch LAUNCH.yaml DRIVE...``: map many drives, one Ray task per drive (docs/fleet.md).

Examples::

    mogs batch launch/bag.yaml drives/*.mcap --out runs/fleet            # local Ray, all cores
    mogs batch launch/kitti.yaml --drives-from drives.txt --cpus-per-drive 2
    mogs batch launch/bag.yaml d1 d2 --ray-address auto                  # a running cluster

Each drive's run folder is ``OUT/<drive id>``; the table is ``OUT/fleet.csv``, ``OUT/fleet.md``
and ``OUT/fleet.png``. Re-running the same command skips the drives that completed (resume).
The exit code is 0 when every drive completed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import sys

from mogs_node.commands.launch import add_run_options, parse_overrides

HELP = "map many drives in one batch on Ray (local or a cluster)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("launch", help="launch file (YAML) run for every drive")
    parser.add_argument(
        "drives", nargs="*", help="drive paths (the launch file's player reads each one)"
    )
    parser.add_argument(
        "--drives-from",
        action="append",
        default=[],
        metavar="FILE",
        help="a text file with one drive path a line; repeatable",
    )
    parser.add_argument("--out", default="runs/fleet", help="output folder (default runs/fleet)")
    parser.add_argument(
        "--ray-address",
        default=None,
        metavar="ADDR",
        help="join this Ray cluster (e.g. auto, ray://head:10001); default: a local Ray",
    )
    parser.add_argument(
        "--num-cpus", type=int, default=None, help="local Ray only: CPUs it may use (default all)"
    )
    parser.add_argument(
        "--cpus-per-drive", type=float, default=1.0, help="Ray CPUs reserved per drive (default 1)"
    )
    parser.add_argument(
        "--max-retries",
        type=int,
        default=1,
        help="attempts after a drive crashed (config errors and timeouts are not retried)",
    )
    timeout_help = "per-drive timeout in seconds (default 3600; 0: none)"
    add_run_options(parser, timeout_help, timeout_s=3600.0, grace_s=10.0)
    parser.add_argument(
        "--path-param",
        default="player.path",
        metavar="NODE.PARAM",
        help="the parameter that takes the drive's path (default player.path)",
    )
    parser.add_argument(
        "--no-resume", action="store_true", help="run every drive, also those already complete"
    )


def command(args: argparse.Namespace) -> int:
    from mogs_node.fleet.batch import BatchOptions, run_batch
    from mogs_node.fleet.drives import read_drive_list

    opts = BatchOptions(
        ray_address=args.ray_address,
        num_cpus=args.num_cpus,
        cpus_per_drive=args.cpus_per_drive,
        max_retries=args.max_retries,
        timeout_s=args.timeout or None,
        grace_s=args.grace,
        path_param=args.path_param,
        overrides=parse_overrides(args.set),
        resume=not args.no_resume,
    )
    drives = read_drive_list(args.drives, args.drives_from)
    result = run_batch(args.launch, drives, args.out, opts, progress=sys.stderr)
    ok = sum(r["status"] == "complete" for r in result.rows)
    print(
        f"fleet: {ok}/{len(result.rows)} drives complete ({result.ran} run, {result.skipped} "
        f"skipped as complete) in {result.wall_s:.0f} s; table: {result.out_dir / 'fleet.md'}"
    )
    for r in result.rows:
        if r["status"] != "complete":
            print(f"  {r['drive']}: {r['status']}: {r['error']}")
    return 0 if ok == len(result.rows) else 1
