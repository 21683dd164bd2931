"""Writing figures: JSON for scripts, and one named section of docs/benchmarks.md per benchmark.

Each benchmark owns the text between ``<!-- BEGIN name -->`` and ``<!-- END name -->`` in
``docs/benchmarks.md``; re-running it replaces only that section, so benchmarks never overwrite
each other's figures.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "REPO_ROOT",
    "add_output_options",
    "machine_line",
    "markdown_table",
    "update_markdown_section",
    "write_json",
    "write_results",
]

REPO_ROOT = Path(__file__).resolve().parents[2]


def add_output_options(ap: argparse.ArgumentParser, docs_from: str | None = None) -> None:
    """What every benchmark offers: ``--json PATH`` (the figures, through :func:`write_json`) and
    ``--no-docs`` (leave docs/benchmarks.md as it is); given ``docs_from`` (what a finished run
    left: ``DIR`` or ``JSON``), ``--docs-from`` too: the docs from that run, no new run."""
    ap.add_argument("--json", default=None, metavar="PATH", help="also write the figures here")
    ap.add_argument("--no-docs", action="store_true", help="do not update docs/benchmarks.md")
    if docs_from is not None:
        help_ = f"write the docs section (tables, plots) from a finished run's {docs_from}, no run"
        ap.add_argument("--docs-from", default=None, metavar=docs_from, help=help_)


def write_json(path: str | Path | None, figures: dict[str, Any]) -> None:
    """Write ``figures`` to ``path`` as indented JSON (no-op when ``path`` is None)."""
    if path is None:
        return
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(figures, indent=2, sort_keys=True, default=float) + "\n")


def markdown_table(columns: Sequence[str], rows: Iterable[Sequence[Any]] = ()) -> list[str]:
    """A markdown table's lines: the header, the separator and one line a row (cells formatted
    by the caller, so that each figure keeps its own precision)."""
    out = ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]
    return out + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]


def machine_line() -> str:
    """One line naming the machine, for the record beside the figures."""
    cpu = platform.processor() or platform.machine()
    try:
        model = next(
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        )
        cpu = model
    except (OSError, StopIteration):
        pass
    try:
        rev = subprocess.run(
            ["git", "-C", str(REPO_ROOT), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        rev = ""
    return f"{cpu}, Python {platform.python_version()}" + (f", commit {rev}" if rev else "")


def write_results(
    section: str, md: str, figures: dict[str, Any], json_path: Any, docs: bool
) -> None:
    """The end of a benchmark: its markdown on stdout, the figures as JSON at ``json_path`` (if
    any) and, with ``docs``, the markdown as the ``section`` of docs/benchmarks.md."""
    print(md)
    write_json(json_path, figures)
    if docs:
        update_markdown_section(section, md)


def update_markdown_section(name: str, body_md: str, path: str | Path | None = None) -> Path:
    """Replace (or append) the ``name`` section of ``docs/benchmarks.md`` with ``body_md``."""
    p = Path(path) if path is not None else REPO_ROOT / "docs" / "benchmarks.md"
    p.parent.mkdir(parents=True, exist_ok=True)
    text = (
        p.read_text()
        if p.exists()
        else "# Benchmarks\n\nLatest figures; each section is written by the command shown in it.\n"
    )
    begin, end = f"<!-- BEGIN {name} -->", f"<!-- END {name} -->"
    block = f"{begin}\n{body_md.rstrip()}\n{end}"
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        text = head + block + tail
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    p.write_text(text)
    return p
