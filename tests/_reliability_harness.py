"""Shared by the burst and fuzz tests: a broker and real node processes on a private ipc bus, a
``/diagnostics`` monitor, and resident-memory sampling of every process."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil
import zmq

from mogs_node import msgs
from mogs_node.bus import BusConfig, Subscriber

REPO = Path(__file__).resolve().parents[1]


def private_bus(**kwargs: Any) -> BusConfig:
    d = Path("/tmp") / f"mogs-rel-{uuid.uuid4().hex[:8]}"
    d.mkdir()
    return BusConfig(f"ipc://{d}/pub.ipc", f"ipc://{d}/sub.ipc", **kwargs)


def node_argv(cls: str, name: str, params: dict[str, Any], bus: BusConfig) -> list[str]:
    """The command line of one node process (``mogs node``) on ``bus``."""
    return [
        sys.executable,
        "-m",
        "mogs_node.cli",
        "node",
        cls,
        "--name",
        name,
        "--params-json",
        json.dumps(params),
        "--bus-json",
        json.dumps(bus.to_dict()),
    ]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")  # 2 shared cores: no thread pools per process
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


@dataclass
class Procs:
    """The broker and node processes of one test, stopped in order by :meth:`stop`."""

    bus: BusConfig
    broker: subprocess.Popen | None = None
    nodes: dict[str, subprocess.Popen] = field(default_factory=dict)
    logs: dict[str, Path] = field(default_factory=dict)

    def start_broker(self, log_dir: Path) -> None:
        log = log_dir / "broker.log"
        self.logs["broker"] = log
        self.broker = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "mogs_node.cli",
                "broker",
                "--bus-json",
                json.dumps(self.bus.to_dict()),
            ],
            cwd=REPO,
            env=_env(),
            stdout=log.open("wb"),
            stderr=subprocess.STDOUT,
        )

    def start_node(self, name: str, cls: str, params: dict[str, Any], log_dir: Path) -> None:
        log = log_dir / f"{name}.log"
        self.logs[name] = log
        self.nodes[name] = subprocess.Popen(
            node_argv(cls, name, params, self.bus),
            cwd=REPO,
            env=_env(),
            stdout=log.open("wb"),
            stderr=subprocess.STDOUT,
        )

    def pids(self) -> dict[str, int]:
        out = {n: p.pid for n, p in self.nodes.items()}
        if self.broker is not None:
            out["broker"] = self.broker.pid
        return out

    def alive(self) -> dict[str, bool]:
        return {n: p.poll() is None for n, p in self.nodes.items()}

    def stop_nodes(self, timeout_s: float = 30.0) -> dict[str, int | None]:
        for p in self.nodes.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        codes = {}
        for n, p in self.nodes.items():
            try:
                codes[n] = p.wait(timeout_s)
            except subprocess.TimeoutExpired:
                p.kill()
                codes[n] = None
        return codes

    def stop(self) -> None:
        self.stop_nodes(10)
        if self.broker is not None and self.broker.poll() is None:
            self.broker.send_signal(signal.SIGINT)
            try:
                self.broker.wait(10)
            except subprocess.TimeoutExpired:
                self.broker.kill()

    def tail(self, name: str, n: int = 3000) -> str:
        with contextlib.suppress(OSError):
            return self.logs[name].read_text(errors="replace")[-n:]
        return ""


class Monitor:
    """A subscriber thread: the latest ``/diagnostics`` of every node and per-topic message counts
    (with the stamps seen) of the extra topics it is asked to watch, counting only messages of the
    type ``types`` names for a topic (when given)."""

    def __init__(
        self,
        bus: BusConfig,
        topics: tuple[str, ...] = (),
        types: dict[str, type[msgs.Message]] | None = None,
    ) -> None:
        self.bus = bus
        self._types = types or {}
        self.diag: dict[str, msgs.Diagnostics] = {}
        self.counts: dict[str, int] = defaultdict(int)
        self.stamps: dict[str, list[int]] = defaultdict(list)
        self._topics = topics
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        assert self._ready.wait(5)

    def _run(self) -> None:
        ctx = zmq.Context()
        sub = Subscriber(self.bus, context=ctx)
        sub.subscribe("/diagnostics")
        for t in self._topics:
            sub.subscribe(t)
        self._ready.set()
        try:
            while not self._stop.is_set():
                env = sub.receive(timeout_ms=100)
                if env is None:
                    continue
                with self._lock:
                    if env.topic == "/diagnostics":
                        if isinstance(env.msg, msgs.Diagnostics):
                            self.diag[env.msg.node] = env.msg
                    elif isinstance(env.msg, self._types.get(env.topic, msgs.Message)):
                        self.counts[env.topic] += 1
                        self.stamps[env.topic].append(env.msg.stamp_ns)
        finally:
            sub.close()
            ctx.term()

    def latest(self, node: str) -> msgs.Diagnostics | None:
        with self._lock:
            return self.diag.get(node)

    def wait_for(self, pred, timeout_s: float, period_s: float = 0.2) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if pred(self):
                    return True
            time.sleep(period_s)
        with self._lock:
            return bool(pred(self))

    def wait_for_nodes(self, names: list[str], timeout_s: float) -> bool:
        return self.wait_for(lambda m: all(n in m.diag for n in names), timeout_s)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


class RssSampler:
    """Samples the resident memory (RSS, bytes) of named processes every ``period_s``."""

    def __init__(self, pids: dict[str, int], period_s: float = 0.25) -> None:
        self.procs = {n: psutil.Process(pid) for n, pid in pids.items()}
        self.samples: dict[str, list[tuple[float, int]]] = {n: [] for n in pids}
        self._stop = threading.Event()
        self._period = period_s
        self._thread = threading.Thread(target=self._run, daemon=True)

    def sample(self) -> dict[str, int]:
        now, out = time.monotonic(), {}
        for n, p in self.procs.items():
            with contextlib.suppress(psutil.Error):
                rss = p.memory_info().rss
                self.samples[n].append((now, rss))
                out[n] = rss
        return out

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._period):
            self.sample()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def peak(self, name: str, since: float = 0.0) -> int:
        return max((r for t, r in self.samples[name] if t >= since), default=0)
