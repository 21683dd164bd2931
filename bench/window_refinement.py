"""Keyframe poses as the frontend first publishes them and as its sliding window leaves them
(``/frontend/refined_pose``, which the ROS bridges' ``/mogs/path`` follows): keyframe ATE of both
against the sim's ground truth, on a sim drive with a static start (the frontend alone, no bus).

Usage::

    python bench/window_refinement.py [--frames 60] [--json PATH] [--no-docs]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mogs_node.eval.bench_docs import (  # noqa: E402
    add_output_options,
    machine_line,
    update_markdown_section,
    write_json,
)
from mogs_node.eval.frontend_runs import window_refinement  # noqa: E402
from mogs_node.frontend.frontend import FrontendParams  # noqa: E402
from mogs_node.frontend.keyframes import KeyframeParams  # noqa: E402
from mogs_node.sim import SimConfig, make_sequence  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=60)
    add_output_options(ap)
    args = ap.parse_args(argv)
    rows = {}
    for n in sorted({40, args.frames}):
        seq = make_sequence(
            SimConfig(seed=0, n_frames=n, width=621, height=188, static_start_s=2.0)
        )
        # launch/ros1.yaml's keyframe policy
        params = FrontendParams(keyframes=KeyframeParams(min_parallax_px=20.0, max_interval_s=1.0))
        rows[n] = window_refinement(seq, params)
    fig = {f"frames_{n}_{k}": v for n, r in rows.items() for k, v in r.items()}
    print(json.dumps(fig, indent=2))
    write_json(args.json, fig)
    if not args.no_docs:
        table = "\n".join(
            f"| {n} | {r['keyframes']} ({r['refined']} moved) | {1e3 * r['ate_first_m']:.1f} mm "
            f"| {1e3 * r['ate_refined_m']:.1f} mm | {1e3 * r['max_move_m']:.1f} mm |"
            for n, r in rows.items()
        )
        update_markdown_section(
            "window-refinement",
            f"""## Keyframe poses refined by the frontend's window (the ROS path)

`python bench/window_refinement.py --frames {args.frames}` ({machine_line()}). Sim drives (10 Hz,
621x188, 2 s static start) through the frontend alone with `launch/ros1.yaml`'s keyframe policy;
each keyframe's pose as first published (`/frontend/keyframe`) and as the sliding window's solves
last left it (`/frontend/refined_pose`, what `/mogs/path` follows); SE(3)-aligned keyframe ATE
against ground truth. Deterministic (no timing involved).

| frames | keyframes | ATE as first published | ATE refined | largest move |
| --- | --- | --- | --- | --- |
{table}
""",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
