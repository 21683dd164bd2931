"""``mogs play kitti|euroc|bag|sim``: stream a sequence onto the bus (the player node, in-process).

The broker must be running (``mogs launch FILE`` or ``mogs broker``); ``--launch FILE`` or
``--bus-name NAME`` pick its endpoints. Examples::

    mogs play kitti ../shared/data/kitti_raw_2011_09_26_78 --launch launch/kitti.yaml
    mogs play euroc ../shared/data/euroc_v1_01_micro --rate 0.5
    mogs play bag run.mcap --image-topic /cam/image_raw --imu-topic /imu0 --fast
    mogs play sim --frames 40 --size 621x188 --seed 3 --fast

Pause with ``kill -USR1 PID``, resume with ``kill -USR2 PID``.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging

from mogs_node.commands.broker import bus_from_args
from mogs_node.commands.options import field_option, fields_from_args
from mogs_node.errors import ConfigError

HELP = "stream a KITTI / EuRoC / bag / synthetic sequence onto the bus"

log = logging.getLogger(__name__)


def _endpoint_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("bus")
    g.add_argument("--launch", default=None, help="take the bus endpoints from this launch file")
    g.add_argument("--bus-name", default=None, help="name of a default ipc bus (launch file name)")
    g.add_argument("--pub", default=None, help="publisher endpoint of the broker")
    g.add_argument("--sub", default=None, help="subscriber endpoint of the broker")
    g.add_argument("--bus-json", default=None, help=argparse.SUPPRESS)


#: the ``dest`` prefix of the options that set a player parameter (the rest of the ``dest``)
_PLAYER = "player."


def _play_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("playback")
    opt = functools.partial(field_option, g, _PLAYER)  # sets the player parameter it names
    opt("--rate", "rate", type=float, default=1.0, help="speed factor (1 = recorded rate)")
    fast_help = "as fast as the pipeline accepts (flow control on --ack-topic)"
    opt("--fast", "fast", action="store_true", help=fast_help)
    opt("--start", "start_s", type=float, default=0.0, metavar="S", help="skip the first S seconds")
    opt("--end", "end_s", type=float, default=None, metavar="S", help="stop S seconds in")
    lead_help = "IMU from S seconds before frame 1"
    opt("--imu-lead", "imu_lead_s", type=float, default=1.2, metavar="S", help=lead_help)
    height_help = "camera above the road (m)"
    opt("--camera-height", "camera_height_m", type=float, metavar="M", help=height_help)
    opt("--ack-topic", "ack_topic", default="/frontend/odometry", help="fast: acknowledgements")
    in_flight_help = "fast: unacknowledged images at most"
    opt("--max-in-flight", "max_frames_in_flight", type=int, default=1, help=in_flight_help)
    kf_help = "fast: keyframes waiting for /metrizer/depth at most (0 = not watched)"
    opt("--max-keyframes-in-flight", "max_keyframes_in_flight", type=int, default=0, help=kf_help)
    opt("--encoding", "encoding", default="", choices=["", "mono8", "rgb8", "bgr8"])
    opt("--no-groundtruth", "groundtruth", action="store_false", help="no /groundtruth/pose")
    gt_help = "also publish /groundtruth/depth"
    opt("--gt-depth", "groundtruth_depth", action="store_true", help=gt_help)
    wait_help = "seconds to wait for an image subscriber"
    opt("--wait", "wait_for_subscriber_s", type=float, default=10.0, help=wait_help)
    progress_help = "seconds between progress lines"
    opt("--progress", "progress_period_s", type=float, default=2.0, help=progress_help)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="kind", metavar="SOURCE", required=True)
    k = sub.add_parser("kitti", help="KITTI raw drive (or --odometry sequence) folder")
    k.add_argument("path")
    k.add_argument("--odometry", action="store_true", help="KITTI odometry sequences/XX layout")
    e = sub.add_parser("euroc", help="EuRoC ASL folder (holding mav0)")
    e.add_argument("path")
    v = sub.add_parser(
        "vi", help="a visual-inertial folder with a Kalibr camchain.yaml (TUM-VI, Basalt, DM-VIO)"
    )
    v.add_argument("path")
    b = sub.add_parser("bag", help="rosbag1 / rosbag2 (sqlite3, MCAP) or a `mogs record` file")
    b.add_argument("path")
    b.add_argument("--image-topic", default="/camera/image_raw")
    b.add_argument("--imu-topic", default="/imu", help="'' for none")
    b.add_argument("--camera-info-topic", default="/camera/camera_info", help="'' for none")
    b.add_argument("--pose-topic", default="/ground_truth/pose", help="'' for none")
    b.add_argument("--depth-topic", default="/ground_truth/depth", help="'' for none")
    b.add_argument(
        "--intrinsics", default=None, metavar="FX,FY,CX,CY,W,H", help="bag without CameraInfo"
    )
    s = sub.add_parser("sim", help="the synthetic driving world")
    s.add_argument("--frames", type=int, default=30)
    s.add_argument("--size", default="621x188", help="WxH (default 621x188)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--trajectory", choices=["synthetic", "oxts"], default="synthetic")
    for p in (k, e, v, b, s):
        _play_args(p)
        _endpoint_args(p)


def params_from_args(args: argparse.Namespace) -> dict:
    """The player node's parameters (a JSON-able dict) from the parsed command line."""
    params = fields_from_args(args, _PLAYER)
    if args.kind == "kitti":
        params.update(source="kitti_odometry" if args.odometry else "kitti", path=args.path)
    elif args.kind == "euroc":
        params.update(source="euroc", path=args.path)
    elif args.kind == "vi":
        params.update(source="vi_folder", path=args.path)
    elif args.kind == "bag":
        from bridges.recording import is_recording

        if is_recording(args.path):
            params.update(source="recording", path=args.path)
        else:
            params.update(
                source="bag",
                path=args.path,
                bag_image_topic=args.image_topic,
                bag_imu_topic=args.imu_topic,
                bag_camera_info_topic=args.camera_info_topic,
                bag_pose_topic=args.pose_topic,
                bag_depth_topic=args.depth_topic,
            )
            if args.intrinsics:
                try:
                    vals = [float(v) for v in args.intrinsics.split(",")]
                except ValueError as err:
                    raise ConfigError(
                        f"--intrinsics: expected 6 numbers, got {args.intrinsics!r}"
                    ) from err
                if len(vals) != 6:
                    raise ConfigError(f"--intrinsics: expected 6 numbers, got {len(vals)}")
                params["intrinsics"] = vals
    else:
        from mogs_node.commands.sim import parse_size

        w, h = parse_size(args.size)
        params.update(
            source="sim",
            sim={
                "n_frames": args.frames,
                "width": w,
                "height": h,
                "seed": args.seed,
                "trajectory": args.trajectory,
            },
        )
    return params


def command(args: argparse.Namespace) -> int:
    from bridges.player import PlayerNode

    params = params_from_args(args)
    log.debug("player params: %s", json.dumps(params))
    node = PlayerNode("player", params, bus_from_args(args))
    return node.run()
