"""The launcher: the broker and every node of a launch file (:mod:`mogs_node.launch_file`, its
format) as separate OS processes.

The launcher prefixes each child's log lines with its name, respawns crashed nodes by policy, and
on SIGINT/SIGTERM stops every child (SIGINT, then SIGKILL after a grace period) and exits 0.
Children get PR_SET_PDEATHSIG so that they never outlive a killed launcher.

Liveness (issue 23): a node's heartbeat comes from a thread of its own (:mod:`mogs_node.heartbeat`),
so a node that computes is never silent. The launcher kills (then respawns by policy) a node whose
heartbeat stopped for ``heartbeat_timeout_s`` (a dead or frozen interpreter), and a node whose
heartbeat says it has been busy without progress (``busy_s``) for ``progress_timeout_s`` (stuck in
one handler, however alive its heartbeat thread). Its figures (:meth:`Launcher.figures`: kills by
cause, respawns, the largest gap between two heartbeats of each node) go into the run's
``summary.json`` under ``launch`` and ``nodes.<name>.heartbeat_gap_max_s``.

A failure that the run cannot recover from ends it: the other nodes are stopped and the launcher
exits with code 1, its last line naming the node and its error (``[launch] run failed: ...``).
Such failures are a ``respawn: never`` node exiting non-zero, a node that cannot start with its
configuration (exit code :data:`~mogs_node.node.EXIT_CONFIG`: bad parameter, missing dataset or
model file; never respawned, whatever its policy) and a node that has used up ``max_respawns``.

Catch-up: a respawned node, and every node of a resumed run (``resume=True``, ``mogs launch
--resume RUN``), is started with ``MOGS_CATCH_UP=1``; nodes that call
:meth:`~mogs_node.node.Node.catch_up` then replay what they missed from the journal node
(:mod:`mogs_node.journal`). :func:`run_dir_overrides` points the journal, the report, the mapper's
PLY and checkpoints of a launch file at one run folder.

Disk: a run that ends cleanly (its ``exit_when`` nodes finished) needs neither its journal nor
its checkpoints any more (they exist for respawns and ``--resume``): the launcher removes them
(:func:`remove_run_state`) unless ``keep_journal`` (``mogs launch --keep-journal``). A run stopped
by Ctrl-C, a timeout or a failure keeps them, to be resumed.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zmq

from mogs_node import shm
from mogs_node.diagnosis import DIAGNOSED_TOPICS, RunDoctor
from mogs_node.launch_file import (
    LaunchFile,
    NodeSpec,
    load_launch_file,
    parse_launch,
    respawns_without_journal,
    run_dir_overrides,
)
from mogs_node.node import CATCH_UP_ENV
from mogs_node.supervision import (
    CHECKPOINT_FILES,
    EXIT_NODE_FAILED,
    JOURNAL_FILES,
    SUBMAP_FILES,
    TAIL_LINES,
    Beat,
    error_of,
    failure_reason,
    kill_reason,
    merge_launch_figures,
    remove_run_state,
)

__all__ = [
    "LaunchFile",
    "Launcher",
    "NodeSpec",
    "load_launch_file",
    "parse_launch",
    "respawns_without_journal",
    "run_dir_overrides",
]

log = logging.getLogger(__name__)


def _set_pdeathsig() -> None:  # runs in the child between fork and exec
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG: a hung node must not survive either
    except OSError:
        pass


def usable_cpus(cpus: tuple[int, ...]) -> tuple[int, ...]:
    """The CPUs of ``cpus`` this process may use (all of them where the OS has no affinity)."""
    if not cpus or not hasattr(os, "sched_getaffinity"):
        return ()
    return tuple(sorted(set(cpus) & os.sched_getaffinity(0)))


def _child_setup(nice: int, cpus: tuple[int, ...]) -> None:  # in the child, before exec
    _set_pdeathsig()
    if nice:
        os.nice(nice)
    if cpus:
        os.sched_setaffinity(0, cpus)


@dataclass
class _Child:
    name: str
    argv: list[str]
    env: dict[str, str]
    spec: NodeSpec | None
    proc: subprocess.Popen | None = None
    respawns: int = 0
    exited: int | None = None
    restart_at: float | None = None
    reader: threading.Thread | None = None
    started_at: float = 0.0
    tail: deque[str] = field(default_factory=lambda: deque(maxlen=TAIL_LINES))
    killed_pid: int | None = None  # the process the heartbeat watchdog killed
    stopped_when_killed: bool = False  # ... after it had said it stopped: a clean end


class Launcher:
    """Starts, supervises and stops the processes of a :class:`LaunchFile`."""

    def __init__(
        self,
        launch: LaunchFile,
        *,
        out=None,
        grace_s: float = 3.0,
        resume: bool = False,
        diagnose: bool = True,
        keep_journal: bool = False,
    ) -> None:
        self.launch = launch
        self.keep_journal = keep_journal
        self._state: list[tuple[Path, tuple[str, ...]]] = []  # removed after a clean end
        self.diagnose = diagnose  # say why no keyframe / no depth comes (mogs_node.diagnosis)
        self.resume = resume
        self.out = out or sys.stdout
        self.grace_s = grace_s
        self._stop = threading.Event()
        self._out_lock = threading.Lock()
        self.children: list[_Child] = []
        self.failure: str | None = None  # "NODE REASON: ERROR" of a failure that ended the run
        self._heartbeats: dict[str, Beat] = {}  # node -> its latest heartbeat
        self._gap_max_s: dict[str, float] = {}  # node -> largest interval between two heartbeats
        self._hb_lock = threading.Lock()
        self.kills: dict[str, int] = {"heartbeat": 0, "progress": 0}  # by cause
        bus_json = json.dumps(launch.bus.to_dict())
        py = sys.executable
        self._common_env: dict[str, str] = {}
        # catch-up needs a journal to catch up from
        self._has_journal = any(s.cls.endswith(":JournalNode") for s in launch.nodes)
        for spec in launch.nodes:  # an explicit journal endpoint: every node must know it
            if spec.cls.endswith(":JournalNode") and spec.params.get("endpoint"):
                self._common_env["MOGS_JOURNAL_ENDPOINT"] = str(spec.params["endpoint"])
        if launch.start_broker:
            argv = [py, "-m", "mogs_node.cli", "broker", "--bus-json", bus_json]
            if launch.allow_remote:
                argv.append("--allow-remote")
            self.children.append(_Child("broker", argv, {}, None))
        self.report_dir: Path | None = None  # summary.json there gets the launcher's figures
        report_dir = next(
            (
                s.params.get("out_dir", "runs/latest")
                for s in launch.nodes
                if s.cls.endswith(":RunReportNode")
            ),
            None,
        )
        if report_dir:
            self.report_dir = Path(report_dir)
        for spec in launch.nodes:
            params = dict(spec.params)
            if spec.cls.endswith(":JournalNode") and "dir" not in params and report_dir:
                params["dir"] = str(Path(report_dir) / "journal")  # the run's state in one folder
            if spec.cls.endswith(":JournalNode") and params.get("dir"):
                self._state.append((Path(params["dir"]), JOURNAL_FILES))
            if params.get("checkpoint_dir"):
                ck = Path(params["checkpoint_dir"])
                self._state.append((ck / "submaps", SUBMAP_FILES))  # the mapper's offloaded regions
                self._state.append((ck, CHECKPOINT_FILES))
            if spec.host not in ("localhost", "127.0.0.1", os.uname().nodename):
                log.info("node %s runs on host %s: not started here", spec.name, spec.host)
                continue
            argv = [
                py,
                "-m",
                "mogs_node.cli",
                "node",
                spec.cls,
                "--name",
                spec.name,
                "--params-json",
                json.dumps(params),
                "--bus-json",
                bus_json,
            ]
            self.children.append(_Child(spec.name, argv, spec.env, spec))

    def _print(self, line: str) -> None:
        with self._out_lock:
            self.out.write(line if line.endswith("\n") else line + "\n")
            self.out.flush()

    def _pump(self, child: _Child, stream) -> None:
        width = max(len(c.name) for c in self.children)
        for raw in iter(stream.readline, b""):
            line = raw.decode(errors="replace").rstrip()
            child.tail.append(line)
            self._print(f"[{child.name:<{width}}] {line}")
        stream.close()

    def _start(self, child: _Child) -> None:
        env = dict(os.environ)
        env.update(self._common_env)
        env.update(child.env)
        env["PYTHONUNBUFFERED"] = "1"
        # a respawned node, or any node of a resumed run, catches up from the journal
        restart = child.respawns > 0 or self.resume
        env[CATCH_UP_ENV] = "1" if restart and self._has_journal else "0"
        nice, cpus = self._cpu_priority(child)
        child.proc = subprocess.Popen(
            child.argv,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            start_new_session=True,
            preexec_fn=functools.partial(_child_setup, nice, cpus),
        )
        child.exited = None
        child.restart_at = None
        child.started_at = time.monotonic()
        child.tail.clear()
        child.reader = threading.Thread(
            target=self._pump, args=(child, child.proc.stdout), daemon=True
        )
        child.reader.start()
        self._print(f"[launch] started {child.name} (pid {child.proc.pid})")

    def _cpu_priority(self, child: _Child) -> tuple[int, tuple[int, ...]]:
        """The child's niceness and CPUs (those of the launch file this machine has)."""
        spec = child.spec
        if spec is None:
            return 0, ()
        cpus = usable_cpus(spec.cpus)
        if spec.cpus and not cpus and child.respawns == 0:
            self._print(
                f"[launch] {spec.name}: none of cpus {list(spec.cpus)} is usable here "
                "(or the OS has no CPU affinity): it runs on every CPU"
            )
        return spec.nice, cpus

    def request_stop(self) -> None:
        self._stop.set()

    def run(self, *, install_signal_handlers: bool = True, timeout_s: float | None = None) -> int:
        """Run until a signal, ``exit_when`` nodes finished, or ``timeout_s``; returns exit code."""
        if install_signal_handlers:
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda *_: self._stop.set())
        end = None if timeout_s is None else time.monotonic() + timeout_s
        code = 0
        finished = False  # the exit_when nodes finished: a clean end
        watcher = threading.Thread(
            target=self._watch_heartbeats, name="mogs-heartbeats", daemon=True
        )
        watcher.start()
        try:
            for i, child in enumerate(self.children):
                self._start(child)
                if i == 0 and child.name == "broker":
                    time.sleep(0.3)  # let the broker bind before nodes connect
            while not self._stop.wait(0.1):
                if end is not None and time.monotonic() > end:
                    self._print("[launch] timeout reached")
                    code = 124
                    break
                if self._supervise():
                    finished = self.failure is None
                    break
        finally:
            self._stop.set()
            watcher.join(timeout=2.0)  # its last word: why the run made no keyframe, if so
            self.shutdown()
        if self.report_dir is not None:
            merge_launch_figures(self.report_dir / "summary.json", self.figures())
        if self.failure is not None:
            self._print(f"[launch] run failed: {self.failure}")
            return EXIT_NODE_FAILED
        freed = 0
        if finished and self._state and not self.keep_journal:
            freed = remove_run_state(self._state)
        if freed:
            self._print(
                f"[launch] run complete: removed its journal and checkpoints ({freed / 2**20:.1f} "
                "MiB; --keep-journal keeps them)"
            )
        return code

    def _watch_heartbeats(self) -> None:
        """Record the last /diagnostics heartbeat of every node and, with ``diagnose``, say why
        no keyframe or no depth comes (:mod:`mogs_node.diagnosis`; runs in a thread)."""
        from mogs_node import msgs
        from mogs_node.bus import Subscriber

        doctor = RunDoctor() if self.diagnose else None
        ctx = zmq.Context()
        try:
            sub = Subscriber(self.launch.bus, context=ctx)
            sub.subscribe("/diagnostics")
            for topic in DIAGNOSED_TOPICS if doctor is not None else ():
                sub.subscribe(topic)
            next_check = time.monotonic() + 1.0
            while not self._stop.is_set():
                env = sub.receive(timeout_ms=200)
                now = time.monotonic()
                if env is not None and isinstance(env.msg, msgs.Diagnostics):
                    self._on_heartbeat(env.msg, now)
                if doctor is None:
                    continue
                lines = [] if env is None else doctor.observe(env.topic, env.msg, now)
                if now >= next_check:
                    next_check = now + 1.0
                    lines += doctor.check(now)
                for line in lines:
                    self._print(f"[launch] {line}")
            for line in doctor.at_end() if doctor is not None else ():
                self._print(f"[launch] {line}")
            sub.close()
        except Exception:  # supervision by exit codes goes on without heartbeats
            log.exception("heartbeat watcher stopped")
        finally:
            ctx.term()

    def _on_heartbeat(self, msg: Any, now: float) -> None:
        """Record a node's heartbeat and the gap since its previous one (same process)."""
        busy = float(msg.counters.get("busy_s", 0.0))
        what = msg.status.removeprefix("busy: ") if msg.status.startswith("busy: ") else ""
        with self._hb_lock:
            prev = self._heartbeats.get(msg.node)
            if prev is not None and prev.pid == msg.pid and msg.status != "stopped":
                gap = now - prev.t
                self._gap_max_s[msg.node] = max(self._gap_max_s.get(msg.node, 0.0), gap)
            self._heartbeats[msg.node] = Beat(now, msg.pid, busy, what, msg.status == "stopped")

    def _check_heartbeat(self, child: _Child, now: float) -> None:
        """Kill a running node that is hung (no heartbeat) or stuck (busy without progress);
        the respawn policy then applies."""
        spec = child.spec
        if spec is None or child.proc is None or child.exited is not None:
            return
        if child.killed_pid == child.proc.pid:  # killed, not yet reaped: said once
            return
        with self._hb_lock:
            seen = self._heartbeats.get(child.name)
        if seen is None or seen.pid != child.proc.pid:
            seen = None  # not heard from this process yet: start-up (imports, model loading)
        why = kill_reason(seen, now, started_at=child.started_at, timeouts=spec)
        if why is None:
            return
        cause, text = why
        self.kills[cause] += 1
        self._print(f"[launch] {child.name} {text}: killing it")
        child.killed_pid = child.proc.pid
        child.stopped_when_killed = bool(seen is not None and seen.stopped)
        child.proc.kill()

    def figures(self) -> dict[str, Any]:
        """The launcher's figures of the run: kills by cause, respawns per node, and the largest
        interval between two heartbeats of each node (seconds, as received here)."""
        with self._hb_lock:
            gaps = dict(self._gap_max_s)
        return {
            "launch": {
                "heartbeat_kills": self.kills["heartbeat"],
                "progress_kills": self.kills["progress"],
                "respawns": {c.name: c.respawns for c in self.children if c.respawns},
            },
            "nodes": {n: {"heartbeat_gap_max_s": round(g, 3)} for n, g in sorted(gaps.items())},
        }

    def _supervise(self) -> bool:
        """Reap, respawn; True when the launch is complete (exit_when nodes done)."""
        now = time.monotonic()
        for child in self.children:
            if child.proc is None:
                continue
            self._check_heartbeat(child, now)
            if child.exited is None:
                rc = child.proc.poll()
                if rc is None:
                    continue
                if rc < 0 and child.stopped_when_killed and child.killed_pid == child.proc.pid:
                    self._print(f"[launch] {child.name} had stopped; its exit was cut short")
                    rc = 0  # its work was done: not a failure
                child.exited = rc
                self._print(f"[launch] {child.name} exited with code {rc}")
                if self._on_exit(child, rc, now):
                    return True
            if child.restart_at is not None and now >= child.restart_at:
                child.respawns += 1
                self._print(f"[launch] respawning {child.name} ({child.respawns})")
                self._start(child)
        if self.launch.exit_when:
            done = all(c.exited == 0 for c in self.children if c.name in self.launch.exit_when)
            if done:
                self._print("[launch] " + ", ".join(self.launch.exit_when) + " finished")
                return True
        return False

    def _on_exit(self, child: _Child, rc: int, now: float) -> bool:
        """Schedule a respawn by policy, or record a failure that ends the run (True)."""
        policy = "always" if child.spec is None else child.spec.respawn
        max_r = 1000 if child.spec is None else child.spec.max_respawns
        reason = failure_reason(rc, policy=policy, respawns=child.respawns, max_respawns=max_r)
        if reason is None:
            respawn = policy == "always" or (policy == "on_failure" and rc != 0)
            if respawn and child.respawns < max_r:
                child.restart_at = now + (0.2 if child.spec is None else child.spec.respawn_delay_s)
            return False
        if child.reader is not None:  # its last lines hold the error
            child.reader.join(timeout=1.0)
        error = error_of(child.tail)
        self.failure = f"{child.name} {reason}" + (f": {error}" if error else "")
        self._print(f"[launch] {self.failure}; stopping every node")
        return True

    def shutdown(self) -> None:
        """SIGINT to every node (broker last), SIGKILL what is left after the grace period."""
        nodes = [c for c in self.children if c.name != "broker"]
        broker = [c for c in self.children if c.name == "broker"]
        for group in (nodes, broker):
            live = [c for c in group if c.proc is not None and c.proc.poll() is None]
            for c in live:
                with contextlib.suppress(ProcessLookupError):
                    c.proc.send_signal(signal.SIGINT)
            deadline = time.monotonic() + self.grace_s
            for c in live:
                try:
                    c.proc.wait(timeout=max(0.05, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    self._print(f"[launch] {c.name} did not stop in {self.grace_s} s: killing")
                    c.proc.kill()
                    c.proc.wait()
        for c in self.children:
            if c.reader is not None:
                c.reader.join(timeout=1.0)
        if self.launch.bus.uses_shm:  # what killed nodes left in /dev/shm
            shm.sweep_stale()
        self._print("[launch] all processes stopped")
