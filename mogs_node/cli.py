"""The ``mogs`` command: argparse -> a typed ``command(args) -> exit code`` -> library code.

Each subcommand lives in ``mogs_node/commands/<name>.py`` and exposes ``HELP`` (one line),
``add_arguments(parser)`` and ``command(args) -> int``. Modules are imported lazily so that
``mogs --help`` stays fast and a missing optional dependency only affects its own command.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from mogs_node.errors import MogsError

__all__ = ["main"]

# name -> (module, one-line help); the help is here so `mogs --help` imports nothing heavy.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "launch": ("mogs_node.commands.launch", "start the broker and every node of a launch file"),
    "broker": ("mogs_node.commands.broker", "run the XSUB/XPUB message broker"),
    "node": ("mogs_node.commands.node", "run one node (used by the launcher)"),
    "topic": ("mogs_node.commands.topic", "inspect live topics: list, echo, hz"),
    "demo": (
        "mogs_node.commands.demo",
        "run the whole pipeline on the embedded synthetic sequence",
    ),
    "sim": ("mogs_node.commands.sim", "generate a synthetic driving sequence with ground truth"),
    "eval": ("mogs_node.commands.eval", "evaluate depth, trajectory or map against ground truth"),
    "play": ("mogs_node.commands.play", "stream a KITTI / EuRoC / bag / synthetic sequence"),
    "live": ("mogs_node.commands.live", "stream a live camera or IMU onto the bus"),
    "record": ("mogs_node.commands.record", "record bus topics to an MCAP file"),
    "ros2": ("mogs_node.commands.ros2", "mirror bus topics to and from ROS 2 (needs rclpy)"),
    "keys": ("mogs_node.commands.keys", "generate CURVE key pairs for an authenticated tcp bus"),
    "batch": ("mogs_node.commands.batch", "map many drives in one batch on Ray (local or cluster)"),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog="mogs",
        description="MOGS node: online monocular visual-inertial Gaussian splatting over ZeroMQ.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="subcommand", metavar="COMMAND")
    # Find the chosen subcommand first so only its module is imported.
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            module = importlib.import_module(module_name)
            module.add_arguments(sp)
            sp.set_defaults(_command=module.command)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose > 1 else logging.INFO,
        format="%(asctime)s %(levelname).1s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    if not getattr(args, "_command", None):
        parser.print_help()
        return 2
    try:
        return int(args._command(args) or 0)
    except MogsError as err:
        logging.getLogger("mogs").error("%s", err)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
