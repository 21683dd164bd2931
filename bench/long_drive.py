"""A long synthetic drive through the whole pipeline: memory and time per keyframe against distance.

Runs ``launch/demo.yaml`` (player in ``fast`` mode: paced by the slowest node, nothing dropped) on a
drive of ``--frames`` frames at 10 Hz (3000: five minutes, about 3 km), with the run's state in one
folder as ``mogs demo`` has it (journal, mapper checkpoints and offloaded submaps, ``map.ply``),
and measures from outside the processes, in the same run:

- the mapper's resident memory (psutil, every 0.5 s) against frames played and distance driven
  (the keyframes' path length): peak at frame 600 and at the end, and their ratio;
- the mapper's time per keyframe, first 10 % of the keyframes against the last 10 %: its CPU time
  (the mapper process's user + system time between two ``/mapper/stats``: everything it does per
  keyframe, and independent of what else runs on a shared machine), and for reference the wall
  time of its core step (``/mapper/stats`` ``extra.map_ms``: submap reload, insertion, window
  iterations);
- keyframes made (``/frontend/keyframe``) and mapped (``/mapper/stats``): lost = made - mapped;
- the final PLY (Gaussians in its header, bytes), streamed from the offloaded submaps;
- the launcher's figures: kills for a missing heartbeat / for no progress, respawns, the largest
  gap between two heartbeats of each node.

The run report node is left out: it keeps every frame's ground truth and renders the final map at
the end, which is not the mapper's cost on a long drive. Writes a PNG (RSS and time per keyframe
against distance) beside the JSON, and the ``long-drive`` section of ``docs/benchmarks.md``.

Usage::

    python bench/long_drive.py [--frames 3000] [--json PATH] [--out DIR] [--no-docs]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import signal
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import zmq

from mogs_node import msgs
from mogs_node.bus import Subscriber
from mogs_node.commands.launch import add_run_options, parse_overrides
from mogs_node.eval.bench_docs import (
    REPO_ROOT,
    add_output_options,
    machine_line,
    update_markdown_section,
    write_json,
)
from mogs_node.launch import Launcher, load_launch_file, run_dir_overrides

RSS_FRAME = 600  # the reference point of the memory ratio (issue 17)


@dataclasses.dataclass
class Trace:
    """What the bench saw on the bus and in the process table, in arrival order."""

    frames: int = 0
    kf_pos: dict[int, np.ndarray] = dataclasses.field(default_factory=dict)  # id -> camera centre
    mapped: dict[int, dict[str, float]] = dataclasses.field(default_factory=dict)  # id -> stats
    rss: list[tuple[float, int, float]] = dataclasses.field(default_factory=list)  # t, frames, MiB
    mapped_at: list[tuple[int, float]] = dataclasses.field(default_factory=list)  # id, t
    cpu_ms: dict[int, float] = dataclasses.field(default_factory=dict)  # id -> mapper CPU since
    # the previous keyframe's stats (ms)
    node_cpu_s: dict[str, float] = dataclasses.field(default_factory=dict)  # node -> CPU s, all
    # its processes (respawns summed): which node paces the drive


def _ply_vertices(path: Path) -> int:
    with open(path, "rb") as f:
        for raw in f:
            line = raw.decode("ascii", "replace").strip()
            if line.startswith("element vertex"):
                return int(line.split()[-1])
            if line == "end_header":
                break
    return 0


def _count_lines(path: Path, text: str) -> int:
    try:
        return sum(text in line for line in path.read_text(errors="replace").splitlines())
    except OSError:
        return 0


def _path_lengths(trace: Trace) -> dict[int, float]:
    """Distance driven (m) at each keyframe, along the keyframes' camera centres."""
    out, s, prev = {}, 0.0, None
    for kid in sorted(trace.kf_pos):
        c = trace.kf_pos[kid]
        if prev is not None:
            s += float(np.linalg.norm(c - prev))
        out[kid], prev = s, c
    return out


def _launch(args: argparse.Namespace, out: Path) -> Any:
    base = load_launch_file(args.launch)
    overrides = run_dir_overrides(base, out, resume=False)
    player = next(n for n in base.nodes if n.name == "player")
    sim = dict(player.params.get("sim", {}))
    sim["n_frames"] = args.frames
    waits = [n for n in player.params.get("wait_for_nodes", []) if n != "report"]
    overrides["player"] = {
        "sim": sim,
        "wait_for_nodes": waits,
        "wait_for_nodes_s": 1800.0,  # a first-use compile under load takes minutes
        "groundtruth_depth": False,
    }
    overrides.pop("report", None)
    for node, params in parse_overrides(args.set).items():
        overrides.setdefault(node, {}).update(params)
    launch = load_launch_file(args.launch, overrides=overrides)
    nodes = tuple(n for n in launch.nodes if not n.cls.endswith(":RunReportNode"))
    return dataclasses.replace(launch, nodes=nodes, exit_when=())


def _mapper_cpu_s(launcher: Launcher, procs: dict[int, psutil.Process]) -> tuple[int, float] | None:
    """(pid, user + system CPU seconds) of the running mapper process, or None."""
    mapper = next((c for c in launcher.children if c.name == "mapper"), None)
    if mapper is None or mapper.proc is None or mapper.exited is not None:
        return None
    try:
        if mapper.proc.pid not in procs:
            procs[mapper.proc.pid] = psutil.Process(mapper.proc.pid)
        t = procs[mapper.proc.pid].cpu_times()
    except psutil.NoSuchProcess:
        return None
    return mapper.proc.pid, t.user + t.system


def _sample_node_cpu(
    launcher: Launcher, procs: dict[int, psutil.Process], cpu_by_pid: dict[int, tuple[str, float]]
) -> None:
    """Latest user + system CPU seconds of every child process (with its own children), by
    pid; a pid keeps its last value once it has exited."""
    for child in launcher.children:
        if child.proc is None:
            continue
        pid = child.proc.pid
        try:
            if pid not in procs:
                procs[pid] = psutil.Process(pid)
            p = procs[pid]
            total = sum(p.cpu_times()[:2])
            for sub in p.children(recursive=True):
                with contextlib.suppress(psutil.NoSuchProcess):
                    total += sum(sub.cpu_times()[:2])
        except psutil.NoSuchProcess:
            continue
        cpu_by_pid[pid] = (child.name, total)


def _watch(launcher: Launcher, runner: threading.Thread, trace: Trace, drain_s: float) -> None:
    """Follow the run; once the player has finished and the mapper has mapped every keyframe
    (or nothing arrived for ``drain_s``), stop the launcher (the mapper then writes its PLY)."""
    ctx = zmq.Context()
    sub = Subscriber(launcher.launch.bus, context=ctx)
    for t in ("/frontend/odometry", "/frontend/keyframe", "/mapper/stats"):
        sub.subscribe(t)
    procs: dict[int, psutil.Process] = {}
    cpu_prev: tuple[int, float] | None = None  # (pid, user + system s) at the previous stats
    cpu_by_pid: dict[int, tuple[str, float]] = {}
    last_sample = last_input = time.monotonic()
    try:
        for now, env in sub.arrivals(runner.is_alive, timeout_ms=100):
            if env is not None:
                last_input = now
                m = env.msg
                if env.topic == "/frontend/odometry":  # one per frame, small (not the image)
                    trace.frames += 1
                elif isinstance(m, msgs.Keyframe):
                    trace.kf_pos[m.keyframe_id] = np.asarray(m.T_world_cam)[:3, 3].copy()
                elif isinstance(m, msgs.MapStats):
                    trace.mapped[m.keyframe_id] = {**m.extra, "n_gaussians": m.n_gaussians}
                    trace.mapped_at.append((m.keyframe_id, now))
                    cpu = _mapper_cpu_s(launcher, procs)
                    if cpu is not None and cpu_prev is not None and cpu[0] == cpu_prev[0]:
                        trace.cpu_ms[m.keyframe_id] = 1000 * (cpu[1] - cpu_prev[1])
                    cpu_prev = cpu
            if now - last_sample >= 0.5:
                last_sample = now
                _sample_node_cpu(launcher, procs, cpu_by_pid)
                mapper = next((c for c in launcher.children if c.name == "mapper"), None)
                if mapper is not None and mapper.proc is not None and mapper.exited is None:
                    with contextlib.suppress(psutil.NoSuchProcess):
                        if mapper.proc.pid not in procs:
                            procs[mapper.proc.pid] = psutil.Process(mapper.proc.pid)
                        rss = procs[mapper.proc.pid].memory_info().rss / 2**20
                        trace.rss.append((now, trace.frames, rss))
                player = next(c for c in launcher.children if c.name == "player")
                done = player.exited == 0 and set(trace.kf_pos) <= set(trace.mapped)
                if done or (player.exited is not None and now - last_input > drain_s):
                    launcher.request_stop()
    finally:
        sub.close()
        ctx.term()
        trace.node_cpu_s.clear()
        for name, cpu_s in cpu_by_pid.values():
            trace.node_cpu_s[name] = trace.node_cpu_s.get(name, 0.0) + cpu_s


def _figures(trace: Trace, launcher: Launcher, out: Path, wall_s: float) -> dict[str, Any]:
    dist = _path_lengths(trace)
    ids = [k for k, _ in trace.mapped_at]
    nan = float("nan")

    def first_last(values: list[float]) -> tuple[float, float]:
        n10 = max(1, len(values) // 10)
        if not values:
            return nan, nan
        return statistics.median(values[:n10]), statistics.median(values[-n10:])

    cpu_first, cpu_last = first_last([trace.cpu_ms[k] for k in ids if k in trace.cpu_ms])
    first, last = first_last([float(trace.mapped[k].get("map_ms", nan)) for k in ids])
    # the reference only once the drive got past it (a drive stopped earlier has no ratio)
    reached = trace.frames > RSS_FRAME
    rss_600 = max((r for _, f, r in trace.rss if f <= RSS_FRAME), default=nan) if reached else nan
    rss_end = max((r for _, _, r in trace.rss), default=float("nan"))
    ply = out / "map.ply"
    lf = launcher.figures()
    fig: dict[str, Any] = {
        "frames": trace.frames,
        "keyframes": len(trace.kf_pos),
        "keyframes_mapped": len(set(trace.mapped) & set(trace.kf_pos)),
        "keyframes_lost": len(set(trace.kf_pos) - set(trace.mapped)),
        "distance_m": round(max(dist.values(), default=0.0), 1),
        "wall_s": round(wall_s, 1),
        "rss_mib_600": round(rss_600, 1),
        "rss_mib_end": round(rss_end, 1),
        "rss_end_over_rss_600": round(rss_end / rss_600, 3),
        "keyframe_cpu_ms_first10": round(cpu_first, 1),
        "keyframe_cpu_ms_last10": round(cpu_last, 1),
        "keyframe_time_ratio_last_first": round(cpu_last / cpu_first, 3),
        "keyframe_wall_ms_first10": round(first, 1),
        "keyframe_wall_ms_last10": round(last, 1),
        "keyframe_wall_ratio_last_first": round(last / first, 3),
        "gaussians": _ply_vertices(ply) if ply.exists() else 0,
        "ply_bytes": ply.stat().st_size if ply.exists() else 0,
        "gaussians_in_ram_end": int(trace.mapped[ids[-1]].get("gaussians_in_ram", 0)) if ids else 0,
        "gaussians_on_disk_end": int(trace.mapped[ids[-1]].get("gaussians_on_disk", 0))
        if ids
        else 0,
        # the player's warning, once per timeout (its counters leave with its last heartbeat)
        "ack_timeouts": _count_lines(out / "launch.log", "no acknowledgement for"),
        "heartbeat_kills": lf["launch"]["heartbeat_kills"],
        "progress_kills": lf["launch"]["progress_kills"],
        # CPU seconds of each node over the run (sampled every 0.5 s): on a CPU-bound machine
        # the node with the largest share paces the drive
        "node_cpu_s": {n: round(v, 1) for n, v in sorted(trace.node_cpu_s.items())},
        "launch": lf["launch"],
        "nodes": lf["nodes"],
    }
    for node, v in lf["nodes"].items():
        fig[f"heartbeat_gap_max_s.{node}"] = v["heartbeat_gap_max_s"]
    return fig


def save_trace(trace: Trace, dist: dict[int, float], path: Path) -> None:
    """What the plot needs of a run, as JSON (``load_trace`` reads it back)."""
    path.write_text(
        json.dumps(
            {
                "rss": trace.rss,
                "mapped": [[k, t, trace.mapped[k]] for k, t in trace.mapped_at],
                "cpu_ms": trace.cpu_ms,
                "distance_m": dist,
            },
            default=float,
        )
    )


def load_trace(path: Path) -> tuple[Trace, dict[int, float]]:
    """The trace and the distance per keyframe saved by :func:`save_trace`."""
    saved = json.loads(path.read_text())
    trace = Trace(
        rss=[(float(t), int(f), float(r)) for t, f, r in saved["rss"]],
        mapped={int(k): m for k, _, m in saved["mapped"]},
        mapped_at=[(int(k), float(t)) for k, t, _ in saved["mapped"]],
        cpu_ms={int(k): float(v) for k, v in saved["cpu_ms"].items()},
    )
    return trace, {int(k): float(v) for k, v in saved["distance_m"].items()}


def _plot(trace: Trace, out_png: Path, dist: dict[int, float]) -> None:
    """RSS and time per keyframe against ``dist`` (keyframe id -> distance driven, m)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ids = [k for k, _ in trace.mapped_at if k in dist]
    # RSS samples against distance: the distance of the latest keyframe mapped at that time
    at = sorted((t, dist[k]) for k, t in trace.mapped_at if k in dist)
    ts = np.array([t for t, _ in at]) if at else np.zeros(0)
    ds = np.maximum.accumulate(np.array([d for _, d in at])) if at else np.zeros(0)
    rss_d = [
        (float(ds[i - 1]) if i > 0 else 0.0, r)
        for t, _, r in trace.rss
        for i in [int(np.searchsorted(ts, t, side="right"))]
    ]
    fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    if rss_d:
        ax[0].plot([d for d, _ in rss_d], [r for _, r in rss_d], lw=1)
    ax[0].set_ylabel("mapper RSS [MiB]")
    ax[0].grid(alpha=0.3)
    ax[1].plot(
        [dist[k] for k in ids],
        [trace.mapped[k].get("map_ms", np.nan) for k in ids],
        ".",
        ms=3,
        color="0.7",
        label="wall time of the core step (shared machine)",
    )
    cpu_ids = [k for k in ids if k in trace.cpu_ms]
    ax[1].plot(
        [dist[k] for k in cpu_ids],
        [trace.cpu_ms[k] for k in cpu_ids],
        ".",
        ms=3,
        label="mapper process CPU time",
    )
    ax[1].legend(loc="upper left", fontsize=8)
    ax[1].set_ylabel("mapper time per keyframe [ms]")
    ax[1].set_xlabel("distance driven [m]")
    ax[1].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_png, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--launch", default=str(REPO_ROOT / "launch" / "long_drive.yaml"))
    ap.add_argument("--frames", type=int, default=3000, help="frames of the drive (10 Hz)")
    add_run_options(ap, "stop the run after this many seconds", timeout_s=6 * 3600.0)
    ap.add_argument("--drain", type=float, default=300.0, help="s without input before giving up")
    ap.add_argument("--out", default=None, help="run folder (default: a temporary one)")
    add_output_options(ap, docs_from="DIR")
    args = ap.parse_args(argv)
    if args.docs_from:
        return _docs_from(Path(args.docs_from), args)

    out = Path(args.out or tempfile.mkdtemp(prefix="mogs-long-drive-")).resolve()
    out.mkdir(parents=True, exist_ok=True)
    launch = _launch(args, out)
    # the mapper writes the whole map (streamed from its submaps) when stopped: give it time
    log = open(out / "launch.log", "w")  # noqa: SIM115 - closed below
    launcher = Launcher(launch, out=log, grace_s=600.0, keep_journal=False)
    runner = threading.Thread(
        target=launcher.run, kwargs={"install_signal_handlers": False, "timeout_s": args.timeout}
    )
    trace = Trace()
    t0 = time.monotonic()
    for sig in (signal.SIGINT, signal.SIGTERM):  # stop the drive, keep its figures (nohup runs)
        signal.signal(sig, lambda *_: launcher.request_stop())
    runner.start()
    try:
        _watch(launcher, runner, trace, args.drain)
    finally:
        launcher.request_stop()
        runner.join()
        log.close()
    wall = time.monotonic() - t0
    figures = _figures(trace, launcher, out, wall)
    cmd = "python bench/long_drive.py " + " ".join(argv if argv is not None else sys.argv[1:])
    figures["command"] = cmd.strip()
    figures["load_average_end"] = round(psutil.getloadavg()[0], 1)
    figures["frames_requested"] = args.frames
    figures["launch_file"] = os.path.relpath(Path(args.launch).resolve(), REPO_ROOT)
    dist = _path_lengths(trace)
    save_trace(trace, dist, out / "trace.json")
    write_json(str(out / "figures.json"), figures)
    png = out / "long_drive.png"
    _plot(trace, png, dist)
    for k, v in figures.items():
        if not isinstance(v, dict):
            print(f"{k:40s} {v}")
    print(f"outputs in {out} (plot {png})")
    write_json(args.json, figures)
    if not args.no_docs:
        _write_docs(args.frames, figures, png)
    return 0


def _docs_from(run_dir: Path, args: argparse.Namespace) -> int:
    """The plot and the docs section of a finished run (its ``figures.json``, ``trace.json``)."""
    figures = json.loads((run_dir / "figures.json").read_text())
    trace, dist = load_trace(run_dir / "trace.json")
    png = run_dir / "long_drive.png"
    _plot(trace, png, dist)
    _write_docs(figures.get("frames_requested", args.frames), figures, png)
    return 0


def _write_docs(frames: int, f: dict, png: Path) -> None:
    import shutil

    docs_png = REPO_ROOT / "docs" / "long_drive.png"
    docs_png.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(png, docs_png)
    gaps = ", ".join(f"{n} {v['heartbeat_gap_max_s']}" for n, v in f["nodes"].items())
    cpu = f.get("node_cpu_s", {})
    total = sum(cpu.values()) or float("nan")
    shares = ", ".join(f"{n} {v:.0f} s ({100 * v / total:.0f} %)" for n, v in cpu.items())
    load = round(f.get("load_average_end", psutil.getloadavg()[0]), 1)
    body = f"""## Long drive: memory and time per keyframe against distance (issues 17, 23)

Command: `{f.get("command", "python bench/long_drive.py")}`

Machine: {machine_line()}; 2 cores shared with other jobs (load average {load}
at the end): times are upper bounds. `{f.get("launch_file", "launch/long_drive.yaml")}` (the
demo pipeline with a lighter mapper schedule, stated in the file) on a synthetic drive of
{frames} frames at 10 Hz, player `fast: true`, the run's state in one folder as `mogs demo` has it
(journal, checkpoints, offloaded submaps); the report node is left out.

| figure | value |
| --- | ---: |
| frames / keyframes / mapped / lost | {f["frames"]} / {f["keyframes"]} / {f["keyframes_mapped"]} / {f["keyframes_lost"]} |
| distance driven (keyframe path) [m] | {f["distance_m"]} |
| mapper peak RSS at frame {RSS_FRAME} / at the end [MiB] | {f["rss_mib_600"]} / {f["rss_mib_end"]} |
| `rss_end_over_rss_600` | {f["rss_end_over_rss_600"]} |
| mapper CPU time per keyframe, median of first / last 10 % [ms] | {f["keyframe_cpu_ms_first10"]} / {f["keyframe_cpu_ms_last10"]} |
| `keyframe_time_ratio_last_first` (CPU time) | {f["keyframe_time_ratio_last_first"]} |
| wall time of the core step, first / last 10 % [ms] (ratio; shared machine) | {f["keyframe_wall_ms_first10"]} / {f["keyframe_wall_ms_last10"]} ({f["keyframe_wall_ratio_last_first"]}) |
| Gaussians in the final PLY / its bytes | {f["gaussians"]} / {f["ply_bytes"]} |
| Gaussians in RAM / on disk at the end | {f["gaussians_in_ram_end"]} / {f["gaussians_on_disk_end"]} |
| kills for no heartbeat / for no progress; player ack timeouts | {f["heartbeat_kills"]} / {f["progress_kills"]}; {f["ack_timeouts"]} |
| largest heartbeat gap per node [s] | {gaps} |
| wall time [s] | {f["wall_s"]} |
| CPU time per node over the run (share) | {shares} |

![mapper RSS and time per keyframe against distance](long_drive.png)
"""
    update_markdown_section("long-drive", body)


if __name__ == "__main__":
    sys.exit(main())
