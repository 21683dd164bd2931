"""End-to-end pipeline benchmark on the demo sequence (``launch/demo.yaml``).

Runs the whole pipeline as separate processes (player in ``fast`` mode, so the drive is paced by
the slowest node) and measures from the bus, in the same run:

- latency per keyframe: image published on ``/camera/image`` -> its metrized depth on
  ``/metrizer/depth`` (matched through the keyframe's stamp), and -> ``/mapper/stats``;
- throughput: frames/s and keyframes/s, and the real-time factor of the online part:
  ``real_time_factor`` = sequence duration / (last keyframe mapped - first image). The mapper's
  refinement of the whole map after the drive (``final_refine_iters``) is reported apart, as a
  SLAM system reports its final global bundle adjustment apart: ``final_refine_s`` (last keyframe
  mapped -> the final map's stats) and ``real_time_factor_incl_final`` (sequence duration /
  (final map - first image));
- CPU (% of one core, mean over the run) and peak resident memory of every node process.

Usage::

    python bench/pipeline.py [--frames 100] [--json PATH] [--no-docs]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil
import zmq

from mogs_node import msgs
from mogs_node.bus import Subscriber
from mogs_node.commands.launch import parse_overrides
from mogs_node.eval.bench_docs import REPO_ROOT, machine_line, update_markdown_section, write_json
from mogs_node.launch import Launcher, load_launch_file


def drive_cpu_percent(samples: list[tuple[float, float]], t0: float, t1: float) -> float:
    """CPU (% of one core) of a process between ``t0`` and ``t1`` (the drive: first image to
    last mapped keyframe) from its ``(time, cumulative CPU s)`` samples: the CPU it used between
    the samples nearest inside that span (work before or after the drive, such as start-up or
    the report's final renders, is left out). NaN with fewer than two samples inside."""
    inside = [(t, c) for t, c in samples if t0 <= t <= t1]
    if len(inside) < 2 or inside[-1][0] <= inside[0][0]:
        return float("nan")
    (ta, ca), (tb, cb) = inside[0], inside[-1]
    return round(100.0 * (cb - ca) / (tb - ta), 1)


def mapper_cpu_per_keyframe(
    map_cpu_s: dict[int, float], samples: list[tuple[float, float]], t0: float, t1: float
) -> dict[str, float]:
    """The mapper's CPU per keyframe: insertion + iterations as its stats report them
    (``map_cpu_ms``, ``map_cpu_s`` by keyframe id), and its whole process during the drive
    ``t0``-``t1`` (also decoding, the snapshot, the map update; ``samples`` as for
    :func:`drive_cpu_percent`) over the keyframes mapped."""
    out: dict[str, float] = {}
    if map_cpu_s:
        out["mapper_map_cpu_s_per_keyframe_mean"] = round(statistics.mean(map_cpu_s.values()), 3)
        pct = drive_cpu_percent(samples, t0, t1)
        out["mapper_process_cpu_s_per_keyframe_drive"] = round(
            pct / 100 * (t1 - t0) / len(map_cpu_s), 3
        )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--launch", default=str(REPO_ROOT / "launch" / "demo.yaml"))
    ap.add_argument("--frames", type=int, default=60, help="frames of the synthetic drive")
    ap.add_argument("--timeout", type=float, default=1500.0)
    ap.add_argument("--json", default=None)
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NODE.PARAM=VALUE",
        help="e.g. mapper.device=cuda",
    )
    ap.add_argument("--no-docs", action="store_true")
    args = ap.parse_args(argv)

    out = Path(tempfile.mkdtemp(prefix="mogs-bench-pipeline-"))
    base = load_launch_file(args.launch)
    sim = dict(next(n for n in base.nodes if n.name == "player").params.get("sim", {}))
    sim["n_frames"] = args.frames
    overrides = {
        "player": {"sim": sim},
        "report": {"out_dir": str(out)},
        "mapper": {"ply_path": str(out / "map.ply")},
    }
    for node, params in parse_overrides(args.set).items():
        overrides.setdefault(node, {}).update(params)
    launch = load_launch_file(args.launch, overrides=overrides)
    frame_rate_hz = float(sim.get("frame_rate_hz", 10.0))

    ctx = zmq.Context()
    sub = Subscriber(launch.bus, context=ctx)
    for t in ("/camera/image", "/frontend/keyframe", "/metrizer/depth", "/mapper/stats"):
        sub.subscribe(t)
    launcher = Launcher(launch, out=open(out / "launch.log", "w"))  # noqa: SIM115 - closed at exit
    runner = threading.Thread(
        target=launcher.run, kwargs={"install_signal_handlers": False, "timeout_s": args.timeout}
    )
    t_start = time.monotonic()
    runner.start()

    image_t: dict[int, float] = {}  # stamp -> arrival
    kf_stamp: dict[int, int] = {}  # keyframe id -> stamp
    kf_t: dict[int, float] = {}  # keyframe id -> arrival of the frontend's keyframe
    depth_t: dict[int, float] = {}
    stats_t: dict[int, float] = {}
    map_cpu_s: dict[int, float] = {}  # keyframe id -> the mapper's CPU for it (its stats)
    final_t: float | None = None  # the mapper's final (refined) map, when it refines
    cpu: dict[str, list[float]] = {}
    cpu_t: dict[str, list[tuple[float, float]]] = {}  # name -> (time, user + system CPU s)
    rss: dict[str, float] = {}
    procs: dict[int, tuple[str, psutil.Process]] = {}
    last_sample = 0.0
    while runner.is_alive():
        env = sub.receive(timeout_ms=100)
        now = time.monotonic()
        if env is not None:
            m = env.msg
            if env.topic == "/camera/image":
                image_t.setdefault(m.stamp_ns, now)
            elif isinstance(m, msgs.Keyframe):
                kf_stamp[m.keyframe_id] = m.stamp_ns
                kf_t.setdefault(m.keyframe_id, now)
            elif env.topic == "/metrizer/depth":
                depth_t.setdefault(m.keyframe_id, now)
            elif env.topic == "/mapper/stats":
                if m.extra.get("final"):  # the map refined after the drive: part of the run
                    final_t = now
                else:
                    stats_t.setdefault(m.keyframe_id, now)
                    if "map_cpu_ms" in m.extra:
                        map_cpu_s[m.keyframe_id] = float(m.extra["map_cpu_ms"]) / 1000
        if now - last_sample >= 0.5:
            last_sample = now
            for child in launcher.children:
                if child.proc is not None and child.proc.pid not in procs:
                    try:
                        p = psutil.Process(child.proc.pid)
                        p.cpu_percent(None)
                        procs[child.proc.pid] = (child.name, p)
                    except psutil.NoSuchProcess:
                        pass
            for _pid, (name, p) in list(procs.items()):
                try:
                    with p.oneshot():
                        cpu.setdefault(name, []).append(p.cpu_percent(None))
                        ct = p.cpu_times()
                        cpu_t.setdefault(name, []).append((now, ct.user + ct.system))
                        rss[name] = max(rss.get(name, 0.0), p.memory_info().rss / 2**20)
                except psutil.NoSuchProcess:
                    pass
    runner.join()
    sub.close()
    ctx.term()
    wall = time.monotonic() - t_start

    lat_depth = [
        depth_t[k] - image_t[s] for k, s in kf_stamp.items() if k in depth_t and s in image_t
    ]
    lat_map = [
        stats_t[k] - image_t[s] for k, s in kf_stamp.items() if k in stats_t and s in image_t
    ]
    first = min(image_t.values(), default=0.0)
    # the online part ends when the last keyframe is mapped (or metrized, if the mapper lags
    # behind the metrizer); the final refinement comes after it and is reported apart
    last = max([*depth_t.values(), *stats_t.values()], default=0.0)
    span = max(last - first, 1e-9)
    span_final = max(max(last, final_t or 0.0) - first, 1e-9)
    seq_s = len(image_t) / frame_rate_hz
    figures: dict[str, float] = {
        "frames": len(image_t),
        "keyframes": len(kf_stamp),
        "keyframes_metrized": len(depth_t),
        "keyframes_mapped": len(stats_t),
        "wall_s": round(wall, 1),
        "latency_image_to_depth_ms_median": round(1000 * statistics.median(lat_depth), 1)
        if lat_depth
        else float("nan"),
        "latency_image_to_depth_ms_max": round(1000 * max(lat_depth), 1)
        if lat_depth
        else float("nan"),
        "latency_image_to_map_ms_median": round(1000 * statistics.median(lat_map), 1)
        if lat_map
        else float("nan"),
        "frames_per_s": round(len(image_t) / span, 2),
        "keyframes_per_s": round(len(depth_t) / span, 3),
        "real_time_factor": round(seq_s / span, 3),
        "real_time_factor_incl_final": round(seq_s / span_final, 3)
        if final_t is not None
        else None,
        # None (JSON null): the final map did not come before the run ended (e.g. --timeout)
        "final_refine_s": round(final_t - max(stats_t.values()), 2)
        if final_t is not None and stats_t
        else None,
    }
    # where each keyframe's time goes: seconds after the first image at which its image, its
    # keyframe, its metrized depth and its mapper stats arrived (the critical path of the drive)
    figures["timeline_s"] = {
        str(k): [
            round(t - first, 3) if t is not None else None
            for t in (image_t.get(s), kf_t.get(k), depth_t.get(k), stats_t.get(k))
        ]
        for k, s in sorted(kf_stamp.items())
    }
    figures.update(mapper_cpu_per_keyframe(map_cpu_s, cpu_t.get("mapper", []), first, last))
    for name in cpu:
        figures[f"{name}_cpu_percent_mean"] = round(statistics.mean(cpu[name]), 1)
        figures[f"{name}_cpu_percent_drive"] = drive_cpu_percent(cpu_t[name], first, last)
        figures[f"{name}_rss_mib_peak"] = round(rss[name], 1)
    for k, v in figures.items():
        print(f"{k:40s} {v}")
    write_json(args.json, figures)
    if not args.no_docs:
        cmd = "python bench/pipeline.py " + " ".join(argv if argv is not None else sys.argv[1:])
        rows = "\n".join(
            f"| {n} | {figures[f'{n}_cpu_percent_mean']} | {figures[f'{n}_cpu_percent_drive']} "
            f"| {figures[f'{n}_rss_mib_peak']} |"
            for n in cpu
        )
        body = f"""## Pipeline end to end (issue 8)

Command: `{cmd.strip()}`

Machine: {machine_line()}; 2 cores shared by all processes. Demo sequence: synthetic drive at 621x188,
{args.frames} frames at {frame_rate_hz:g} Hz (2 s standing still), player in `fast` mode (paced by the
slowest node, no frame or keyframe dropped). The real-time factor is the online part's: sequence
time over first image -> last keyframe mapped. The mapper's refinement of the whole map after the
drive (`final_refine_iters`, docs/mapper.md) is reported apart, as a SLAM system reports its final
global bundle adjustment apart, and with it in the second real-time factor.

| figure | value |
| --- | ---: |
| frames / keyframes / metrized / mapped | {figures["frames"]} / {figures["keyframes"]} / {figures["keyframes_metrized"]} / {figures["keyframes_mapped"]} |
| latency image -> metrized depth, median / max [ms] | {figures["latency_image_to_depth_ms_median"]} / {figures["latency_image_to_depth_ms_max"]} |
| latency image -> mapper stats, median [ms] | {figures["latency_image_to_map_ms_median"]} |
| throughput [frames/s] / [keyframes/s] | {figures["frames_per_s"]} / {figures["keyframes_per_s"]} |
| real-time factor, online (sequence time / first image -> last keyframe mapped) | {figures["real_time_factor"]} |
| final refinement after the drive [s] / real-time factor with it | {figures["final_refine_s"]} / {figures["real_time_factor_incl_final"]} |
| wall time incl. start-up and drain [s] | {figures["wall_s"]} |

| node | CPU, mean over its life [% of one core] | CPU during the drive [%] | peak RSS [MiB] |
| --- | ---: | ---: | ---: |
{rows}
"""
        update_markdown_section("pipeline", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
