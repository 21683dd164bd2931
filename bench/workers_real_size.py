"""Per-keyframe cost of the learned workers at real model sizes (issue 20; ``workers.py --real-size``).

Depth Anything V2 Small and Base, SAM ViT-B and MobileSAM, each of its real size with random
weights (mogs_node/eval/real_size_models.py: the exports are cached, made when missing, which
needs the ``models`` extra), run on one 1242x375 KITTI excerpt frame through our backends with
onnxruntime on ``--threads`` intra-op threads. For each: the wall time per keyframe, the part of it
inside the networks (``..._model_ms``) and ours (``..._ours_ms``: pre/post-processing, prompt
selection, filters, NMS, painting), and the process CPU seconds per keyframe from the OS
(``..._cpu_s``, comparable on a loaded machine where wall times are not). Random weights cost what
the real ones cost; the masks and depths they give are meaningless and are not figures here,
except the prompt and decoder-call counts, which depend on what the random masks cover.
"""

from __future__ import annotations

import logging
import resource
import time
from pathlib import Path

import numpy as np

from mogs_node.depth_prior.depth_anything_onnx import DepthAnythingOnnx, DepthAnythingParams
from mogs_node.segmentation.sam_onnx import SamOnnx, SamParams

log = logging.getLogger(__name__)

SAM_MODELS = {"sam_vit_b": "sam_vit_b", "sam_small": "mobile_sam"}
DA_MODELS = {
    "depth_anything_vits": "depth_anything_vits",
    "depth_anything_vitb": "depth_anything_vitb",
}


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _paths(name: str) -> dict[str, str]:
    from mogs_node.eval.real_size_models import cache_dir, ensure

    root = cache_dir()
    files = (
        [root / f"{name}_hf.onnx"]
        if name.startswith("depth_anything")
        else [root / f"{name}_encoder.onnx", root / f"{name}_decoder.onnx"]
    )
    if all(f.is_file() for f in files):
        if len(files) == 1:
            return {"model_path": str(files[0])}
        return {"encoder_path": str(files[0]), "decoder_path": str(files[1])}
    try:
        return ensure(name)  # needs torch + the `models` extra
    except ImportError as err:
        log.warning("%s: not exported and the `models` extra is missing (%s): skipped", name, err)
        return {}


def _timed(fn, repeats: int) -> tuple[list[float], list[float], list]:
    """Wall ms, CPU s and results of ``repeats`` runs after one warm-up."""
    fn()
    walls, cpus, outs = [], [], []
    for _ in range(repeats):
        c, t = _cpu_s(), time.perf_counter()
        outs.append(fn())
        walls.append((time.perf_counter() - t) * 1e3)
        cpus.append(_cpu_s() - c)
    return walls, cpus, outs


# (key suffix, input_size, resize_method, models): ours first (the longer side at 518, aspect
# kept: 154x518 for 1242x375), then the reference pre-processing (the shorter side at 518:
# 518x1722, 4551 tokens) for Small only: Base there holds 12 GB (its attention matrices), more
# than a shared 23 GB machine should give one benchmark
DA_CONFIGS = (
    ("", 518, "upper_bound", tuple(DA_MODELS)),
    ("_lb518", 518, "lower_bound", ("depth_anything_vits",)),
)
# the prompts of launch/learned.yaml: a square-cell grid, 16 along the longer side (16x5 on
# 1242x375), run coarse to fine, covered prompts skipped, at most 16 per keyframe
SAM_PROMPTS = dict(points_per_side=16, square_cells=True, max_prompts=16)


def real_size_latency(
    rgb: np.ndarray,
    *,
    repeats: int = 2,
    threads: int = 2,
    provider: str = "cpu",
    da_configs: tuple[tuple[str, int, str, tuple[str, ...]], ...] = DA_CONFIGS,
    sam_prompts: dict | None = None,
) -> dict[str, float]:
    """Figures per model (see the module docstring); ``rgb`` ``[375, 1242, 3]`` uint8."""
    out: dict[str, float] = {"real_size_threads": float(threads)}
    for key, name in DA_MODELS.items():
        path = _paths(name).get("model_path")
        if path is None:
            continue
        for suffix, size, method, models in da_configs:
            if key not in models:
                continue
            net = DepthAnythingOnnx(
                DepthAnythingParams(
                    model_path=path,
                    threads=threads,
                    provider=provider,
                    input_size=size,
                    resize_method=method,
                )
            )
            walls, cpus, res = _timed(lambda net=net: net.infer(rgb), repeats)
            k = key + suffix
            model = float(np.median([r.model_ms for r in res]))
            out[f"{k}_ms"] = float(np.median(walls))
            out[f"{k}_model_ms"] = model
            out[f"{k}_ours_ms"] = float(np.median([w - r.model_ms for w, r in zip(walls, res)]))
            out[f"{k}_cpu_s"] = float(np.median(cpus))
            out[f"{k}_net_h"], out[f"{k}_net_w"] = map(float, res[0].net_hw)
            assert res[0].value.shape == rgb.shape[:2] and res[0].value.dtype == np.float32
            log.info("%s: %.0f ms, %.2f CPU-s", k, out[f"{k}_ms"], out[f"{k}_cpu_s"])
    for key, name in SAM_MODELS.items():
        paths = _paths(name)
        if not paths:
            continue
        prompts = SAM_PROMPTS if sam_prompts is None else sam_prompts
        sam = SamOnnx(SamParams(**paths, threads=threads, provider=provider, **prompts))
        enc_walls, enc_cpus, _ = _timed(lambda sam=sam: sam.embed(rgb), 1)
        walls, cpus, res = _timed(lambda sam=sam: sam.generate(rgb), repeats)
        out[f"{key}_ms"] = float(np.median(walls))
        out[f"{key}_model_ms"] = float(np.median([r.stats["model_ms"] for r in res]))
        out[f"{key}_ours_ms"] = float(
            np.median([w - r.stats["model_ms"] for w, r in zip(walls, res)])
        )
        out[f"{key}_cpu_s"] = float(np.median(cpus))
        out[f"{key}_encoder_ms"] = float(enc_walls[0])
        out[f"{key}_encoder_cpu_s"] = float(enc_cpus[0])
        for stat in ("n_prompts", "n_prompts_run", "n_decoder_calls", "n_masks", "coverage"):
            out[f"{key}_{stat}"] = float(res[-1].stats[stat])
        out[f"{key}_decoder_batched"] = float(sam.batched)
        out[f"{key}_decoder_adapted"] = float(sam.adapted)
        log.info("%s: %.0f ms, %.2f CPU-s", key, out[f"{key}_ms"], out[f"{key}_cpu_s"])
    return out


def markdown(fig: dict[str, float], command: str, machine: str) -> str:
    """The ``workers-real-size`` section of docs/benchmarks.md."""
    lines = [
        "## Learned workers at real model sizes (random weights)",
        "",
        f"Command: `{command}`. Machine: {machine}; onnxruntime "
        f"{fig['real_size_threads']:.0f} intra-op threads, load average at the start "
        f"{fig['load_average_1min']:.1f}. One 1242x375 KITTI excerpt frame; median of the timed "
        "runs after one warm-up. Random weights: costs are the real models' costs, outputs "
        "are meaningless (never read depth or mask quality from them).",
        "",
        "| model | wall ms / keyframe | in the network | ours | ours share | CPU s / keyframe |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    names = {
        "depth_anything_vits": "Depth Anything V2 Small, longer side 518 (net {h}x{w})",
        "depth_anything_vits_lb518": "Depth Anything V2 Small, shorter side 518 (net {h}x{w})",
        "depth_anything_vitb": "Depth Anything V2 Base, longer side 518 (net {h}x{w})",
        "depth_anything_vitb_lb518": "Depth Anything V2 Base, shorter side 518 (net {h}x{w})",
        "sam_small": "MobileSAM automatic masks",
        "sam_vit_b": "SAM ViT-B automatic masks",
    }
    for k, label in names.items():
        if f"{k}_ms" not in fig:
            continue
        label = label.format(h=int(fig.get(f"{k}_net_h", 0)), w=int(fig.get(f"{k}_net_w", 0)))
        if k.startswith("sam"):
            label += (
                f" ({fig[f'{k}_n_prompts_run']:.0f} of {fig[f'{k}_n_prompts']:.0f} prompts run, "
                f"{fig[f'{k}_n_decoder_calls']:.0f} decoder calls; encoder "
                f"{fig[f'{k}_encoder_ms']:.0f} ms"
                + (
                    f", {fig[f'{k}_encoder_cpu_s']:.2f} CPU-s)"
                    if f"{k}_encoder_cpu_s" in fig
                    else ")"
                )
            )
        lines.append(
            f"| {label} | {fig[f'{k}_ms']:.0f} | {fig[f'{k}_model_ms']:.0f} | "
            f"{fig[f'{k}_ours_ms']:.0f} | {fig[f'{k}_ours_ms'] / fig[f'{k}_ms']:.1%} | "
            f"{fig[f'{k}_cpu_s']:.2f} |"
        )
    lines += [
        "",
        "Prompts (SAM rows): a square-cell grid 16 along the longer side (16x5 here), run coarse "
        "to fine, covered prompts skipped, at most 16 per keyframe (launch/learned.yaml); the "
        "decoder pruned of its full-size masks output and fed 8 prompts per call "
        '(docs/workers.md "Cost"). A CPU-only user: MobileSAM and Depth Anything V2 Small '
        "with the longer side at 518 (docs/workers.md).",
    ]
    return "\n".join(lines)


def frame(data_dir: str | None) -> np.ndarray:
    """The KITTI excerpt frame the other worker latencies use (index 20)."""
    from mogs_node.eval.depth_kitti78 import DEFAULT_DIR, load_kitti78

    return load_kitti78(Path(data_dir) if data_dir else DEFAULT_DIR).rgb[20]
