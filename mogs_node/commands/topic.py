"""``mogs topic list|echo|hz``: look at live topics through the broker."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time

import numpy as np

from mogs_node import msgs
from mogs_node.bus import Subscriber
from mogs_node.commands.broker import bus_from_args

DIAGNOSTICS_TOPIC = "/diagnostics"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    for name, help_text in (
        ("list", "listen for a while and list the topics seen, with types and rates"),
        ("echo", "print messages of a topic (arrays summarised)"),
        ("hz", "rate, bandwidth, gaps, drops and malformed counts of a topic"),
    ):
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name != "list":
            p.add_argument("topic", help="topic name, e.g. /frontend/odometry")
        p.add_argument(
            "--launch", default=None, help="take the bus endpoints from this launch file"
        )
        p.add_argument(
            "--bus-name", default=None, help="name of a default ipc bus (launch file 'name')"
        )
        p.add_argument("--pub", default=None, help=argparse.SUPPRESS)
        p.add_argument("--sub", default=None, help="subscriber endpoint of the broker")
        p.add_argument(
            "--duration",
            type=float,
            default=None if name != "list" else 2.0,
            help="seconds to listen (default: until Ctrl-C; list: 2 s)",
        )
        if name == "echo":
            p.add_argument("-n", "--count", type=int, default=None, help="stop after N messages")


def _summary(value: object) -> str:
    if isinstance(value, np.ndarray):
        if value.size and value.dtype.kind in "fiu":
            return (
                f"<{value.dtype} {list(value.shape)} min {value.min():.4g} max {value.max():.4g}>"
            )
        return f"<{value.dtype} {list(value.shape)}>"
    return repr(value)


def format_message(env: msgs.Envelope) -> str:
    lines = [f"--- {env.topic} {env.msg.TYPE} seq={env.seq} bytes={env.nbytes}"]
    for name in list(type(env.msg).SCALARS) + list(type(env.msg).ARRAYS):
        lines.append(f"  {name}: {_summary(getattr(env.msg, name))}")
    return "\n".join(lines)


def command(args: argparse.Namespace) -> int:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    sub = Subscriber(bus_from_args(args))
    topic = getattr(args, "topic", "/")
    sub.subscribe(topic)
    # hz also reads the nodes' heartbeats: their drops, losses, malformed counts and latency
    diags: dict[str, msgs.Diagnostics] = {}
    if args.action == "hz" and topic != DIAGNOSTICS_TOPIC:
        sub.subscribe(DIAGNOSTICS_TOPIC)
    t0 = time.monotonic()
    end = None if args.duration is None else t0 + args.duration
    types: dict[str, str] = {}
    n = 0
    last_report = t0
    try:
        while not stop.is_set() and (end is None or time.monotonic() < end):
            env = sub.receive(timeout_ms=100)
            now = time.monotonic()
            if env is not None and env.topic == DIAGNOSTICS_TOPIC and topic != DIAGNOSTICS_TOPIC:
                if isinstance(env.msg, msgs.Diagnostics):
                    diags[env.msg.node] = env.msg
                env = None
            if env is not None:
                n += 1
                types[env.topic] = env.msg.TYPE
                if args.action == "echo":
                    print(format_message(env), flush=True)
                    if args.count is not None and n >= args.count:
                        break
            if args.action == "hz" and now - last_report >= 1.0:
                _print_hz(sub, topic, now - t0, diags)
                last_report = now
    finally:
        sub.close()
    if args.action == "list":
        dt = time.monotonic() - t0
        for t in sorted(sub.stats):
            st = sub.stats[t]
            print(
                f"{t:<28} {types.get(t, '?'):<14} {st.received / dt:8.1f} msg/s  "
                f"lost {st.lost}  malformed {st.malformed}"
            )
        if not sub.stats:
            print(
                "no messages seen (is the broker running, and on which endpoints?)", file=sys.stderr
            )
    if args.action == "hz":
        _print_hz(sub, topic, time.monotonic() - t0, diags)
    return 0


def node_topic_lines(topic: str, diags: dict[str, msgs.Diagnostics]) -> list[str]:
    """One line per node that publishes or subscribes ``topic``, from its latest ``/diagnostics``:
    what it published or received, dropped (best effort, latest wins), lost (sequence gaps) and
    rejected as malformed on that topic, and its handler latency."""
    lines = []
    for name in sorted(diags):
        d = diags[name]
        st = d.topics.get(topic)
        if not isinstance(st, dict):
            continue
        parts = []
        if "published" in st:
            parts.append(f"published {st['published']}")
        if "received" in st:
            parts.append(
                f"received {st.get('received', 0)}  dropped {st.get('dropped', 0)}  "
                f"lost {st.get('lost', 0)}  malformed {st.get('malformed', 0)}"
            )
        lat = d.counters.get("loop_latency_ms")
        if lat is not None and "received" in st:
            parts.append(
                f"latency {lat:.1f} ms (max {d.counters.get('handler_ms_max', 0.0):.1f})  "
                f"queue {int(d.counters.get('queue_depth', 0))}"
            )
        lines.append(f"  {name:<14} [{d.status}] " + "  ".join(parts))
    return lines


def _print_hz(
    sub: Subscriber, topic: str, dt: float, diags: dict[str, msgs.Diagnostics] | None = None
) -> None:
    st = sub.stats.get(topic)
    if st is None or dt <= 0:
        print(f"{topic}: no messages yet", flush=True)
    else:
        print(
            f"{topic}: {st.received / dt:.2f} msg/s  {st.received_bytes / dt / 1e6:.2f} MB/s  "
            f"received {st.received}  lost {st.lost} in {st.gaps} gaps  malformed {st.malformed}",
            flush=True,
        )
    for line in node_topic_lines(topic, diags or {}):
        print(line, flush=True)
