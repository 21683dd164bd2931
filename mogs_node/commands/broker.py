"""``mogs broker``: run the XSUB/XPUB message broker until SIGINT/SIGTERM."""

from __future__ import annotations

import argparse
import json
import signal
import threading

from mogs_node.bus import BusConfig, default_bus_config, run_broker, tune_malloc_for_large_messages


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pub", help="endpoint publishers connect to (broker binds XSUB)")
    parser.add_argument("--sub", help="endpoint subscribers connect to (broker binds XPUB)")
    parser.add_argument("--bus-json", help="full bus configuration as JSON (used by the launcher)")
    parser.add_argument(
        "--allow-remote", action="store_true", help="allow non-loopback tcp addresses"
    )


def bus_from_args(args: argparse.Namespace) -> BusConfig:
    if getattr(args, "bus_json", None):
        return BusConfig.from_dict(json.loads(args.bus_json))
    if getattr(args, "launch", None):
        from mogs_node.launch import load_launch_file

        return load_launch_file(args.launch).bus
    cfg = default_bus_config(getattr(args, "bus_name", None) or "default")
    if getattr(args, "pub", None) or getattr(args, "sub", None):
        cfg = BusConfig(
            pub_endpoint=args.pub or cfg.pub_endpoint, sub_endpoint=args.sub or cfg.sub_endpoint
        )
    return cfg


def command(args: argparse.Namespace) -> int:
    config = bus_from_args(args)
    tune_malloc_for_large_messages()
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    run_broker(config, stop, allow_remote=args.allow_remote)
    return 0
