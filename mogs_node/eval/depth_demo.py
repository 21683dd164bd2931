"""``mogs eval depth --dataset demo``: the metrizer on the demo drive's own inputs, in the loop.

The keyframes of ``mogs demo`` (``launch/demo.yaml``: the frontend run in-process on the demo
sequence, :func:`mogs_node.eval.pipeline_stages.prepare_keyframes`), its graph masks and its
weight-free dense prior with the metrizer in the loop (:func:`mogs_node.eval.depth_prior_eval.
run_priors`: each keyframe's metrized depth is warped into the next keyframe's prior, as in the
running pipeline). Every keyframe is then metrized by each method of DESIGN.md section 7 on the
same inputs; scored against the sim's ground truth as the run report scores depth (AbsRel pooled
over pixels, coverage = share of ground-truth pixels with a depth, mean over keyframes).

``--viz DIR`` writes one strip per keyframe: image (with the sparse points) | prior (confident
pixels) | metrized depth (full) | ground truth | AbsRel of the metrized depth.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.eval.figures import write_titled_strip

__all__ = ["evaluate", "write_strip"]

log = logging.getLogger(__name__)

METHODS = ("no_msc_cdr", "no_msc", "full")


def _inv_colour(depth: NDArray, valid: NDArray) -> NDArray[np.uint8]:
    """Log-depth colour map from 1 m (red) to 80 m (blue), black where not valid; RGB uint8."""
    x = np.log(np.clip(np.where(valid, depth, 1.0), 1.0, 80.0)) / np.log(80.0)
    img = cv2.applyColorMap((255 * (1.0 - x)).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    return np.where(valid[..., None], img, 0).astype(np.uint8)


def write_strip(
    path: Path,
    rgb: NDArray[np.uint8],
    uv: NDArray,
    prior: NDArray,
    prior_conf: NDArray,
    depth: NDArray,
    gt: NDArray,
) -> None:
    """Stacked panels ``image | prior | metrized | ground truth | error`` (all ``[H, W]`` /
    ``[H, W, 3]`` RGB; ``uv`` ``[N, 2]`` sparse points drawn on the image), as a PNG."""
    img = np.ascontiguousarray(rgb.copy())
    for u, v in np.asarray(uv).reshape(-1, 2):
        cv2.circle(img, (int(round(u)), int(round(v))), 2, (0, 255, 0), -1)
    has_gt = gt > 0
    m = has_gt & (depth > 0)
    err = np.zeros(gt.shape, np.float32)
    err[m] = np.abs(depth[m] - gt[m]) / gt[m]
    err_img = cv2.applyColorMap((np.clip(err / 0.3, 0, 1) * 255).astype(np.uint8), 2)[..., ::-1]
    err_img = np.where(m[..., None], err_img, 40).astype(np.uint8)
    panels = [
        img,
        _inv_colour(prior, prior_conf > 0),
        _inv_colour(depth, depth > 0),
        _inv_colour(gt, has_gt),
        err_img,
    ]
    titles = [
        f"image + {len(uv)} sparse points",
        "dense prior (pixels with confidence > 0)",
        "metrized depth (full MOGS)",
        "ground truth",
        "AbsRel 0 (blue) .. 0.3 (red); grey: no depth",
    ]
    write_titled_strip(path, panels, titles)


def _pool(scores: list) -> dict[str, float]:
    n = sum(s.count for s in scores)
    cov = [s.coverage for s in scores]
    return {
        "absrel": sum(s.sum_abs_rel for s in scores) / n if n else float("nan"),
        "rmse": float(np.sqrt(sum(s.sum_sq for s in scores) / n)) if n else float("nan"),
        "delta1": sum(s.n_delta1 for s in scores) / n if n else float("nan"),
        "coverage": float(np.mean(cov)) if cov else 0.0,
        "min_keyframe_coverage": float(min(cov, default=0.0)),
    }


def evaluate(args: argparse.Namespace) -> dict[str, Any]:
    """Run the protocol of the module docstring; returns the DESIGN.md section 7 dict plus
    ``coverage`` and ``min_keyframe_coverage`` per method."""
    from mogs_node import msgs
    from mogs_node.eval.depth_prior_eval import metrizer_params, prior_params, run_priors
    from mogs_node.eval.pipeline_stages import demo_params, graph_masks, prepare_keyframes
    from mogs_node.metrizer.matching import MatchedKeyframe, metrizer_inputs
    from mogs_node.metrizer.pipeline import metrize
    from mogs_node.report.collect import score_depth

    t0 = time.perf_counter()
    params = demo_params(getattr(args, "launch", None))
    kfs, info = prepare_keyframes(params, seed=getattr(args, "seed", None) or None)
    tracked = info.pop("tracked_frames")  # images: not for the JSON
    n_want = getattr(args, "frames", None)
    masks = graph_masks(kfs, params)
    keyframes = [s.keyframe for s in kfs]
    run = run_priors(
        keyframes,
        *prior_params(params),
        masks=masks,
        params=params,
        frames=tracked,
    )
    mparams, _ = metrizer_params(params)
    viz = Path(args.viz) if getattr(args, "viz", None) else None
    scores: dict[str, list] = {m: [] for m in METHODS}
    for i, s in enumerate(kfs[:n_want] if n_want else kfs):
        prior = run.priors[i]
        msg = msgs.DepthMap(
            stamp_ns=s.keyframe.stamp_ns,
            frame_id="world",
            keyframe_id=s.keyframe.keyframe_id,
            kind="metric",
            depth=prior.depth_m,
            confidence=prior.confidence,
            source="flow",
        )
        entry = MatchedKeyframe(
            s.keyframe.keyframe_id, keyframe=s.keyframe, masks=masks[i], prior=msg
        )
        inputs = metrizer_inputs(entry)
        for m in METHODS:
            out = metrize(inputs, mparams, m)
            scores[m].append(
                score_depth(s.keyframe.keyframe_id, s.keyframe.stamp_ns, out.depth_m, s.gt_depth_m)
            )
            if m == "full" and viz is not None:
                write_strip(
                    viz / f"demo_kf{s.keyframe.keyframe_id:03d}.png",
                    s.keyframe.rgb(),
                    s.keyframe.feature_uv_px,
                    prior.depth_m,
                    prior.confidence,
                    out.depth_m,
                    s.gt_depth_m,
                )
    info.pop("K_sim", None)
    return {
        "dataset": "demo",
        "frames": len(scores["full"]),
        "methods": {m: _pool(v) for m, v in scores.items()},
        "per_keyframe_full": [
            {"keyframe_id": x.keyframe_id, "absrel": x.absrel, "coverage": x.coverage}
            for x in scores["full"]
        ],
        "info": info,
        "wall_s": time.perf_counter() - t0,
    }
