"""The issue-21 acceptance run: a batch on a local Ray (``num_cpus=2``) of three tiny sim drives
(different seeds, 30 frames each, through launch/bag.yaml's whole graph) and one drive with a
wrong path. The three complete with the same summary.json figures as each drive run alone with
``mogs launch``; the bad one is reported failed with its error; the table has four rows; a
second run of the same batch does no work for the three finished drives.

Minutes to tens of minutes on 2 shared cores: slow (the fast path: tests/fleet/test_fleet.py)."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import uuid
from pathlib import Path

import pytest
from _reliability_harness import cli_argv

pytest.importorskip("ray")

from mogs_node.fleet.batch import BatchOptions, run_batch  # noqa: E402
from mogs_node.fleet.drives import PATIENT_PLAYER, drive_id, write_sim_drives  # noqa: E402
from mogs_node.fleet.table import comparable_figures  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
LAUNCH = REPO / "launch" / "bag.yaml"
PATIENT = PATIENT_PLAYER  # the figures then do not depend on the machine's load


def launch_alone(drive: Path, run_dir: Path) -> subprocess.Popen:
    """``mogs launch launch/bag.yaml --set player.path=DRIVE --run-dir RUN`` on its own bus."""
    bus_dir = Path("/tmp") / f"mogs-fleet-ref-{uuid.uuid4().hex[:8]}"
    bus_dir.mkdir()
    sets = [f"{n}.{k}={v}" for n, p in PATIENT.items() for k, v in p.items()]
    argv = cli_argv(
        "launch",
        str(LAUNCH),
        "--set",
        f"player.path={drive}",
        *[a for s in sets for a in ("--set", s)],
        "--run-dir",
        str(run_dir),
        "--timeout",
        "3000",
    )
    run_dir.mkdir(parents=True)
    log = (run_dir / "launch.log").open("w")
    env = {**os.environ, "MOGS_BUS_DIR": str(bus_dir)}
    return subprocess.Popen(argv, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, env=env)


@pytest.mark.slow
@pytest.mark.timeout(5400)
def test_batch_of_three_sim_drives_and_a_bad_one(tmp_path: Path) -> None:
    drives = write_sim_drives(tmp_path / "drives", [1, 2, 3], n_frames=30)
    bad = tmp_path / "drives" / "no_such_drive"
    out = tmp_path / "fleet"
    opts = BatchOptions(num_cpus=2, cpus_per_drive=1, timeout_s=3000, overrides=PATIENT)
    paths = [str(p) for p in drives] + [str(bad)]

    result = run_batch(LAUNCH, paths, out, opts, progress=None)

    rows = {Path(r["drive"]).name: r for r in result.rows}
    assert len(result.rows) == 4 and result.ran == 4 and result.skipped == 0
    assert rows["no_such_drive"]["status"] == "failed"
    assert "could not start with its configuration" in rows["no_such_drive"]["error"]
    assert f"{bad}: no such file or folder" in rows["no_such_drive"]["error"]
    assert rows["no_such_drive"]["attempts"] == 1  # a config error is not retried
    for d in drives:
        r = rows[d.name]
        assert r["status"] == "complete", (r, (out / drive_id(str(d)) / "launch.log").read_text())
        assert r["keyframes"] >= 2 and r["depth_absrel"] is not None
        assert r["ate_se3_rmse_m"] is not None and r["heldout_psnr_db"] is not None
    with (out / "fleet.csv").open() as f:
        assert len(list(csv.DictReader(f))) == 4
    assert (out / "fleet.md").read_text().count("\n| `") == 4
    assert (out / "fleet.png").stat().st_size > 0

    # the same drives, each alone with `mogs launch` (in parallel, each on its own bus)
    procs = {d: launch_alone(d, tmp_path / "alone" / d.name) for d in drives}
    for d, p in procs.items():
        assert p.wait(timeout=3100) == 0, (tmp_path / "alone" / d.name / "launch.log").read_text()
    for d in drives:
        alone = json.loads((tmp_path / "alone" / d.name / "summary.json").read_text())
        batch = json.loads((out / drive_id(str(d)) / "summary.json").read_text())
        # every figure the same, bit for bit: frames, keyframes, trajectory, depth, the map's
        # digest and PSNR (docs/fleet.md); the prior's waits say why when they are not
        waits = [s["nodes"]["prior"]["metrized_wait_timeouts"] for s in (batch, alone)]
        assert comparable_figures(batch) == comparable_figures(alone), (d.name, waits)
        f = comparable_figures(batch)
        assert f["keyframes"] >= 2 and f["depth"]["keyframes_scored"] == f["keyframes"]
        assert f["gaussians"] > 0 and f["map_digest"]

    # re-running the batch does no work for the finished drives (the bad one is tried again)
    def state(d: Path) -> tuple[int, str]:  # the summary's time and every attempt made so far
        run = out / drive_id(str(d))
        return (run / "summary.json").stat().st_mtime_ns, (run / "attempts.log").read_text()

    before = {d: state(d) for d in drives}
    again = run_batch(LAUNCH, paths, out, opts, progress=None)
    assert again.ran == 1 and again.skipped == 3
    assert {d: state(d) for d in drives} == before
    assert [r["status"] for r in again.rows] == ["complete"] * 3 + ["failed"]
    assert [r["resumed"] for r in again.rows] == [True] * 3 + [False]
