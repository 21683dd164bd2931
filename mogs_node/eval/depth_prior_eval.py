"""The weight-free dense prior on the demo drive: coverage, AbsRel and confidence calibration.

Runs the prior over the demo's keyframes (from :func:`mogs_node.eval.pipeline_stages.prepare_keyframes`)
as the prior node does (:class:`mogs_node.depth_prior.sequence.PriorSequence`), optionally with the
metrizer in the loop: each keyframe is metrized from the frontend's points, the demo's graph masks
and its prior, and that metrized depth reaches the prior of the keyframe ``lag`` keyframes later
(``lag = 1``: the next keyframe; the live pipeline is between 1 and 2, it does not wait for the
metrizer). Scores the prior against the sim's ground truth as the run report scores depth
(:func:`mogs_node.report.collect.score_depth`), and bins its pixels by confidence: the error
against confidence curve (:func:`calibration_bins`). Pure apart from what the caller passes in.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mogs_node import msgs
from mogs_node.depth_prior.dense_prior import SOURCES, DensePrior, FusionParams
from mogs_node.depth_prior.flow_prior import FlowPriorParams
from mogs_node.depth_prior.road import RoadPriorParams
from mogs_node.depth_prior.sequence import PriorSequence
from mogs_node.params import parse_group, parse_params

__all__ = [
    "CONFIDENCE_EDGES",
    "PriorRun",
    "calibration_bins",
    "metrizer_params",
    "prior_params",
    "run_priors",
    "score_priors",
]

log = logging.getLogger(__name__)

CONFIDENCE_EDGES = (0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)


@dataclass
class PriorRun:
    """The priors (and metrized depths, if run) of a keyframe sequence."""

    priors: list[DensePrior]
    metrized: list[NDArray[np.float32] | None]
    references: list[list[int]]


def prior_params(
    params: dict[str, dict[str, Any]],
) -> tuple[FlowPriorParams, RoadPriorParams, FusionParams]:
    """The prior node's parameters from a launch file's ``prior`` section."""
    p = params.get("prior", {})
    return (
        parse_params(FlowPriorParams, p.get("flow", {}), where="prior.flow"),
        parse_params(RoadPriorParams, p.get("road", {}), where="prior.road"),
        parse_params(FusionParams, p.get("fusion", {}), where="prior.fusion"),
    )


def metrizer_params(params: dict[str, dict[str, Any]]):
    """The metrizer node's ``(MetrizerParams, mode)`` from a launch file's ``metrizer`` section."""
    from mogs_node.metrizer.consensus import ConsensusParams
    from mogs_node.metrizer.params import MetrizerNodeParams
    from mogs_node.metrizer.pipeline import MetrizerParams
    from mogs_node.metrizer.refinement import CdrParams

    mp = parse_params(MetrizerNodeParams, params.get("metrizer", {}), where="metrizer")
    top = dict(mp.metrizer)
    top["consensus"] = parse_group(ConsensusParams, mp, "consensus", "metrizer")
    top["cdr"] = parse_group(CdrParams, mp, "cdr", "metrizer")
    return parse_params(MetrizerParams, top, where="metrizer.metrizer"), mp.mode


def run_priors(
    keyframes: Sequence[msgs.Keyframe],
    flow: FlowPriorParams,
    road: RoadPriorParams,
    fusion: FusionParams,
    *,
    masks: Sequence[msgs.Masks] | None = None,
    params: dict[str, dict[str, Any]] | None = None,
    lag: int = 1,
    frames: Sequence[tuple[int, NDArray, NDArray]] = (),
) -> PriorRun:
    """Priors of ``keyframes`` in order; with ``masks`` and ``params`` the metrizer runs in the
    loop (module docstring), else the prior has no metrized depth to warp. ``frames``: the
    tracked frames ``(stamp_ns, image, T_world_cam)`` (``prepare_keyframes``'s
    ``tracked_frames``), offered to the sequence up to each keyframe, as the node receives them."""
    from mogs_node.metrizer.matching import MatchedKeyframe, metrizer_inputs
    from mogs_node.metrizer.pipeline import metrize_depth

    if lag < 1:
        raise ValueError(f"lag: must be >= 1, got {lag}")
    metrize = masks is not None and params is not None
    mparams, mode = metrizer_params(params) if metrize else (None, None)
    seq = PriorSequence(flow, road, fusion)
    run = PriorRun([], [], [])
    fed = 0
    for i, kf in enumerate(keyframes):
        j = i - lag
        if metrize and j >= 0 and run.metrized[j] is not None:
            seq.add_metrized(keyframes[j].keyframe_id, *run.metrized[j])
        while fed < len(frames) and frames[fed][0] <= kf.stamp_ns:
            seq.add_frame(*frames[fed])
            fed += 1
        prior, refs = seq.next(kf.keyframe_id, kf.image, kf.K, kf.T_world_cam, kf.stamp_ns)
        run.priors.append(prior)
        run.references.append(refs)
        if not metrize:
            run.metrized.append(None)
            continue
        msg = msgs.DepthMap(
            stamp_ns=kf.stamp_ns,
            frame_id="world",
            keyframe_id=kf.keyframe_id,
            kind="metric",
            depth=prior.depth_m,
            confidence=prior.confidence,
            source="flow",
        )
        entry = MatchedKeyframe(kf.keyframe_id, keyframe=kf, masks=masks[i], prior=msg)
        out = metrize_depth(**metrizer_inputs(entry), params=mparams, mode=mode)
        run.metrized.append((out.depth_m.astype(np.float32), out.confidence.astype(np.float32)))
    return run


def score_priors(
    depths: Sequence[NDArray], gts: Sequence[NDArray], keyframe_ids: Sequence[int]
) -> dict[str, Any]:
    """AbsRel pooled over pixels, coverage (share of ground-truth pixels with a value) per
    keyframe and its mean and minimum, as the run report scores depth."""
    from mogs_node.report.collect import score_depth

    sc = [score_depth(k, 0, d, g) for k, d, g in zip(keyframe_ids, depths, gts, strict=True)]
    n = sum(s.count for s in sc)
    return {
        "absrel": sum(s.sum_abs_rel for s in sc) / n if n else float("nan"),
        "delta1": sum(s.n_delta1 for s in sc) / n if n else float("nan"),
        "coverage": float(np.mean([s.coverage for s in sc])) if sc else 0.0,
        "min_keyframe_coverage": float(min((s.coverage for s in sc), default=0.0)),
        "per_keyframe": [
            {"keyframe_id": s.keyframe_id, "coverage": s.coverage, "absrel": s.absrel} for s in sc
        ],
    }


def calibration_bins(
    priors: Sequence[DensePrior],
    gts: Sequence[NDArray],
    edges: Sequence[float] = CONFIDENCE_EDGES,
) -> list[dict[str, float]]:
    """Pixels with a prior and a ground truth, binned by confidence ``(lo, hi]``: per bin the
    share of those pixels, AbsRel, median relative error, the predicted relative error (median of
    ``DensePrior.rel_err``) and the share led by each source."""
    c_all, e_all, p_all, s_all = [], [], [], []
    for p, g in zip(priors, gts, strict=True):
        g = np.asarray(g, np.float64)
        m = (p.confidence > 0) & np.isfinite(g) & (g > 0)
        c_all.append(p.confidence[m])
        e_all.append(np.abs(p.depth_m[m] - g[m]) / g[m])
        p_all.append(p.rel_err[m])
        s_all.append(p.source[m])
    c, e, pe, s = (np.concatenate(a) if a else np.zeros(0) for a in (c_all, e_all, p_all, s_all))
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (c > lo) & (c <= hi)
        n = int(m.sum())
        row = {
            "conf_lo": float(lo),
            "conf_hi": float(hi),
            "pixels": n,
            "share": n / max(1, c.size),
            "absrel": float(np.mean(e[m])) if n else float("nan"),
            "median_rel_err": float(np.median(e[m])) if n else float("nan"),
            "predicted_rel_err": float(np.median(pe[m])) if n else float("nan"),
        }
        for name, code in SOURCES.items():
            row[f"share_{name}"] = float(np.mean(s[m] == code)) if n else 0.0
        out.append(row)
    return out
