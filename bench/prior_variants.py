"""The demo's depth for variants of the weight-free prior's parameters, one frontend run (issue 16).

Runs the demo's frontend in-process once (``prepare_keyframes``, graph masks: the keyframes of
``mogs eval depth --dataset demo``) and then the prior with the metrizer in the loop
(``run_priors``) once per variant, scoring the metrized depth as ``summary.json`` does (pooled
AbsRel, mean and lowest keyframe coverage) and splitting the ground-truth pixels by source as
``bench/demo_depth_account.py`` does. The default row gives ``mogs demo``'s depth figures.

``python bench/prior_variants.py [--launch FILE] [--json OUT] NAME=JSON ...`` where JSON maps
``fusion`` / ``flow`` / ``road`` to the fields to change, e.g.
``'edge_off={"fusion": {"edge_window_px": 0}}'``. Without variants: the launch file's prior.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from demo_depth_account import CATS, categories  # noqa: E402

from mogs_node.eval.depth_prior_eval import prior_params, run_priors  # noqa: E402
from mogs_node.eval.pipeline_stages import demo_params, graph_masks, prepare_keyframes  # noqa: E402


def score(kfs: list, run) -> dict:
    """Pooled AbsRel, mean / lowest keyframe coverage, per keyframe and per source figures."""
    pooled = {n: [0, 0.0] for n in CATS}
    covs, absrels, err, n_out = [], [], 0.0, 0
    for s, prior, (depth, _) in zip(kfs, run.priors, run.metrized, strict=True):
        gt = s.gt_depth_m
        has = np.isfinite(gt) & (gt > 0)
        out = np.isfinite(depth) & (depth > 0)
        rel = np.where(out & has, np.abs(depth - gt) / np.where(has, gt, 1.0), 0.0)
        for n, m in categories(prior.source, prior.sky, prior.confidence > 0, out).items():
            pooled[n][0] += int((m & has).sum())
            pooled[n][1] += float(rel[m & has].sum())
        covs.append(float((out & has).sum() / max(has.sum(), 1)))
        absrels.append(float(rel[out & has].sum() / max((out & has).sum(), 1)))
        err += float(rel[out & has].sum())
        n_out += int((out & has).sum())
    n_all = sum(k for k, _ in pooled.values())
    return {
        "absrel": err / max(n_out, 1),
        "coverage": float(np.mean(covs)),
        "min_keyframe_coverage": float(np.min(covs)),
        "per_keyframe": [{"coverage": c, "absrel": a} for c, a in zip(covs, absrels, strict=True)],
        "sources": {
            n: {
                "share": k / max(n_all, 1),
                "absrel": e / k if k else float("nan"),
                "err_share": e / err if err else 0.0,
            }
            for n, (k, e) in pooled.items()
        },
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--launch", default=None, help="demo launch file (default launch/demo.yaml)")
    ap.add_argument("--json", default=None, help="write the figures here")
    ap.add_argument("variants", nargs="*", help='NAME={"fusion": {...}, "flow": {...}}')
    args = ap.parse_args()
    variants = {"default": {}}
    for v in args.variants:
        name, _, spec = v.partition("=")
        variants[name] = json.loads(spec)
    params = demo_params(args.launch)
    kfs, info = prepare_keyframes(params)
    tracked = info.pop("tracked_frames")
    masks = graph_masks(kfs, params)
    base = dict(zip(("flow", "road", "fusion"), prior_params(params), strict=True))
    out = {}
    for name, spec in variants.items():
        groups = {g: replace(p, **spec.get(g, {})) for g, p in base.items()}
        run = run_priors(
            [s.keyframe for s in kfs],
            groups["flow"],
            groups["road"],
            groups["fusion"],
            masks=masks,
            params=params,
            frames=tracked,
        )
        out[name] = sc = score(kfs, run)
        src = ", ".join(
            f"{n} {100 * v['share']:.1f} % / {v['absrel']:.3f}" for n, v in sc["sources"].items()
        )
        print(
            f"{name}: AbsRel {sc['absrel']:.4f} coverage {sc['coverage']:.3f} "
            f"min {sc['min_keyframe_coverage']:.3f}; {src}",
            flush=True,
        )
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
