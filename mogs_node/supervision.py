"""What the launcher decides when a node exits, and what a finished run no longer needs (issue 18).

- :func:`failure_reason`: whether an exit ends the run (a ``respawn: never`` node failing, a node
  that cannot start with its configuration, :data:`~mogs_node.node.EXIT_CONFIG`, never respawned,
  a node out of respawns) or a respawn is due;
- :func:`error_of`: the error line to name, from the last lines a node printed;
- :func:`remove_run_state`: the journal and checkpoint files of a run that ended cleanly;
- :func:`kill_reason`: whether a running node is hung (no heartbeat) or stuck (busy without
  progress), from its latest heartbeat (issue 23);
- :func:`merge_launch_figures`: the launcher's figures into a run's ``summary.json``.

Pure decisions over exit codes and text, plus one file-removal helper; no processes, no bus.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from mogs_node.node import EXIT_CONFIG

__all__ = [
    "Beat",
    "CHECKPOINT_FILES",
    "EXIT_NODE_FAILED",
    "JOURNAL_FILES",
    "LivenessTimeouts",
    "SUBMAP_FILES",
    "error_of",
    "failure_reason",
    "kill_reason",
    "merge_launch_figures",
    "remove_run_state",
]

#: exit code of ``mogs launch`` when a node failed in a way that ends the run
EXIT_NODE_FAILED = 1
#: lines of a child's output kept to name its error when it fails
TAIL_LINES = 40
#: a log line at level ERROR / CRITICAL (format of mogs_node.cli) or the last line of a traceback
_LOG_ERROR = re.compile(r"^\d\d:\d\d:\d\d [EC] \S+: (?P<msg>.+)$")
_LOG_OTHER = re.compile(r"^\d\d:\d\d:\d\d [DIW] ")
_TRACEBACK_END = re.compile(r"^(?:[A-Za-z_][\w.]*\.)?[A-Z]\w*(?:Error|Exception|Exit): .+$")

#: files of a run's state, per kind of folder: the journal's, and a checkpoint_dir's (the mapper's
#: mapper.ckpt, one moved aside as corrupt, a temporary file of an interrupted save)
JOURNAL_FILES = ("journal.log",)
CHECKPOINT_FILES = ("*.ckpt", "*.ckpt.corrupt", ".*.ckpt.*.tmp")
#: files of a mapper's ``checkpoint_dir/submaps`` (regions of a long drive offloaded to disk)
SUBMAP_FILES = ("submap_*.pt", ".submap_*.tmp")


def remove_run_state(folders: list[tuple[Path, tuple[str, ...]]]) -> int:
    """Delete the files matching each folder's patterns, then the folder if it is left empty;
    returns the bytes freed. Only these files: a folder a user pointed elsewhere keeps the rest."""
    freed = 0
    for folder, patterns in folders:
        if not folder.is_dir():
            continue
        for pattern in patterns:
            for f in folder.glob(pattern):
                if f.is_file():
                    freed += f.stat().st_size
                    f.unlink(missing_ok=True)
        with contextlib.suppress(OSError):  # not empty: something else lives there
            folder.rmdir()
    return freed


def error_of(lines: list[str] | deque[str]) -> str:
    """The error a failed process printed: its last ERROR/CRITICAL log line, else the last line
    of a traceback, else its last line that is not a debug / info / warning log line ("" when
    there is none)."""
    last_traceback = ""
    for line in reversed(lines):
        m = _LOG_ERROR.match(line)
        if m:
            return m.group("msg").removeprefix("cannot start: ")
        if not last_traceback and _TRACEBACK_END.match(line):
            last_traceback = line
    if last_traceback:
        return last_traceback
    return next((ln for ln in reversed(lines) if ln.strip() and not _LOG_OTHER.match(ln)), "")


def failure_reason(rc: int, *, policy: str, respawns: int, max_respawns: int) -> str | None:
    """Why a node's exit with code ``rc`` ends the run, or None when it does not (exit 0, or a
    respawn is due). A configuration failure (:data:`~mogs_node.node.EXIT_CONFIG`) is never
    respawned: the same parameters would fail again."""
    if rc == 0:
        return None
    if rc == EXIT_CONFIG:
        return f"could not start with its configuration (exit code {rc})"
    how = f"was killed by {_signal_name(-rc)}" if rc < 0 else f"exited with code {rc}"
    if policy == "never":
        return f"{how} (respawn: never)"
    if respawns >= max_respawns:
        return f"{how} after {respawns} respawns (max_respawns {max_respawns})"
    return None


def _signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


@dataclass(frozen=True)
class Beat:
    """A node's latest heartbeat as the launcher received it."""

    t: float  # monotonic time of arrival
    pid: int
    busy_s: float  # seconds its run loop had then been busy without progress (0: idle)
    busy_with: str = ""  # what it was busy with ("handler of /topic", "timer name")
    stopped: bool = False  # its last heartbeat said "stopped": it is exiting


#: a node that said it stopped has this many heartbeat timeouts to exit (its teardown and the
#: interpreter's exit send no heartbeat; on a machine at load ~100 they took over 30 s)
STOPPED_EXIT_TIMEOUTS = 4


class LivenessTimeouts(Protocol):
    """A node's liveness timeouts in seconds, 0 = check off (a launch file's ``NodeSpec``)."""

    heartbeat_timeout_s: float
    progress_timeout_s: float
    startup_timeout_s: float


def kill_reason(
    beat: Beat | None, now: float, *, started_at: float, timeouts: LivenessTimeouts
) -> tuple[str, str] | None:
    """``(cause, text)`` when a running node must be killed, else None.

    ``beat``: the node's latest heartbeat from its current process (None: none yet); the
    timeouts are those of ``timeouts`` (the node's spec). Causes:
    ``"heartbeat"``, silent for ``heartbeat_timeout_s`` (before its first heartbeat: for the
    larger of that and ``startup_timeout_s``); ``"progress"``, busy without progress for
    ``progress_timeout_s`` (its reported ``busy_s`` plus the time since that heartbeat). A timeout
    of 0 turns that check off. A node whose last heartbeat said "stopped" is exiting: it is killed
    only after :data:`STOPPED_EXIT_TIMEOUTS` heartbeat timeouts.
    """
    heartbeat_timeout_s = timeouts.heartbeat_timeout_s
    progress_timeout_s = timeouts.progress_timeout_s
    if beat is None:
        startup_timeout_s = timeouts.startup_timeout_s
        silent = now - started_at
        timeout = max(heartbeat_timeout_s, startup_timeout_s) if heartbeat_timeout_s > 0 else 0
        if timeout > 0 and silent > timeout:
            return "heartbeat", f"sent no heartbeat for {silent:.1f} s since it started"
        return None
    silent = now - beat.t
    if beat.stopped:  # exiting: only an exit that never ends is killed
        if heartbeat_timeout_s > 0 and silent > STOPPED_EXIT_TIMEOUTS * heartbeat_timeout_s:
            return "heartbeat", f"stopped but did not exit in {silent:.1f} s"
        return None
    if heartbeat_timeout_s > 0 and silent > heartbeat_timeout_s:
        return "heartbeat", f"sent no heartbeat for {silent:.1f} s"
    if progress_timeout_s > 0 and beat.busy_s > 0:
        stuck = beat.busy_s + silent
        if stuck > progress_timeout_s:
            what = f" ({beat.busy_with})" if beat.busy_with else ""
            return "progress", f"made no progress for {stuck:.1f} s{what}"
    return None


def merge_launch_figures(summary_path: Path, figures: dict[str, Any]) -> bool:
    """Add the launcher's ``figures`` (``launch`` and ``nodes.<name>.*``) to a run's
    ``summary.json`` if the run wrote one; returns whether it did. Written atomically."""
    if not summary_path.is_file():
        return False
    try:
        summary = json.loads(summary_path.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    if not isinstance(summary, dict):
        return False
    summary["launch"] = figures.get("launch", {})
    nodes = summary.setdefault("nodes", {})
    for name, values in figures.get("nodes", {}).items():
        nodes.setdefault(name, {}).update(values)
    tmp = summary_path.with_name(f".{summary_path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(summary, indent=2, default=float) + "\n")
    os.replace(tmp, summary_path)
    return True
