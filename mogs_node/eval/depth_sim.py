"""``mogs eval depth --dataset sim``: Table-IV-style ablation of the metrizer on the sim world.

Per keyframe: the ground-truth render gives the image, the depth and the instance ids; the prior is
the simulated LFM (relative inverse depth, full confidence); the sparse points are the ground-truth
depth at Shi-Tomasi corners (as a VI frontend would track them) with 1% multiplicative noise; the
masks are the oracle instance ids and/or the graph over-segmentation. Every method gets the same
inputs. Metrics (AbsRel, RMSE, delta1) over pixels with ground truth in ``(0, d_max]``, averaged
over all such pixels of all keyframes.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mogs_node.errors import ConfigError
from mogs_node.eval.bench_docs import machine_line, markdown_table, update_markdown_section

__all__ = ["SimDepthCase", "evaluate", "make_cases", "run_methods"]

log = logging.getLogger(__name__)
METHODS = ("full", "no_msc", "no_msc_cdr")
# "full" / "no_msc" without the two output departures of docs/metrizer.md (model output, residual
# field): the calibrated prior of eq. (6) alone, as the paper composes it
EQ6_ONLY = {"full_eq6": "full", "no_msc_eq6": "no_msc"}
BASELINES = ("interp_nearest", "interp_edge_aware")


class SimDepthCase:
    """Inputs and ground truth of one simulated keyframe."""

    def __init__(self, K, rgb, gt_m, oracle, graph, uv, z, prior):
        self.K, self.rgb, self.gt_m = K, rgb, gt_m
        self.masks = {"oracle": oracle, "graph": graph}
        self.uv, self.z, self.prior = uv, z, prior

    def metrizer_inputs(self, labels: np.ndarray):
        """The metrizer's inputs for this keyframe with ``labels`` (the simulated LFM prior at full
        confidence, every sparse point at weight 1)."""
        from mogs_node.metrizer.pipeline import MetrizerInputs

        return MetrizerInputs(
            K=self.K,
            labels=labels,
            feature_uv_px=self.uv,
            feature_depth_m=self.z,
            feature_weight=np.ones(len(self.z)),
            prior=self.prior,
            prior_confidence=np.ones_like(self.prior),
            prior_kind="relative_inverse_depth",
            image_rgb=self.rgb,
        )


def make_cases(
    n_frames: int = 20,
    seed: int = 0,
    size: tuple[int, int] = (621, 188),
    max_corners: int = 500,
    noise: float = 0.01,
    masks: tuple[str, ...] = ("oracle", "graph"),
    reject_occlusion_corners: bool = True,
) -> list[SimDepthCase]:
    """Render ``n_frames`` keyframes (every 2nd sim frame) and build the metrizer inputs.

    Sparse points: Shi-Tomasi corners with ground-truth depth times ``1 + noise * N(0, 1)``. With
    ``reject_occlusion_corners`` a corner whose 5x5 neighbourhood spans more than +-5% of depth is
    dropped: such T-junction corners on occlusion boundaries slide as the camera moves, so a VI
    frontend's KLT forward-backward and epipolar checks reject them and they never become metric
    points.
    """
    from mogs_node.sim import LfmParams, SimConfig, make_sequence, simulated_lfm

    W, H = size
    seq = make_sequence(SimConfig(seed=seed, n_frames=2 * n_frames, width=W, height=H))
    rng = np.random.default_rng(seed + 7)
    cases = []
    for i in range(n_frames):
        f = seq.render(2 * i)
        gray = cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY)
        pts = cv2.goodFeaturesToTrack(gray, 4 * max_corners, 0.005, 5)
        uv = np.zeros((0, 2)) if pts is None else pts[:, 0, :].astype(np.float64)
        ui = np.clip(np.round(uv[:, 0]).astype(int), 0, W - 1)
        vi = np.clip(np.round(uv[:, 1]).astype(int), 0, H - 1)
        z = f.depth_m[vi, ui].astype(np.float64)
        ok = np.isfinite(z) & (z > 0)
        if reject_occlusion_corners:  # a KLT track on a depth edge slides and is rejected
            ok &= _depth_edge_free(f.depth_m)[vi, ui]
        uv, z = uv[ok][:max_corners], z[ok][:max_corners]  # strongest corners first
        z = z * (1.0 + noise * rng.standard_normal(len(z)))
        prior = simulated_lfm(f.depth_m, rng, LfmParams())
        graph = None
        if "graph" in masks:
            from mogs_node.segmentation.graph import GraphSegParams, segment_graph

            # the defaults are tuned for 1242x375 at scale 0.5: keep that processing resolution
            graph = segment_graph(f.rgb, GraphSegParams(scale=min(1.0, 0.5 * 1242 / W)))
        cases.append(
            SimDepthCase(seq.camera.K, f.rgb, f.depth_m, f.instance_id, graph, uv, z, prior)
        )
    return cases


def _depth_edge_free(depth_m: np.ndarray, jump: float = 0.15, radius: int = 2) -> np.ndarray:
    """True where no 4-neighbour depth jump above ``jump`` (relative) lies within ``radius`` px."""
    d = np.where(np.isfinite(depth_m), depth_m, 1e6).astype(np.float32)
    j = np.zeros(d.shape, np.float32)
    jx = np.abs(np.diff(d, axis=1)) / np.minimum(d[:, 1:], d[:, :-1])
    jy = np.abs(np.diff(d, axis=0)) / np.minimum(d[1:], d[:-1])
    j[:, 1:] = np.maximum(j[:, 1:], jx)
    j[:, :-1] = np.maximum(j[:, :-1], jx)
    j[1:] = np.maximum(j[1:], jy)
    j[:-1] = np.maximum(j[:-1], jy)
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    return cv2.dilate((j > jump).astype(np.uint8), k) == 0


def run_methods(
    case: SimDepthCase, mask_source: str, methods=METHODS + tuple(EQ6_ONLY) + BASELINES, params=None
):
    """Depth per method ``{name: MetrizedDepth}`` for one case and mask source."""
    from mogs_node.metrizer.baselines import BASELINES as REGISTRY
    from mogs_node.metrizer.pipeline import MetrizerParams, metrize

    params = params or MetrizerParams()
    inputs = case.metrizer_inputs(case.masks[mask_source])
    out = {}
    for m in methods:
        if m in EQ6_ONLY:
            pp = replace(params, model_output=False, residual_field=False)
            out[m] = metrize(inputs, pp, EQ6_ONLY[m])
        elif m in METHODS:
            out[m] = metrize(inputs, params, m)
        else:
            out[m] = REGISTRY[m](**inputs, params=params)
    return out


def _pool(acc: dict[str, list], name: str, pred, gt, valid) -> None:
    m = valid & np.isfinite(gt) & (pred > 0)
    p, g = pred[m].astype(np.float64), gt[m].astype(np.float64)
    acc.setdefault(name, []).append(
        (np.abs(p - g) / g, (p - g) ** 2, np.maximum(p / g, g / p) < 1.25)
    )


def _summary(acc: dict[str, list]) -> dict[str, dict[str, float]]:
    out = {}
    for name, parts in acc.items():
        ar = np.concatenate([a for a, _, _ in parts])
        se = np.concatenate([s for _, s, _ in parts])
        d1 = np.concatenate([d for _, _, d in parts])
        out[name] = {
            "absrel": float(ar.mean()),
            "rmse": float(np.sqrt(se.mean())),
            "delta1": float(d1.mean()),
            "count": int(len(ar)),
        }
    return out


def evaluate(args: argparse.Namespace) -> dict[str, Any]:
    """Run the ablation and return ``{"dataset", "frames", "methods", "by_masks", ...}``."""
    n = args.frames or 20
    size = (621, 188)
    if args.size:
        try:
            size = tuple(int(v) for v in args.size.lower().split("x"))  # type: ignore[assignment]
        except ValueError as err:
            raise ConfigError(f"--size: expected WxH, got {args.size!r}") from err
    sources = ("oracle", "graph") if args.masks == "both" else (args.masks,)
    cases = make_cases(n, args.seed, size, masks=sources)
    from mogs_node.metrizer.pipeline import MetrizerParams

    d_max = MetrizerParams().d_max_m
    acc_all: dict[str, list] = {}
    acc_src: dict[str, dict[str, list]] = {s: {} for s in sources}
    timing: dict[str, list[float]] = {}
    for case in cases:
        valid = np.isfinite(case.gt_m) & (case.gt_m > 0) & (case.gt_m <= d_max)
        for src in sources:
            res = run_methods(case, src)
            for name, r in res.items():
                _pool(acc_src[src], name, r.depth_m, case.gt_m, valid)
                if name in METHODS:
                    _pool(acc_all, name, r.depth_m, case.gt_m, valid)
                    timing.setdefault(f"{src}/{name}", []).append(r.stats["ms"]["total"])
    by_src = {s: _summary(a) for s, a in acc_src.items()}
    figures: dict[str, Any] = {
        "dataset": "sim",
        "frames": len(cases),
        "methods": {
            k: {m: v[m] for m in ("absrel", "rmse", "delta1")} for k, v in _summary(acc_all).items()
        },
        "by_masks": by_src,
        "ms_per_keyframe": {k: float(np.mean(v)) for k, v in timing.items()},
        "size": f"{size[0]}x{size[1]}",
    }
    if getattr(args, "viz", None):
        _write_viz(Path(args.viz), cases[0], sources[0], d_max)
    standard = len(cases) >= 20 and args.size is None and args.masks == "both"
    if standard and getattr(args, "write_docs", False):
        _write_markdown(figures, args)  # only the standard run updates docs/benchmarks.md
    return figures


_SCORES = ("AbsRel", "RMSE [m]", "delta1")


def _score_cells(v: dict[str, float]) -> list[str]:
    return [f"{v['absrel']:.4f}", f"{v['rmse']:.3f}", f"{v['delta1']:.4f}"]


def _ms_cell(t: float | None) -> str:
    return f"{t:.1f}" if t is not None else "-"


def _write_markdown(fig: dict[str, Any], args: argparse.Namespace) -> None:
    lines = [
        "## Depth metrizer ablation on the synthetic world (Table IV style)",
        "",
        f"`mogs eval depth --dataset sim --frames {fig['frames']} --seed {args.seed}` "
        f"({fig['size']}, simulated LFM prior with full confidence, sparse points = ground "
        "truth at Shi-Tomasi corners away from depth edges, with 1% noise). Pixels with ground "
        "truth in (0, 80] m, pooled over all keyframes. ms/keyframe: wall time on a shared "
        "machine (see the metrizer-speed section for CPU time at 1242x375). "
        "`full_eq6` / `no_msc_eq6`: the same without the model output and the residual field "
        "(docs/metrizer.md, departures 7-8), i.e. the calibrated prior of eq. (6) alone.",
        "",
        *markdown_table(
            ["masks", "method", *_SCORES, "ms/keyframe"],
            [
                [src, name, *_score_cells(v), _ms_cell(fig["ms_per_keyframe"].get(f"{src}/{name}"))]
                for src, table in fig["by_masks"].items()
                for name, v in table.items()
            ],
        ),
        "",
        "Both mask sources pooled:",
        "",
        *markdown_table(
            ["method", *_SCORES],
            [[name, *_score_cells(v)] for name, v in fig["methods"].items()],
        ),
    ]
    m = fig["methods"]
    if all(k in m for k in METHODS):
        lines += [
            "",
            "full / global affine (no_msc_cdr) AbsRel ratio: "
            f"pooled {m['full']['absrel'] / m['no_msc_cdr']['absrel']:.3f}",
        ]
        for src, t in fig["by_masks"].items():
            lines[-1] += f", {src} {t['full']['absrel'] / t['no_msc_cdr']['absrel']:.3f}"
    lines += ["", f"Machine: {machine_line()}"]
    update_markdown_section("metrizer-sim-ablation", "\n".join(lines))


def _write_viz(out_dir: Path, case: SimDepthCase, src: str, d_max: float) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    res = run_methods(case, src, methods=METHODS)

    def colour(d):
        v = np.where(d > 0, 1.0 / np.maximum(d, 1e-3), 0.0)
        v = np.clip(v / max(np.percentile(v[v > 0], 99) if np.any(v > 0) else 1.0, 1e-6), 0, 1)
        return cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_MAGMA)

    gt = np.where(np.isfinite(case.gt_m), case.gt_m, 0)
    rows = [cv2.cvtColor(case.rgb, cv2.COLOR_RGB2BGR), colour(gt)]
    for r in res.values():
        rows.append(colour(r.depth_m))
        err = np.where(gt > 0, np.abs(r.depth_m - gt) / np.maximum(gt, 1e-6), 0)
        rows.append(
            cv2.applyColorMap((np.clip(err / 0.2, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_JET)
        )
    cv2.imwrite(str(out_dir / f"metrizer_{src}.png"), np.vstack(rows))
