"""``mogs topic list|echo|hz``: look at live topics through the broker.

``echo`` prints small arrays (a pose, K) in full and summarises large ones (``--full``: all in
full); when nothing has come on the topic after :data:`SILENT_HINT_S` it says so once, with the
topics the nodes publish (from their heartbeats), so that a misspelt topic does not wait silently.
"""

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
#: echo: seconds without a message on the topic before saying who publishes what
SILENT_HINT_S = 2.0
#: echo: arrays up to this many elements are printed in full
SMALL_ARRAY = 16


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
            p.add_argument("--full", action="store_true", help="print every array in full")


def _summary(value: object, *, full: bool = False) -> str:
    if isinstance(value, np.ndarray):
        if full or (0 < value.size <= SMALL_ARRAY):
            text = np.array2string(value, threshold=sys.maxsize, max_line_width=100)
            return f"<{value.dtype} {list(value.shape)}>\n" + _indent(text, "    ")
        if value.size and value.dtype.kind in "fiu":
            return (
                f"<{value.dtype} {list(value.shape)} min {value.min():.4g} max {value.max():.4g}>"
            )
        return f"<{value.dtype} {list(value.shape)}>"
    return repr(value)


def _indent(text: str, prefix: str) -> str:
    return "\n".join(prefix + line for line in text.splitlines())


def format_message(env: msgs.Envelope, *, full: bool = False) -> str:
    lines = [f"--- {env.topic} {env.msg.TYPE} seq={env.seq} bytes={env.nbytes}"]
    for name in list(type(env.msg).SCALARS) + list(type(env.msg).ARRAYS):
        lines.append(f"  {name}: {_summary(getattr(env.msg, name), full=full)}")
    return "\n".join(lines)


def silent_topic_hint(topic: str, diags: dict[str, msgs.Diagnostics], waited_s: float) -> str:
    """What to tell a user whose ``topic`` has had no message for ``waited_s``: who publishes it,
    or that no node does, with the topics the nodes publish (from their latest heartbeats)."""
    publishers: dict[str, list[str]] = {}
    for name, d in sorted(diags.items()):
        for t, st in d.topics.items():
            if isinstance(st, dict) and st.get("published", 0) > 0 and t != DIAGNOSTICS_TOPIC:
                publishers.setdefault(t, []).append(name)
    if not diags:
        return (
            f"nothing on {topic} after {waited_s:.0f} s and no node heard on this bus: is the run "
            "going, and on these endpoints (--launch FILE or --bus-name NAME)?"
        )
    # a subscription is to the exact name; "/" alone is every topic
    mine = [n for t, ns in publishers.items() if topic in (t, "/") for n in ns]
    if mine:
        return (
            f"nothing on {topic} after {waited_s:.0f} s; it is published by {sorted(set(mine))}: "
            "waiting for the next message"
        )
    live = ", ".join(f"{t} ({', '.join(ns)})" for t, ns in sorted(publishers.items()))
    return f"no publisher of {topic} seen after {waited_s:.0f} s; the live topics are: " + (
        live or "none yet"
    )


def command(args: argparse.Namespace) -> int:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    sub = Subscriber(bus_from_args(args))
    topic = getattr(args, "topic", "/")
    sub.subscribe(topic)
    # hz also reads the nodes' heartbeats: their drops, losses, malformed counts and latency
    diags: dict[str, msgs.Diagnostics] = {}
    if args.action in ("hz", "echo") and topic != DIAGNOSTICS_TOPIC:
        sub.subscribe(DIAGNOSTICS_TOPIC)
    hinted = args.action != "echo" or topic == DIAGNOSTICS_TOPIC
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
                    print(format_message(env, full=args.full), flush=True)
                    if args.count is not None and n >= args.count:
                        break
            if not hinted and n == 0 and now - t0 >= SILENT_HINT_S:
                hinted = True
                print(silent_topic_hint(topic, diags, now - t0), file=sys.stderr, flush=True)
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
