"""A/B of two versions of the C++ compositing kernel: bitwise equality and CPU time per call.

Builds ``--old`` and ``--new`` (default: this tree's ``composite_cpu.cpp``) as two extensions,
captures the forward and backward inputs of one render of :func:`bench.rasterizer.make_scene`
(``--gaussians`` at the demo's 621x188 and half of it), checks that both versions give bitwise the
same image, transmittance, contributor counts, weights and gradients (a random upstream gradient),
then times them interleaved call by call (process CPU time, one thread: fair on a loaded machine).

    git show main:mogs_node/mapper/csrc/composite_cpu.cpp > /tmp/old.cpp
    .venv/bin/python bench/composite_ab.py --old /tmp/old.cpp

``--journal J --at-keyframe N`` captures the inputs of a real training render instead: the demo
journal ``J`` replayed through the mapper core (``bench/mapper_replay.py``, ``launch/demo.yaml``'s
mapper) for ``N`` keyframes, then one training iteration of the newest keyframe at the training
resolution, with that iteration's loss gradient as the upstream gradient.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

import mogs_node.mapper.composite as comp

if not __package__:  # run as a script (python bench/composite_ab.py): the repo root holds bench/
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.rasterizer import make_scene  # noqa: E402
from mogs_node.mapper.rasterizer import RasterParams, render

SIZES = [(621, 188), (310, 94)]


def build(name: str, src: Path, root: Path, flags: list[str]):
    """Compile ``src`` as extension ``name`` with the flags the mapper uses plus ``flags``."""
    from torch.utils.cpp_extension import load

    build_dir = root / name
    build_dir.mkdir(parents=True, exist_ok=True)
    return load(
        name=name,
        sources=[str(src)],
        extra_cflags=["-O3", "-fopenmp", "-ffp-contract=off", *flags],
        extra_ldflags=["-fopenmp"],
        build_directory=str(build_dir),
        verbose=False,
    )


class _Recorder:
    """Stands in for the extension module: records the last forward and backward arguments."""

    def __init__(self, real) -> None:
        self.real, self.cap = real, {}

    def forward(self, *a):
        self.cap["f"] = a
        return self.real.forward(*a)

    def backward(self, *a):
        self.cap["b"] = a
        return self.real.backward(*a)


def capture_journal(journal: Path, n_keyframes: int) -> tuple[tuple, list, str]:
    """The (forward, backward) arguments of one real training iteration: the newest keyframe after
    replaying ``n_keyframes`` of ``journal`` through the mapper core."""
    from bench.mapper_replay import mapper_params, read_journal, replay

    p = mapper_params(str(Path(comp.__file__).parents[2] / "launch" / "demo.yaml"), {})
    mapper, _ = replay(read_journal(journal), p, n_keyframes)
    rec = _Recorder(comp.load_cpp_extension())
    saved = comp.load_cpp_extension
    comp.load_cpp_extension = lambda: rec
    try:
        mapper._train_step(mapper.window[0], -1, mapper._lrs())
    finally:
        comp.load_cpp_extension = saved
    w, h = mapper.train_size
    return rec.cap["f"], list(rec.cap["b"]), f"journal kf {n_keyframes} {w}x{h}"


def capture_args(n: int, width: int, height: int) -> tuple[tuple, list]:
    """The (forward, backward) argument tuples of the C++ passes for one render + gradient."""
    real = comp.load_cpp_extension()
    cap: dict[str, tuple] = {}

    class Recorder:
        def forward(self, *a):
            cap["f"] = a
            return real.forward(*a)

        def backward(self, *a):
            cap["b"] = a
            return real.backward(*a)

    saved = comp.load_cpp_extension
    comp.load_cpp_extension = Recorder
    try:
        scene, K = make_scene(n, width, height)
        leaves = [t.requires_grad_() for t in scene.tensors()]
        out = render(scene, torch.eye(4), K, width, height, params=RasterParams(backend="cpp"))
        torch.autograd.grad(out.color.sum() + 0.1 * out.depth.sum(), leaves)
    finally:
        comp.load_cpp_extension = saved
    back = list(cap["b"])
    back[-8] = torch.randn(back[-8].shape, generator=torch.Generator().manual_seed(1))  # grad_out
    return cap["f"], back


def run_forward(ext, fa: list, threads: int) -> list:
    """``ext``'s forward on the captured arguments (this tree's signature: ..., nthreads,
    record) at ``threads``; an older kernel without the record flag gets the arguments without it."""
    a = [*fa[:-2], threads, True]
    try:
        return list(ext.forward(*a))
    except TypeError:  # an older kernel: no record flag
        return list(ext.forward(*a[:-1]))


def run_backward(ext, ba: list, fwd: list, threads: int):
    """``ext``'s backward on the captured arguments, with what its own forward ``fwd`` returned
    (the record of this tree's kernel, or ``n_contrib`` for an older one) at ``threads``."""
    head, tail = ba[:9], [*ba[-8:-1], threads]  # ... final_T | grad_out, W, ..., nthreads
    if len(fwd) > 5:
        return ext.backward(*head, *fwd[5:9], *tail)
    return ext.backward(*head, fwd[2], *tail)


def median(v: list[float]) -> float:
    return sorted(v)[len(v) // 2]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", type=Path, required=True, help="composite_cpu.cpp to compare against")
    ap.add_argument("--new", type=Path, default=Path(comp._SOURCE))
    ap.add_argument("--new-flags", default="", help="extra compiler flags for --new")
    ap.add_argument("--gaussians", type=int, default=40_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--journal", type=Path, default=None, help="a demo run's journal.log")
    ap.add_argument("--at-keyframe", type=int, default=8, help="with --journal: replay this many")
    ap.add_argument("--threads", type=int, default=1, help="the kernels' thread count")
    args = ap.parse_args()
    torch.set_num_threads(1)
    root = Path(os.environ.get("TORCH_EXTENSIONS_DIR") or tempfile.gettempdir()) / "composite_ab"
    old = build("composite_ab_old", args.old, root, [])
    new = build("composite_ab_new", args.new, root, args.new_flags.split())
    cases = []
    if args.journal is not None:
        cases.append(capture_journal(args.journal, args.at_keyframe))
    else:
        for width, height in SIZES:
            cases.append((*capture_args(args.gaussians, width, height), f"{width}x{height}"))
    for fa, ba, label in cases:
        fa, ba = list(fa), list(ba)
        th = args.threads
        fo, fn = run_forward(old, fa, th), run_forward(new, fa, th)
        same_f = all(torch.equal(x, y) for x, y in zip(fo[:5], fn[:5]))
        same_b = torch.equal(run_backward(old, ba, fo, th), run_backward(new, ba, fn, th))
        if th > 1:  # and against the old kernel on one thread (thread-count free?)
            f1 = run_forward(old, fa, 1)
            same_f = same_f and all(torch.equal(x, y) for x, y in zip(f1[:5], fn[:5]))
            same_one_b = torch.equal(run_backward(old, ba, f1, 1), run_backward(new, ba, fn, th))
            print(f"{label}: new on {th} threads == old on 1 thread: {same_one_b}")
        times: dict[str, list[float]] = {k: [] for k in ("of", "nf", "ob", "nb")}
        walls: dict[str, list[float]] = {k: [] for k in times}
        for _ in range(args.repeats):
            for tag, ext in (("o", old), ("n", new)):
                c, w = time.process_time(), time.perf_counter()
                fwd = run_forward(ext, fa, th)
                times[tag + "f"].append(time.process_time() - c)
                walls[tag + "f"].append(time.perf_counter() - w)
                c, w = time.process_time(), time.perf_counter()
                run_backward(ext, ba, fwd, th)
                times[tag + "b"].append(time.process_time() - c)
                walls[tag + "b"].append(time.perf_counter() - w)
        m = {k: median(v) * 1e3 for k, v in times.items()}
        mw = {k: median(v) * 1e3 for k, v in walls.items()}
        print(
            f"{label} entries={len(fa[1])} bit-identical forward={same_f} "
            f"backward={same_b} | forward old {m['of']:.1f} ms new {m['nf']:.1f} ms "
            f"(old/new {m['of'] / m['nf']:.2f}) | backward old {m['ob']:.1f} ms new "
            f"{m['nb']:.1f} ms (old/new {m['ob'] / m['nb']:.2f}) | wall ms fwd old/new "
            f"{mw['of']:.1f}/{mw['nf']:.1f} bwd {mw['ob']:.1f}/{mw['nb']:.1f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
