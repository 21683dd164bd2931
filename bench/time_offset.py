"""Camera-IMU time offset on the handheld walk: the frontend alone, in-process, with the offset
estimated and with estimation off (the launch value 0 used as it is), for several true offsets.

    .venv/bin/python bench/time_offset.py [--frames 1200] [--offsets-ms 50 -30 0] [--json PATH]
        [--platform handheld] [--set GROUP.FIELD=VALUE ...] [--no-imu-noise] [--write-docs]

The walk is ``mogs sim --motion handheld --size 621x188`` (the same images for every offset: only
the camera stamps move). Per run: the offset in use at the end, ATE (SE(3)-aligned, keyframes)
against the path length, resets by reason, keyframes per second, and the wall time (the machine
is shared: an upper bound). ``--set estimator.window_size=16`` (repeatable) overrides a field of
a ``FrontendParams`` group (estimator, imu, keyframes, init, tracker) for every run: the
experiments of docs/frontend.md round 8. ``--write-docs`` replaces the ``time-offset`` section of
``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


import numpy as np  # noqa: E402

from mogs_node.eval.bench_docs import machine_line, write_results  # noqa: E402
from mogs_node.eval.frontend_runs import RunResult, run_frontend, score_run  # noqa: E402
from mogs_node.frontend.camera import CameraModel  # noqa: E402
from mogs_node.frontend.frontend import Frontend, FrontendParams  # noqa: E402
from mogs_node.frontend.keyframes import KeyframeParams  # noqa: E402
from mogs_node.frontend.time_offset import TimeOffsetParams  # noqa: E402
from mogs_node.sim import SimConfig, make_sequence  # noqa: E402
from mogs_node.sim.imu import ImuNoiseParams  # noqa: E402


def run_one(seq, images, params: FrontendParams) -> dict:
    fe = Frontend(params, CameraModel(seq.camera), seq.T_imu_cam)
    t0 = time.perf_counter()
    outs = run_frontend(
        fe, seq.stamps_ns, images, seq.imu_stamps_ns, seq.imu_gyro_rad_s, seq.imu_accel_m_s2
    )
    wall = time.perf_counter() - t0
    figs = fe.figures()
    if os.environ.get("MOGS_TRAJ_NPZ"):  # per-frame poses and truth, for a look at the drift
        posed = [(i, o) for i, o in enumerate(outs) if o.T_world_cam is not None]
        np.savez(
            os.environ["MOGS_TRAJ_NPZ"],
            index=np.array([i for i, _ in posed]),
            keyframe=np.array([o.keyframe is not None for _, o in posed]),
            est=np.stack([o.T_world_cam for _, o in posed]),
            gt=np.asarray(seq.T_world_cam)[[i for i, _ in posed]],
        )
    out = {
        "time_offset_ms": figs["time_offset_ms"],
        "time_offset_sigma_ms": figs["time_offset_sigma_ms"],
        "keyframes_per_s": figs["keyframes_per_s"],
        "resets": {k[7:]: v for k, v in fe.counters.items() if k.startswith("resets_")},
        "init_rejected": {k[14:]: v for k, v in figs.items() if k.startswith("init_rejected_")},
        "wall_s": wall,
    }
    try:
        sc = score_run(RunResult(outs, seq.T_world_cam, seq.stamps_ns, dict(fe.counters), wall))
        out.update(
            {
                k: sc[k]
                for k in (
                    "path_length_m",
                    "ate_se3_rmse_m",
                    "ate_se3_percent_of_path",
                    "ate_sim3_rmse_m",
                    "scale_error",
                    "rpe_rot_deg",
                    "first_pose_s",
                )
            }
        )
    except Exception as err:  # a run without poses (never initialised): report it
        out["error"] = str(err)
    return out


def markdown(rows: list[dict], args: argparse.Namespace) -> str:
    lines = [
        f"Frontend alone, in-process, handheld walk of {args.frames} frames at 621x188, 10 Hz "
        f"(`mogs sim --motion handheld`), platform `{args.platform}`, bag.yaml's keyframe "
        "policy. Command: `python bench/time_offset.py --frames "
        f"{args.frames} --offsets-ms {' '.join(str(o) for o in args.offsets_ms)}"
        f"{''.join(' --set ' + x for x in args.set)} --write-docs`. "
        f"{machine_line()}; shared with other jobs (load {os.getloadavg()[0]:.1f}): wall times "
        "are upper bounds.",
        "",
        "| true offset [ms] | estimation | offset used [ms] | ATE [m] | ATE / path | scale error "
        "| resets | keyframes/s | first pose [s] | wall [s] |",
        "| ---: | --- | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: |",
    ]
    for r in rows:
        if "error" in r:
            lines.append(
                f"| {r['true_ms']:g} | {r['estimation']} | {r['time_offset_ms']:.1f} | "
                f"not scored: {r['error']} | | | {r['resets'] or 0} | "
                f"{r['keyframes_per_s']:.2f} | | {r['wall_s']:.0f} |"
            )
            continue
        lines.append(
            f"| {r['true_ms']:g} | {r['estimation']} | {r['time_offset_ms']:.1f} | "
            f"{r['ate_se3_rmse_m']:.2f} | {r['ate_se3_percent_of_path']:.2f} % | "
            f"{r['scale_error']:.3f} | {r['resets'] or 0} | {r['keyframes_per_s']:.2f} | "
            f"{r['first_pose_s']:.1f} | {r['wall_s']:.0f} |"
        )
    return "\n".join(lines)


def with_overrides(params: FrontendParams, sets: list[str]) -> FrontendParams:
    """``GROUP.FIELD=VALUE`` (VALUE as YAML) applied to ``params``'s dataclass groups, or
    ``FIELD=VALUE`` to a top-level field."""
    import yaml

    for item in sets:
        key, _, value = item.partition("=")
        if "." not in key and key in params.__dataclass_fields__:  # a top-level field
            val = yaml.safe_load(value)
            params = replace(params, **{key: val})
            continue
        group, _, name = key.partition(".")
        sub = getattr(params, group, None)
        if not _ or not name or sub is None or name not in sub.__dataclass_fields__:
            raise SystemExit(f"--set {item!r}: expected GROUP.FIELD=VALUE of FrontendParams")
        val = yaml.safe_load(value)
        if isinstance(val, str):  # YAML 1.1 reads 2e-3 as a string
            with contextlib.suppress(ValueError):
                val = float(val)
        params = replace(params, **{group: replace(sub, **{name: val})})
    return params


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1200)
    ap.add_argument("--offsets-ms", type=float, nargs="+", default=[50.0, -30.0, 0.0])
    ap.add_argument("--platform", default="handheld")
    ap.add_argument("--no-contrast", action="store_true", help="skip the runs with estimation off")
    ap.add_argument("--json", default=None)
    ap.add_argument("--set", action="append", default=[], help="GROUP.FIELD=VALUE")
    ap.add_argument("--write-docs", action="store_true")
    ap.add_argument("--cache", default=None, help=".npy of the rendered images (made if absent)")
    ap.add_argument("--no-imu-noise", action="store_true", help="exact IMU readings, no biases")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cfg = SimConfig(motion="handheld", n_frames=args.frames, width=621, height=188)
    if args.no_imu_noise:  # the same images (the IMU's noise does not touch them)
        cfg = replace(cfg, imu_noise=ImuNoiseParams(enabled=False))
    base = make_sequence(cfg)
    if args.cache and Path(args.cache).exists():
        images = list(np.load(args.cache, mmap_mode="r"))
    else:
        images = [base.render(i).rgb for i in range(len(base))]
        if args.cache:
            np.save(args.cache, np.stack(images))
    params = FrontendParams(
        platform=args.platform,
        keyframes=KeyframeParams(min_parallax_px=20.0, max_interval_s=1.0),  # launch/bag.yaml's
    )
    params = with_overrides(params, args.set)
    rows = []
    for off in args.offsets_ms:
        seq = make_sequence(replace(base.config, time_offset_ns=int(round(off * 1e6))))
        for est in [True] if args.no_contrast else [True, False]:
            p = replace(params, time_offset=TimeOffsetParams(enabled=est))
            r = run_one(seq, images, p)
            r.update(true_ms=off, estimation="on" if est else "off")
            print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()})
            rows.append(r)
    figures = {"runs": rows, "frames": args.frames, "platform": args.platform}
    write_results("time-offset", markdown(rows, args), figures, args.json, args.write_docs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
