"""Benchmark of the segmentation and depth-prior workers (issue 5).

1. Latency per keyframe at 1242x375 on one core (OpenCV, onnxruntime and BLAS limited to one
   thread) of each backend: graph segmentation, SLIC, the flow prior (one and two reference
   keyframes), and the ONNX backends run on the tiny test models of tests/ (SAM automatic mask
   generation with a 32x32 prompt grid; Depth Anything at 518 px). The ONNX figures measure the
   pipeline overhead only (pre/post-processing, prompt loop, filtering, NMS, painting); a real
   ViT encoder adds its own run time on top.
2. The flow prior's coverage of LiDAR pixels and its AbsRel against LiDAR as a function of the
   baseline to the reference keyframe, on the real KITTI excerpt (poses by PnP as in
   ``mogs eval depth --dataset kitti78``).

3. With ``--real-size`` instead: the learned workers at real model sizes with random weights
   (bench/workers_real_size.py; Depth Anything V2 Small/Base, SAM ViT-B, MobileSAM), split into
   network time and ours, on ``--threads`` onnxruntime threads; section ``workers-real-size``.
   ``python bench/workers.py --real-size --json -`` takes about 4 CPU-minutes (2 repeats).

Usage: ``python bench/workers.py [--real-size [--threads N]] [--json PATH] [--repeats N]
[--frames N]``. Prints the figures, writes them to ``--json`` (a flat object, units in the names;
``-`` for standard output) and, with ``--write-docs``, to docs/benchmarks.md.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from mogs_node.depth_prior.flow_prior import (  # noqa: E402
    FlowPriorParams,
    compute_flow_prior,
    two_view_depth,
)
from mogs_node.eval.bench_docs import (  # noqa: E402
    machine_line,
    markdown_table,
    update_markdown_section,
    write_json,
)
from mogs_node.geometry import se3_inverse  # noqa: E402
from mogs_node.segmentation.graph import GraphSegParams, segment_graph  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
BASELINES_M = (0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0)


def _median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return float(np.median(times))


def latency(data, poses, repeats: int) -> dict[str, float]:
    """Median latency per keyframe [ms] of each backend at the excerpt's 1242x375."""
    cv2.setNumThreads(1)
    i = 20
    rgb = data.rgb[i]
    fp = FlowPriorParams()
    refs_one = [(data.rgb[i - 4], poses[i - 4])]
    refs_two = refs_one + [(data.rgb[i - 8], poses[i - 8])]
    out = {
        "graph_seg_ms_per_keyframe": _median_ms(lambda: segment_graph(rgb), repeats),
        "slic_seg_ms_per_keyframe": _median_ms(
            lambda: segment_graph(rgb, GraphSegParams(method="slic")), repeats
        ),
        "flow_prior_1ref_ms_per_keyframe": _median_ms(
            lambda: compute_flow_prior(rgb, data.K, poses[i], refs_one, fp), repeats
        ),
        "flow_prior_2ref_ms_per_keyframe": _median_ms(
            lambda: compute_flow_prior(rgb, data.K, poses[i], refs_two, fp), repeats
        ),
    }
    out.update(_onnx_latency(rgb, max(1, repeats // 3)))
    return out


def _onnx_latency(rgb: np.ndarray, repeats: int) -> dict[str, float]:
    """Tiny-model latency of the ONNX backends (pipeline overhead only)."""
    try:
        import torch  # noqa: F401
    except ImportError:
        return {}
    sys.path.insert(0, str(REPO / "tests"))
    import _tiny_onnx

    from mogs_node.depth_prior.depth_anything_onnx import DepthAnythingOnnx, DepthAnythingParams
    from mogs_node.segmentation.sam_onnx import SamOnnx, SamParams

    with tempfile.TemporaryDirectory() as tmp:
        enc, dec = _tiny_onnx.export(Path(tmp))
        da_path = _tiny_onnx.export_depth_anything(Path(tmp) / "da.onnx", dynamic=True)
        sam = SamOnnx(SamParams(encoder_path=enc, decoder_path=dec, threads=1))
        da = DepthAnythingOnnx(DepthAnythingParams(model_path=da_path, threads=1))
        SamOnnx(
            SamParams(encoder_path=enc, decoder_path=dec, threads=1, points_per_side=2)
        ).generate(rgb)  # warm-up
        da_runs = []
        for _ in range(repeats + 1):
            t = time.perf_counter()
            out = da.infer(rgb)
            da_runs.append(((time.perf_counter() - t) * 1e3, out.model_ms))
        da_runs = da_runs[1:]
        t = time.perf_counter()
        res = sam.generate(rgb)  # one run: 1024 prompts
        sam_total = (time.perf_counter() - t) * 1e3
        sam_model = res.stats["model_ms"]
        return {
            "sam_tiny_amg32_total_ms_per_keyframe": sam_total,
            "sam_tiny_amg32_overhead_ms_per_keyframe": sam_total - sam_model,
            "depth_anything_tiny_518_total_ms_per_keyframe": float(
                np.median([a for a, _ in da_runs])
            ),
            "depth_anything_tiny_518_overhead_ms_per_keyframe": float(
                np.median([a - b for a, b in da_runs])
            ),
        }


def coverage_vs_baseline(data, poses, n_frames: int) -> dict[str, float]:
    """Flow prior (one pair) against LiDAR for reference keyframes at several baselines."""
    fp = FlowPriorParams()
    centres = poses[:, :3, 3]
    out: dict[str, float] = {}
    for b in BASELINES_M:
        cov, err_sum, n_px, used = [], 0.0, 0, 0
        err_near_sum, n_near = 0.0, 0
        cand = []
        for i in range(len(poses)):
            d = np.linalg.norm(centres[:i] - centres[i], axis=1)
            if len(d) == 0:
                continue
            j = int(np.argmin(np.abs(d - b)))
            if abs(d[j] - b) <= 0.2 * b:
                cand.append((i, j))
        pick = (
            [cand[k] for k in np.unique(np.linspace(0, len(cand) - 1, n_frames).astype(int))]
            if cand
            else []
        )
        for i, j in pick:
            pair = two_view_depth(
                data.rgb[i], data.rgb[j], data.K, se3_inverse(poses[j]) @ poses[i], fp
            )
            gt = data.lidar_m[i]
            g = gt > 0
            m = g & pair.valid
            cov.append(m.sum() / max(g.sum(), 1))
            rel = np.abs(pair.depth_m[m] - gt[m]) / gt[m]
            err_sum += float(rel.sum())
            n_px += int(m.sum())
            near = gt[m] < 20.0
            err_near_sum += float(rel[near].sum())
            n_near += int(near.sum())
            used += 1
        key = f"{b:g}m"
        out[f"flow_frames_b{key}"] = float(used)
        out[f"flow_coverage_ratio_b{key}"] = float(np.mean(cov)) if cov else float("nan")
        out[f"flow_absrel_b{key}"] = err_sum / n_px if n_px else float("nan")
        out[f"flow_absrel_0_20m_b{key}"] = err_near_sum / n_near if n_near else float("nan")
    return out


def _markdown(fig: dict[str, float], args: argparse.Namespace) -> str:
    names = {
        "graph_seg_ms_per_keyframe": "graph segmentation (default, half resolution)",
        "slic_seg_ms_per_keyframe": "SLIC superpixels",
        "flow_prior_1ref_ms_per_keyframe": "flow prior, 1 reference (DIS medium, full resolution)",
        "flow_prior_2ref_ms_per_keyframe": "flow prior, 2 references",
        "sam_tiny_amg32_total_ms_per_keyframe": "SAM ONNX AMG 32x32 prompts, tiny test models, "
        "total (the tiny decoder's mask upsampling to "
        "1024^2 included)",
        "sam_tiny_amg32_overhead_ms_per_keyframe": "SAM ONNX AMG 32x32, pipeline overhead only "
        "(pre/post-processing, filters, NMS, painting)",
        "depth_anything_tiny_518_total_ms_per_keyframe": "Depth Anything ONNX 518 px, tiny test "
        "model, total",
        "depth_anything_tiny_518_overhead_ms_per_keyframe": "Depth Anything ONNX 518 px, "
        "pipeline overhead only",
    }
    flow = []
    for b in BASELINES_M:
        cells = [fig[f"flow_{f}_b{b:g}m"] for f in ("frames", "coverage_ratio", "absrel")]
        cells.append(fig[f"flow_absrel_0_20m_b{b:g}m"])
        flow.append([f"{b:g}", f"{cells[0]:.0f}", *(f"{c:.3f}" for c in cells[1:])])
    lines = [
        "## Segmentation and depth-prior workers",
        "",
        f"Command: `python bench/workers.py --repeats {args.repeats} --frames {args.frames}`. "
        f"Machine: {machine_line()}. One core (OpenCV, BLAS and onnxruntime at one thread); "
        f"load average at the start {fig['load_average_1min']:.1f} (the machine is shared: "
        "latencies are upper bounds).",
        "",
        "Latency per keyframe at 1242x375 (KITTI excerpt frame), median:",
        "",
        *markdown_table(
            ["backend", "ms per keyframe"],
            [(label, f"{fig[k]:.1f}") for k, label in names.items() if k in fig],
        ),
        "",
        "Flow prior (one pair) against LiDAR on the real KITTI excerpt, by baseline to the "
        "reference keyframe (poses by PnP on LiDAR-sampled corners):",
        "",
        *markdown_table(
            ["baseline [m]", "frames", "coverage of LiDAR pixels", "AbsRel", "AbsRel 0-20 m"], flow
        ),
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=None, metavar="PATH")
    ap.add_argument(
        "--repeats", type=int, default=None, help="timed runs per backend (5; --real-size 2)"
    )
    ap.add_argument("--frames", type=int, default=8, help="keyframes per baseline")
    ap.add_argument("--data", default=None, help="KITTI excerpt folder")
    ap.add_argument("--real-size", action="store_true", help="real-size learned models only")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime threads (--real-size)")
    ap.add_argument("--provider", default="cpu", help="onnxruntime provider (--real-size)")
    ap.add_argument("--write-docs", action="store_true", help="update docs/benchmarks.md")
    args = ap.parse_args(argv)
    if args.real_size:
        args.repeats = 2 if args.repeats is None else args.repeats
        return _main_real_size(args, argv)
    args.repeats = 5 if args.repeats is None else args.repeats

    from mogs_node.eval.depth_kitti78 import DEFAULT_DIR, load_kitti78, localise_pnp

    data = load_kitti78(Path(args.data) if args.data else DEFAULT_DIR)
    poses, _, _ = localise_pnp(data)
    fig = {"load_average_1min": float(os.getloadavg()[0])}
    fig.update(latency(data, poses, args.repeats))
    fig.update(coverage_vs_baseline(data, poses, args.frames))
    for k, v in fig.items():
        print(f"{k}: {v:.4g}")
    _write_json(args.json, fig)
    if args.write_docs:
        update_markdown_section("workers", _markdown(fig, args))
    return 0


def _write_json(path: str | None, fig: dict[str, float]) -> None:
    if path == "-":
        print(json.dumps(fig, indent=2, sort_keys=True))
    else:
        write_json(path, fig)


def _main_real_size(args: argparse.Namespace, argv: list[str] | None) -> int:
    sys.path.insert(0, str(REPO / "bench"))
    import workers_real_size as wrs

    fig = {"load_average_1min": float(os.getloadavg()[0])}
    fig.update(
        wrs.real_size_latency(
            wrs.frame(args.data),
            repeats=args.repeats,
            threads=args.threads,
            provider=args.provider,
        )
    )
    if args.json != "-":
        for k, v in fig.items():
            print(f"{k}: {v:.4g}")
    _write_json(args.json, fig)
    if args.write_docs:
        cmd = "python bench/workers.py " + " ".join(argv if argv is not None else sys.argv[1:])
        update_markdown_section("workers-real-size", wrs.markdown(fig, cmd, machine_line()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
