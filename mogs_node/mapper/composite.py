"""Front-to-back alpha compositing of depth-sorted screen-space Gaussians per tile (3DGS section 6).

Two implementations with identical semantics (the per-pixel loop of 3DGS, including its skips and
early termination; see ``csrc/composite_cpu.cpp``):

- ``"cpp"``: a C++/OpenMP torch extension with a hand-written backward, compiled with
  :func:`torch.utils.cpp_extension.load` on first use and cached by torch. If compilation fails
  (no compiler, no headers) the failure is logged once and ``"torch"`` is used instead.
- ``"torch"``: pure PyTorch, vectorised over tiles x pixels x a chunk of list entries, with exact
  per-tile early termination (finished tiles leave the active set); gradients by autograd.

Features are generic channels ``[N, C]`` (the rasterizer passes rgb, depth and a constant 1 so
that colour, depth and accumulated alpha come out of one pass).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import logging
import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import torch

from mogs_node.mapper.raster_types import TileBins

__all__ = [
    "CompositeJob",
    "composite",
    "composite_torch",
    "cpp_extension_available",
    "load_cpp_extension",
]

log = logging.getLogger(__name__)

_EXT: ModuleType | None = None
_EXT_FAILED = False
_EXT_LOCK = threading.Lock()


_NAME = "mogs_composite_cpu"
_SOURCE = Path(__file__).with_name("csrc") / "composite_cpu.cpp"


def _source_tag(src: Path) -> str:
    """Short hash of the C++ source: each version of it builds into its own cached module, so
    checkouts with different sources on one machine never rebuild over each other."""
    return hashlib.sha1(src.read_bytes()).hexdigest()[:10]


def extension_name() -> str:
    """The cached module's name: ``mogs_composite_cpu_<hash of the C++ source>``."""
    return f"{_NAME}_{_source_tag(_SOURCE)}"


@contextlib.contextmanager
def _build_lock(build_dir: Path) -> Iterator[None]:
    """Hold an flock on the build directory while torch builds or loads the extension.

    torch's own build lock is a plain file: a builder killed mid-compile (a hung-node kill, a
    SIGKILL in a test) leaves it behind and every later process waits on it forever. An flock
    dies with its process, so whoever holds ours knows no other process of ours is building and
    may remove a leftover torch lock.
    """
    with open(build_dir / "mogs.flock", "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            stale = build_dir / "lock"
            if stale.exists():
                log.warning("removing a stale build lock left by a killed build: %s", stale)
                stale.unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def load_cpp_extension() -> ModuleType | None:
    """Compile (first use) or load the cached C++ extension; ``None`` if that is impossible.

    Set ``MOGS_NO_CPP_EXT=1`` to force the pure-PyTorch path.
    """
    global _EXT, _EXT_FAILED
    if _EXT is not None or _EXT_FAILED:
        return _EXT
    with _EXT_LOCK:
        if _EXT is not None or _EXT_FAILED:
            return _EXT
        if os.environ.get("MOGS_NO_CPP_EXT", "") not in ("", "0"):
            _EXT_FAILED = True
            return None
        try:
            from torch.utils.cpp_extension import get_default_build_root, load

            src = _SOURCE
            name = extension_name()
            root = os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root()
            build_dir = Path(root) / f"mogs_torch{torch.__version__}" / name
            build_dir.mkdir(parents=True, exist_ok=True)
            if not (build_dir / f"{name}.so").exists():  # first use: say why start-up waits
                log.info("building the C++ compositing extension (once, ~20-40 s) in %s", build_dir)
            with _build_lock(build_dir):
                # build from a copy inside the build directory: torch's build.ninja names the
                # source path, so checkouts of the same source at different paths (worktrees,
                # site-packages) would otherwise rebuild the cached module over each other
                copy = build_dir / src.name
                if not copy.exists() or copy.read_bytes() != src.read_bytes():
                    copy.write_bytes(src.read_bytes())
                _EXT = load(
                    name=name,
                    sources=[str(copy)],
                    extra_cflags=["-O3", "-fopenmp", "-ffp-contract=off"],
                    extra_ldflags=["-fopenmp"],
                    build_directory=str(build_dir),
                    verbose=False,
                )
        except Exception as err:  # noqa: BLE001 - any build failure means: use the fallback
            log.warning("C++ compositing extension unavailable, using pure PyTorch: %s", err)
            _EXT_FAILED = True
    return _EXT


def cpp_extension_available() -> bool:
    """True when the C++ extension is (or can be) loaded."""
    return load_cpp_extension() is not None


def _entry_weights_per_gaussian(
    gauss_ids: torch.Tensor, entry_w: torch.Tensor, n: int
) -> torch.Tensor:
    """Sum the per-list-entry weights [M] into per-Gaussian weights [n] (float64 accumulation in
    a fixed order: ``bincount`` is serial, so the result is bitwise repeatable)."""
    if len(gauss_ids) == 0:
        return torch.zeros(n, dtype=entry_w.dtype)
    w = torch.bincount(gauss_ids, weights=entry_w.double(), minlength=n)
    return w.to(entry_w.dtype)


@dataclass(frozen=True)
class CompositeJob:
    """What one compositing pass needs: screen-space Gaussians ``means2d`` [N, 2] px,
    ``conics`` [N, 3], ``opacity`` [N], their features ``feats`` [N, C] (C <= 8) and the
    background ``bg`` [C], all one float dtype; their depth-sorted tile lists ``bins``, the image
    size and ``thresholds = (alpha_min, alpha_max, t_min)``; ``threads`` of the C++ passes (0:
    ``torch.get_num_threads()``; the result does not depend on it)."""

    means2d: torch.Tensor
    conics: torch.Tensor
    opacity: torch.Tensor
    feats: torch.Tensor
    bg: torch.Tensor
    bins: TileBins
    width: int
    height: int
    thresholds: tuple[float, float, float]
    threads: int = 0

    def tensors(
        self,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The differentiable inputs, in order: means2d, conics, opacity, feats, bg."""
        return self.means2d, self.conics, self.opacity, self.feats, self.bg


class _CompositeCpp(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx, means2d, conics, opacity, feats, bg, bins, width, height, thresholds, threads, record
    ):
        ext = load_cpp_extension()
        alpha_min, alpha_max, t_min = thresholds
        nthreads = threads or torch.get_num_threads()
        args = (
            bins.tile_offsets,
            bins.gauss_ids,
            means2d.contiguous(),
            conics.contiguous(),
            opacity.contiguous(),
            feats.contiguous(),
            bg.contiguous(),
            bins.extent_px.to(feats.dtype).contiguous(),
        )
        # record: the forward keeps its contributions for the backward (only when one can follow)
        out, final_T, _, counts, entry_w, *rec = ext.forward(
            *args,
            width,
            height,
            bins.tile_px,
            bins.tiles_x,
            alpha_min,
            alpha_max,
            t_min,
            nthreads,
            record,
        )
        weights = _entry_weights_per_gaussian(bins.gauss_ids, entry_w, means2d.shape[0])
        ctx.save_for_backward(*args[2:], final_T, *rec)
        ctx.bins, ctx.size, ctx.thr, ctx.nthreads = bins, (width, height), thresholds, nthreads
        ctx.mark_non_differentiable(final_T, counts, weights)
        return out, final_T, counts, weights

    @staticmethod
    def backward(ctx, grad_out, _grad_T, _grad_counts, _grad_weights):
        means2d, conics, opacity, feats, bg, ext, final_T, *rec = ctx.saved_tensors
        bins, (width, height) = ctx.bins, ctx.size
        alpha_min, alpha_max, _ = ctx.thr
        g = load_cpp_extension().backward(
            bins.tile_offsets,
            bins.gauss_ids,
            means2d,
            conics,
            opacity,
            feats,
            bg,
            ext,
            final_T,
            *rec,
            grad_out.contiguous(),
            width,
            height,
            bins.tile_px,
            bins.tiles_x,
            alpha_min,
            alpha_max,
            ctx.nthreads,
        )
        grad_bg = (final_T[..., None] * grad_out).sum((0, 1))
        return g[:, 0:2], g[:, 2:5], g[:, 5], g[:, 6:], grad_bg, None, None, None, None, None, None


def composite_torch(
    job: CompositeJob, chunk: int = 32
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pure-PyTorch compositing; same inputs/outputs as :func:`composite`."""
    means2d, conics, opacity, feats, bg = job.tensors()
    bins, width, height = job.bins, job.width, job.height
    alpha_min, alpha_max, t_min = job.thresholds
    ts, tx_n, ty_n = bins.tile_px, bins.tiles_x, bins.tiles_y
    n_tiles = tx_n * ty_n
    C = feats.shape[1]
    dt = feats.dtype
    offs = bins.tile_offsets
    lengths = offs[1:] - offs[:-1]
    # pixel coordinates of each tile slot [n_tiles, ts*ts]; slots outside the image are masked
    ly, lx = torch.meshgrid(torch.arange(ts), torch.arange(ts), indexing="ij")
    tiles = torch.arange(n_tiles)
    pxs = (tiles % tx_n)[:, None] * ts + lx.reshape(1, -1)
    pys = (tiles // tx_n)[:, None] * ts + ly.reshape(1, -1)
    inimg = (pxs < width) & (pys < height)
    T = torch.ones(n_tiles, ts * ts, dtype=dt)
    acc = torch.zeros(n_tiles, ts * ts, C, dtype=dt)
    counts = torch.zeros(means2d.shape[0], dtype=torch.int32)
    weights = torch.zeros(means2d.shape[0], dtype=torch.float64)
    done = torch.zeros(n_tiles, ts * ts, dtype=torch.bool)
    thr = torch.log(alpha_min / opacity.detach().clamp_min(1e-30))
    max_len = int(lengths.max()) if n_tiles else 0
    for k0 in range(0, max_len, chunk):
        act = torch.nonzero((lengths > k0) & ~done.all(1)).flatten()
        if len(act) == 0:
            break
        k = torch.arange(k0, k0 + chunk)
        in_list = k[None, :] < lengths[act, None]  # [A, K]
        idx = torch.where(in_list, offs[act, None] + k[None, :], torch.zeros_like(k[None, :]))
        gid = bins.gauss_ids[idx]  # [A, K]
        dx = means2d[gid, 0][:, None, :] - pxs[act][:, :, None].to(dt)  # [A, P, K]
        dy = means2d[gid, 1][:, None, :] - pys[act][:, :, None].to(dt)
        a, b, c = conics[gid, 0][:, None], conics[gid, 1][:, None], conics[gid, 2][:, None]
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        keep = (power <= 0) & (power >= thr[gid][:, None]) & in_list[:, None, :]
        keep &= (~done[act] & inimg[act])[:, :, None]
        alpha = torch.clamp_max(
            opacity[gid][:, None] * torch.exp(power.clamp(-30.0, 0.0)), alpha_max
        )
        keep &= alpha >= alpha_min
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        T0 = T[act]
        with torch.no_grad():  # early termination: first entry with T (1 - alpha) < t_min and after
            T_incl = T0.detach()[:, :, None] * torch.cumprod(1 - alpha.detach(), -1)
            stop = T_incl < t_min
        alpha = torch.where(stop, torch.zeros_like(alpha), alpha)
        one_minus = 1 - alpha
        T_excl = torch.cumprod(
            torch.cat([torch.ones_like(alpha[..., :1]), one_minus[..., :-1]], -1), -1
        )
        w = alpha * T_excl * T0[:, :, None]
        acc_new = acc[act] + torch.einsum("apk,akc->apc", w, feats[gid])
        T_new = T0 * T_excl[..., -1] * one_minus[..., -1]
        with torch.no_grad():
            used = (alpha > 0) & ~stop
            counts.index_add_(0, gid.flatten(), used.sum(1).flatten().to(torch.int32))
            weights.index_add_(0, gid.flatten(), w.detach().sum(1).flatten().double())
            done_new = done[act] | stop.any(-1)
        acc = acc.index_copy(0, act, acc_new)
        T = T.index_copy(0, act, T_new)
        done = done.index_copy(0, act, done_new)
    # keep the graph connected when nothing is drawn (empty slices: zero gradients, never NaN)
    anchor = means2d[:0].sum() + conics[:0].sum() + opacity[:0].sum() + feats[:0].sum()
    out = acc + T[..., None] * bg + anchor
    # [n_tiles, ts*ts, C] -> [H, W, C]
    out = out.reshape(ty_n, tx_n, ts, ts, C).permute(0, 2, 1, 3, 4).reshape(ty_n * ts, tx_n * ts, C)
    T_img = T.reshape(ty_n, tx_n, ts, ts).permute(0, 2, 1, 3).reshape(ty_n * ts, tx_n * ts)
    return out[:height, :width], T_img[:height, :width].detach(), counts, weights.to(dt)


def composite(
    job: CompositeJob, backend: str = "auto"
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite the screen-space Gaussians of ``job`` into ``[H, W, C]`` features.

    Returns
    ``(out [H, W, C], final_transmittance [H, W], counts [N] int32, weights [N])`` where ``counts``
    is the number of pixels each Gaussian contributed to and ``weights`` its summed blending
    weight ``sum_p alpha_i(p) T_i(p)`` over those pixels (3DGS eq. 3's per-pixel weights; not
    differentiable), so that pruning by contribution needs no extra pass. ``backend``: ``"auto"`` (C++ if available), ``"cpp"``,
    ``"torch"``.
    """
    if backend in ("auto", "cpp") and load_cpp_extension() is not None:
        record = torch.is_grad_enabled() and any(t.requires_grad for t in job.tensors())
        return _CompositeCpp.apply(
            *job.tensors(), job.bins, job.width, job.height, job.thresholds, job.threads, record
        )
    if backend == "cpp":
        log.warning("composite: C++ backend requested but unavailable; using pure PyTorch")
    return composite_torch(job)
