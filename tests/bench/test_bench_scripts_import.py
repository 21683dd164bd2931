"""The bench scripts that import their siblings (``from bench... import``) run as the docs say:
``python bench/X.py`` from a clean environment (no PYTHONPATH), where only ``bench/`` is on the path."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _imports_bench(path: Path) -> bool:
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "bench":
            return True
        if isinstance(node, ast.Import) and any(
            a.name.split(".")[0] == "bench" for a in node.names
        ):
            return True
    return False


SCRIPTS = sorted(p for p in (REPO / "bench").glob("*.py") if _imports_bench(p))


def test_some_scripts_import_their_siblings() -> None:
    assert len(SCRIPTS) >= 3  # front, pipeline_table2, table2_convergence, composite_ab, ...


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_script_runs_without_pythonpath(script: Path, tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    res = subprocess.run(
        [sys.executable, str(script), "--help"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert "usage" in res.stdout.lower()
