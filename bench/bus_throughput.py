"""Bus throughput: messages/s and MB/s through the MOGS broker vs a bare pyzmq PUB/SUB baseline.

Both cases run publisher and subscriber as separate processes on the same machine and transport.

- ``bare``: a pyzmq PUB socket bound by the publisher, a SUB socket connected by the subscriber;
  the publisher sends pre-built multipart frames of the same sizes as ours (no codec, no broker).
- ``mogs``: ``Publisher.publish(topic, msg)`` (our msgpack header + zero-copy arrays) -> broker
  process (XSUB/XPUB ``zmq.proxy``) -> ``Subscriber.receive`` (strict decode + gap accounting).

The ratio ``mogs / bare`` is measured in the same run. Usage::

    python bench/bus_throughput.py [--transport ipc|tcp] [--keyframes 300] [--imu 100000] [--json PATH]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import socket
import sys
import tempfile
import threading
import time

import zmq

from mogs_node import msgs
from mogs_node.bus import (
    BusConfig,
    Publisher,
    Subscriber,
    run_broker,
    tune_malloc_for_large_messages,
)
from mogs_node.demo_nodes import make_keyframe
from mogs_node.eval.report import machine_line, update_markdown_section, write_json


def imu_msg(k: int) -> msgs.Imu:
    return msgs.Imu(
        stamp_ns=k, frame_id="imu", gyro_rad_s=(0.01, 0.02, 0.03), accel_m_s2=(0.1, 0.2, 9.81)
    )


def make_msg(kind: str, k: int) -> msgs.Message:
    return make_keyframe(k % 4, width=800, height=640) if kind == "keyframe" else imu_msg(k)


TOPIC = {"keyframe": "/frontend/keyframe", "imu": "/imu"}


# ------------------------------------------------------------------------- bare pyzmq


def bare_sub(endpoint: str, n: int, q: mp.Queue, ready: mp.Event) -> None:
    ctx = zmq.Context()
    s = ctx.socket(zmq.SUB)
    s.rcvhwm = 0
    s.connect(endpoint)
    s.setsockopt(zmq.SUBSCRIBE, b"/")
    ready.set()
    frames = s.recv_multipart(copy=False)
    t0 = time.perf_counter()
    nbytes = sum(len(f.buffer) for f in frames)
    for _ in range(n - 1):
        frames = s.recv_multipart(copy=False)
        nbytes += sum(len(f.buffer) for f in frames)
    q.put((time.perf_counter() - t0, nbytes))
    s.close(0)
    ctx.term()


def bare_pub(endpoint: str, kind: str, n: int, ready: mp.Event) -> None:
    ctx = zmq.Context()
    s = ctx.socket(zmq.PUB)
    s.sndhwm = 0
    s.bind(endpoint)
    ready.wait(10)
    time.sleep(0.5)  # slow joiner
    # the same frames our codec produces, built once: the baseline pays no codec cost
    frames = [msgs.encode(TOPIC[kind], make_msg(kind, k)) for k in range(4)]
    frames = [
        [bytes(f) if not isinstance(f, memoryview) or f.nbytes < 65536 else f for f in fr]
        for fr in frames
    ]
    for k in range(n):
        s.send_multipart(frames[k % 4], copy=False)
    s.close(linger=-1)
    ctx.term()


# ------------------------------------------------------------------------- through the broker


def mogs_sub(bus_d: dict, kind: str, n: int, q: mp.Queue, ready: mp.Event) -> None:
    tune_malloc_for_large_messages()  # as `mogs node` does at start
    sub = Subscriber(BusConfig.from_dict(bus_d), hwm=0)
    sub.subscribe(TOPIC[kind])
    ready.set()
    env = sub.receive(timeout_ms=None)
    t0 = time.perf_counter()
    nbytes = env.nbytes
    for _ in range(n - 1):
        env = sub.receive(timeout_ms=None)
        nbytes += env.nbytes
    dt = time.perf_counter() - t0
    st = sub.stats[TOPIC[kind]]
    q.put((dt, nbytes, st.lost, st.malformed))
    sub.close()
    zmq.Context.instance().term()


def mogs_pub(bus_d: dict, kind: str, n: int, ready: mp.Event) -> None:
    tune_malloc_for_large_messages()
    pub = Publisher(BusConfig.from_dict(bus_d), hwm=0)
    ready.wait(10)
    assert pub.wait_for_subscriber(TOPIC[kind], 10)
    messages = [make_msg(kind, k) for k in range(4)]
    topic = TOPIC[kind]
    for k in range(n):
        pub.publish(topic, messages[k % 4])
    pub.close(linger_ms=-1)
    zmq.Context.instance().term()  # blocks until every zero-copy frame has been sent


def broker_proc(bus_d: dict, stop: mp.Event) -> None:
    tune_malloc_for_large_messages()  # as `mogs broker` does at start
    ev = threading.Event()
    t = threading.Thread(target=run_broker, args=(BusConfig.from_dict(bus_d), ev))
    t.start()
    stop.wait()
    ev.set()
    t.join()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint(transport: str, tmp: str, name: str) -> str:
    return f"tcp://127.0.0.1:{free_port()}" if transport == "tcp" else f"ipc://{tmp}/{name}.ipc"


def run_case(case: str, kind: str, n: int, transport: str, tmp: str) -> dict[str, float]:
    q: mp.Queue = mp.Queue()
    ready = mp.Event()
    procs = []
    if case == "bare":
        ep = endpoint(transport, tmp, f"bare-{kind}")
        procs = [
            mp.Process(target=bare_sub, args=(ep, n, q, ready)),
            mp.Process(target=bare_pub, args=(ep, kind, n, ready)),
        ]
        stop = None
    else:
        bus = BusConfig(
            endpoint(transport, tmp, f"p-{kind}"),
            endpoint(transport, tmp, f"s-{kind}"),
            reliable_hwm=0,
        ).to_dict()
        stop = mp.Event()
        broker = mp.Process(target=broker_proc, args=(bus, stop))
        broker.start()
        time.sleep(0.3)
        procs = [
            broker,
            mp.Process(target=mogs_sub, args=(bus, kind, n, q, ready)),
            mp.Process(target=mogs_pub, args=(bus, kind, n, ready)),
        ]
        procs = procs[1:]
        procs_all = [broker]
    for p in procs:
        p.start()
    res = q.get(timeout=600)
    for p in procs:
        p.join(60)
    if stop is not None:
        stop.set()
        for p in procs_all:
            p.join(10)
    dt, nbytes = res[0], res[1]
    out = {"msgs_per_s": (n - 1) / dt, "mb_per_s": nbytes / dt / 1e6}
    if case == "mogs":
        out["lost"] = res[2]
        out["malformed"] = res[3]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--transport", choices=["ipc", "tcp"], default="ipc")
    ap.add_argument("--keyframes", type=int, default=300, help="1.5 MB keyframes per case")
    ap.add_argument("--imu", type=int, default=100_000, help="IMU messages per case")
    ap.add_argument("--repeats", type=int, default=3, help="best of N runs per case")
    ap.add_argument("--json", default=None)
    ap.add_argument("--no-docs", action="store_true", help="do not update docs/benchmarks.md")
    args = ap.parse_args(argv)
    mp.set_start_method("spawn", force=True)
    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="mogs-bench-") as tmp:
        for kind, n in (("keyframe", args.keyframes), ("imu", args.imu)):
            for case in ("bare", "mogs"):
                runs = [run_case(case, kind, n, args.transport, tmp) for _ in range(args.repeats)]
                best = max(runs, key=lambda r: r["msgs_per_s"])
                figures[f"{kind}_{case}_msgs_per_s"] = round(best["msgs_per_s"], 1)
                figures[f"{kind}_{case}_mb_per_s"] = round(best["mb_per_s"], 1)
                if case == "mogs":
                    figures[f"{kind}_mogs_lost_msgs"] = sum(r["lost"] for r in runs)
                print(
                    f"{kind:9s} {case:5s} {best['msgs_per_s']:10.1f} msg/s {best['mb_per_s']:9.1f} MB/s",
                    flush=True,
                )
            figures[f"{kind}_ratio_vs_bare_zmq"] = round(
                figures[f"{kind}_mogs_msgs_per_s"] / figures[f"{kind}_bare_msgs_per_s"], 3
            )
            print(
                f"{kind:9s} ratio mogs/bare = {figures[f'{kind}_ratio_vs_bare_zmq']:.3f}",
                flush=True,
            )
    figures["transport"] = args.transport  # type: ignore[assignment]
    write_json(args.json, figures)
    if not args.no_docs:
        cmd = "python bench/bus_throughput.py " + " ".join(
            argv if argv is not None else sys.argv[1:]
        )
        body = [
            "## Bus throughput (issue 2)",
            "",
            f"Command: `{cmd.strip()}`  ",
            f"Machine: {machine_line()}; transport {args.transport}; best of {args.repeats} runs; "
            "publisher, broker and subscriber are separate processes.",
            "",
            "| message | bare pyzmq msg/s | bare MB/s | MOGS bus msg/s | MOGS MB/s | ratio | lost |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for kind, label in (
            ("keyframe", "Keyframe 800x640 RGB + 500 features (1.55 MB)"),
            ("imu", "Imu (small)"),
        ):
            body.append(
                f"| {label} | {figures[f'{kind}_bare_msgs_per_s']:.0f} | {figures[f'{kind}_bare_mb_per_s']:.0f} | "
                f"{figures[f'{kind}_mogs_msgs_per_s']:.0f} | {figures[f'{kind}_mogs_mb_per_s']:.0f} | "
                f"{figures[f'{kind}_ratio_vs_bare_zmq']:.2f} | {figures[f'{kind}_mogs_lost_msgs']} |"
            )
        update_markdown_section("bus_throughput", "\n".join(body))
    return 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
