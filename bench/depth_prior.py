"""The weight-free dense prior on the demo drive (issue 16 item 2): before / after, calibration.

Runs the demo's frontend in-process, then the prior over its keyframes with the metrizer in the
loop (:mod:`mogs_node.eval.depth_prior_eval`), for: main's flow-only prior; + the road plane;
+ the previous prior carried; + earlier metrized depth warped in (the default). Prints coverage
and AbsRel of the prior and of the metrized depth against the sim's ground truth, the error against confidence table, and
writes the curve as a PNG. Writes the ``depth-prior`` section of docs/benchmarks.md.

    python bench/depth_prior.py [--seed S] [--launch launch/demo.yaml] [--lag 1] [--json OUT]
        [--png docs/depth_prior_calibration.png] [--no-docs]
    python bench/depth_prior.py --kitti ../shared/data/kitti_raw_2011_09_26_78   (real images)
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from mogs_node.eval.bench_docs import (  # noqa: E402
    add_output_options,
    machine_line,
    write_results,
)
from mogs_node.eval.depth_prior_eval import (  # noqa: E402
    calibration_bins,
    prior_params,
    run_priors,
    score_priors,
)
from mogs_node.eval.figures import save_figure  # noqa: E402
from mogs_node.eval.pipeline_stages import (  # noqa: E402
    demo_params,
    graph_masks,
    prepare_keyframes,
)

REPO = Path(__file__).resolve().parents[1]
BEFORE = "flow only, references from 0.3 m (main)"
AFTER = "flow + road + carried + warped metrized depth + frames as references (default)"


def plot(bins: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [b for b in bins if b["pixels"]]
    mid = [0.5 * (b["conf_lo"] + b["conf_hi"]) for b in rows]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(mid, [b["absrel"] for b in rows], "o-", label="measured AbsRel")
    ax.plot(mid, [b["median_rel_err"] for b in rows], "s-", label="measured median rel. error")
    ax.plot(mid, [b["predicted_rel_err"] for b in rows], "x--", label="predicted rel. error")
    ax.set_yscale("log")
    ax.set_xlabel("prior confidence (bin centre)")
    ax.set_ylabel("relative depth error")
    ax.set_title(title, fontsize=9)
    ax2 = ax.twinx()
    ax2.bar(mid, [b["share"] for b in rows], width=0.04, alpha=0.2, color="grey")
    ax2.set_ylabel("share of prior pixels")
    ax.legend(fontsize=8, loc="upper right")
    save_figure(fig, path)


def markdown(fig: dict, command: str, png: str) -> str:
    lines = [
        "## Dense weight-free depth prior on the demo drive (issue 16 item 2)",
        "",
        f"Command: `{command}`",
        "",
        f"Machine: {machine_line()}. The demo's sequence and parameters (`launch/demo.yaml`), the "
        f"frontend in-process: {fig['keyframes']} keyframes. The metrizer runs in the loop (frontend "
        f"points, graph masks); its depth of a keyframe reaches the prior {fig['lag']} keyframe(s) "
        "later. Coverage: share of ground-truth pixels with a value (mean over keyframes; min = "
        "worst keyframe); AbsRel pooled over pixels.",
        "",
        "| prior | prior AbsRel | prior coverage | prior min kf cov. | conf > 0, all pixels | "
        "metrized AbsRel | metrized coverage |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, v in fig["variants"].items():
        p, m = v["prior"], v["metrized"]
        lines.append(
            f"| {name} | {p['absrel']:.3f} | {p['coverage']:.3f} | "
            f"{p['min_keyframe_coverage']:.3f} | {v['prior_coverage_all_pixels']:.3f} | "
            f"{m['absrel']:.3f} | {m['coverage']:.3f} |"
        )
    lines += [
        "",
        "Error against confidence of the default prior (all keyframes' pixels with a prior and "
        "a ground truth, bins `(lo, hi]`; predicted = the prior's own error model):",
        "",
        "| confidence | share | AbsRel | median rel. err. | predicted | led by flow | road | "
        "warp | carry |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for b in fig["calibration"]:
        if not b["pixels"]:
            continue
        lines.append(
            f"| {b['conf_lo']:.2f}-{b['conf_hi']:.2f} | {b['share']:.3f} | {b['absrel']:.3f} | "
            f"{b['median_rel_err']:.3f} | {b['predicted_rel_err']:.3f} | {b['share_flow']:.2f} | "
            f"{b['share_road']:.2f} | {b['share_warp']:.2f} | {b['share_carry']:.2f} |"
        )
    lines += ["", f"![error against confidence]({png})"]
    return "\n".join(lines)


def kitti(folder: str, command: str) -> tuple[dict, str]:
    """The prior on the real KITTI excerpt: PnP poses from LiDAR (as ``mogs eval depth --dataset
    kitti78``), every frame with a reference, no metrizer in the loop, LiDAR as the truth."""
    from mogs_node.depth_prior.dense_prior import FusionParams
    from mogs_node.depth_prior.flow_prior import FlowPriorParams
    from mogs_node.depth_prior.road import RoadPriorParams
    from mogs_node.depth_prior.sequence import PriorSequence
    from mogs_node.eval.depth_kitti78 import load_kitti78, localise_pnp

    data = load_kitti78(folder)
    poses, _, _ = localise_pnp(data)
    f, u = FlowPriorParams(), FusionParams(warp_sources=0)
    r = RoadPriorParams(up_world=None)  # the PnP world is the first camera's: camera-fixed up
    variants = {
        "flow only": (f, replace(r, enabled=False), replace(u, carry=False)),
        "flow + road plane": (f, r, replace(u, carry=False)),
        "flow + road + previous prior carried": (f, r, u),
    }
    fig: dict = {"dataset": "kitti78", "variants": {}}
    for name, (a, b, c) in variants.items():
        seq = PriorSequence(a, b, c)
        priors, gts, ids = [], [], []
        for i in range(len(data.rgb)):
            p, refs = seq.next(i, data.rgb[i], data.K, poses[i])
            if refs:
                priors.append(p)
                gts.append(data.lidar_m[i])
                ids.append(i)
        sc = score_priors([p.depth_m for p in priors], gts, ids)
        fig["variants"][name] = {**sc, "calibration": calibration_bins(priors, gts)}
        logging.info("kitti78 %s: %.3f @ %.3f", name, sc["absrel"], sc["coverage"])
    lines = [
        "## Dense weight-free depth prior on real KITTI (issue 16 item 2)",
        "",
        f"Command: `{command}`",
        "",
        f"Machine: {machine_line()}. The 78-frame excerpt, PnP poses from LiDAR as in `mogs eval "
        f"depth --dataset kitti78`, the {len(ids)} frames with a reference; no metrizer in the "
        "loop (no warped metrized depth); `road.up_world: null` (the PnP world is the first "
        "camera's). Coverage: share of LiDAR pixels with a prior, mean over frames.",
        "",
        "| prior | AbsRel | coverage | AbsRel by confidence bin (0-0.05, 0.05-0.1, 0.1-0.2, ..., "
        "0.9-1) |",
        "| --- | ---: | ---: | --- |",
    ]
    for name, v in fig["variants"].items():
        curve = ", ".join(f"{b['absrel']:.2f}" for b in v["calibration"] if b["pixels"])
        lines.append(f"| {name} | {v['absrel']:.3f} | {v['coverage']:.3f} | {curve} |")
    return fig, "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--launch", default=None, help="demo launch file (default launch/demo.yaml)")
    ap.add_argument("--seed", type=int, default=None, help="sim seed (default: the demo's)")
    ap.add_argument("--lag", type=int, default=1, help="keyframes until metrized depth arrives")
    add_output_options(ap)
    ap.add_argument("--png", default="docs/depth_prior_calibration.png", help="curve (PNG)")
    ap.add_argument("--kitti", default=None, help="KITTI excerpt folder: measure there instead")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    command = "python bench/depth_prior.py" + "".join(
        f" {a}" for a in sys.argv[1:] if a != "--no-docs"
    )
    if args.kitti:
        fig, md = kitti(args.kitti, command)
        write_results("depth-prior-kitti", md, fig, args.json, not args.no_docs)
        return
    t0 = time.process_time()
    params = demo_params(args.launch)
    kfs, info = prepare_keyframes(params, seed=args.seed)
    tracked = info.pop("tracked_frames")  # the frames between keyframes (flow.frame_references)
    masks = graph_masks(kfs, params)
    flow, road, fusion = prior_params(params)
    no_feedback = replace(fusion, warp_sources=0, carry=False)
    variants = {
        # main's prior: one or two flow references from 0.3 m, nothing else
        BEFORE: (
            replace(flow, min_baseline_m=0.3, frame_references=0),
            replace(road, enabled=False),
            no_feedback,
        ),
        "flow + road plane": (replace(flow, frame_references=0), road, no_feedback),
        "flow + road + previous prior carried": (
            replace(flow, frame_references=0),
            road,
            replace(fusion, warp_sources=0),
        ),
        "... + warped metrized depth (keyframes only as references)": (
            replace(flow, frame_references=0),
            road,
            fusion,
        ),
        AFTER: (flow, road, fusion),
    }
    keyframes = [s.keyframe for s in kfs]
    gts = [s.gt_depth_m for s in kfs]
    ids = [k.keyframe_id for k in keyframes]
    fig: dict = {"keyframes": len(kfs), "lag": args.lag, "variants": {}}
    for name, (f, r, u) in variants.items():
        run = run_priors(
            keyframes, f, r, u, masks=masks, params=params, lag=args.lag, frames=tracked
        )
        fig["variants"][name] = {
            "prior": score_priors([p.depth_m for p in run.priors], gts, ids),
            "prior_coverage_all_pixels": float(np.mean([p.stats["coverage"] for p in run.priors])),
            "metrized": score_priors([m[0] for m in run.metrized], gts, ids),
        }
        log_v = fig["variants"][name]
        logging.info(
            "%s: prior %.3f @ %.3f, metrized %.3f @ %.3f",
            name,
            log_v["prior"]["absrel"],
            log_v["prior"]["coverage"],
            log_v["metrized"]["absrel"],
            log_v["metrized"]["coverage"],
        )
    fig["calibration"] = calibration_bins(run.priors, gts)
    after = fig["variants"][AFTER]
    before = fig["variants"][BEFORE]
    fig.update(
        prior_coverage=after["prior"]["coverage"],
        prior_absrel=after["prior"]["absrel"],
        prior_min_keyframe_coverage=after["prior"]["min_keyframe_coverage"],
        prior_coverage_before=before["prior"]["coverage"],
        prior_absrel_before=before["prior"]["absrel"],
        metrized_absrel=after["metrized"]["absrel"],
        metrized_coverage=after["metrized"]["coverage"],
        cpu_s=time.process_time() - t0,
    )
    png = Path(args.png)
    plot(fig["calibration"], png if png.is_absolute() else REPO / png, "dense prior, demo drive")
    md = markdown(fig, command, Path(args.png).name if not png.is_absolute() else str(png))
    write_results("depth-prior", md, fig, args.json, not args.no_docs)


if __name__ == "__main__":
    main()
