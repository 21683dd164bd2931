"""``mogs record OUT.mcap [--topics ...]``: record bus topics to MCAP (replay with ``mogs play bag``).

Each message is stored twice: its raw multipart frames (bit-exact replay) and, where one exists,
its standard ROS 2 form under ``/ros2<topic>`` (see :mod:`bridges.recording`). Stops on Ctrl-C,
after ``--duration`` seconds or ``--count`` messages.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading

from mogs_node.commands.broker import bus_from_args
from mogs_node.commands.play import _endpoint_args

HELP = "record bus topics to an MCAP file"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", help="output: FILE.mcap (one file) or a folder (rosbag2 + MCAP)")
    parser.add_argument("--topics", nargs="+", default=[], help="topics to record (default: all)")
    parser.add_argument("--duration", type=float, default=None, help="stop after S seconds")
    parser.add_argument("--count", type=int, default=0, help="stop after N messages")
    parser.add_argument("--no-ros2", action="store_true", help="raw frames only")
    _endpoint_args(parser)


def command(args: argparse.Namespace) -> int:
    from bridges.recording import BusRecorder

    rec = BusRecorder(
        bus_from_args(args), args.out, topics=tuple(args.topics), ros2_types=not args.no_ros2
    )
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    log.info("recording %s to %s", " ".join(args.topics) or "every topic", args.out)
    counts = rec.run(stop, duration_s=args.duration, max_messages=args.count)
    log.info("recorded %d messages: %s", sum(counts.values()), counts)
    return 0
