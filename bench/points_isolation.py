"""Why more frontend points can make the metrized depth worse (issue 16, item 2 of h16f's brief):
the demo's keyframes metrized with one kind of sparse points swapped at a time.

    python bench/points_isolation.py [--launch launch/demo.yaml] [--round9]
        [--set GROUP.FIELD=VALUE ...] [--priors lfm,flow] [--sparse frontend,...] [--json OUT]

Runs the demo's frontend in-process (:func:`mogs_node.eval.pipeline_stages.prepare_keyframes`;
``--set`` overrides a field of a frontend group, e.g. ``points.max_tracks=3000``), then metrizes every keyframe with the simulated LFM and
the flow prior (graph masks) and each of these sparse inputs:

- ``frontend``: the points as published;
- ``gt_same``: ground-truth depth at exactly the frontend's pixels (same count, places, weights;
  none dropped, so that only the depth errors differ);
- ``gt_same_w1``: the same with every weight 1 (the weights' part);
- ``frontend_w1``: the frontend's points with every weight 1;
- ``frontend_no_outliers``: the frontend's points without those more than 10 % off the truth at
  their pixel (oracle filter: what the few gross errors cost);
- ``frontend_err_lt3``: only those within 3 % (the rest of the error distribution);
- ``frontend_rescaled``: the frontend's points times the keyframe's median ratio truth / point
  (oracle: a scale error common to the keyframe's points taken out);
- ``gt_corners``: ground truth at up to 500 Shi-Tomasi corners off depth edges (more places).

Prints one line per combination (pooled AbsRel, coverage) and the points' error figures.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mogs_node.eval.pipeline_stages import (  # noqa: E402
    _with_points,
    demo_params,
    evaluate_stages,
    prepare_keyframes,
    stage_inputs,
)


def _truth_at(kf, depth_m: np.ndarray) -> np.ndarray:
    H, W = depth_m.shape
    uv = np.asarray(kf.feature_uv_px, np.float64).reshape(-1, 2)
    ui = np.clip(np.round(uv[:, 0]).astype(int), 0, W - 1)
    vi = np.clip(np.round(uv[:, 1]).astype(int), 0, H - 1)
    return depth_m[vi, ui]


def sparse_variants(kfs, base: dict[str, list]) -> dict[str, list]:
    """The sparse inputs listed in the module docstring, one message per keyframe."""
    out: dict[str, list] = {"frontend": base["frontend"], "gt_corners": base["gt_corners"]}
    for name in (
        "gt_same",
        "gt_same_w1",
        "frontend_w1",
        "frontend_no_outliers",
        "frontend_err_lt3",
    ):
        out[name] = []
    for s, kf in zip(kfs, base["frontend"], strict=True):
        gt = _truth_at(kf, s.gt_depth_m)
        z = np.asarray(kf.feature_xyz_cam_m, np.float64).reshape(-1, 3)[:, 2]
        rel = np.where(gt > 0, np.abs(z - gt) / np.where(gt > 0, gt, 1.0), np.inf)
        uv = np.asarray(kf.feature_uv_px, np.float64).reshape(-1, 2)
        w = np.asarray(kf.feature_weight, np.float32)
        has = gt > 0  # sky pixels have no truth: the GT variants cannot place a point there
        out["gt_same"].append(_with_points(kf, uv[has], s.gt_depth_m, w[has]))
        out["gt_same_w1"].append(_with_points(kf, uv[has], s.gt_depth_m, np.ones(has.sum())))
        out["frontend_w1"].append(replace(kf, feature_weight=np.ones_like(w)))
        # oracle: the keyframe's points scaled by the median ratio truth / point (a scale error
        # common to every point of the keyframe, e.g. the poses', taken out)
        scale = float(np.median(gt[gt > 0] / z[gt > 0])) if (gt > 0).any() else 1.0
        xyz = np.asarray(kf.feature_xyz_cam_m, np.float32).reshape(-1, 3) * np.float32(scale)
        out.setdefault("frontend_rescaled", []).append(replace(kf, feature_xyz_cam_m=xyz))
        for name, keep in (
            ("frontend_no_outliers", rel <= 0.10),
            ("frontend_err_lt3", rel <= 0.03),
        ):
            out[name].append(
                replace(
                    kf,
                    feature_ids=np.asarray(kf.feature_ids)[keep],
                    feature_uv_px=np.asarray(kf.feature_uv_px)[keep],
                    feature_xyz_cam_m=np.asarray(kf.feature_xyz_cam_m).reshape(-1, 3)[keep],
                    feature_weight=w[keep],
                )
            )
    return out


def point_errors(kfs, frontend: list) -> dict[str, float]:
    """Relative depth error of the published points against the truth at their pixels."""
    rel, n, bias, signed_all, gt_all = [], [], [], [], []
    for s, kf in zip(kfs, frontend, strict=True):
        gt = _truth_at(kf, s.gt_depth_m)
        z = np.asarray(kf.feature_xyz_cam_m, np.float64).reshape(-1, 3)[:, 2]
        ok = gt > 0
        signed = (z[ok] - gt[ok]) / gt[ok]
        rel.append(np.abs(signed))
        signed_all.append(signed)
        gt_all.append(gt[ok])
        bias.append(float(np.median(signed)) if ok.any() else float("nan"))
        n.append(len(z))
    r = np.concatenate(rel) if rel else np.zeros(0)
    sg, g = (np.concatenate(signed_all), np.concatenate(gt_all)) if rel else (r, r)
    bins = ((0, 10), (10, 20), (20, 40), (40, 1e9))  # true depth [m]
    by_depth = {
        f"{lo:.0f}-{hi:.0f}m": [int(np.sum(m)), round(float(np.median(sg[m])), 4)]
        for lo, hi in bins
        if np.any(m := (g >= lo) & (g < hi))
    }
    return {
        "count_and_signed_err_median_by_depth": by_depth,
        "signed_err_median_per_keyframe": [round(b, 4) for b in bias],
        "points_per_keyframe_median": float(np.median(n)) if n else 0.0,
        "points_total": int(sum(n)),
        "rel_err_median": float(np.median(r)) if len(r) else float("nan"),
        "rel_err_p90": float(np.percentile(r, 90)) if len(r) else float("nan"),
        "share_over_10pct": float(np.mean(r > 0.10)) if len(r) else float("nan"),
        "share_over_3pct": float(np.mean(r > 0.03)) if len(r) else float("nan"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--launch", default=None, help="demo launch file (default launch/demo.yaml)")
    ap.add_argument(
        "--round9", action="store_true", help="round 9's points (bench/frontend.py: ROUND9)"
    )
    ap.add_argument("--set", action="append", default=[], metavar="GROUP.FIELD=VALUE")
    ap.add_argument("--json", default=None, metavar="PATH")
    ap.add_argument("--priors", default="lfm,flow", help="comma-separated: lfm, flow")
    ap.add_argument("--sparse", default=None, help="comma-separated subset of the variants")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    params = demo_params(args.launch)
    fe = params.setdefault("frontend", {})
    if args.round9:
        from bench.frontend import ROUND9

        fe["points"] = {**fe.get("points", {}), **ROUND9}
    for item in args.set:
        key, value = item.split("=", 1)
        group, field = key.split(".", 1)
        fe.setdefault(group, {})[field] = yaml.safe_load(value)
    kfs, _ = prepare_keyframes(params)
    inputs = stage_inputs(kfs, params)
    inputs["sparse"] = sparse_variants(kfs, inputs["sparse"])
    fig = evaluate_stages(
        kfs,
        inputs,
        params,
        sparse=tuple(args.sparse.split(",")) if args.sparse else tuple(inputs["sparse"]),
        priors=tuple(args.priors.split(",")),
        masks=("graph",),
    )
    res = {
        "points": point_errors(kfs, inputs["sparse"]["frontend"]),
        "set": args.set,
        "keyframe_frames": [s.frame_index for s in kfs],
    }
    for key, c in fig["combos"].items():
        res[key] = {k: c[k] for k in ("absrel", "coverage", "keyframes")}
        res[key]["per_keyframe_absrel"] = [round(a, 4) for a, _ in c["per_keyframe"]]
        print(f"{key:40s} AbsRel {c['absrel']:.4f} coverage {c['coverage']:.3f}", flush=True)
    print(json.dumps(res["points"]), "keyframe frames", res["keyframe_frames"])
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
