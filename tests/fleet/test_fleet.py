"""``mogs batch`` (mogs_node/fleet): the pure parts (drive list, ids, resume, overrides, table) and
the Ray path on a tiny graph (player + report: seconds, not minutes), with a drive with a wrong
path, a crashing graph that Ray retries, and resume. The whole pipeline on three sim drives:
tests/fleet/test_fleet_drives.py (slow)."""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError
from mogs_node.fleet.batch import BatchOptions, format_bar, run_batch
from mogs_node.fleet.drives import (
    MARKER,
    Drive,
    check_launch_for_fleet,
    config_digest,
    drive_id,
    drive_overrides,
    is_complete,
    make_drives,
    read_drive_list,
)
from mogs_node.fleet.table import COLUMNS, make_row, write_csv, write_markdown, write_plot
from mogs_node.fleet.task import DriveCrashedError, DriveJob, run_drive

# ------------------------------------------------------------------------------ pure helpers


@settings(max_examples=100, deadline=None)
@given(st.lists(st.text(min_size=1, max_size=40).filter(lambda s: "\x00" not in s), max_size=8))
def test_drive_ids_are_safe_folder_names_stable_and_distinct(names: list[str]) -> None:
    paths = sorted({f"/data/{n.replace('/', '_')}" for n in names})
    ids = [drive_id(p) for p in paths]
    assert all(i and "/" not in i and not i.startswith(".") and len(i) <= 39 for i in ids)
    assert all(c.isalnum() or c in "_.-" for i in ids for c in i)
    assert ids == [drive_id(p) for p in paths]  # the same drive: the same run folder (resume)
    assert len(set(ids)) == len(ids)


def test_drive_list_from_arguments_and_files(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    lst = tmp_path / "sub" / "drives.txt"
    lst.write_text("# my drives\n/abs/one\n\nrel/two  # a comment\n")
    got = read_drive_list(["/x/zero"], [str(lst)])
    assert got == ["/x/zero", "/abs/one", str(tmp_path / "sub" / "rel" / "two")]
    with pytest.raises(ConfigError, match="no drives given"):
        read_drive_list([], [])
    with pytest.raises(ConfigError, match="cannot read"):
        read_drive_list([], [str(tmp_path / "absent.txt")])
    with pytest.raises(ConfigError, match="given twice"):
        make_drives(["/a/b", "/a/b/"])
    d = make_drives(["/a/drive_1", "/b/drive_1"])
    assert d[0].drive_id != d[1].drive_id and d[0].drive_id.startswith("drive_1-")


def test_launch_files_that_cannot_run_many_times_at_once_are_refused() -> None:
    check_launch_for_fleet({"name": "x", "nodes": [{"name": "a"}]}, "f.yaml")
    with pytest.raises(ConfigError, match=r"f.yaml: bus.pub_endpoint is set"):
        check_launch_for_fleet({"bus": {"pub_endpoint": "tcp://1.2.3.4:7700"}}, "f.yaml")
    with pytest.raises(ConfigError, match=r"f.yaml.nodes\[1\].host: 'gpu1'"):
        check_launch_for_fleet({"nodes": [{"name": "a"}, {"name": "b", "host": "gpu1"}]}, "f.yaml")
    with pytest.raises(ConfigError, match="mapping"):
        check_launch_for_fleet(["nodes"], "f.yaml")


def test_drive_overrides_put_the_path_in_and_let_set_win() -> None:
    base = {"report": {"out_dir": "/r"}, "mapper": {"ply_path": "/r/map.ply"}}
    got = drive_overrides(base, "player.path", "/d", {"mapper": {"iters": 3}, "player": {"x": 1}})
    assert got == {
        "report": {"out_dir": "/r"},
        "mapper": {"ply_path": "/r/map.ply", "iters": 3},
        "player": {"path": "/d", "x": 1},
    }
    assert base == {"report": {"out_dir": "/r"}, "mapper": {"ply_path": "/r/map.ply"}}
    assert drive_overrides({}, "player.path", "/d", {"player": {"path": "/e"}})["player"] == {
        "path": "/e"
    }
    with pytest.raises(ConfigError, match="NODE.PARAM"):
        drive_overrides({}, "path", "/d", {})


def test_resume_needs_a_complete_marker_a_summary_and_the_same_configuration(
    tmp_path: Path,
) -> None:
    d = Drive("/data/d1", "d1-abc123")
    digest = config_digest("name: x", {}, "player.path")
    assert digest != config_digest("name: x", {"mapper": {"iters": 1}}, "player.path")
    assert not is_complete(tmp_path, d, digest)  # nothing there
    marker = {"status": "complete", "drive": d.path, "digest": digest}
    (tmp_path / MARKER).write_text(json.dumps(marker))
    assert not is_complete(tmp_path, d, digest)  # no summary
    (tmp_path / "summary.json").write_text('{"keyframes": 4')
    assert not is_complete(tmp_path, d, digest)  # truncated summary
    (tmp_path / "summary.json").write_text('{"keyframes": 4}')
    assert is_complete(tmp_path, d, digest)
    assert not is_complete(tmp_path, d, "other")  # launch file or --set changed
    assert not is_complete(tmp_path, Drive("/data/d2", d.drive_id), digest)
    (tmp_path / MARKER).write_text(json.dumps({**marker, "status": "failed"}))
    assert not is_complete(tmp_path, d, digest)


@settings(max_examples=60, deadline=None)
@given(total=st.integers(0, 500), data=st.data())
def test_progress_bar_counts(total: int, data: st.DataObject) -> None:
    done = data.draw(st.integers(0, total))
    failed = data.draw(st.integers(0, done))
    line = format_bar(done, total, {"complete": done - failed, "failed": failed}, 65.2, width=20)
    bar = line[1 : line.index("]")]
    assert len(bar) == 20 and set(bar) <= {"#", "-"}
    assert bar.count("#") == (round(20 * done / total) if total else 0)
    assert f" {done}/{total} drives" in line and f"{total - done} to go, 1m05s" in line
    assert (f"{failed} failed" in line) == (failed > 0)


def test_table_rows_csv_markdown_and_plot(tmp_path: Path) -> None:
    run = tmp_path / "d1"
    run.mkdir()
    summary = {
        "keyframes": 5,
        "depth": {"absrel": 0.1, "coverage": 0.6},
        "trajectory": {"ate_se3_rmse_m": 0.02, "ate_sim3_rmse_m": float("nan")},
        "map": {"gaussians": 1500, "heldout_psnr_db": 18.5},
    }
    (run / "summary.json").write_text(json.dumps(summary))
    ok = {"drive": "/x/d1", "run_dir": str(run), "status": "complete", "attempt": 2, "wall_s": 9.5}
    bad = {"drive": "/x/d2", "run_dir": str(tmp_path / "d2"), "status": "failed", "attempt": 1}
    bad["error"] = "player could not start:\n  /x/d2: no such file"
    rows = [make_row(ok, resumed=True), make_row(bad)]
    assert rows[0]["keyframes"] == 5 and rows[0]["depth_absrel"] == 0.1
    assert rows[0]["ate_sim3_rmse_m"] is None  # not a number: left empty, never zero
    assert rows[0]["attempts"] == 2 and rows[0]["resumed"] is True
    assert rows[1]["keyframes"] is None and rows[1]["error"].count("\n") == 0
    write_csv(rows, tmp_path / "fleet.csv")
    with (tmp_path / "fleet.csv").open() as f:
        got = list(csv.DictReader(f))
    assert tuple(got[0]) == COLUMNS and len(got) == 2
    assert got[0]["depth_absrel"] == "0.100000" and got[0]["ate_sim3_rmse_m"] == ""
    assert got[1]["status"] == "failed" and got[1]["gaussians"] == ""
    write_markdown(rows, tmp_path / "fleet.md", title="T", notes=["n1"])
    md = (tmp_path / "fleet.md").read_text()
    assert "2 drives: 1 complete, 1 failed." in md and "- n1" in md
    assert md.count("\n| `") == 2 and "`/x/d2` (failed): player could not start: /x/d2" in md
    write_plot(rows, tmp_path / "fleet.png")
    assert (tmp_path / "fleet.png").read_bytes()[:4] == b"\x89PNG"


def test_batch_command_errors_before_any_drive_starts(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from mogs_node.cli import main

    launch = tmp_path / "l.yaml"
    launch.write_text(yaml.safe_dump(TINY))
    out = str(tmp_path / "out")
    assert main(["batch", str(launch), "--out", out]) == 1
    assert "no drives given" in caplog.text
    assert main(["batch", str(launch), "/d1", "--set", "mapper.iters=3", "--out", out]) == 1
    assert "override(s) for unknown node(s) ['mapper']" in caplog.text
    assert main(["batch", str(launch), "/d1", "--path-param", "path", "--out", out]) == 1
    assert "--path-param 'path': expected NODE.PARAM" in caplog.text
    tcp = {**TINY, "bus": {"pub_endpoint": "tcp://127.0.0.1:7700"}}
    launch.write_text(yaml.safe_dump(tcp))
    assert main(["batch", str(launch), "/d1", "--out", out]) == 1
    assert "bus.pub_endpoint is set" in caplog.text
    assert not (tmp_path / "out").exists()  # nothing ran


# -------------------------------------------------------------- the Ray path, on a tiny graph

needs_ray = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None, reason="Ray is not installed (pip install '.[fleet]')"
)

#: a drive's whole graph, as small as it gets: the player streams the drive, the report writes
#: summary.json (no keyframes: no frontend); and a node that hangs when asked (supervision kills
#: it: a crash, retried)
TINY = {
    "name": "tiny",
    "exit_when": ["report"],
    "nodes": [
        {
            "name": "player",
            "class": "bridges.player:PlayerNode",
            "params": {
                "source": "bag",
                "path": "",
                "rate": 0,
                "wait_for_nodes": ["report", "recorder"],
                "wait_for_nodes_s": 600.0,
                "groundtruth": True,
            },
            "respawn": "never",
        },
        {
            "name": "report",
            "class": "mogs_node.report.node:RunReportNode",
            "params": {"settle_s": 0.5, "render_backend": "torch", "save_depth": False},
            "respawn": "never",
        },
        {
            "name": "recorder",
            "class": "mogs_node.demo_nodes:Recorder",
            "params": {"topics": ["/camera/image"]},
            "respawn": "never",
            "heartbeat_timeout_s": 3.0,
        },
    ],
}


@pytest.fixture(scope="module")
def tiny_drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 6-frame sim bag at 96x32 and the tiny launch file."""
    from mogs_node.fleet.drives import write_sim_drives

    d = tmp_path_factory.mktemp("fleet")
    (drive,) = write_sim_drives(d / "drives", [5], n_frames=6, size=(96, 32), static_start_s=0.0)
    launch = d / "tiny.yaml"
    launch.write_text(yaml.safe_dump(TINY))
    return drive, launch


def test_run_drive_without_ray_and_a_crash_is_worth_a_retry(
    tiny_drive: tuple[Path, Path], tmp_path: Path
) -> None:
    drive, launch = tiny_drive
    job = DriveJob(
        drive=make_drives([str(drive)])[0],
        launch_path=str(launch),
        launch_text=launch.read_text(),
        run_dir=str(tmp_path / "run"),
        overrides={"recorder": {"crash_after": 1}},
        timeout_s=300,
        grace_s=3,
        batch_id="b1",
    )
    with pytest.raises(DriveCrashedError) as info:
        run_drive(job)
    out = info.value.result
    assert out["status"] == "failed" and out["attempt"] == 1
    assert "recorder exited with code 3 (respawn: never)" in out["error"]
    assert json.loads((tmp_path / "run" / MARKER).read_text())["status"] == "failed"
    # the report's teardown may still write a summary.json: the marker is what resume trusts
    assert not is_complete(tmp_path / "run", job.drive, job.digest)


@needs_ray
def test_batch_on_local_ray_bad_drive_crash_retried_and_resume(
    tiny_drive: tuple[Path, Path], tmp_path: Path
) -> None:
    import ray

    drive, launch = tiny_drive
    bad = tmp_path / "no_such_drive"
    out = tmp_path / "fleet"
    opts = BatchOptions(num_cpus=2, cpus_per_drive=1, timeout_s=300, grace_s=3)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        res = run_batch(launch, [str(drive), str(bad)], out, opts, progress=None)
        good, failed = res.rows
        assert good["status"] == "complete" and good["attempts"] == 1, good
        summary = json.loads((Path(good["run_dir"]) / "summary.json").read_text())
        assert summary["nodes"]["player"]["frames_published"] == 6 and good["keyframes"] == 0
        assert failed["status"] == "failed" and failed["attempts"] == 1  # not retried
        assert f"{bad}: no such file or folder" in failed["error"]
        assert len((out / "fleet.csv").read_text().splitlines()) == 3

        # resume: the complete drive is not run again, the failed one is
        again = run_batch(launch, [str(drive), str(bad)], out, opts, progress=None)
        assert (again.ran, again.skipped) == (1, 1)
        assert [r["resumed"] for r in again.rows] == [True, False]
        assert (Path(good["run_dir"]) / "attempts.log").read_text().count("\n") == 1

        # a graph that crashes every time: Ray retries it (max_retries), then it is reported
        crash = BatchOptions(
            num_cpus=2,
            timeout_s=300,
            grace_s=3,
            max_retries=1,
            overrides={"recorder": {"crash_after": 1}},
        )
        res = run_batch(launch, [str(drive)], tmp_path / "crash", crash, progress=None)
        (row,) = res.rows
        assert row["status"] == "failed" and row["attempts"] == 2, row
        assert "recorder exited with code 3" in row["error"]
    finally:
        ray.shutdown()
