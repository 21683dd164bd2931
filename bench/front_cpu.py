"""CPU seconds and peak RSS of every process of a launched pipeline, sampled over time, for
bench/front.py's cost axis (psutil: user + system time per process, so nodes that respawn are
counted with all their processes)."""

from __future__ import annotations

import contextlib

import psutil

from mogs_node.launch import Launcher

__all__ = ["CpuSampler", "cpu_between"]


class CpuSampler:
    """Cumulative CPU seconds and RSS of every process of a launcher, sampled over time."""

    def __init__(self, launcher: Launcher) -> None:
        self.launcher = launcher
        self.procs: dict[int, tuple[str, psutil.Process]] = {}
        self.samples: list[tuple[float, dict[str, float]]] = []  # (time, node -> CPU s)
        self.cpu_s: dict[str, float] = {}  # node -> CPU s of its exited processes + live one
        self._done: dict[str, float] = {}  # CPU s of processes of a node that have exited
        self._last: dict[int, float] = {}
        self.rss_mib: dict[str, float] = {}

    def sample(self, now: float) -> None:
        for child in self.launcher.children:
            proc = child.proc
            if proc is not None and proc.pid not in self.procs:
                with contextlib.suppress(psutil.NoSuchProcess):
                    self.procs[proc.pid] = (child.name, psutil.Process(proc.pid))
        live: dict[str, float] = {}
        for pid, (name, p) in list(self.procs.items()):
            try:
                with p.oneshot():
                    ct = p.cpu_times()
                    self._last[pid] = ct.user + ct.system
                    self.rss_mib[name] = max(
                        self.rss_mib.get(name, 0.0), p.memory_info().rss / 2**20
                    )
                live[name] = live.get(name, 0.0) + self._last[pid]
            except (psutil.NoSuchProcess, psutil.ZombieProcess):
                self._done[name] = self._done.get(name, 0.0) + self._last.get(pid, 0.0)
                del self.procs[pid]
        cum = {n: self._done.get(n, 0.0) + live.get(n, 0.0) for n in {*self._done, *live}}
        self.samples.append((now, cum))

    def at(self, t: float) -> dict[str, float]:
        """Cumulative CPU per node at the last sample at or before ``t`` (first sample if none)."""
        best = self.samples[0][1]
        for ts, cum in self.samples:
            if ts > t:
                break
            best = cum
        return best


def cpu_between(sampler: CpuSampler, t0: float, t1: float) -> dict[str, float]:
    """CPU seconds per node between the samples at or before ``t0`` and ``t1``."""
    a, b = sampler.at(t0), sampler.at(t1)
    return {n: max(0.0, b.get(n, 0.0) - a.get(n, 0.0)) for n in b}
