"""The prior with the camera height given, measured (``road.auto_height``) or unknown (issue 18).

Runs the demo's frontend in-process on the demo drive, then the prior node's ``PriorSequence`` over
its keyframes three ways: the demo's height (1.65 m, typed), no height (road plane and ground bound
off: what a generic VI folder had), and the height measured from the flow depth
(docs/depth_prior.md, "Camera height from the flow depth"). Scores each keyframe's prior against
the sim's depth (no metrizer in the loop: the prior alone). Prints a table and JSON.

    python bench/ground_height.py [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mogs_node.depth_prior.sequence import PriorSequence  # noqa: E402
from mogs_node.eval.depth_prior_eval import prior_params  # noqa: E402
from mogs_node.eval.pipeline_stages import demo_params, prepare_keyframes  # noqa: E402

VARIANTS = {
    "given_1.65": ({"camera_height_m": 1.65}, {}),
    "unknown": ({"camera_height_m": 0.0}, {}),
    "measured": ({"camera_height_m": 0.0}, {"auto_height": True}),
}


def score(kfs: list, prior: dict, flow: dict, road: dict) -> dict:
    """Pooled AbsRel and mean coverage of the prior over the keyframes; heights used."""
    cfg = dict(
        prior, flow={**prior.get("flow", {}), **flow}, road={**prior.get("road", {}), **road}
    )
    seq = PriorSequence(*prior_params({"prior": cfg}))
    errs, covs, heights = [], [], []
    for s in kfs:
        k = s.keyframe
        p, _ = seq.next(k.keyframe_id, k.image, k.K, k.T_world_cam)
        gt = s.gt_depth_m
        m = (gt > 0) & (p.depth_m > 0)
        errs.append(np.abs(p.depth_m[m] - gt[m]) / gt[m])
        covs.append(float(m.sum() / max(1, (gt > 0).sum())))
        heights.append(round(float(p.stats.get("ground_height_m", flow["camera_height_m"])), 3))
    e = np.concatenate(errs)
    return {"absrel": float(e.mean()), "coverage": float(np.mean(covs)), "heights_m": heights}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()
    params = demo_params()
    kfs, info = prepare_keyframes(params)
    out = {"keyframes": len(kfs)}
    for name, (flow, road) in VARIANTS.items():
        out[name] = score(kfs, params["prior"], flow, road)
    print("| height | prior AbsRel | coverage | height used per keyframe [m] |")
    print("| --- | ---: | ---: | --- |")
    for name in VARIANTS:
        r = out[name]
        print(f"| {name} | {r['absrel']:.4f} | {r['coverage']:.3f} | {r['heights_m']} |")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
