"""Benchmark: CPU rasterizer forward and forward+backward, and mapper iterations per second.

Scenes are synthetic but shaped like the mapper's maps: Gaussians back-projected from random pixels
at depths 2-60 m with a pixel-footprint scale (as :mod:`mogs_node.mapper.insertion` makes them).
Prints figures and writes them to ``--json PATH`` and to the ``rasterizer`` section of
``docs/benchmarks.md`` (with ``--write-docs``).

    .venv/bin/python bench/rasterizer.py --threads 2 --json /tmp/raster.json --write-docs
"""

from __future__ import annotations

import argparse
import math
import os
import time

import torch

from mogs_node.eval.bench_docs import machine_line, update_markdown_section, write_json
from mogs_node.mapper.composite import load_cpp_extension
from mogs_node.mapper.rasterizer import GaussianTensors, RasterParams, render

SIZES = [(320, 96), (640, 192), (1242, 375)]
COUNTS = [10_000, 50_000, 200_000]
TORCH_CASES = {(10_000, 320, 96), (50_000, 640, 192)}
PROTOTYPE_S = 0.6  # issue 7: a quick pure-PyTorch prototype, 50k Gaussians at 640x192, fwd+bwd


def make_scene(n: int, width: int, height: int, seed: int = 0) -> tuple[GaussianTensors, tuple]:
    """``n`` Gaussians in the frustum of a camera with a 90 degree horizontal field of view."""
    g = torch.Generator().manual_seed(seed)
    fx = width / 2.0
    K = (fx, fx, (width - 1) / 2.0, (height - 1) / 2.0)
    u = torch.rand(n, generator=g) * width
    v = torch.rand(n, generator=g) * height
    z = 2.0 + 58.0 * torch.rand(n, generator=g) ** 2
    means = torch.stack([(u - K[2]) / fx * z, (v - K[3]) / fx * z, z], -1)
    # footprint scale: as many pixels as n leaves per pixel, a few px at this resolution
    px = math.sqrt(width * height / n) * 1.5
    log_scales = torch.log(px * z / fx)[:, None] + 0.3 * torch.randn(n, 3, generator=g)
    quats = torch.randn(n, 4, generator=g)
    opacity_logit = torch.randn(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return GaussianTensors(means, quats, log_scales, opacity_logit, colors), K


def time_render(
    n: int, width: int, height: int, backend: str, repeats: int
) -> tuple[float, float, float]:
    """Best wall time of forward and of forward+backward, and the CPU time (all threads) of
    that forward+backward run (less sensitive to other jobs on a shared machine)."""
    scene, K = make_scene(n, width, height)
    device = "cuda" if backend == "gsplat" else "cpu"  # gsplat renders CUDA tensors only
    scene = GaussianTensors(*(t.to(device) for t in scene.tensors()))
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    params = RasterParams(backend=backend)
    leaves = [t.requires_grad_() for t in scene.tensors()]
    T = torch.eye(4, device=device)
    fwd, both, cpu = [], [], []
    for _ in range(repeats + 1):
        sync()
        t0 = time.perf_counter()
        with torch.no_grad():
            render(scene, T, K, width, height, params=params)
        sync()
        t1 = time.perf_counter()
        c1 = time.process_time()
        out = render(scene, T, K, width, height, params=params)
        loss = out.color.sum() + 0.1 * out.depth.sum()
        torch.autograd.grad(loss, leaves)
        sync()
        t2 = time.perf_counter()
        cpu.append(time.process_time() - c1)
        fwd.append(t1 - t0)
        both.append(t2 - t1)
    return (
        min(fwd[1:]),
        min(both[1:]),
        min(cpu[1:]),
    )  # first run: warm-up (allocator, extension load)


def mapper_iterations_per_s(width: int, height: int, n_iters: int = 10) -> tuple[float, int]:
    """Window iterations (one sampled view each) per second of the mapper core on 5 keyframes
    of a synthetic street."""
    import numpy as np

    from mogs_node.mapper.mapper import GaussianMapper, MapperParams

    rng = np.random.default_rng(0)
    f = width / 2.0
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    vv, uu = np.mgrid[0:height, 0:width]
    # ground plane below the horizon, a wall 20 m ahead above it
    ray_y = (vv - K[1, 2]) / f
    depth = np.where(ray_y > 0.05, np.minimum(1.6 / np.maximum(ray_y, 1e-3), 20.0), 20.0)
    mapper = GaussianMapper(MapperParams(window_size=4, n_random_past=1), K, width, height)
    for k in range(5):
        img = (rng.uniform(0, 255, (height // 4 + 1, width // 4 + 1, 3))).astype(np.uint8)
        img = np.repeat(np.repeat(img, 4, 0), 4, 1)[:height, :width]
        T = np.eye(4)
        T[2, 3] = 1.0 * k
        mapper.add_keyframe(k, img, T, depth.astype(np.float32), np.ones_like(depth, np.float32))
    mapper.optimize(1)
    t0 = time.perf_counter()
    mapper.optimize(n_iters)
    return n_iters / (time.perf_counter() - t0), len(mapper.map)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--backends", default="cpp,torch")
    ap.add_argument("--quick", action="store_true", help="only 50k at 640x192")
    ap.add_argument("--mapper", action="store_true", help="also time mapper iterations")
    ap.add_argument("--json", default=None, metavar="PATH")
    ap.add_argument("--write-docs", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()[0]
    load_cpp_extension()
    figures: dict[str, float] = {"threads": args.threads}
    rows = []
    cases = [(50_000, 640, 192)] if args.quick else [(n, w, h) for (w, h) in SIZES for n in COUNTS]
    for backend in args.backends.split(","):
        for n, w, h in cases:
            if backend == "torch" and (n, w, h) not in TORCH_CASES:
                continue  # the pure-PyTorch fallback is only timed for reference
            repeats = args.repeats if backend in ("cpp", "gsplat") else 1
            f, b, c = time_render(n, w, h, backend, repeats)
            key = f"{backend}_{n // 1000}k_{w}x{h}"
            figures[f"{key}_forward_ms"] = 1000 * f
            figures[f"{key}_fwd_bwd_ms"] = 1000 * b
            figures[f"{key}_fwd_bwd_cpu_ms"] = 1000 * c
            rows.append((backend, n, f"{w}x{h}", 1000 * f, 1000 * b, 1000 * c))
            print(
                f"{backend:6s} {n:7d} {w}x{h:<4d} forward {1000 * f:8.1f} ms  "
                f"fwd+bwd {1000 * b:8.1f} ms (cpu {1000 * c:8.1f} ms)",
                flush=True,
            )
    ref_key = "cpp_50k_640x192_fwd_bwd_ms"
    if ref_key in figures:
        figures["speedup_vs_prototype_50k_640x192_ratio"] = PROTOTYPE_S * 1000 / figures[ref_key]
        print(
            f"speed-up vs the 0.6 s prototype (50k, 640x192, fwd+bwd): "
            f"{figures['speedup_vs_prototype_50k_640x192_ratio']:.2f}x"
        )
    if "torch_50k_640x192_fwd_bwd_ms" in figures and ref_key in figures:
        figures["cpp_vs_torch_50k_640x192_ratio"] = (
            figures["torch_50k_640x192_fwd_bwd_ms"] / figures[ref_key]
        )
    if args.mapper:
        for w, h in SIZES[:2]:
            its, n = mapper_iterations_per_s(w, h)
            figures[f"mapper_{w}x{h}_iterations_per_s"] = its
            figures[f"mapper_{w}x{h}_n_gaussians"] = n
            print(f"mapper {w}x{h}: {its:.2f} iterations/s ({n} Gaussians, one view per iteration)")
    write_json(args.json, figures)
    if args.write_docs:
        lines = [
            "## Rasterizer (CPU)" + (": the goal case" if args.quick else ""),
            "",
            f"`.venv/bin/python bench/rasterizer.py --threads {args.threads} "
            f"--repeats {args.repeats}{' --quick' if args.quick else ''}"
            f"{' --mapper' if args.mapper else ''} --write-docs` on "
            f"{machine_line()}; best of {args.repeats} after a warm-up run. The machine's 2 cores "
            "are shared with other jobs: figures are upper bounds (1-min load average "
            f"{load_start:.1f} at the start, {os.getloadavg()[0]:.1f} at the end).",
            "",
            "| backend | Gaussians | size | forward ms | forward+backward ms | fwd+bwd CPU ms |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        lines += [
            f"| {b} | {n} | {s} | {f:.1f} | {fb:.1f} | {c:.1f} |" for b, n, s, f, fb, c in rows
        ]
        for k, v in figures.items():
            if k.endswith("_ratio") or k.endswith("_per_s"):
                lines.append(f"\n- `{k}`: {v:.2f}")
        # --quick (the goal case, many repeats) keeps its own section beside the full table
        update_markdown_section("rasterizer-50k" if args.quick else "rasterizer", "\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
