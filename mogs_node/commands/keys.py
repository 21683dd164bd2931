"""``mogs keys DIR``: generate CURVE key pairs for a bus that crosses hosts.

Writes ``broker.key`` / ``broker.key_secret`` and one pair per client name, and copies the client
public keys into ``DIR/authorized`` (the broker's accept list). Point the launch file's
``bus.curve`` at them (see docs/architecture.md).
"""

from __future__ import annotations

import argparse

from mogs_node.bus import generate_keys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", help="folder for the key files (created)")
    parser.add_argument("--clients", nargs="+", default=["client"], help="client key names")


def command(args: argparse.Namespace) -> int:
    written = generate_keys(args.dir, ["broker", *args.clients])
    for name, path in written.items():
        print(f"{name}: {path} (secret) and {path.with_suffix('.key')} (public)")
    print(f"authorised client keys: {args.dir}/authorized")
    return 0
