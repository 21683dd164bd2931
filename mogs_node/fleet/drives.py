"""Drives of a batch: the list, their ids and run folders, what a drive's launch is, resume.

Pure helpers (no Ray, no processes): the batch driver (:mod:`mogs_node.fleet.batch`) and the
task that runs a drive (:mod:`mogs_node.fleet.task`) share them.

A drive is a path that the launch file's player reads (``--set player.path=DRIVE``): a KITTI /
EuRoC / sim folder or a bag. Its run folder is ``OUT/<drive id>``; the id is the path's last
component plus a short hash of the whole absolute path, so two drives named alike never share a
folder and the same drive always maps to the same folder (what resume relies on).
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from mogs_node.errors import ConfigError

__all__ = [
    "MARKER",
    "PATIENT_PLAYER",
    "Drive",
    "check_launch_for_fleet",
    "config_digest",
    "drive_overrides",
    "make_drives",
    "read_drive_list",
    "write_sim_drives",
    "read_marker",
    "is_complete",
]

#: player overrides that make a run's figures independent of the machine's load: the player waits
#: for every node to be up and for every acknowledgement however long it takes (by default it
#: plays after 60 s without the slowest node's heartbeat: the report then misses the first frames
#: and keyframes, and two runs of one drive differ; measured on 2 loaded cores). For the fleet
#: test and bench/fleet.py, which compare a batch's figures with single runs'.
PATIENT_PLAYER = {"player": {"wait_for_nodes_s": 1800.0, "ack_timeout_s": 1800.0}}
#: written by the task into a drive's run folder when its run has ended: status, error, wall time
MARKER = "drive.json"
_NAME_CHARS = re.compile(r"[^A-Za-z0-9_.-]+")


@dataclass(frozen=True)
class Drive:
    """One drive of a batch: its absolute path and its run folder's name."""

    path: str
    drive_id: str


def read_drive_list(paths: list[str], list_files: list[str] = ()) -> list[str]:
    """Drive paths from the command line and from text files (one path a line, ``#`` comments and
    blank lines ignored; relative paths are relative to the list file's folder)."""
    out = list(paths)
    for f in list_files:
        p = Path(f)
        try:
            text = p.read_text()
        except OSError as err:
            raise ConfigError(f"--drives-from {p}: cannot read it: {err}") from err
        for line in text.splitlines():
            line = line.split("#", 1)[0].strip()
            if line:
                q = Path(line).expanduser()
                out.append(str(q if q.is_absolute() else p.parent / q))
    if not out:
        raise ConfigError("mogs batch: no drives given (DRIVE... or --drives-from FILE)")
    return out


def drive_id(path: str) -> str:
    """``<last component>-<6 hex of the absolute path's sha1>``, safe as a folder name."""
    p = Path(path).expanduser().absolute()
    name = _NAME_CHARS.sub("_", p.name or "drive").strip("_.")[:32] or "drive"
    return f"{name}-{hashlib.sha1(str(p).encode()).hexdigest()[:6]}"


def make_drives(paths: list[str]) -> list[Drive]:
    """Absolute paths and ids; a drive given twice is an error (its runs would share a folder)."""
    drives: list[Drive] = []
    seen: dict[str, str] = {}
    for raw in paths:
        if not raw.strip():
            raise ConfigError("mogs batch: an empty drive path")
        path = str(Path(raw).expanduser().absolute())
        if path in seen:
            raise ConfigError(f"mogs batch: drive {raw!r} is given twice")
        seen[path] = raw
        drives.append(Drive(path, drive_id(path)))
    return drives


def check_launch_for_fleet(data: Any, where: str) -> None:
    """A batch runs many copies of one launch file at once: each drive gets its own ipc bus, so
    the file must not fix its endpoints, and all its nodes must run where the drive runs."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping at top level")
    bus = data.get("bus") or {}
    fixed = sorted(k for k in ("pub_endpoint", "sub_endpoint") if k in bus)
    if fixed:
        raise ConfigError(
            f"{where}: bus.{fixed[0]} is set; in a batch every drive gets its own ipc bus, so "
            "drives never see each other's messages: remove the launch file's bus endpoints"
        )
    for i, node in enumerate(data.get("nodes") or []):
        host = node.get("host", "localhost") if isinstance(node, dict) else "localhost"
        if host != "localhost":
            raise ConfigError(
                f"{where}.nodes[{i}].host: {host!r}; a drive's whole graph runs on the worker "
                "its Ray task lands on: use localhost"
            )


def drive_overrides(
    base: dict[str, dict], path_param: str, drive_path: str, user: dict[str, dict]
) -> dict[str, dict]:
    """The parameter overrides of one drive: ``base`` (its run folder, from
    :func:`mogs_node.launch.run_dir_overrides`), the drive's path as ``path_param``
    (``NODE.PARAM``), then the user's ``--set`` (which wins, as in ``mogs launch``)."""
    node, dot, param = path_param.partition(".")
    if not (dot and node and param):
        raise ConfigError(f"--path-param {path_param!r}: expected NODE.PARAM")
    out = {k: dict(v) for k, v in base.items()}
    out.setdefault(node, {})[param] = drive_path
    for n, params in user.items():
        out.setdefault(n, {}).update(params)
    return out


def config_digest(launch_text: str, overrides: dict[str, dict], path_param: str) -> str:
    """What a finished drive was run with: the launch file's text, the user's overrides and the
    parameter that takes the drive's path; resume re-runs a drive whose digest changed."""
    blob = json.dumps([launch_text, overrides, path_param], sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:16]


def read_marker(run_dir: Path) -> dict[str, Any] | None:
    """The drive's :data:`MARKER`, or None when absent or unreadable."""
    try:
        data = json.loads((run_dir / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def is_complete(run_dir: Path, drive: Drive, digest: str) -> bool:
    """A finished run of this drive with this configuration: its marker says ``complete`` and
    its ``summary.json`` (written by the report node) is there and parses."""
    marker = read_marker(run_dir)
    if not marker or marker.get("status") != "complete":
        return False
    if marker.get("drive") != drive.path or marker.get("digest") != digest:
        return False
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(summary, dict) and "keyframes" in summary


def load_launch_data(path: Path) -> tuple[str, dict]:
    """The launch file's text and parsed YAML; errors name the file."""
    try:
        text = path.read_text()
        data = yaml.safe_load(text)
    except OSError as err:
        raise ConfigError(f"cannot read launch file {path}: {err}") from err
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: invalid YAML: {err}") from err
    check_launch_for_fleet(data, str(path))
    return text, data


def write_sim_drives(
    out_dir: str | Path,
    seeds: list[int],
    *,
    n_frames: int = 30,
    size: tuple[int, int] = (621, 188),
    static_start_s: float = 1.0,
) -> list[Path]:
    """Tiny synthetic drives with ground truth (``mogs sim --format mcap``), one per seed, for
    ``launch/bag.yaml`` (whose frontend defaults are the sim rig at 621x188): the bag carries the
    ground-truth poses and depth, so the table gets depth AbsRel and ATE. For tests and
    bench/fleet.py; a folder per drive, ``OUT/sim_seed<N>``."""
    from mogs_node.datasets.writers import write_sim_bag
    from mogs_node.sim import SimConfig, make_sequence

    out = Path(out_dir)
    paths = []
    for seed in seeds:
        cfg = SimConfig(
            seed=seed,
            n_frames=n_frames,
            width=size[0],
            height=size[1],
            static_start_s=static_start_s,
        )
        paths.append(Path(write_sim_bag(make_sequence(cfg), out / f"sim_seed{seed}", fmt="mcap")))
    return paths
