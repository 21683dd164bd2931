"""Frontend benchmark: per-frame latency and throughput on one core, split into tracking and
estimation, at 1242x375 and 621x188, and run time against trajectory error over the main knobs;
the keyframes' sparse points against ground truth on the demo drive, and CPU time per frame with
and without them.

    .venv/bin/python bench/frontend.py [--frames 100] [--json PATH] [--no-markdown] [--points-only]

Images are rendered by the simulator before timing starts (rendering is not part of the
frontend). The process is pinned to one CPU core and OpenCV to one thread. Frames processed while
the dynamic initialisation is still scoring its hypotheses are reported apart ("init"), the
per-frame figures are for tracking frames. The knob sweep scores the keyframe trajectory with evo
(ATE after SE(3) alignment); it starts the estimator from the true state (harness only).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.frontend_tables import (  # noqa: E402
    POINTS_HEAD,
    current_section,
    kept_tables,
    points_lines,
    speed_lines,
    sweep_lines,
    traj_lines,
    with_new_points,
)
from mogs_node.eval.bench_docs import (  # noqa: E402
    REPO_ROOT,
    machine_line,
    update_markdown_section,
    write_json,
)
from mogs_node.eval.frontend_runs import (  # noqa: E402
    keyframe_point_figures,
    load_dataset,
    run_dataset_frames,
    score_run,
)
from mogs_node.frontend.camera import CameraModel  # noqa: E402
from mogs_node.frontend.frontend import FrontendParams  # noqa: E402
from mogs_node.launch import load_launch_file  # noqa: E402


def pin_one_core() -> None:
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def prerender(seconds: float, size: tuple[int, int], seed: int) -> dict:
    # moving from frame 0, as in the earlier speed figures (a parked start adds idle frames)
    d = load_dataset("sim", seconds=seconds, seed=seed, size=size, static_start_s=0.0)
    images = [d["image"](i) for i in range(len(d["stamps_ns"]))]
    d["image"] = images.__getitem__
    return d


def with_knob(params: FrontendParams, group: str, name: str, value) -> FrontendParams:
    return dataclasses.replace(
        params, **{group: dataclasses.replace(getattr(params, group), **{name: value})}
    )


def seeded_run(seq, images, params: FrontendParams):
    """Sweep harness: the frontend starts from the true state at frame 0 (benchmark only, never in
    product code) so that a knob's effect is not drowned by the initialisation's scale choice."""
    from mogs_node.eval.frontend_runs import RunResult, run_frontend
    from mogs_node.frontend.camera import CameraModel
    from mogs_node.frontend.frontend import Frontend

    fe = Frontend(params, CameraModel(seq.camera), seq.T_imu_cam)
    k = int(np.searchsorted(seq.imu_stamps_ns, seq.stamps_ns[0], side="right"))
    fe.add_imu_batch(seq.imu_stamps_ns[:k], seq.imu_gyro_rad_s[:k], seq.imu_accel_m_s2[:k])
    res = fe.tracker.track(images[0])
    fe.estimator.initialize(
        int(seq.stamps_ns[0]),
        seq.T_world_imu[0],
        seq.velocity_world_m_s[0],
        np.zeros(3),
        np.zeros(3),
        res.ids,
        res.uv_px,
        res.track_len,
    )
    fe._last_kf = (int(seq.stamps_ns[0]), res.ids, res.uv_px)
    fe._last_frame_ns = int(seq.stamps_ns[0])
    fe._last_image_ns = int(seq.stamps_ns[0])
    t0 = time.perf_counter()
    outs = run_frontend(
        fe,
        seq.stamps_ns[1:],
        images[1:],
        seq.imu_stamps_ns[k:],
        seq.imu_gyro_rad_s[k:],
        seq.imu_accel_m_s2[k:],
    )
    wall = time.perf_counter() - t0
    timings = {
        n: float(np.mean([o.timings_ms[n] for o in outs])) for n in ("tracking", "estimation")
    }
    return RunResult(outs, seq.T_world_cam[1:], seq.stamps_ns[1:], dict(fe.counters), wall, timings)


def timing_figures(run) -> dict:
    # a tracking frame whose predecessor was not tracking completed the initialisation in its
    # call: that cost is the init's (reported apart), not the tracking's
    outs = run.outputs
    tracking = [
        o
        for k, o in enumerate(outs)
        if o.status == "tracking" and k and outs[k - 1].status == o.status
    ]
    tr = np.array([o.timings_ms["tracking"] for o in tracking])
    es = np.array([o.timings_ms["estimation"] for o in tracking])
    gr = np.array([o.timings_ms.get("ground", 0.0) for o in tracking])
    timed = {id(o) for o in tracking}
    init = [o for o in outs if id(o) not in timed]
    tot = tr + es + gr
    if len(tot) == 0:  # never initialised in this run
        tot = np.array([np.nan])
    return {
        "tracking_ms_per_frame": float(np.mean(tr)),
        "estimation_ms_per_frame": float(np.mean(es)),
        "ground_ms_per_frame": float(np.mean(gr)) if len(gr) else 0.0,
        "total_ms_per_frame_p50": float(np.median(tot)),
        "total_ms_per_frame_p95": float(np.percentile(tot, 95)),
        "frames_per_s": float(1000.0 / np.mean(tot)),
        "init_ms_per_frame": float(np.mean([sum(o.timings_ms.values()) for o in init]))
        if init
        else 0.0,
        "tracking_frames": len(tracking),
    }


def cpu_run(
    d: dict, params: FrontendParams, stamps: list[int] | None = None
) -> tuple[list, list[float]]:
    """Stream a prerendered dataset; CPU time (``time.process_time``) of each image's call that
    gives tracking frames (their stamps appended to ``stamps`` when given). The call that
    completes the initialisation is left out: it also solves the initialisation (~1 s on the
    dynamic start, once per run), which is no per-frame tracking cost (the module docstring's
    "init" frames); before this, that one call added ~15 ms to a 70-frame mean."""
    from mogs_node.frontend.frontend import Frontend

    fe = Frontend(params, d["camera"], d["T_imu_cam"])
    imu_t, gyro, accel = d["imu"]
    outs, cpu_s, k = [], [], 0
    for i, t in enumerate(d["stamps_ns"].tolist()):
        while k < len(imu_t) and imu_t[k] <= t + params.time_offset_ns:
            outs += fe.add_imu(int(imu_t[k]), gyro[k], accel[k])
            k += 1
        tracking = fe.initialized
        c0 = time.process_time()
        res = fe.add_image(int(t), d["image"](i))
        dt = time.process_time() - c0
        outs += res
        if tracking and res and all(o.status == "tracking" for o in res):
            cpu_s.append(dt)
            if stamps is not None:
                stamps.append(int(t))
    return outs, cpu_s


# Round 8's dense points (900 tracks >= 5 px apart, new corners every 2nd frame, 10 frames of
# views, the gates of then, both sides of every depth jump dropped, the last 3 keyframes
# re-observed): the figures before round 9 (docs/frontend.md), for comparison.
# round 9's denser points (docs/frontend.md "Round 9"): more points per keyframe and fewer
# straddling edges on the demo drive, but a worse metrized depth on the real KITTI excerpt and with
# the simulated LFM, and ~1.4x the tracking CPU; so not the default (session 11)
ROUND9 = {
    "max_tracks": 3000,
    "min_distance_px": 2,
    "top_up_every": 1,
    "history_frames": 16,
    "view_stride": 3,
    "gn_iterations": 1,
    "max_reproj_px": 0.8,
    "min_patch_zncc": 0.85,
    "edge_rule": "unsupported",
    "edge_rel_jump": 0.05,
    "reproject_keyframes": 6,
    "reproject_min_zncc": 0.7,
}


# round 13 (docs/frontend.md, session 15): round 9's points, the tracks around the focus of
# expansion thinned to a quarter (they seldom triangulate); with the round's cheaper
# triangulation and re-observation; opt-in, as round 9's
ROUND13 = {**ROUND9, "epipole_radius_deg": 10.0, "epipole_cap_share": 0.25}

# round 14 (docs/frontend.md, session 16): round 13's points, the re-observed points tested for
# the contrast they had (a point behind a flat occluder is dropped), re-observed at ZNCC 0.55;
# opt-in: its extra points cost the demo's metrized depth (a mask fill, docs/frontend.md)
ROUND14 = {**ROUND13, "reproject_min_contrast": 0.5, "reproject_min_zncc": 0.55}


def demo_points(launch: Path = REPO_ROOT / "launch" / "demo.yaml") -> dict:
    """The frontend's ``points`` of the demo launch file (issue 16 measures the demo's frontend;
    since session 16 that is round 14's, not the code's defaults, which KITTI keeps)."""
    node = next(n for n in load_launch_file(launch).nodes if n.name == "frontend")
    return dict(node.params.get("points", {}))


def with_points(params: FrontendParams, **fields) -> FrontendParams:
    return dataclasses.replace(params, points=dataclasses.replace(params.points, **fields))


def points_figures(seed: int, frames: int, repeats: int = 3) -> tuple[dict, list[str]]:
    """Sparse points on the demo drive (launch/demo.yaml: parked 2 s, keyframes every 20 px /
    1 s) against ground truth, with the estimator window's landmarks as before for reference;
    CPU time per tracking frame at 621x188 with and without the points (moving start; the
    least of ``repeats`` interleaved runs per setting: on the shared machine a single run of the
    same code varied by x1.9, session 15). Returns the figures and the docs' block."""
    demo = demo_points()
    out = points_on_demo_drive(seed, demo)
    out.update(points_cpu(seed, frames, repeats, demo))
    return out, points_lines(out, seed, frames, repeats)


def points_on_demo_drive(seed: int, demo: dict) -> dict[str, float]:
    """The points' figures against ground truth and the CPU per frame parked / driving, per
    variant (``demo``: the demo launch file's ``points``), keys prefixed by the variant."""
    from mogs_node.frontend.keyframes import KeyframeParams
    from mogs_node.sim import SimConfig, make_sequence

    cfg = SimConfig(seed=seed, n_frames=60, width=621, height=188, static_start_s=2.0)
    seq = make_sequence(cfg)
    sim_frames = [seq.render(i) for i in range(cfg.n_frames)]
    index = {int(t): i for i, t in enumerate(seq.stamps_ns)}
    speed = np.linalg.norm(seq.velocity_world_m_s, axis=1)
    d = {
        "stamps_ns": seq.stamps_ns,
        "image": lambda i: sim_frames[i].rgb,
        "imu": (seq.imu_stamps_ns, seq.imu_gyro_rad_s, seq.imu_accel_m_s2),
        "camera": CameraModel(seq.camera),
        "T_imu_cam": seq.T_imu_cam,
    }
    base = FrontendParams(keyframes=KeyframeParams(min_parallax_px=20.0, max_interval_s=1.0))
    out: dict[str, float] = {}
    variants = {"": demo, "defaults_": {}, "landmarks_": {"enabled": False}, "round9_": ROUND9}
    variants["round13_"] = ROUND13
    variants["round14_"] = ROUND14
    for tag, fields in variants.items():
        stamps: list[int] = []
        outs, cpu_s = cpu_run(d, with_points(base, **fields), stamps)
        fig = keyframe_point_figures(
            outs, lambda t: sim_frames[index[t]].depth_m, lambda t: float(speed[index[t]])
        )
        out.update({f"{tag}{k}": v for k, v in fig.items()})
        # the frontend's CPU per frame while parked against while driving (issue 27)
        v = speed[[index[t] for t in stamps]]
        cpu = np.asarray(cpu_s)
        out[f"{tag}cpu_ms_per_frame_standstill"] = 1e3 * float(np.mean(cpu[v < 0.01]))
        out[f"{tag}cpu_ms_per_frame_moving"] = 1e3 * float(np.mean(cpu[v > 0.5]))
    return out


def points_cpu(seed: int, frames: int, repeats: int, demo: dict) -> dict[str, float]:
    """CPU time per tracking frame at 621x188 (moving start) per variant, the least of
    ``repeats`` interleaved runs."""
    out: dict[str, float] = {}
    moving = prerender((frames - 1) / 10.0, (621, 188), seed)
    timed = {"": demo, "_defaults": {}, "_no_points": {"enabled": False}, "_round9": ROUND9}
    timed["_round13"] = ROUND13
    timed["_round14"] = ROUND14
    runs: dict[str, list[float]] = {tag: [] for tag in timed}
    for _ in range(repeats):  # the variants interleaved, the least loaded run of each kept
        for tag, fields in timed.items():
            _, cpu_s = cpu_run(moving, with_points(FrontendParams(), **fields))
            runs[tag].append(1e3 * float(np.mean(cpu_s)))
    for tag, ms_runs in runs.items():
        ms = min(ms_runs)
        out[f"cpu_ms_per_frame_621x188{tag}"] = ms
        out[f"cpu_frames_per_s_621x188{tag}"] = 1e3 / ms
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100, help="frames per run (10 Hz)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--cpu-repeats",
        type=int,
        default=3,
        help="interleaved runs per setting of the points' CPU figures (the least is kept)",
    )
    ap.add_argument("--json", default=None, metavar="PATH")
    ap.add_argument("--no-markdown", action="store_true", help="do not update docs/benchmarks.md")
    ap.add_argument("--no-sweep", action="store_true", help="skip the knob sweep")
    ap.add_argument(
        "--points-only",
        action="store_true",
        help="only the sparse points and the CPU time with / without them (docs: with "
        "--write-points-docs only)",
    )
    ap.add_argument(
        "--write-points-docs",
        action="store_true",
        help="with --points-only: replace the sparse-points block of the frontend section of "
        "docs/benchmarks.md, keep the rest of it (the speed tables come from their own run)",
    )
    ap.add_argument(
        "--traj-json",
        nargs="*",
        default=[],
        metavar="PATH",
        help="figures of `mogs eval traj --json` runs to list in the section",
    )
    return ap.parse_args(argv)


def bench_command(argv: list[str] | None) -> str:
    """The command line of this run, as the docs quote it."""
    cmd = "python bench/frontend.py " + " ".join(argv if argv is not None else sys.argv[1:])
    return cmd.strip()


def points_only(
    args: argparse.Namespace, argv: list[str] | None, points: dict, point_lines: list[str]
) -> int:
    """``--points-only``: write the points' figures, and with ``--write-points-docs`` replace the
    sparse-points block of the docs' ``frontend`` section (with a note on this run)."""
    figures = {**points, "load_average_1min": float(os.getloadavg()[0])}
    write_json(args.json, figures)
    new = with_new_points(current_section(), point_lines)
    if args.write_points_docs and new is not None:
        note = (
            f"Sparse points block: `{bench_command(argv)}` ({machine_line()}), 1-min load "
            f"average {figures['load_average_1min']:.1f} (times inflated; each CPU figure is the "
            "least of interleaved runs, the ratios with / without points from the same rounds); "
            "the speed tables above it are from their own run."
        )
        update_markdown_section(
            "frontend",
            new.replace(POINTS_HEAD, "\n" + note + "\n" + POINTS_HEAD, 1).lstrip("\n"),
        )
    print(json.dumps(figures, indent=1, default=float))
    return 0


def speed_runs(
    frames: int, seed: int, base: FrontendParams, figures: dict
) -> list[tuple[str, dict]]:
    """Per-frame timings at 1242x375 and 621x188, camera + IMU and with the road; adds them to
    ``figures`` and returns ``(resolution tag, timings)`` rows for the docs."""
    seconds = (frames - 1) / 10.0
    rows = []
    for size, road in (
        ((1242, 375), False),
        ((621, 188), False),
        ((1242, 375), True),
        ((621, 188), True),
    ):
        d = prerender(seconds, size, seed)
        params = base
        if road:  # the road measurement at the sim's calibrated camera height
            params = with_knob(base, "ground", "camera_height_m", d["camera_height_m"])
        run = run_dataset_frames(d, params)
        t = timing_figures(run)
        tag = f"{size[0]}x{size[1]}" + (" + road" if road else "")
        for k, v in t.items():
            figures[f"{k}_{tag.replace(' + ', '_')}"] = v
        rows.append((tag, t))
        print(
            f"{tag}: tracking {t['tracking_ms_per_frame']:.1f} ms + estimation "
            f"{t['estimation_ms_per_frame']:.1f} ms + road {t['ground_ms_per_frame']:.1f} ms "
            f"-> {t['frames_per_s']:.1f} frames/s",
            flush=True,
        )
    return rows


def knob_sweep(frames: int, seed: int, base: FrontendParams, figures: dict) -> list[tuple]:
    """Run time against keyframe ATE, one knob at a time from ``base`` (621x188, from the true
    state); adds them to ``figures`` and returns ``(knob, value, ms, frames/s, ATE m, ATE %)``."""
    from mogs_node.sim import SimConfig, make_sequence

    seq = make_sequence(SimConfig(seed=seed, n_frames=frames, width=621, height=188))
    images = [seq.render(i).rgb for i in range(frames)]
    knobs = [("tracker", "max_features", v) for v in (60, 100, 150, 250)]
    knobs += [("estimator", "window_size", v) for v in (3, 5, 8, 12)]
    knobs += [("estimator", "lm_iterations", v) for v in (1, 2, 3, 6)]
    sweep = []
    for group, name, value in knobs:
        run = seeded_run(seq, images, with_knob(base, group, name, value))
        t = timing_figures(run)
        try:
            m = score_run(run)
            ate = m["ate_se3_rmse_m"]
            pct = m["ate_se3_percent_of_path"]
        except Exception as err:  # a knob setting may fail to initialise: record it
            print(f"{name}={value}: not scored ({err})", flush=True)
            ate = pct = float("nan")
        sweep.append((name, value, t["total_ms_per_frame_p50"], t["frames_per_s"], ate, pct))
        figures[f"{name}_{value}_ms_per_frame"] = t["total_ms_per_frame_p50"]
        figures[f"{name}_{value}_ate_se3_m"] = ate
        print(
            f"{name}={value}: {t['total_ms_per_frame_p50']:.1f} ms/frame, "
            f"{t['frames_per_s']:.1f} frames/s, ATE {ate:.3f} m ({pct:.2f} %)",
            flush=True,
        )
    return sweep


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    pin_one_core()
    points, point_lines = points_figures(args.seed, args.frames, max(args.cpu_repeats, 1))
    print("\n".join(point_lines), flush=True)
    if args.points_only:
        return points_only(args, argv, points, point_lines)
    base = FrontendParams()
    figures: dict[str, float] = {}
    rows = speed_runs(args.frames, args.seed, base, figures)
    sweep = [] if args.no_sweep else knob_sweep(args.frames, args.seed, base, figures)
    figures.update(points)
    figures["load_average_1min"] = float(os.getloadavg()[0])
    write_json(args.json, figures)
    if not args.no_markdown:
        lines = speed_lines(bench_command(argv), args.frames, figures["load_average_1min"], rows)
        lines += sweep_lines(sweep)
        lines += point_lines
        if not sweep or not args.traj_json:  # keep what this run does not redo
            lines += kept_tables(current_section(), sweep=not sweep, accuracy=not args.traj_json)
        lines += traj_lines(args.traj_json)
        update_markdown_section("frontend", "\n".join(lines))
    print(json.dumps(figures, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
