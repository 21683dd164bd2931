"""A run that ends cleanly removes its journal and checkpoints unless ``--keep-journal``; one
stopped early keeps them for ``--resume`` (issue 18: each demo run left ~160 MB)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
import yaml
from _reliability_harness import REPO, cli_argv

from mogs_node.supervision import CHECKPOINT_FILES, JOURNAL_FILES, remove_run_state


def test_remove_run_state_removes_only_the_state_files(tmp_path: Path) -> None:
    j = tmp_path / "journal"
    j.mkdir()
    (j / "journal.log").write_bytes(b"x" * 1000)
    c = tmp_path / "ckpt"
    c.mkdir()
    (c / "mapper.ckpt").write_bytes(b"y" * 300)
    (c / "mapper.ckpt.corrupt").write_bytes(b"z" * 20)
    (c / ".mapper.ckpt.abc123.tmp").write_bytes(b"t" * 5)
    (c / "notes.txt").write_text("mine")  # not ours: kept, and so is the folder
    freed = remove_run_state(
        [(j, JOURNAL_FILES), (c, CHECKPOINT_FILES), (tmp_path / "absent", JOURNAL_FILES)]
    )
    assert freed == 1325
    assert not j.exists()
    assert sorted(p.name for p in c.iterdir()) == ["notes.txt"]


def _launch(tmp_path: Path, n_frames: int) -> Path:
    run = tmp_path / "run"
    launch = {
        "name": f"disk{n_frames}",
        "exit_when": ["source"],
        "nodes": [
            {
                "name": "source",
                "class": "mogs_node.demo_nodes:SyntheticSource",
                "params": {"n_frames": n_frames, "rate_hz": 20.0, "width": 16, "height": 8},
                "respawn": "never",
            },
            {
                "name": "journal",
                "class": "mogs_node.journal.node:JournalNode",
                "params": {"dir": str(run / "journal"), "topics": ["/camera/image"]},
            },
        ],
    }
    path = tmp_path / "disk.yaml"
    path.write_text(yaml.safe_dump(launch))
    return path


@pytest.mark.parametrize("keep", [False, True])
def test_a_clean_end_removes_the_journal_unless_kept(tmp_path: Path, keep: bool) -> None:
    env = {**os.environ, "MOGS_BUS_DIR": str(tmp_path / "bus")}
    argv = cli_argv("launch", str(_launch(tmp_path, 20))) + (["--keep-journal"] if keep else [])
    r = subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    journal = tmp_path / "run" / "journal" / "journal.log"
    assert journal.exists() == keep
    assert ("removed its journal and checkpoints" in r.stdout) == (not keep)


def test_a_run_stopped_by_its_timeout_keeps_the_journal(tmp_path: Path) -> None:
    env = {**os.environ, "MOGS_BUS_DIR": str(tmp_path / "bus")}
    argv = cli_argv("launch", str(_launch(tmp_path, 0)), "--timeout", "6")  # 0: never ends
    r = subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 124, r.stdout + r.stderr
    assert (tmp_path / "run" / "journal" / "journal.log").exists()
