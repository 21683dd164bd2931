"""Rendering speed of the synthetic world (frames/s) at 1242x375 and 621x188 on one core.

Usage: ``python bench/sim_render.py [--frames 5] [--seed 0] [--json PATH] [--no-docs]``.
The world is sized to about 200 primitives (``density``) and the frames span the drive.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from mogs_node.eval.bench_docs import (  # noqa: E402
    add_output_options,
    machine_line,
    update_markdown_section,
    write_json,
)
from mogs_node.sim import SimConfig, WorldParams, make_sequence  # noqa: E402


def bench(width: int, height: int, frames: int, seed: int) -> dict[str, float]:
    seq = make_sequence(
        SimConfig(
            seed=seed, n_frames=40, width=width, height=height, world=WorldParams(density=1.3)
        )
    )
    picks = np.linspace(0, len(seq) - 1, frames).round().astype(int)
    seq.render(int(picks[0]))  # warm-up (KD-tree, caches)
    times, visible = [], []
    for i in picks:
        t = time.perf_counter()
        seq.render(int(i))
        times.append(time.perf_counter() - t)
        visible.append(len(seq.world.visible_boxes(seq.T_world_cam[i], seq.camera)))
    med = float(np.median(times))
    return {
        "frames_per_s": 1.0 / med,
        "ms_per_frame": 1000.0 * med,
        "ms_per_frame_max": 1000.0 * max(times),
        "n_primitives": float(len(seq.world.primitives)),
        "n_visible_median": float(np.median(visible)),
    }


def _row(fig: dict[str, float], w: int, h: int) -> str:
    k = f"{w}x{h}"
    cells = [
        k,
        f"{fig['frames_per_s_' + k]:.2f}",
        f"{fig['ms_per_frame_' + k]:.0f}",
        f"{fig['ms_per_frame_max_' + k]:.0f}",
        f"{fig['n_primitives_' + k]:.0f}",
        f"{fig['n_visible_median_' + k]:.0f}",
    ]
    return "| " + " | ".join(cells) + " |"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=5, help="frames timed per resolution")
    ap.add_argument("--seed", type=int, default=0)
    add_output_options(ap)
    args = ap.parse_args(argv)
    figures: dict[str, float] = {}
    for w, h in ((1242, 375), (621, 188)):
        r = bench(w, h, args.frames, args.seed)
        for k, v in r.items():
            figures[f"{k}_{w}x{h}"] = v
        print(
            f"{w}x{h}: {r['frames_per_s']:.2f} frames/s ({r['ms_per_frame']:.0f} ms/frame median, "
            f"max {r['ms_per_frame_max']:.0f} ms), {r['n_primitives']:.0f} primitives, "
            f"{r['n_visible_median']:.0f} in view"
        )
    ratio = figures["frames_per_s_621x188"] / figures["frames_per_s_1242x375"]
    figures["ratio_speed_621x188_vs_1242x375"] = ratio
    goal = figures["ms_per_frame_1242x375"] < 1000.0
    print(
        f"ratio 621x188 / 1242x375 speed: {ratio:.2f}; goal (<1 s per 1242x375 frame): "
        f"{'met' if goal else 'NOT met'}"
    )
    write_json(args.json, figures)
    if not args.no_docs:
        cmd = "python bench/sim_render.py " + " ".join(
            shlex.quote(a) for a in (argv or sys.argv[1:])
        )
        body = "\n".join(
            [
                "## Synthetic world rendering (`bench/sim_render.py`)",
                "",
                f"Command: `{cmd.strip()}`  ",
                f"Machine: {machine_line()}, one thread, load average {os.getloadavg()[0]:.1f} "
                "(shared machine: other processes compete for the cores)",
                "",
                "| resolution | frames/s | ms/frame (median) | ms/frame (max) | primitives "
                "| in view |",
                "| --- | --- | --- | --- | --- | --- |",
                *[_row(figures, w, h) for w, h in ((1242, 375), (621, 188))],
                "",
                f"Speed ratio 621x188 / 1242x375: {ratio:.2f}. Goal, a 1242x375 frame with ~200 "
                f"primitives in under 1 s on one core: {'met' if goal else 'not met'}.",
            ]
        )
        update_markdown_section("sim_render", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
