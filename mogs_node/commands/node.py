"""``mogs node MODULE:CLASS``: run one node process (the launcher calls this)."""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import signal

from mogs_node.bus import tune_malloc_for_large_messages
from mogs_node.commands.broker import bus_from_args
from mogs_node.errors import ConfigError
from mogs_node.node import EXIT_CONFIG, STARTUP_ERRORS, Node


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "cls", metavar="MODULE:CLASS", help="node class, e.g. mogs_node.metrizer.node:MetrizerNode"
    )
    parser.add_argument("--name", default=None, help="node name (default: class name)")
    parser.add_argument("--params-json", default="{}", help="parameters as a JSON object")
    parser.add_argument("--bus-json", default=None, help="bus configuration as JSON")
    parser.add_argument(
        "--launch", default=None, help="take the bus configuration from this launch file"
    )
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds")


def load_node_class(spec: str) -> type[Node]:
    module_name, _, cls_name = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise ConfigError(f"node class {spec}: cannot import {module_name}: {err}") from err
    cls = getattr(module, cls_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise ConfigError(f"node class {spec}: {cls_name} is not a Node subclass in {module_name}")
    return cls


def _interruptible_start() -> list[int]:
    """SIGINT / SIGTERM before the node runs interrupt the start-up (as by default) and are
    remembered in the returned list: an import interrupted that way surfaces as an ImportError,
    which must not read as a configuration error (``Node.run`` installs its own handlers)."""
    received: list[int] = []

    def interrupt(signum: int, _frame: object) -> None:
        received.append(signum)
        raise KeyboardInterrupt

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, interrupt)
    return received


def command(args: argparse.Namespace) -> int:
    """Build the node and run it; a node that cannot start with its configuration (class,
    parameters, dataset or model files: :data:`~mogs_node.node.STARTUP_ERRORS`) logs one error
    line and exits with :data:`~mogs_node.node.EXIT_CONFIG`, which the launcher never respawns."""
    tune_malloc_for_large_messages()
    name = args.name or args.cls.partition(":")[2]
    stopping = _interruptible_start()
    try:
        cls = load_node_class(args.cls)
        try:
            params = json.loads(args.params_json)
        except json.JSONDecodeError as err:
            raise ConfigError(f"--params-json: {err}") from err
        node = cls(name, params, bus_from_args(args))
    except STARTUP_ERRORS as err:
        if stopping:  # the launcher stopped us mid-import: not a configuration error
            return 130
        logging.getLogger(f"mogs.{name}").error("cannot start: %s", err)
        return EXIT_CONFIG
    return node.run(duration_s=args.duration)
