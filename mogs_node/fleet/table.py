"""The fleet table: one row per drive (``fleet.csv``, ``fleet.md``) and a plot across drives.

A row joins a drive's outcome (``drive.json``: status, error, attempts, wall time) with the
figures of its run report (``summary.json``: keyframes, depth AbsRel / coverage and ATE where the
drive has ground truth, Gaussians, held-out PSNR). A figure the drive does not have (no ground
truth, a failed run) is left empty, never zero.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

__all__ = [
    "COLUMNS",
    "comparable_figures",
    "make_row",
    "write_csv",
    "write_markdown",
    "write_plot",
]

#: the table's columns, in order
COLUMNS = (
    "drive",
    "status",
    "resumed",
    "attempts",
    "keyframes",
    "depth_absrel",
    "depth_coverage",
    "ate_se3_rmse_m",
    "ate_sim3_rmse_m",
    "gaussians",
    "heldout_psnr_db",
    "wall_s",
    "host",
    "run_dir",
    "error",
)


def _get(d: dict[str, Any], *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    if isinstance(d, float) and not math.isfinite(d):
        return None
    return d


def make_row(outcome: dict[str, Any], *, resumed: bool = False) -> dict[str, Any]:
    """The table row of one drive from its outcome (:func:`mogs_node.fleet.task.run_drive`);
    the figures are read from ``summary.json`` in its run folder when the drive completed."""
    summary: dict[str, Any] = {}
    if outcome.get("status") == "complete":
        try:
            summary = json.loads((Path(outcome["run_dir"]) / "summary.json").read_text())
        except (OSError, ValueError, KeyError):
            summary = {}
    return {
        "drive": outcome.get("drive", ""),
        "status": outcome.get("status", "failed"),
        "resumed": resumed,
        "attempts": outcome.get("attempt", 0),
        "keyframes": _get(summary, "keyframes"),
        "depth_absrel": _get(summary, "depth", "absrel"),
        "depth_coverage": _get(summary, "depth", "coverage"),
        "ate_se3_rmse_m": _get(summary, "trajectory", "ate_se3_rmse_m"),
        "ate_sim3_rmse_m": _get(summary, "trajectory", "ate_sim3_rmse_m"),
        "gaussians": _get(summary, "map", "gaussians"),
        "heldout_psnr_db": _get(summary, "map", "heldout_psnr_db"),
        "wall_s": outcome.get("wall_s"),
        "host": outcome.get("host", ""),
        "run_dir": outcome.get("run_dir", ""),
        "error": " ".join(str(outcome.get("error", "")).split()),  # one line
    }


def comparable_figures(summary: dict[str, Any]) -> dict[str, Any]:
    """The figures of a run's summary.json that must not depend on how the run was started
    (``mogs launch`` or a batch, which worker, which bus, how loaded the machine): what the
    mapping produced. A drive reproduces them bit for bit (tests/fleet/test_fleet_drives.py), the map
    itself by its digest; its PSNRs to 9 significant digits: the report renders and averages with
    as many threads as the process may use (Ray sets ``OMP_NUM_THREADS`` to a task's CPUs), and
    the summation order moves the last bits (seen: 18.81440672419527 against ...273)."""
    m = summary.get("map", {})
    return {
        "keyframes": summary.get("keyframes"),
        "keyframes_with_depth": summary.get("keyframes_with_depth"),
        "keyframes_mapped": summary.get("keyframes_mapped"),
        "frames_with_odometry": summary.get("frames_with_odometry"),
        "frames_acknowledged": summary.get("frames_acknowledged"),
        "depth": summary.get("depth"),
        "trajectory": summary.get("trajectory"),
        "gaussians": m.get("gaussians"),
        "map_digest": m.get("digest"),
        "heldout_psnr_db": _significant(m.get("heldout_psnr_db")),
        "keyframe_psnr_db": _significant(m.get("keyframe_psnr_db")),
    }


def _significant(v: Any, digits: int = 9) -> Any:
    return float(f"{v:.{digits}g}") if isinstance(v, float) else v


def _cell(v: Any, digits: int = 3) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: _cell(r.get(k), 6) for k in COLUMNS})


def write_markdown(rows: list[dict[str, Any]], path: Path, *, title: str, notes: list[str]) -> None:
    """``fleet.md``: counts, the batch's notes (launch file, wall time), the table, then the
    full error of each failed drive."""
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    shown = [c for c in COLUMNS if c not in ("run_dir", "error", "host")]
    lines = [f"# {title}", ""]
    lines.append(
        f"{len(rows)} drives: " + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) + "."
    )
    lines += [f"- {n}" for n in notes]
    lines += ["", "| " + " | ".join(shown) + " |", "|" + " --- |" * len(shown)]
    for r in rows:
        cells = [_cell(r.get(c), 2 if c in ("wall_s", "heldout_psnr_db") else 3) for c in shown]
        cells[0] = f"`{Path(r['drive']).name}`"
        lines.append("| " + " | ".join(cells) + " |")
    failed = [r for r in rows if r["status"] != "complete"]
    if failed:
        lines += ["", "## Drives that did not complete", ""]
        lines += [f"- `{r['drive']}` ({r['status']}): {r['error']}" for r in failed]
    path.write_text("\n".join(lines) + "\n")


def write_plot(rows: list[dict[str, Any]], path: Path) -> None:
    """``fleet.png``: wall time, depth AbsRel, ATE and held-out PSNR per drive (bars; a drive
    that did not complete is red, a red x where it has no value)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (
        ("wall_s", "wall time [s]"),
        ("depth_absrel", "depth AbsRel"),
        ("ate_se3_rmse_m", "ATE SE(3) RMSE [m]"),
        ("heldout_psnr_db", "held-out PSNR [dB]"),
    )
    names = [Path(r["drive"]).name for r in rows]
    x = list(range(len(rows)))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.4), squeeze=False)
    bad = [i for i, r in enumerate(rows) if r["status"] != "complete"]
    for ax, (key, label) in zip(axes[0], panels):
        vals = [r.get(key) for r in rows]
        ok = [i for i, v in enumerate(vals) if v is not None]
        colors = ["tab:blue" if rows[i]["status"] == "complete" else "tab:red" for i in ok]
        ax.bar([x[i] for i in ok], [float(vals[i]) for i in ok], color=colors)
        missing = [i for i in bad if vals[i] is None]
        if missing:
            ax.plot(missing, [0.0] * len(missing), "rx", markersize=10, label="not complete")
            ax.legend(fontsize=7)
        if not ok:
            ax.text(
                0.5,
                0.5,
                "no values\n(no ground truth\nor no run)",
                ha="center",
                va="center",
                transform=ax.transAxes,
                fontsize=8,
                color="gray",
            )
        ax.set_title(label, fontsize=9)
        ax.set_xlim(-0.6, len(rows) - 0.4)
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=45, ha="right", fontsize=7)
    fig.suptitle(f"fleet: {len(rows)} drives", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
