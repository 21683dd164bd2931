"""One drive: the launch file's whole node graph, run by the launcher on the worker it lands on.

:func:`run_drive` is the body of a batch's Ray task (:mod:`mogs_node.fleet.batch`); it is plain
Python and runs without Ray too (the tests call it directly). Each drive gets

- its own bus: ipc endpoints in a fresh folder (``MOGS_BUS_DIR``, :func:`mogs_node.bus.
  default_bus_config`), so drives on one host never see each other's messages (their journal
  endpoint and shared-memory cursors derive from those endpoints);
- its own run folder: report, map, journal and checkpoints there
  (:func:`mogs_node.launch.run_dir_overrides`), the launcher's log in ``launch.log``, and the
  outcome in ``drive.json`` (:data:`~mogs_node.fleet.drives.MARKER`).

What is retried (by Ray, ``retry_exceptions=[DriveCrashedError]``): a run that a node's crash ended
(:class:`DriveCrashedError`). Not retried, because a new attempt would fail the same way: a node that
cannot start with its configuration (a wrong drive path, a bad parameter: exit code
:data:`~mogs_node.node.EXIT_CONFIG`) and a run that reached the per-drive timeout.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import tempfile
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mogs_node.fleet.drives import MARKER, Drive, drive_overrides
from mogs_node.node import EXIT_CONFIG
from mogs_node.supervision import failure_reason

__all__ = ["DriveCrashedError", "DriveJob", "run_drive"]

#: the launcher's words for a node that cannot start with its configuration (never retried)
_CONFIG_FAILURE = failure_reason(EXIT_CONFIG, policy="never", respawns=0, max_respawns=0) or ""
#: the launcher's exit code when its timeout is reached
_TIMEOUT_CODE = 124


class DriveCrashedError(RuntimeError):
    """A drive's run ended by a node's crash: worth another attempt. ``result`` is the attempt's
    outcome (what the table shows when the last attempt fails too)."""

    def __init__(self, result: dict[str, Any]) -> None:
        super().__init__(result.get("error", "drive failed"))
        self.result = result

    def __reduce__(self):  # pickled across processes with its result
        return (DriveCrashedError, (self.result,))


@dataclass(frozen=True)
class DriveJob:
    """Everything a worker needs to run one drive (the launch file travels as text)."""

    drive: Drive
    launch_path: str
    launch_text: str
    run_dir: str
    path_param: str = "player.path"
    overrides: dict[str, dict] = field(default_factory=dict)
    digest: str = ""
    timeout_s: float | None = None
    grace_s: float = 10.0
    cwd: str = ""  # relative paths of the launch file resolve here, as in `mogs launch`
    batch_id: str = ""


def _count_attempt(run_dir: Path, batch_id: str) -> int:
    """Record this attempt; how many this batch has made of the drive (1 = the first)."""
    log = run_dir / "attempts.log"
    with log.open("a") as f:
        f.write(f"{batch_id} {socket.gethostname()} {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")
    return sum(1 for line in log.read_text().splitlines() if line.split(" ", 1)[0] == batch_id)


@contextlib.contextmanager
def _own_bus_dir():
    """A fresh ``MOGS_BUS_DIR`` for one drive (short: ipc paths are limited to ~100 bytes)."""
    root = Path(tempfile.gettempdir()) / f"mogs-fleet-{os.getuid()}"
    root.mkdir(mode=0o700, exist_ok=True)
    bus_dir = root / uuid.uuid4().hex[:12]
    bus_dir.mkdir(mode=0o700)
    old = os.environ.get("MOGS_BUS_DIR")
    os.environ["MOGS_BUS_DIR"] = str(bus_dir)
    try:
        yield bus_dir
    finally:
        if old is None:
            os.environ.pop("MOGS_BUS_DIR", None)
        else:
            os.environ["MOGS_BUS_DIR"] = old
        shutil.rmtree(bus_dir, ignore_errors=True)


@contextlib.contextmanager
def _working_dir(path: str):
    old = os.getcwd()
    if path and Path(path).is_dir():
        os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)


def _launch(job: DriveJob, run_dir: Path, log) -> tuple[int, str | None]:
    """Parse the launch file for this drive and run it; (exit code, failure text)."""
    from mogs_node.errors import MogsError
    from mogs_node.launch import Launcher, parse_launch, run_dir_overrides

    path = Path(job.launch_path)
    try:
        data = yaml.safe_load(job.launch_text)
        base = parse_launch(data, path=path)
        overrides = drive_overrides(
            run_dir_overrides(base, run_dir, resume=False),
            job.path_param,
            job.drive.path,
            job.overrides,
        )
        launch = parse_launch(data, path=path, overrides=overrides)
    except MogsError as err:  # the launch file or an override is wrong: a config failure
        return 1, f"launch file {path}: {_CONFIG_FAILURE}: {err}"
    launcher = Launcher(launch, out=log, grace_s=job.grace_s)
    code = launcher.run(install_signal_handlers=False, timeout_s=job.timeout_s)
    return code, launcher.failure


def run_drive(job: DriveJob) -> dict[str, Any]:
    """Run one drive to its end; its outcome (also written to ``drive.json``). Raises
    :class:`DriveCrashedError` when a node's crash ended it (the caller may retry)."""
    run_dir = Path(job.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    for stale in (MARKER, "summary.json"):  # a new attempt: no figures of an earlier one
        (run_dir / stale).unlink(missing_ok=True)
    attempt = _count_attempt(run_dir, job.batch_id)
    t0 = time.monotonic()
    with (
        _own_bus_dir(),
        _working_dir(job.cwd),
        (run_dir / "launch.log").open("a" if attempt > 1 else "w") as log,
    ):
        log.write(f"[fleet] drive {job.drive.path}, attempt {attempt} on {socket.gethostname()}\n")
        code, failure = _launch(job, run_dir, log)
    wall_s = time.monotonic() - t0
    has_summary = (run_dir / "summary.json").exists()
    if code == 0 and has_summary:
        status, error = "complete", ""
    elif code == _TIMEOUT_CODE:
        status, error = "timeout", f"timed out after {job.timeout_s:g} s (per-drive timeout)"
    else:
        status = "failed"
        error = failure or (
            f"launcher exited with code {code}"
            if code
            else "the run ended without a summary.json (does the launch file have a report node?)"
        )
    result = {
        "drive": job.drive.path,
        "drive_id": job.drive.drive_id,
        "run_dir": str(run_dir),
        "status": status,
        "error": error,
        "exit_code": code,
        "attempt": attempt,
        "wall_s": round(wall_s, 3),
        "host": socket.gethostname(),
        "digest": job.digest,
        "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    (run_dir / MARKER).write_text(json.dumps(result, indent=2) + "\n")
    if status == "failed" and code != 0 and _CONFIG_FAILURE not in error:
        raise DriveCrashedError(result)
    return result
