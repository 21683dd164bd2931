"""Per-stage breakdown of the demo's depth error (issue 8): one input swapped at a time.

Runs the demo's frontend in-process on the demo sequence and metrizes each keyframe with every
combination of sparse points (frontend | ground truth at the same pixels), prior (flow on the
frontend poses | flow on ground-truth poses | simulated LFM) and masks (graph | oracle); see
:mod:`mogs_node.eval.pipeline_stages`. Writes the ``pipeline-depth-stages`` section of
docs/benchmarks.md.

    python bench/pipeline_depth_stages.py [--seed S] [--launch launch/demo.yaml] [--json OUT]
        [--live | --live-runs DEMO_DIR LFM_DIR] [--no-docs]  (without it the section of
        docs/benchmarks.md is rewritten)

``--live`` also runs the pipeline itself (``mogs demo``, one OS process per node) with the demo
launch file and with ``launch/demo_lfm.yaml`` (the simulated LFM as prior, evaluation only) and
reads their ``summary.json``: the figures a user sees (JSON keys ``live_absrel``,
``live_coverage``, ``live_min_keyframe_coverage``, ``live_lfm_absrel``, ``live_lfm_coverage``).

The simulated-LFM rows are also run with the flow prior (frontend poses) beside the LFM as dense
metric anchors (``MetrizerInputs.anchor_*``, docs/metrizer.md "Dense metric anchors"; JSON
``anchored``, keyed as ``combos``), with the demo's metrizer parameters, + ``edge_snap``, and with
``launch/demo_lfm.yaml``'s (+ ``sky_anchor``, ``road_snap_rel``): its wiring.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mogs_node.eval.bench_docs import add_output_options, machine_line, write_results  # noqa: E402
from mogs_node.eval.pipeline_stages import (  # noqa: E402
    MASKS,
    SPARSE,
    _pool,
    demo_params,
    evaluate_stages,
    prepare_keyframes,
    stage_inputs,
)

SPARSE_NAME = {
    "frontend": "frontend points",
    "gt": "GT depth at the same pixels",
    "gt_corners": "GT depth at 500 corners",
}
PRIOR_NAME = {
    "flow": "flow prior, frontend poses",
    "flow_gtpose": "flow prior, GT poses",
    "lfm": "simulated LFM",
}
MASK_NAME = {"graph": "graph masks", "oracle": "oracle masks"}
ANCHORED_NAME = {
    "lfm_anchored": "simulated LFM + flow prior as dense metric anchors",
    "lfm_anchored_snap": "the same + edge snap",
    "lfm_launch": "the same + sky anchor + road snap (`launch/demo_lfm.yaml`)",
}
REPO = Path(__file__).resolve().parents[1]
LFM_LAUNCH = "launch/demo_lfm.yaml"
LIVE_ANCHOR = 'What each stage costs and what is inherent: docs/bridges.md, "Pipeline end to end".'


def markdown(fig: dict, info: dict, command: str) -> str:
    c = fig["combos"]
    base = c["frontend|flow|graph"]
    lines = [
        "## Pipeline depth error by stage (issue 8)",
        "",
        f"Command: `{command}`",
        "",
        f"Machine: {machine_line()}. The demo's sequence and node parameters (`launch/demo.yaml`); "
        f"the frontend run in-process on all {info['frames']} frames: {info['keyframes']} "
        f"keyframes, {info['estimated_frames']} frames with a pose. AbsRel pooled over pixels, "
        "coverage = share of ground-truth pixels with a metrized depth (mean over keyframes), "
        "scored as the run report scores (`mogs_node/report/collect.py`).",
        "",
        "| sparse points | prior | masks | AbsRel | delta1 | coverage | vs demo inputs |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for key, v in c.items():
        sp, pr, mk = key.split("|")
        lines.append(
            f"| {SPARSE_NAME[sp]} | {PRIOR_NAME[pr]} | {MASK_NAME[mk]} | {v['absrel']:.3f} | "
            f"{v['delta1']:.3f} | {v['coverage']:.3f} | {v['absrel'] - base['absrel']:+.3f} |"
        )
    anchored = fig.get("anchored", {})
    for key, v in anchored.items():
        sp, pr, mk = key.split("|")
        lines.append(
            f"| {SPARSE_NAME[sp]} | {ANCHORED_NAME[pr]} | {MASK_NAME[mk]} | {v['absrel']:.3f} | "
            f"{v['delta1']:.3f} | {v['coverage']:.3f} | {v['absrel'] - base['absrel']:+.3f} |"
        )
    lines += [
        "",
        "The priors on their own (pixels where their confidence > 0):",
        "",
        "| prior | AbsRel | delta1 | coverage |",
        "| --- | ---: | ---: | ---: |",
    ]
    for pr, v in fig["prior_alone"].items():
        lines.append(
            f"| {PRIOR_NAME[pr]} | {v['absrel']:.3f} | {v['delta1']:.3f} | {v['coverage']:.3f} |"
        )
    sp = [s for s in fig["sparse"] if s["n"]]
    if sp:
        med = sorted(s["median_relerr"] for s in sp)[len(sp) // 2]
        scales = [s["scale"] for s in sp]
        counts = [s["n"] + s["on_depth_edge"] for s in fig["sparse"]]
        lines += [
            "",
            f"Frontend sparse points against the truth at their pixels (off depth edges): median "
            f"over keyframes of the per-keyframe median relative error {med:.3f}; scale (median "
            f"z / z_gt) {min(scales):.3f}-{max(scales):.3f}. Points per keyframe: "
            f"{', '.join(map(str, counts))} ({sum(s['on_depth_edge'] for s in fig['sparse'])} "
            "on a depth edge in all).",
        ]
    lines += [
        "",
        'What each stage costs and what is inherent: docs/bridges.md, "Pipeline end to end".',
    ]
    return "\n".join(lines)


def anchored_stages(kfs: list, inputs: dict, params: dict) -> dict:
    """The simulated-LFM combinations with the flow prior (frontend poses) as dense metric anchors,
    with the demo's metrizer parameters (``lfm_anchored``), + the edge snap
    (``lfm_anchored_snap``) and with ``launch/demo_lfm.yaml``'s (``lfm_launch``: + the sky anchor
    and the road snap), scored as :func:`evaluate_stages` scores."""
    from mogs_node.eval.depth_prior_eval import metrizer_params
    from mogs_node.metrizer.matching import MatchedKeyframe, metrizer_inputs
    from mogs_node.metrizer.pipeline import metrize
    from mogs_node.report.collect import score_depth

    p_demo, mode = metrizer_params(params)
    variants = {
        "lfm_anchored": (p_demo, mode),
        "lfm_anchored_snap": (replace(p_demo, edge_snap=True), mode),
        "lfm_launch": metrizer_params(demo_params(REPO / LFM_LAUNCH)),
    }
    out = {}
    for (name, (p, mode)), sp, mk in itertools.product(variants.items(), SPARSE, MASKS):
        scores = []
        for i, s in enumerate(kfs):
            entry = MatchedKeyframe(
                s.keyframe.keyframe_id,
                keyframe=inputs["sparse"][sp][i],
                masks=inputs["masks"][mk][i],
                prior=inputs["prior"]["lfm"][i],
                anchor=inputs["prior"]["flow"][i],
            )
            d = metrize(metrizer_inputs(entry), p, mode).depth_m
            scores.append(score_depth(s.keyframe.keyframe_id, 0, d, s.gt_depth_m))
        out[f"{sp}|{name}|{mk}"] = {
            **_pool(scores),
            "per_keyframe": [(x.absrel, x.coverage) for x in scores],
        }
        logging.info("%s|%s|%s: %s", sp, name, mk, _pool(scores))
    return out


def live(launch: str) -> dict:
    """``mogs demo --launch LAUNCH`` in a temporary folder; its ``summary.json`` depth figures."""
    with tempfile.TemporaryDirectory(prefix="mogs-live-") as tmp:
        cmd = [sys.executable, "-m", "mogs_node.cli", "demo", "--launch", launch, "--out", tmp]
        logging.info("running %s", " ".join(cmd))
        run = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
        if run.returncode != 0:
            tail = (run.stdout + run.stderr)[-4000:]
            raise RuntimeError(f"{' '.join(cmd)} failed ({run.returncode}):\n{tail}")
        summary = json.loads((Path(tmp) / "summary.json").read_text())
    return summary["depth"]


def live_markdown(fig: dict) -> list[str]:
    rows = [
        "",
        "The running pipeline (`mogs demo`, one process per node; `--live`), its `summary.json`:",
        "",
        "| launch file | prior | AbsRel | delta1 | coverage | min keyframe coverage |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for key, launch, prior in (
        ("live", "launch/demo.yaml", "weight-free dense prior (default)"),
        (
            "live_lfm",
            "launch/demo_lfm.yaml",
            "simulated LFM + flow prior as dense metric anchors + edge snap + sky anchor + road "
            "snap (evaluation only)",
        ),
    ):
        d = fig.get(f"{key}_depth")
        if d:
            rows.append(
                f"| `{launch}` | {prior} | {d['absrel']:.3f} | {d['delta1']:.3f} | "
                f"{d['coverage']:.3f} | {d['min_keyframe_coverage']:.3f} |"
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--launch", default=None, help="demo launch file (default launch/demo.yaml)")
    ap.add_argument("--seed", type=int, default=None, help="sim seed (default: the demo's)")
    add_output_options(ap)
    ap.add_argument("--live", action="store_true", help="also run the pipeline (two mogs demo)")
    ap.add_argument(
        "--live-runs",
        nargs=2,
        metavar=("DEMO_DIR", "LFM_DIR"),
        default=None,
        help="instead of --live: the output folders of `mogs demo` runs made with the demo "
        "launch file and launch/demo_lfm.yaml (their summary.json)",
    )
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    t0 = time.perf_counter()
    params = demo_params(args.launch)
    kfs, info = prepare_keyframes(params, seed=args.seed)
    inputs = stage_inputs(kfs, params)
    fig = evaluate_stages(kfs, inputs, params)
    fig["anchored"] = anchored_stages(kfs, inputs, params)
    info.pop("K_sim", None)
    info.pop("tracked_frames", None)  # images, not figures (the stage priors do not use them)
    fig["info"] = info
    if args.live or args.live_runs:
        launches = (("live", args.launch or "launch/demo.yaml"), ("live_lfm", LFM_LAUNCH))
        for i, (key, launch) in enumerate(launches):
            if args.live_runs:
                summary = json.loads((Path(args.live_runs[i]) / "summary.json").read_text())
                d = summary["depth"]
            else:
                d = live(launch)
            fig[f"{key}_depth"] = d
            fig[f"{key}_absrel"] = d["absrel"]
            fig[f"{key}_coverage"] = d["coverage"]
            fig[f"{key}_min_keyframe_coverage"] = d["min_keyframe_coverage"]
    fig["wall_s"] = time.perf_counter() - t0
    command = "python bench/pipeline_depth_stages.py" + "".join(
        f" {a}" for a in sys.argv[1:] if a != "--no-docs"
    )
    md = markdown(fig, info, command)
    if args.live or args.live_runs:
        md = md.replace(LIVE_ANCHOR, "\n".join(live_markdown(fig)) + "\n\n" + LIVE_ANCHOR)
    write_results("pipeline-depth-stages", md, fig, args.json, not args.no_docs)


if __name__ == "__main__":
    main()
