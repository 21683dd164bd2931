"""Shared by the tests that start real processes: ``mogs`` command lines, a broker, node and command
processes and how to stop them, receiving for a while; for the burst and fuzz tests also a private
ipc bus, a ``/diagnostics`` monitor and resident-memory sampling of every process; for in-process
worker node tests a publisher and watcher wired to the node."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil
import zmq

from mogs_node import msgs
from mogs_node.bus import BusConfig, Publisher, Subscriber, run_broker
from mogs_node.node import Node

REPO = Path(__file__).resolve().parents[1]


def private_bus(**kwargs: Any) -> BusConfig:
    d = Path("/tmp") / f"mogs-rel-{uuid.uuid4().hex[:8]}"
    d.mkdir()
    return BusConfig(f"ipc://{d}/pub.ipc", f"ipc://{d}/sub.ipc", **kwargs)


def cli_argv(*args: str, bus: BusConfig | None = None) -> list[str]:
    """The command line of ``mogs ARGS``, on ``bus`` (``--bus-json``) when one is given."""
    argv = [sys.executable, "-m", "mogs_node.cli", *args]
    if bus is not None:
        argv += ["--bus-json", json.dumps(bus.to_dict())]
    return argv


def node_argv(cls: str, name: str, params: dict[str, Any], bus: BusConfig) -> list[str]:
    """The command line of one node process (``mogs node``) on ``bus``."""
    return cli_argv("node", cls, "--name", name, "--params-json", json.dumps(params), bus=bus)


def run_cli(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    """Runs ``mogs ARGS`` to its end; its output as text."""
    return subprocess.run(
        cli_argv(*args), cwd=REPO, capture_output=True, text=True, timeout=timeout_s
    )


def cli_process(bus: BusConfig, *args: str) -> subprocess.Popen:
    """``mogs ARGS`` on ``bus`` as a process, stdout and stderr together on its stdout pipe."""
    return subprocess.Popen(
        cli_argv(*args, bus=bus), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )


def start_node(cls: str, name: str, params: dict[str, Any], bus: BusConfig) -> subprocess.Popen:
    """One node process on ``bus``, its output left on the test's terminal."""
    return subprocess.Popen(node_argv(cls, name, params, bus), cwd=REPO)


def free_tcp_port() -> int:
    """A tcp port on 127.0.0.1 that nothing listens on (at the time of asking)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listening(endpoint: str) -> bool:
    if endpoint.startswith("ipc://"):
        return Path(endpoint[len("ipc://") :]).exists()
    host, port = endpoint[len("tcp://") :].rsplit(":", 1)
    with socket.socket() as s:
        return s.connect_ex((host, int(port))) == 0


def start_broker(bus: BusConfig, timeout_s: float = 10.0) -> subprocess.Popen:
    """A broker process on ``bus`` (ipc or tcp), returned once its subscriber endpoint accepts
    connections, so that what the test starts next connects at once."""
    proc = subprocess.Popen(cli_argv("broker", bus=bus), cwd=REPO)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if _listening(bus.sub_endpoint):
            return proc
        time.sleep(0.05)
    proc.kill()
    raise RuntimeError("broker did not come up")


@contextlib.contextmanager
def broker_thread(bus: BusConfig) -> Iterator[zmq.Context]:
    """``run_broker`` on ``bus`` in a thread of this process, stopped on leaving; yields the context
    it runs in (on inproc endpoints every socket of the test must use it)."""
    ctx = zmq.Context()
    stop, ready = threading.Event(), threading.Event()
    t = threading.Thread(
        target=run_broker, args=(bus, stop), kwargs={"ready": ready, "context": ctx}
    )
    t.start()
    try:
        assert ready.wait(5)
        yield ctx
    finally:
        stop.set()
        t.join(5)
        ctx.destroy(linger=0)  # a failed test may leave sockets open: term() would wait for them


def stop_process(proc: subprocess.Popen, timeout_s: float = 10.0) -> None:
    """SIGINT (the clean shutdown every ``mogs`` command handles), then SIGKILL after ``timeout_s``."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def receive_until(sub: Subscriber, pred, timeout_s: float) -> list[msgs.Envelope]:
    """Everything ``sub`` receives up to and including the first envelope ``pred`` accepts (or
    until ``timeout_s`` has passed)."""
    got: list[msgs.Envelope] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        env = sub.receive(timeout_ms=100)
        if env is not None:
            got.append(env)
            if pred(env):
                break
    return got


def receive_for(sub: Subscriber, seconds: float) -> list[msgs.Envelope]:
    """Everything ``sub`` receives in the next ``seconds`` (and nothing later: the last wait ends
    with the window, for tests that assert that nothing came during it)."""
    out, deadline = [], time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        env = sub.receive(timeout_ms=int(left * 1000) + 1)
        if env is not None:
            out.append(env)
    return out


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
            cli_argv("broker", bus=self.bus),
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


@dataclass
class WiredNode:
    """An in-process node with a publisher its inputs have subscribed to and a watcher of its
    output topic (made by the ``wired_node`` fixture, which closes all three)."""

    node: Node
    pub: Publisher
    watcher: Subscriber

    def collect(
        self, n: int, timeout_s: float, spin_ms: int = 100, receive_ms: int = 50
    ) -> list[msgs.Message]:
        """Spins the node until the watcher has received ``n`` messages or ``timeout_s`` passed."""
        got: list[msgs.Message] = []
        deadline = time.monotonic() + timeout_s
        while len(got) < n and time.monotonic() < deadline:
            self.node.spin_once(spin_ms)
            env = self.watcher.receive(timeout_ms=receive_ms)
            if env is not None:
                got.append(env.msg)
        return got

    def collect_one(self, timeout_s: float) -> msgs.Message | None:
        """The first message the node publishes within ``timeout_s``, None when none came."""
        got = self.collect(1, timeout_s)
        return got[0] if got else None

    def close(self) -> None:
        self.pub.close(0)  # open sockets would block the context's termination
        self.watcher.close()
        self.node.close()
