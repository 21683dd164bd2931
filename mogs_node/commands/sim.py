"""``mogs sim``: generate a synthetic driving sequence with ground truth, write it, preview it.

Examples::

    mogs sim --preview sim.png                                   # a picture only
    mogs sim --out /tmp/sim_kitti --frames 50 --size 621x188      # KITTI-raw layout
    mogs sim --out /tmp/sim.mcap --format mcap --trajectory oxts  # MCAP rosbag2
    mogs sim --motion handheld --time-offset-ms 50 --format rosbag2 --out /tmp/walk  # a walk
"""

from __future__ import annotations

import argparse
import functools
import logging
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from mogs_node.commands.options import field_option, fields_from_args
from mogs_node.errors import ConfigError

HELP = "generate a synthetic driving sequence with ground truth"
FORMATS = ("kitti", "rosbag2", "mcap", "rosbag1", "kitti-odometry", "vi-folder")

log = logging.getLogger(__name__)

#: the ``dest`` prefix of the options that set a ``SimConfig`` field (the rest of the ``dest``)
_SIM = "sim."


def parse_size(text: str) -> tuple[int, int]:
    """``'621x188'`` -> (621, 188)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise ConfigError(f"--size: expected WxH, got {text!r}") from err
    if w < 8 or h < 8:
        raise ConfigError(f"--size: too small ({text})")
    return w, h


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out",
        default=None,
        metavar="PATH",
        help="destination: a folder (kitti), a bag folder (rosbag2/mcap) or a .bag file (rosbag1)",
    )
    parser.add_argument(
        "--format", choices=FORMATS, default="kitti", help="output format (default kitti)"
    )
    opt = functools.partial(field_option, parser, _SIM)  # sets the SimConfig field it names
    opt("--frames", "n_frames", type=int, default=30, help="number of frames (default 30)")
    parser.add_argument(
        "--size", default="1242x375", help="image size WxH (default 1242x375, KITTI)"
    )
    opt("--seed", "seed", type=int, default=0)
    opt(
        "--trajectory",
        "trajectory",
        choices=["synthetic", "oxts"],
        default="synthetic",
        help="random curvy drive, or the real KITTI OXTS drive in ../shared/data",
    )
    opt("--oxts-dir", "oxts_dir", default=None, help="OXTS folder for --trajectory oxts")
    opt(
        "--motion",
        "motion",
        choices=["car", "handheld"],
        default="car",
        help="synthetic: a car drive, or a handheld walk (1.4 m/s, step bounce, head turns up "
        "to 90 deg/s, hand shake)",
    )
    opt(
        "--speed",
        "speed_m_s",
        type=float,
        default=None,
        help="mean speed of the synthetic trajectory (m/s; default 10 car, 1.4 handheld)",
    )
    parser.add_argument(
        "--time-offset-ms",
        type=float,
        default=0.0,
        metavar="MS",
        help="camera stamps shifted against the IMU: a frame taken at IMU time t is stamped "
        "t - MS (the frontend's time_offset_ns convention, t_imu = t_cam + offset); all formats",
    )
    opt("--fps", "frame_rate_hz", type=float, default=10.0, help="camera frame rate (Hz)")
    opt("--imu-rate", "imu_rate_hz", type=float, default=200.0, help="IMU rate (Hz)")
    parser.add_argument(
        "--no-imu-noise", action="store_true", help="exact IMU readings, zero biases"
    )
    opt(
        "--static-start",
        "static_start_s",
        type=float,
        default=0.0,
        metavar="S",
        help="synthetic: stand still for S seconds before driving off",
    )
    parser.add_argument(
        "--compressed", action="store_true", help="bags: PNG CompressedImage instead of Image"
    )
    parser.add_argument(
        "--poses-out",
        default=None,
        metavar="TXT",
        help="also write the ground-truth camera poses T_world_cam at the frame stamps (TUM), "
        "e.g. for `player.poses` (the sim's world: z up, origin on the road)",
    )
    parser.add_argument(
        "--preview",
        nargs="?",
        const="",
        default=None,
        metavar="PNG",
        help="write a PNG strip image|depth|instances (default OUT/preview.png or sim_preview.png)",
    )


def command(args: argparse.Namespace) -> int:
    from mogs_node.sim import ImuNoiseParams, SimConfig, make_sequence
    from mogs_node.sim.preview import preview_strip

    w, h = parse_size(args.size)
    offset_ns = int(round(args.time_offset_ms * 1e6))
    cfg = SimConfig(width=w, height=h, time_offset_ns=offset_ns, **fields_from_args(args, _SIM))
    if args.no_imu_noise:
        cfg = replace(cfg, imu_noise=ImuNoiseParams(enabled=False))
    if args.out is None and args.preview is None and args.poses_out is None:
        raise ConfigError("mogs sim: give --out PATH, --poses-out TXT and/or --preview [PNG]")
    seq = make_sequence(cfg)
    log.info(
        "sequence: %d frames %dx%d, %d primitives, %.1f m, %d IMU samples",
        len(seq),
        w,
        h,
        len(seq.world.primitives),
        float(np.linalg.norm(np.diff(seq.T_world_cam[:, :3, 3], axis=0), axis=1).sum()),
        len(seq.imu_stamps_ns),
    )
    if args.out is not None:
        from mogs_node.datasets.writers import write_kitti_raw, write_sim_bag

        if args.format == "kitti":
            write_kitti_raw(seq, args.out)
        else:
            write_sim_bag(seq, args.out, fmt=args.format, compressed=args.compressed)
        print(f"wrote {len(seq)} frames ({args.format}) to {args.out}")
    if args.poses_out is not None:
        from mogs_node.frontend.trajectory_io import write_tum

        Path(args.poses_out).parent.mkdir(parents=True, exist_ok=True)
        write_tum(args.poses_out, seq.stamps_ns, seq.T_world_cam)
        print(f"wrote {len(seq)} camera poses (TUM, T_world_cam) to {args.poses_out}")
    if args.preview is not None:
        if args.preview:
            path = Path(args.preview)
        elif args.out is not None and args.format == "kitti":
            path = Path(args.out) / "preview.png"
        else:
            path = Path("sim_preview.png")
        picks = sorted({0, len(seq) // 2, len(seq) - 1})
        strip = preview_strip([seq.render(i) for i in picks])
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), strip[..., ::-1]):
            raise ConfigError(f"--preview: cannot write {path}")
        print(f"wrote preview {path} ({strip.shape[1]}x{strip.shape[0]})")
    return 0
