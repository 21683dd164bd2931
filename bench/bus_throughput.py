"""Bus throughput: messages/s and MB/s through the MOGS broker vs a bare pyzmq PUB/SUB baseline.

Every case runs publisher and subscriber (and the broker, where there is one) as separate
processes on the same machine and transport; the cases alternate within each repeat so that
they share whatever else the machine is doing.

- ``bare``: a pyzmq PUB socket bound by the publisher, a SUB socket connected by the subscriber;
  the publisher sends pre-built multipart frames of the same sizes as ours (no codec, no broker).
  This is the baseline of the issue's goal (MOGS >= 0.8 of it).
- ``hop``: the same bare pyzmq publisher and subscriber, but through the MOGS broker process
  (``run_broker``: XSUB/XPUB ``zmq.proxy_steerable``, no Python per message). None of our codec
  or client code runs: this is what the extra process hop alone costs, i.e. an upper bound for
  any design that routes through a broker.
- ``inline``: ``Publisher.publish(topic, msg)`` (our msgpack header + zero-copy arrays) -> broker
  -> ``Subscriber.receive`` (strict decode + gap accounting), everything through the broker
  (``bus.shm_min_bytes: 0``). Keyframes only: IMU messages have no arrays, so it is ``mogs``.
- ``mogs``: the same with the bus's defaults: on ipc endpoints, arrays of 256 KiB and more go
  through a shared-memory ring of the topic and only the header through the broker
  (mogs_node/shm.py); a message whose slot a subscriber has not yet read goes inline.

Besides rates, each process reports its CPU time (user + system, all threads) per message over
the timed window: on a machine with few cores, throughput is bounded by total CPU per message.

Usage::

    python bench/bus_throughput.py [--transport ipc|tcp|both] [--keyframes 300] [--imu 100000]
        [--json PATH]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
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
from mogs_node.eval.bench_docs import (
    add_output_options,
    machine_line,
    update_markdown_section,
    write_json,
)

CASES = ("bare", "hop", "inline", "mogs")


def cases_for(kind: str) -> tuple[str, ...]:
    return CASES if kind == "keyframe" else ("bare", "hop", "mogs")


def imu_msg(k: int) -> msgs.Imu:
    return msgs.Imu(
        stamp_ns=k, frame_id="imu", gyro_rad_s=(0.01, 0.02, 0.03), accel_m_s2=(0.1, 0.2, 9.81)
    )


def make_msg(kind: str, k: int) -> msgs.Message:
    return make_keyframe(k % 4, width=800, height=640) if kind == "keyframe" else imu_msg(k)


TOPIC = {"keyframe": "/frontend/keyframe", "imu": "/imu"}


def cpu_s() -> float:
    """CPU time of this process, all threads (ZeroMQ's I/O threads included)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def bare_frames(kind: str) -> list[list[bytes | memoryview]]:
    """The same frames our codec produces, built once: the bare publisher pays no codec cost."""
    frames = [msgs.encode(TOPIC[kind], make_msg(kind, k)) for k in range(4)]
    return [
        [bytes(f) if not isinstance(f, memoryview) or f.nbytes < 65536 else f for f in fr]
        for fr in frames
    ]


# ------------------------------------------------------------------------- bare pyzmq


def bare_sub(endpoint: str, n: int, q: mp.Queue, ready: mp.Event) -> None:
    ctx = zmq.Context()
    s = ctx.socket(zmq.SUB)
    s.rcvhwm = 0
    s.connect(endpoint)
    s.setsockopt(zmq.SUBSCRIBE, b"/")
    ready.set()
    frames = s.recv_multipart(copy=False)
    t0, c0 = time.perf_counter(), cpu_s()
    nbytes = sum(len(f.buffer) for f in frames)
    for _ in range(n - 1):
        frames = s.recv_multipart(copy=False)
        nbytes += sum(len(f.buffer) for f in frames)
    q.put(("sub", time.perf_counter() - t0, cpu_s() - c0, nbytes, 0))
    s.close(0)
    ctx.term()


def bare_pub(endpoint: str, kind: str, n: int, ready: mp.Event, q: mp.Queue, via: bool) -> None:
    """Plain pyzmq publisher: binds a PUB socket, or (``via`` the broker) connects an XPUB one
    and waits for the subscription to come through (XPUB sends exactly like PUB)."""
    ctx = zmq.Context()
    s = ctx.socket(zmq.XPUB if via else zmq.PUB)
    s.sndhwm = 0
    if via:
        s.connect(endpoint)
    else:
        s.bind(endpoint)
    ready.wait(10)
    if via:
        s.recv()  # the subscription, forwarded by the broker
    else:
        time.sleep(0.5)  # slow joiner
    frames = bare_frames(kind)
    c0 = cpu_s()
    for k in range(n):
        s.send_multipart(frames[k % 4], copy=False)
    s.close(linger=-1)
    ctx.term()
    q.put(("pub", 0.0, cpu_s() - c0, 0, 0))


# ------------------------------------------------------------------------- through the broker


def mogs_sub(bus_d: dict, kind: str, n: int, q: mp.Queue, ready: mp.Event) -> None:
    tune_malloc_for_large_messages()  # as `mogs node` does at start
    sub = Subscriber(BusConfig.from_dict(bus_d), hwm=0)
    sub.subscribe(TOPIC[kind])
    ready.set()
    env = sub.receive(timeout_ms=None)
    t0, c0 = time.perf_counter(), cpu_s()
    nbytes = env.nbytes
    for _ in range(n - 1):
        env = sub.receive(timeout_ms=None)
        nbytes += env.nbytes
    dt, dc = time.perf_counter() - t0, cpu_s() - c0
    st = sub.stats[TOPIC[kind]]
    q.put(("sub", dt, dc, nbytes, st.lost + st.malformed))
    sub.close()
    zmq.Context.instance().term()


def mogs_pub(bus_d: dict, kind: str, n: int, ready: mp.Event, q: mp.Queue) -> None:
    tune_malloc_for_large_messages()
    pub = Publisher(BusConfig.from_dict(bus_d), hwm=0)
    ready.wait(10)
    assert pub.wait_for_subscriber(TOPIC[kind], 10)
    messages = [make_msg(kind, k) for k in range(4)]
    topic = TOPIC[kind]
    c0 = cpu_s()
    for k in range(n):
        pub.publish(topic, messages[k % 4])
    dc = cpu_s() - c0
    pub.close(linger_ms=-1)
    zmq.Context.instance().term()  # blocks until every zero-copy frame has been sent
    q.put(("pub", 0.0, max(dc, cpu_s() - c0), pub.shm_published, 0))


def broker_proc(bus_d: dict, stop: mp.Event, up: mp.Event, q: mp.Queue) -> None:
    tune_malloc_for_large_messages()  # as `mogs broker` does at start
    ev, ready = threading.Event(), threading.Event()
    t = threading.Thread(
        target=run_broker, args=(BusConfig.from_dict(bus_d), ev), kwargs={"ready": ready}
    )
    t.start()
    ready.wait(10)
    c0 = cpu_s()  # idle until the clients start: the window is the traffic
    up.set()
    stop.wait()
    q.put(("broker", 0.0, cpu_s() - c0, 0, 0))
    ev.set()
    t.join()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint(transport: str, tmp: str, name: str) -> str:
    return f"tcp://127.0.0.1:{free_port()}" if transport == "tcp" else f"ipc://{tmp}/{name}.ipc"


def run_case(
    case: str, kind: str, n: int, transport: str, tmp: str, sockbuf: int = 0
) -> dict[str, float]:
    q: mp.Queue = mp.Queue()
    ready = mp.Event()
    broker = stop = None
    if case == "bare":
        ep = endpoint(transport, tmp, f"bare-{kind}")
        procs = [
            mp.Process(target=bare_sub, args=(ep, n, q, ready)),
            mp.Process(target=bare_pub, args=(ep, kind, n, ready, q, False)),
        ]
    else:
        bus = BusConfig(
            endpoint(transport, tmp, f"p-{case}-{kind}"),
            endpoint(transport, tmp, f"s-{case}-{kind}"),
            reliable_hwm=0,
            socket_buffer_bytes=sockbuf,  # the broker's, and our ends' (not the bare ends')
            shm_min_bytes=0 if case == "inline" else BusConfig.shm_min_bytes,
        ).to_dict()
        stop, up = mp.Event(), mp.Event()
        broker = mp.Process(target=broker_proc, args=(bus, stop, up, q))
        broker.start()
        if not up.wait(30):
            raise RuntimeError("broker did not come up")
        if case == "hop":
            procs = [
                mp.Process(target=bare_sub, args=(bus["sub_endpoint"], n, q, ready)),
                mp.Process(target=bare_pub, args=(bus["pub_endpoint"], kind, n, ready, q, True)),
            ]
        else:
            procs = [
                mp.Process(target=mogs_sub, args=(bus, kind, n, q, ready)),
                mp.Process(target=mogs_pub, args=(bus, kind, n, ready, q)),
            ]
    for p in procs:
        p.start()
    res = {}
    for _ in procs:
        role, dt, dc, nbytes, lost = q.get(timeout=600)
        res[role] = (dt, dc, nbytes, lost)
    for p in procs:
        p.join(60)
    if broker is not None and stop is not None:
        stop.set()
        role, _, dc, _, _ = q.get(timeout=60)
        res[role] = (0.0, dc, 0, 0)
        broker.join(10)
    dt, _, nbytes, lost = res["sub"]
    out = {
        "msgs_per_s": (n - 1) / dt,
        "mb_per_s": nbytes / dt / 1e6,
        "lost": lost,
        "shm_share": res["pub"][2] / n,  # our publisher: messages that went by shared memory
    }
    for role in ("pub", "broker", "sub"):
        out[f"cpu_us_{role}"] = res[role][1] / n * 1e6 if role in res else 0.0
    out["cpu_us_total"] = sum(out[f"cpu_us_{r}"] for r in ("pub", "broker", "sub"))
    return out


def load_average() -> str:
    try:
        return " / ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def measure(
    figures: dict, transport: str, kind: str, n: int, args: argparse.Namespace, tmp: str
) -> None:
    """Run every case of ``kind`` on ``transport``; the best of the repeats into ``figures``."""
    cases = cases_for(kind)
    runs: dict[str, list[dict[str, float]]] = {c: [] for c in cases}
    for _ in range(args.repeats):  # interleaved: the cases share the machine's state
        for case in cases:
            runs[case].append(run_case(case, kind, n, transport, tmp, args.socket_buffer))
    for case in cases:
        best = max(runs[case], key=lambda r: r["msgs_per_s"])
        keys = ("msgs_per_s", "mb_per_s", *(k for k in best if k.startswith("cpu")))
        figures[f"{transport}_{kind}_{case}_shm_share"] = round(best["shm_share"], 3)
        for key in keys:
            figures[f"{transport}_{kind}_{case}_{key}"] = round(best[key], 1)
        figures[f"{transport}_{kind}_{case}_lost_msgs"] = sum(r["lost"] for r in runs[case])
        print(
            f"{transport} {kind:9s} {case:6s} {best['msgs_per_s']:10.1f} msg/s "
            f"{best['mb_per_s']:9.1f} MB/s  CPU us/msg pub {best['cpu_us_pub']:.1f} "
            f"broker {best['cpu_us_broker']:.1f} sub {best['cpu_us_sub']:.1f}",
            flush=True,
        )
    for case in cases[1:]:
        figures[f"{transport}_{kind}_{case}_ratio_vs_bare_zmq"] = round(
            figures[f"{transport}_{kind}_{case}_msgs_per_s"]
            / figures[f"{transport}_{kind}_bare_msgs_per_s"],
            3,
        )
    figures[f"{transport}_{kind}_mogs_ratio_vs_hop"] = round(
        figures[f"{transport}_{kind}_mogs_msgs_per_s"]
        / figures[f"{transport}_{kind}_hop_msgs_per_s"],
        3,
    )
    print(
        f"{transport} {kind:9s} ratio "
        + ", ".join(
            f"{c}/bare = {figures[f'{transport}_{kind}_{c}_ratio_vs_bare_zmq']:.3f}"
            for c in cases[1:]
        )
        + f"; mogs via shared memory {figures[f'{transport}_{kind}_mogs_shm_share']:.0%}",
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--transport",
        choices=["ipc", "tcp", "both"],
        default="both",
        help="ipc: one host, the default bus (shared memory for large arrays); tcp: what "
        "containers and several hosts use (everything through the broker)",
    )
    ap.add_argument("--keyframes", type=int, default=300, help="1.5 MB keyframes per case")
    ap.add_argument("--imu", type=int, default=100_000, help="IMU messages per case")
    ap.add_argument("--repeats", type=int, default=3, help="best of N runs per case")
    ap.add_argument(
        "--socket-buffer",
        type=int,
        default=0,
        help="bus.socket_buffer_bytes for the broker and the MOGS ends (0: OS default)",
    )
    ap.add_argument("--only", choices=["keyframe", "imu"], default=None, help="one kind only")
    add_output_options(ap)
    args = ap.parse_args(argv)
    mp.set_start_method("spawn", force=True)
    figures: dict[str, float | str] = {}
    load_before = load_average()
    transports = ("ipc", "tcp") if args.transport == "both" else (args.transport,)
    with tempfile.TemporaryDirectory(prefix="mogs-bench-") as tmp:
        for transport in transports:
            for kind, n in (("keyframe", args.keyframes), ("imu", args.imu)):
                if not args.only or kind == args.only:
                    measure(figures, transport, kind, n, args, tmp)
    figures["transports"] = ",".join(transports)
    figures["socket_buffer_bytes"] = args.socket_buffer
    figures["load_average_before"] = load_before
    figures["load_average_after"] = load_average()
    write_json(args.json, figures)
    if not args.no_docs:
        update_markdown_section("bus_throughput", report_md(figures, args, argv))
    return 0


def contention_note(figures: dict) -> list[str]:
    """A warning paragraph when other work competed for the cores during the run."""
    try:
        load = max(
            float(figures[k].split("/")[0]) for k in ("load_average_before", "load_average_after")
        )
    except (KeyError, ValueError):
        return []
    if load <= (os.cpu_count() or 1) / 2:
        return []
    return [
        f"**Contended run** (1-min load average up to {load:.1f} on {os.cpu_count()} cores): "
        "the scheduler shares the cores per thread, so a case with more processes (`hop`, "
        "`MOGS`) gets a larger share and the msg/s ratios are not the bus's; the CPU time per "
        "message below is the comparable figure. Re-run on an idle machine for the ratios.",
        "",
    ]


def report_md(figures: dict, args: argparse.Namespace, argv: list[str] | None) -> str:
    cmd = "python bench/bus_throughput.py " + " ".join(argv if argv is not None else sys.argv[1:])
    kinds = (
        ("keyframe", "Keyframe 800x640 RGB + 500 features (1.55 MB)"),
        ("imu", "Imu (small)"),
    )
    f = figures
    transports = f["transports"].split(",")
    body = [
        "## Bus throughput (issue 2)",
        "",
        f"Command: `{cmd.strip()}`  ",
        f"Machine: {machine_line()}; {os.cpu_count()} cores; transports {', '.join(transports)}; "
        f"socket buffers {args.socket_buffer or 'OS default'}; best of "
        f"{args.repeats} interleaved runs; publisher, broker and subscriber are separate "
        f"processes. Load average (1/5/15 min) before {f['load_average_before']}, after "
        f"{f['load_average_after']} (anything well above 0 means other work shared the cores).",
        "",
        *contention_note(f),
        "`bare`: plain pyzmq PUB -> SUB, pre-built frames (the baseline). `hop`: the same bare "
        "pyzmq ends through the MOGS broker process, no MOGS code in the ends (what the extra "
        "process hop alone allows). `inline`: `Publisher.publish` -> broker -> "
        "`Subscriber.receive` (encode, strict decode, sequence accounting), every byte through "
        "the broker (`bus.shm_min_bytes: 0`). `MOGS`: the same with the bus's defaults: on ipc "
        "(one host, the default bus) arrays of 256 KiB and more travel through a shared-memory "
        "ring of the topic and only the header through the broker, unless a subscriber has not "
        "yet read the slot (`mogs_node/shm.py`; the share that did is in the table); on tcp "
        "(containers, several hosts) everything goes through the broker. IMU messages have no "
        "arrays: for them `inline` is `MOGS`.",
        "",
        "| transport | message | bare msg/s | bare MB/s | hop / bare | inline / bare "
        "| MOGS msg/s | MOGS MB/s | MOGS / bare | via shared memory | lost |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    measured = [
        (t, kind, label, f"{t}_{kind}")
        for t in transports
        for kind, label in kinds
        if f"{t}_{kind}_mogs_msgs_per_s" in f
    ]
    for t, _, label, k in measured:
        inline = f.get(f"{k}_inline_ratio_vs_bare_zmq")
        body.append(
            f"| {t} | {label} | {f[f'{k}_bare_msgs_per_s']:.0f} "
            f"| {f[f'{k}_bare_mb_per_s']:.0f} | {f[f'{k}_hop_ratio_vs_bare_zmq']:.2f} "
            f"| {'-' if inline is None else f'{inline:.2f}'} "
            f"| {f[f'{k}_mogs_msgs_per_s']:.0f} | {f[f'{k}_mogs_mb_per_s']:.0f} "
            f"| **{f[f'{k}_mogs_ratio_vs_bare_zmq']:.2f}** "
            f"| {f[f'{k}_mogs_shm_share']:.0%} | {f[f'{k}_mogs_lost_msgs']} |"
        )
    body += [
        "",
        "CPU time per message [us] (user + system, all threads of the process, over the timed "
        "window of the best run); with two cores, throughput cannot exceed "
        "2 / total CPU per message:",
        "",
        "| transport | message | case | publisher | broker | subscriber | total | total / bare |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for t, kind, label, k in measured:
        for case in cases_for(kind):
            total = f[f"{k}_{case}_cpu_us_total"]
            first = case == "bare"
            body.append(
                f"| {t if first else ''} | {label if first else ''} | {case} "
                f"| {f[f'{k}_{case}_cpu_us_pub']:.1f} "
                f"| {f[f'{k}_{case}_cpu_us_broker']:.1f} | {f[f'{k}_{case}_cpu_us_sub']:.1f} "
                f"| {total:.1f} | {total / max(f[f'{k}_bare_cpu_us_total'], 1e-9):.2f} |"
            )
    return "\n".join(body)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
