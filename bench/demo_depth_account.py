"""Per-keyframe, per-source account of the demo's metrized depth (issue 16).

Runs the demo loop of ``mogs eval depth --dataset demo`` (frontend in-process, graph masks,
weight-free prior with the metrizer in the loop; the same depth as ``mogs demo``) and splits
every ground-truth pixel (sky has none) of every keyframe by what happened to it:

- ``flow`` / ``road`` / ``warp`` / ``carry``: the metrized output has depth and the prior's
  leading source there was that one (``DensePrior.source``);
- ``fill``: output depth without a prior (the metrizer's own fills near features and shapes);
- ``dropped``: the prior had depth, the metrizer left the pixel empty;
- ``sky``: no depth, the prior's sky mask (the flow prior's) covered a pixel the truth has;
- ``none``: no depth, no source reached the pixel.

For each the share of the ground-truth pixels, the output's AbsRel there and its share of the
error mass; then the simulator's objects (instance ids) that hold the most error or the most
holes. ``python bench/demo_depth_account.py [--launch launch/demo.yaml] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mogs_node.depth_prior.dense_prior import SOURCES  # noqa: E402
from mogs_node.eval.depth_prior_eval import prior_params, run_priors  # noqa: E402
from mogs_node.eval.pipeline_stages import demo_params, graph_masks, prepare_keyframes  # noqa: E402

CATS = ("flow", "road", "warp", "carry", "contour", "fill", "dropped", "sky", "none")


def categories(src: np.ndarray, sky: np.ndarray, has_prior: np.ndarray, out: np.ndarray) -> dict:
    """Boolean masks of :data:`CATS` (disjoint, together every pixel)."""
    c = {n: out & (src == code) for n, code in SOURCES.items()}
    c["fill"] = out & ~has_prior
    c["dropped"] = ~out & has_prior
    c["sky"] = ~out & ~has_prior & sky
    c["none"] = ~out & ~has_prior & ~sky
    return c


def account(launch: str | None) -> dict:
    """The account of the module docstring as a dict (per keyframe and pooled)."""
    params = demo_params(launch)
    kfs, info = prepare_keyframes(params)
    tracked = info.pop("tracked_frames")
    masks = graph_masks(kfs, params)
    run = run_priors(
        [s.keyframe for s in kfs], *prior_params(params), masks=masks, params=params, frames=tracked
    )
    rows, objs = [], {}
    pooled = {n: [0, 0.0] for n in CATS}
    n_gt_all = 0
    for i, s in enumerate(kfs):
        gt = s.gt_depth_m
        has_gt = np.isfinite(gt) & (gt > 0)
        prior, (depth, _) = run.priors[i], run.metrized[i]
        out = np.isfinite(depth) & (depth > 0)
        rel = np.where(out & has_gt, np.abs(depth - gt) / np.where(has_gt, gt, 1.0), 0.0)
        cats = categories(prior.source, prior.sky, prior.confidence > 0, out)
        row = {"keyframe_id": s.keyframe.keyframe_id, "points": len(s.keyframe.feature_uv_px)}
        n_gt = int(has_gt.sum())
        n_gt_all += n_gt
        for n in CATS:
            m = cats[n] & has_gt
            k, e = int(m.sum()), float(rel[m].sum())
            pooled[n][0] += k
            pooled[n][1] += e
            row[n] = {"share": k / max(n_gt, 1), "absrel": e / k if k else float("nan")}
        m_out = out & has_gt
        row["coverage"] = float(m_out.sum() / max(n_gt, 1))
        row["absrel"] = float(rel[m_out].sum() / max(m_out.sum(), 1))
        rows.append(row)
        inst = s.instance_id
        for oid in np.unique(inst[has_gt]):
            m = has_gt & (inst == oid)
            o = objs.setdefault(int(oid), {"pixels": 0, "covered": 0, "err": 0.0, "depth": []})
            o["pixels"] += int(m.sum())
            o["covered"] += int((m & out).sum())
            o["err"] += float(rel[m & out].sum())
            o["depth"].append(float(np.median(gt[m])))
    total_err = sum(e for _, e in pooled.values())
    pool = {
        n: {
            "share": k / max(n_gt_all, 1),
            "absrel": e / k if k else float("nan"),
            "err_share": e / total_err if total_err else 0.0,
        }
        for n, (k, e) in pooled.items()
    }
    for o in objs.values():
        o["median_depth_m"] = float(np.median(o.pop("depth")))
        o["err_share"] = o["err"] / total_err if total_err else 0.0
        o["absrel"] = o["err"] / o["covered"] if o["covered"] else float("nan")
        o["hole_share"] = (o["pixels"] - o["covered"]) / n_gt_all
    covs = [r["coverage"] for r in rows]
    n_out = sum(pooled[n][0] for n in CATS if n not in ("dropped", "sky", "none"))
    overall = {
        "absrel": total_err / max(n_out, 1),
        "coverage": float(np.mean(covs)) if covs else 0.0,
        "min_keyframe_coverage": float(min(covs)) if covs else 0.0,
    }
    return {"per_keyframe": rows, "pooled": pool, "objects": objs, "overall": overall}


def markdown(acc: dict) -> str:
    """Tables of the account (share % / AbsRel per category; objects by error and holes)."""
    head = "| kf | pts | cov | AbsRel | " + " | ".join(CATS) + " |"
    lines = [head, "| " + " | ".join(["---:"] * (4 + len(CATS))) + " |"]
    for r in acc["per_keyframe"]:
        cells = []
        for n in CATS:
            c = r[n]
            a = (
                ""
                if n in ("dropped", "sky", "none") or c["share"] == 0
                else f" / {c['absrel']:.2f}"
            )
            cells.append(f"{100 * c['share']:.0f}{a}")
        lines.append(
            f"| {r['keyframe_id']} | {r['points']} | {r['coverage']:.2f} | {r['absrel']:.3f} | "
            + " | ".join(cells)
            + " |"
        )
    p = acc["pooled"]
    lines.append(
        "| all | | | | "
        + " | ".join(
            f"{100 * p[n]['share']:.1f}"
            + ("" if n in ("dropped", "sky", "none") else f" / {p[n]['absrel']:.3f}")
            + (f" ({100 * p[n]['err_share']:.0f} % err)" if p[n]["err_share"] > 0 else "")
            for n in CATS
        )
        + " |"
    )
    o = acc["overall"]
    lines.append(
        f"\nAbsRel {o['absrel']:.4f}, coverage {o['coverage']:.3f}, "
        f"lowest keyframe {o['min_keyframe_coverage']:.3f}"
    )
    by_err = sorted(acc["objects"].items(), key=lambda kv: -kv[1]["err_share"])[:8]
    by_hole = sorted(acc["objects"].items(), key=lambda kv: -kv[1]["hole_share"])[:8]
    head = "| object | median depth m | err share | AbsRel | hole share |"
    for title, objs in (("most error", by_err), ("most holes", by_hole)):
        lines += ["", f"Objects with the {title}:", "", head, "| ---: " * 5 + "|"]
        lines += [
            f"| {oid} | {o['median_depth_m']:.1f} | {100 * o['err_share']:.1f} % | "
            f"{o['absrel']:.3f} | {100 * o['hole_share']:.1f} % |"
            for oid, o in objs
        ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--launch", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    acc = account(args.launch)
    print(markdown(acc))
    if args.json:
        Path(args.json).write_text(json.dumps(acc, indent=1))


if __name__ == "__main__":
    main()
