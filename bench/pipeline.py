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
import dataclasses
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
from mogs_node.launch import Launcher, LaunchFile, load_launch_file


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


@dataclasses.dataclass
class Recording:
    """What the bench sees on the bus and in the node processes during one run: arrival times
    (``time.monotonic``) by stamp or keyframe id, and CPU / memory samples by node name."""

    image_t: dict[int, float] = dataclasses.field(default_factory=dict)  # stamp -> arrival
    kf_stamp: dict[int, int] = dataclasses.field(default_factory=dict)  # keyframe id -> stamp
    kf_t: dict[int, float] = dataclasses.field(default_factory=dict)  # id -> frontend keyframe
    depth_t: dict[int, float] = dataclasses.field(default_factory=dict)
    stats_t: dict[int, float] = dataclasses.field(default_factory=dict)
    map_cpu_s: dict[int, float] = dataclasses.field(default_factory=dict)  # id -> mapper CPU s
    final_t: float | None = None  # the mapper's final (refined) map, when it refines
    cpu: dict[str, list[float]] = dataclasses.field(default_factory=dict)
    cpu_t: dict[str, list[tuple[float, float]]] = dataclasses.field(default_factory=dict)
    rss: dict[str, float] = dataclasses.field(default_factory=dict)  # name -> peak MiB
    procs: dict[int, tuple[str, psutil.Process]] = dataclasses.field(default_factory=dict)

    def on_message(self, topic: str, m, now: float) -> None:
        """Record the arrival of message ``m`` on ``topic`` at ``now``."""
        if topic == "/camera/image":
            self.image_t.setdefault(m.stamp_ns, now)
        elif isinstance(m, msgs.Keyframe):
            self.kf_stamp[m.keyframe_id] = m.stamp_ns
            self.kf_t.setdefault(m.keyframe_id, now)
        elif topic == "/metrizer/depth":
            self.depth_t.setdefault(m.keyframe_id, now)
        elif topic == "/mapper/stats":
            if m.extra.get("final"):  # the map refined after the drive: part of the run
                self.final_t = now
            else:
                self.stats_t.setdefault(m.keyframe_id, now)
                if "map_cpu_ms" in m.extra:
                    self.map_cpu_s[m.keyframe_id] = float(m.extra["map_cpu_ms"]) / 1000

    def sample(self, launcher: Launcher, now: float) -> None:
        """Sample CPU and resident memory of every node process started so far."""
        for child in launcher.children:
            if child.proc is not None and child.proc.pid not in self.procs:
                try:
                    p = psutil.Process(child.proc.pid)
                    p.cpu_percent(None)
                    self.procs[child.proc.pid] = (child.name, p)
                except psutil.NoSuchProcess:
                    pass
        for _pid, (name, p) in list(self.procs.items()):
            try:
                with p.oneshot():
                    self.cpu.setdefault(name, []).append(p.cpu_percent(None))
                    ct = p.cpu_times()
                    self.cpu_t.setdefault(name, []).append((now, ct.user + ct.system))
                    self.rss[name] = max(self.rss.get(name, 0.0), p.memory_info().rss / 2**20)
            except psutil.NoSuchProcess:
                pass


def parse_args(argv: list[str] | None) -> argparse.Namespace:
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
    return ap.parse_args(argv)


def bench_launch(args: argparse.Namespace, out: Path) -> tuple[LaunchFile, float]:
    """The launch file of the run (``--launch`` with ``--frames``, the report and the map
    written under ``out``, then the ``--set`` overrides) and the drive's frame rate [Hz]."""
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
    return launch, float(sim.get("frame_rate_hz", 10.0))


def record_run(launch: LaunchFile, out: Path, timeout_s: float) -> tuple[Recording, float]:
    """Run ``launch`` to its end in a thread, recording the bus and sampling the node processes
    every 0.5 s; returns the recording and the wall time [s] (start-up and drain included)."""
    ctx = zmq.Context()
    sub = Subscriber(launch.bus, context=ctx)
    for t in ("/camera/image", "/frontend/keyframe", "/metrizer/depth", "/mapper/stats"):
        sub.subscribe(t)
    launcher = Launcher(launch, out=open(out / "launch.log", "w"))  # noqa: SIM115 - closed at exit
    runner = threading.Thread(
        target=launcher.run, kwargs={"install_signal_handlers": False, "timeout_s": timeout_s}
    )
    t_start = time.monotonic()
    runner.start()
    rec = Recording()
    last_sample = 0.0
    while runner.is_alive():
        env = sub.receive(timeout_ms=100)
        now = time.monotonic()
        if env is not None:
            rec.on_message(env.topic, env.msg, now)
        if now - last_sample >= 0.5:
            last_sample = now
            rec.sample(launcher, now)
    runner.join()
    sub.close()
    ctx.term()
    return rec, time.monotonic() - t_start


def _ms(values: list[float], stat) -> float:
    """``stat`` of ``values`` [s] in ms, rounded to 0.1; NaN if there are none."""
    return round(1000 * stat(values), 1) if values else float("nan")


def run_figures(rec: Recording, wall: float, frame_rate_hz: float) -> dict:
    """The bench's figures of one recorded run (latencies, throughput, real-time factors, the
    keyframes' timeline, CPU and memory per node)."""
    image_t, depth_t, stats_t, final_t = rec.image_t, rec.depth_t, rec.stats_t, rec.final_t
    pairs = rec.kf_stamp.items()
    lat_depth = [depth_t[k] - image_t[s] for k, s in pairs if k in depth_t and s in image_t]
    lat_map = [stats_t[k] - image_t[s] for k, s in pairs if k in stats_t and s in image_t]
    first = min(image_t.values(), default=0.0)
    # the online part ends when the last keyframe is mapped (or metrized, if the mapper lags
    # behind the metrizer); the final refinement comes after it and is reported apart
    last = max([*depth_t.values(), *stats_t.values()], default=0.0)
    span = max(last - first, 1e-9)
    span_final = max(max(last, final_t or 0.0) - first, 1e-9)
    seq_s = len(image_t) / frame_rate_hz
    figures: dict = {
        "frames": len(image_t),
        "keyframes": len(rec.kf_stamp),
        "keyframes_metrized": len(depth_t),
        "keyframes_mapped": len(stats_t),
        "wall_s": round(wall, 1),
        "latency_image_to_depth_ms_median": _ms(lat_depth, statistics.median),
        "latency_image_to_depth_ms_max": _ms(lat_depth, max),
        "latency_image_to_map_ms_median": _ms(lat_map, statistics.median),
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
            for t in (image_t.get(s), rec.kf_t.get(k), depth_t.get(k), stats_t.get(k))
        ]
        for k, s in sorted(rec.kf_stamp.items())
    }
    figures.update(mapper_cpu_per_keyframe(rec.map_cpu_s, rec.cpu_t.get("mapper", []), first, last))
    for name in rec.cpu:
        figures[f"{name}_cpu_percent_mean"] = round(statistics.mean(rec.cpu[name]), 1)
        figures[f"{name}_cpu_percent_drive"] = drive_cpu_percent(rec.cpu_t[name], first, last)
        figures[f"{name}_rss_mib_peak"] = round(rec.rss[name], 1)
    return figures


def docs_section(
    cmd: str, figures: dict, nodes: list[str], frames: int, frame_rate_hz: float
) -> str:
    """The ``pipeline`` section of docs/benchmarks.md for one run's ``figures`` (``nodes``: the
    node processes sampled, in order)."""
    rows = "\n".join(
        f"| {n} | {figures[f'{n}_cpu_percent_mean']} | {figures[f'{n}_cpu_percent_drive']} "
        f"| {figures[f'{n}_rss_mib_peak']} |"
        for n in nodes
    )
    return f"""## Pipeline end to end (issue 8)

Command: `{cmd.strip()}`

Machine: {machine_line()}; 2 cores shared by all processes. Demo sequence: synthetic drive at 621x188,
{frames} frames at {frame_rate_hz:g} Hz (2 s standing still), player in `fast` mode (paced by the
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


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out = Path(tempfile.mkdtemp(prefix="mogs-bench-pipeline-"))
    launch, frame_rate_hz = bench_launch(args, out)
    rec, wall = record_run(launch, out, args.timeout)
    figures = run_figures(rec, wall, frame_rate_hz)
    for k, v in figures.items():
        print(f"{k:40s} {v}")
    write_json(args.json, figures)
    if not args.no_docs:
        cmd = "python bench/pipeline.py " + " ".join(argv if argv is not None else sys.argv[1:])
        body = docs_section(cmd, figures, list(rec.cpu), args.frames, frame_rate_hz)
        update_markdown_section("pipeline", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
