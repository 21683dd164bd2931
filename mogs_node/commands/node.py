"""``mogs node MODULE:CLASS``: run one node process (the launcher calls this)."""

from __future__ import annotations

import argparse
import importlib
import json

from mogs_node.bus import tune_malloc_for_large_messages
from mogs_node.commands.broker import bus_from_args
from mogs_node.errors import ConfigError
from mogs_node.node import Node


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


def command(args: argparse.Namespace) -> int:
    tune_malloc_for_large_messages()
    cls = load_node_class(args.cls)
    try:
        params = json.loads(args.params_json)
    except json.JSONDecodeError as err:
        raise ConfigError(f"--params-json: {err}") from err
    node = cls(args.name or cls.__name__, params, bus_from_args(args))
    return node.run(duration_s=args.duration)
