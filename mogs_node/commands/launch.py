"""``mogs launch FILE``: start the broker and every node of a launch file; Ctrl-C stops all."""

from __future__ import annotations

import argparse

import yaml

from mogs_node.errors import ConfigError
from mogs_node.launch import Launcher, load_launch_file


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="launch file (YAML), e.g. launch/demo.yaml")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NODE.PARAM=VALUE",
        help="override a node parameter (value parsed as YAML); repeatable",
    )
    parser.add_argument(
        "--timeout", type=float, default=None, help="stop everything after this many seconds"
    )
    parser.add_argument(
        "--grace", type=float, default=3.0, help="seconds between SIGINT and SIGKILL on shutdown"
    )


def parse_overrides(items: list[str]) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for item in items:
        key, sep, value = item.partition("=")
        node, dot, param = key.partition(".")
        if not (sep and dot and node and param):
            raise ConfigError(f"--set {item!r}: expected NODE.PARAM=VALUE")
        out.setdefault(node, {})[param] = yaml.safe_load(value)
    return out


def command(args: argparse.Namespace) -> int:
    launch = load_launch_file(args.file, overrides=parse_overrides(args.set))
    return Launcher(launch, grace_s=args.grace).run(timeout_s=args.timeout)
