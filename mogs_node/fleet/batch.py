"""The batch driver: one Ray task per drive, retries, resume, progress, the fleet table.

Ray does the scheduling (``ray.remote`` tasks with ``num_cpus``, ``max_retries`` and
``retry_exceptions``; ``ray.wait`` for progress); nothing here decides where or when a drive
runs. Without an address Ray starts on this machine (``ray.init(num_cpus=...)``); with one it
joins a running cluster (``ray.init(address=...)``, e.g. ``auto`` or ``ray://host:10001``). The
run folders must be reachable from every worker under the same path (a shared or synced folder)
for the table to be written here; docs/fleet.md.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from mogs_node.errors import ConfigError
from mogs_node.fleet.drives import (
    config_digest,
    drive_overrides,
    is_complete,
    load_launch_data,
    make_drives,
    read_marker,
)
from mogs_node.fleet.table import make_row, write_csv, write_markdown, write_plot
from mogs_node.fleet.task import DriveCrashedError, DriveJob, run_drive

__all__ = ["BatchOptions", "BatchResult", "format_bar", "run_batch"]

#: Ray's object store holds only the drives' small outcome dicts
_OBJECT_STORE_BYTES = 80 * 2**20


@dataclass(frozen=True)
class BatchOptions:
    """How a batch runs (``mogs batch`` options)."""

    ray_address: str | None = None  # None: a local Ray on this machine
    num_cpus: int | None = None  # local Ray only: CPUs it may use (None: all)
    cpus_per_drive: float = 1.0  # Ray resources of one drive's task
    max_retries: int = 1  # Ray retries of a drive that crashed (not of a config error/timeout)
    timeout_s: float | None = 3600.0  # per drive; None: none
    grace_s: float = 10.0  # SIGINT -> SIGKILL of a drive's nodes when it stops
    path_param: str = "player.path"  # NODE.PARAM that takes the drive's path
    overrides: dict[str, dict] = field(default_factory=dict)  # --set, for every drive
    resume: bool = True  # skip drives whose run folder holds a complete run


@dataclass
class BatchResult:
    rows: list[dict[str, Any]]
    wall_s: float
    ran: int
    skipped: int
    out_dir: Path


def format_bar(done: int, total: int, counts: dict[str, int], elapsed_s: float, width=24) -> str:
    """``[############------------] 2/4 drives (1 complete, 1 failed) 2 to go, 1m05s``."""
    frac = 0.0 if total <= 0 else min(1.0, done / total)
    filled = int(round(frac * width))
    what = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()) if n)
    m, s = divmod(int(elapsed_s), 60)
    return (
        f"[{'#' * filled}{'-' * (width - filled)}] {done}/{total} drives"
        + (f" ({what})" if what else "")
        + f", {total - done} to go, {m}m{s:02d}s"
    )


class _Progress:
    """One line, rewritten in place on a terminal; a new line per change elsewhere (logs)."""

    def __init__(self, total: int, stream: TextIO | None) -> None:
        self.total, self.stream = total, stream
        self.tty = bool(stream is not None and getattr(stream, "isatty", lambda: False)())
        self.t0 = time.monotonic()
        self.counts: dict[str, int] = {}
        self.done = 0
        self._last = ""
        self._last_t = 0.0

    def add(self, status: str) -> None:
        self.done += 1
        self.counts[status] = self.counts.get(status, 0) + 1
        self.show(force=True)

    def show(self, force: bool = False) -> None:
        if self.stream is None:
            return
        now = time.monotonic()
        if not force and now - self._last_t < (1.0 if self.tty else 60.0):
            return
        line = "fleet " + format_bar(self.done, self.total, self.counts, now - self.t0)
        self._last_t = now
        if self.tty:
            self.stream.write("\r" + line.ljust(len(self._last)))
            if self.done == self.total:
                self.stream.write("\n")
        else:
            self.stream.write(line + "\n")
        self._last = line
        self.stream.flush()


def _outcome_of_error(err: BaseException, job: DriveJob) -> dict[str, Any]:
    """A drive's outcome from what ``ray.get`` raised: the last attempt's own outcome when it
    crashed (:class:`DriveCrashedError`), else the error Ray gives (a worker that died, ...)."""
    cause = getattr(err, "cause", None)
    if isinstance(err, DriveCrashedError) or isinstance(cause, DriveCrashedError):
        return dict((cause if isinstance(cause, DriveCrashedError) else err).result)
    marker = read_marker(Path(job.run_dir)) or {}
    first = next((ln for ln in str(err).splitlines() if ln.strip()), type(err).__name__)
    return {
        "drive": job.drive.path,
        "drive_id": job.drive.drive_id,
        "run_dir": job.run_dir,
        "status": "failed",
        "error": f"{type(err).__name__}: {first}",
        "attempt": marker.get("attempt", 0),
        "wall_s": marker.get("wall_s"),
        "host": marker.get("host", ""),
    }


@contextlib.contextmanager
def _ray_session(opts: BatchOptions):
    """Ray, started here (local) or joined (address); left as found when already initialised."""
    try:
        import ray
    except ImportError as err:
        raise ConfigError(
            "mogs batch needs Ray, an optional extra: pip install -e '.[fleet]'"
        ) from err

    started = False
    if not ray.is_initialized():
        if opts.ray_address:
            ray.init(address=opts.ray_address, log_to_driver=False)
        else:
            ray.init(
                num_cpus=opts.num_cpus,
                include_dashboard=False,
                log_to_driver=False,
                object_store_memory=_OBJECT_STORE_BYTES,
            )
        started = True
    try:
        cpus = float(ray.cluster_resources().get("CPU", 0.0))
        if opts.cpus_per_drive > cpus:
            raise ConfigError(
                f"--cpus-per-drive {opts.cpus_per_drive:g}: the Ray cluster has {cpus:g} CPUs, "
                "so no drive could ever be scheduled"
            )
        yield ray
    finally:
        if started:
            ray.shutdown()


def _submit_and_wait(
    jobs: list[DriveJob], opts: BatchOptions, progress: _Progress
) -> dict[str, dict[str, Any]]:
    """Run ``jobs`` as Ray tasks; their outcomes by drive id, as they finish."""
    outcomes: dict[str, dict[str, Any]] = {}
    with _ray_session(opts) as ray:
        task = ray.remote(run_drive).options(
            num_cpus=opts.cpus_per_drive,
            max_retries=opts.max_retries,
            retry_exceptions=[DriveCrashedError],
            name="mogs-drive",
        )
        pending = {task.remote(job): job for job in jobs}
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
                for ref in ready:
                    job = pending.pop(ref)
                    try:
                        outcome = ray.get(ref)
                    except Exception as err:  # the drive failed for good: reported, others go on
                        outcome = _outcome_of_error(err, job)
                    outcomes[job.drive.drive_id] = outcome
                    progress.add(outcome["status"])
                progress.show()
        except KeyboardInterrupt:
            for ref in pending:  # KeyboardInterrupt in the task: its launcher stops its nodes
                ray.cancel(ref)
            with contextlib.suppress(Exception):
                ray.wait(list(pending), num_returns=len(pending), timeout=opts.grace_s + 5.0)
            raise
    return outcomes


def run_batch(
    launch_path: str | Path,
    drive_paths: list[str],
    out_dir: str | Path,
    opts: BatchOptions | None = None,
    *,
    progress: TextIO | None = sys.stderr,
) -> BatchResult:
    """Map every drive with the launch file's graph; write ``fleet.csv``, ``fleet.md`` and
    ``fleet.png`` into ``out_dir`` (one run folder per drive there too)."""
    from mogs_node.launch import parse_launch

    opts = opts or BatchOptions()
    if opts.cpus_per_drive <= 0 or opts.max_retries < 0:
        raise ConfigError("mogs batch: --cpus-per-drive > 0 and --max-retries >= 0")
    launch_path = Path(launch_path).absolute()
    text, data = load_launch_data(launch_path)
    # errors of the launch file and the overrides now, before any drive starts
    parse_launch(
        data,
        path=launch_path,
        overrides=drive_overrides({}, opts.path_param, "DRIVE", opts.overrides),
    )
    drives = make_drives(drive_paths)
    out = Path(out_dir).absolute()
    out.mkdir(parents=True, exist_ok=True)
    digest = config_digest(text, opts.overrides, opts.path_param)
    batch_id = uuid.uuid4().hex[:12]
    t0 = time.monotonic()
    done: dict[str, tuple[dict[str, Any], bool]] = {}  # drive id -> (outcome, resumed)
    jobs: list[DriveJob] = []
    for d in drives:
        run_dir = out / d.drive_id
        if opts.resume and is_complete(run_dir, d, digest):
            done[d.drive_id] = (read_marker(run_dir) or {}, True)
            continue
        jobs.append(
            DriveJob(
                drive=d,
                launch_path=str(launch_path),
                launch_text=text,
                run_dir=str(run_dir),
                path_param=opts.path_param,
                overrides=opts.overrides,
                digest=digest,
                timeout_s=opts.timeout_s,
                grace_s=opts.grace_s,
                cwd=os.getcwd(),
                batch_id=batch_id,
            )
        )
    bar = _Progress(len(drives), progress)
    for outcome, _ in done.values():
        bar.add(outcome.get("status", "complete"))
    if jobs:
        for drive_id, outcome in _submit_and_wait(jobs, opts, bar).items():
            done[drive_id] = (outcome, False)
    wall_s = time.monotonic() - t0
    rows = [make_row(done[d.drive_id][0], resumed=done[d.drive_id][1]) for d in drives]
    notes = [
        f"launch file: `{launch_path}`",
        f"batch wall time: {wall_s:.1f} s for {len(jobs)} drives run, "
        f"{len(drives) - len(jobs)} skipped (complete before: resume)",
        f"Ray: {opts.ray_address or 'local'}, {opts.cpus_per_drive:g} CPU per drive, "
        f"max_retries {opts.max_retries}, per-drive timeout "
        + (f"{opts.timeout_s:g} s" if opts.timeout_s else "none"),
    ]
    write_csv(rows, out / "fleet.csv")
    write_markdown(rows, out / "fleet.md", title="MOGS fleet batch", notes=notes)
    write_plot(rows, out / "fleet.png")
    return BatchResult(rows, wall_s, len(jobs), len(drives) - len(jobs), out)
