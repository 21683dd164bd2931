"""Fault injection: SIGKILL each node at a random time during a replay, and stop + resume a run.

Each case runs the demo pipeline (launch/demo.yaml on a shorter synthetic drive, fewer mapper
iterations) with ``mogs launch`` and compares it with a clean run of the same configuration:

- the run completes (launcher exit code 0) and the killed node was respawned;
- every keyframe of the clean run exists (same ids and stamps), has a metrized depth map and
  reached the mapper;
- the depth maps and the final map match the clean run's within the tolerances below.

"Each node" is every node that processes data and can be respawned: player (the source: it goes
on after the last frame the journal holds), frontend, segmentation, prior, metrizer, mapper and
the journal itself. The report node is the test's scorer, not part of the pipeline: it is not
killed (it does catch up like the others on ``--resume``).

Figures of the last runs: docs/reliability.md ("Kill test", "Resume").
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import re
import signal
import subprocess
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from _reliability_harness import cli_argv

from mogs_node import msgs
from mogs_node.bus import BusConfig, Subscriber
from mogs_node.geometry import se3_inverse
from mogs_node.mapper.ply import read_gaussian_ply

REPO = Path(__file__).resolve().parents[2]
N_FRAMES = 48  # 2 s parked, then ~5 keyframes of driving
TIMEOUT_S = 2400  # one pipeline run takes 3-10 min on 2 shared cores
#: a killed run's depth equals the clean run's to this (metres, on every pixel)
DEPTH_ATOL_M = 1e-3
#: the final maps: Gaussian counts within this fraction, renders of the last keyframe's view
#: at least this PSNR apart (dB)
COUNT_RTOL = 0.02
RENDER_PSNR_DB = 35.0


_BASE: dict = {}


def small_launch(out: Path, name: str) -> Path:
    """launch/demo.yaml on a shorter drive with private endpoints, outputs in ``out``; read once
    per session, so that the clean and the faulty runs use the same configuration."""
    if not _BASE:
        _BASE.update(yaml.safe_load((REPO / "launch" / "demo.yaml").read_text()))
    launch = json.loads(json.dumps(_BASE))
    launch["name"] = name
    d = Path("/tmp") / f"mogs-kill-{uuid.uuid4().hex[:8]}"
    d.mkdir()
    launch["bus"] = {"pub_endpoint": f"ipc://{d}/pub.ipc", "sub_endpoint": f"ipc://{d}/sub.ipc"}
    for node in launch["nodes"]:
        node["respawn"] = "on_failure"
        node["respawn_delay_s"] = 0.2
        p = node.setdefault("params", {})
        if node["name"] == "player":
            p["sim"] = {**p["sim"], "n_frames": N_FRAMES}
            p["progress_period_s"] = 0.0
        elif node["name"] == "mapper":
            # no refinement after the drive: a mapper killed after the source stopped would not
            # see its stop again (docs/mapper.md "Final refinement")
            p.update(iters_per_keyframe=2, final_refine_iters=0, ply_path=str(out / "map.ply"))
        elif node["name"] == "report":
            p["out_dir"] = str(out)
            p["wait_final_map"] = False
        elif node["name"] == "journal":
            p["dir"] = str(out / "journal")
    out.mkdir(parents=True, exist_ok=True)
    path = out / "launch.yaml"
    path.write_text(yaml.safe_dump(launch))
    return path


class Run:
    """``mogs launch`` in a subprocess; its log, the pid of every node, keyframes on the bus."""

    def __init__(self, path: Path, *extra: str, timeout_s: float = 1500) -> None:
        self.path = path
        launch = yaml.safe_load(path.read_text())
        self.bus = BusConfig(launch["bus"]["pub_endpoint"], launch["bus"]["sub_endpoint"])
        self.lines: list[str] = []
        self.pids: dict[str, int] = {}
        self.keyframes = 0
        self._stop = threading.Event()
        self.sub = Subscriber(self.bus)
        self.sub.subscribe("/frontend/keyframe")
        env = dict(os.environ, OMP_NUM_THREADS="1")
        self.proc = subprocess.Popen(
            cli_argv("launch", str(path), "--timeout", str(timeout_s), *extra),
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self._watch = threading.Thread(target=self._watch_keyframes, daemon=True)
        self._watch.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        log = open(self.path.parent / f"launch-{time.time_ns()}.log", "w")  # noqa: SIM115
        for line in self.proc.stdout:
            self.lines.append(line)
            log.write(line)
            log.flush()
            m = re.search(r"\[launch\] started (\S+) \(pid (\d+)\)", line)
            if m:
                self.pids[m.group(1)] = int(m.group(2))

    def _watch_keyframes(self) -> None:
        while not self._stop.is_set():
            env = self.sub.receive(timeout_ms=200)
            if env is not None and isinstance(env.msg, msgs.Keyframe):
                self.keyframes += 1

    def wait_keyframes(self, n: int, timeout_s: float = 900) -> None:
        deadline = time.monotonic() + timeout_s
        while self.keyframes < n:
            assert self.proc.poll() is None, "the run ended early:\n" + self.log[-3000:]
            assert time.monotonic() < deadline, f"no {n} keyframes:\n" + self.log[-3000:]
            time.sleep(0.05)

    def wait(self, timeout_s: float = 1600) -> int:
        try:
            rc = self.proc.wait(timeout=timeout_s)
        finally:
            self._stop.set()
            self._watch.join(2)
            self._reader.join(5)
            self.sub.close()
        return rc

    @property
    def log(self) -> str:
        return "".join(self.lines)


def keyframe_ids(out: Path) -> list[int]:
    return sorted(int(p.stem[3:]) for p in (out / "depth").glob("kf_*.npz"))


def render_last_view(ply: Path, clean_out: Path) -> torch.Tensor:
    """The map in ``ply`` rendered from the clean run's last keyframe pose (621x188 sim camera)."""
    from mogs_node.mapper.rasterizer import GaussianTensors, render

    g = read_gaussian_ply(ply)
    rows = np.loadtxt(clean_out / "trajectory_keyframes.kitti", ndmin=2)
    T_world_cam = np.vstack([rows[-1].reshape(3, 4), [0, 0, 0, 1]])
    gt = GaussianTensors(
        *(
            torch.from_numpy(np.ascontiguousarray(g[k]))
            for k in ("means", "quats_wxyz", "log_scales", "opacity_logit", "colors_rgb")
        )
    )
    T_cam_world = torch.from_numpy(se3_inverse(T_world_cam)).float()
    return render(gt, T_cam_world, (360.77, 361.73, 304.53, 86.41), 621, 188).color


def compare(out: Path, clean: Path) -> dict[str, float]:
    """Figures of a faulty run against the clean one (asserted by the caller)."""
    fig = json.loads((out / "summary.json").read_text())
    ref = json.loads((clean / "summary.json").read_text())
    ids, ref_ids = keyframe_ids(out), keyframe_ids(clean)
    depth_err = 0.0
    for k in ref_ids:
        if k in ids:
            a = np.load(out / "depth" / f"kf_{k:06d}.npz")["depth_m"]
            b = np.load(clean / "depth" / f"kf_{k:06d}.npz")["depth_m"]
            depth_err = max(depth_err, float(np.abs(a - b).max()))
    ra, rb = render_last_view(out / "map.ply", clean), render_last_view(clean / "map.ply", clean)
    mse = float(((ra - rb) ** 2).mean())
    n_a = len(read_gaussian_ply(out / "map.ply")["means"])
    n_b = len(read_gaussian_ply(clean / "map.ply")["means"])
    same_stamps = (
        np.loadtxt(out / "trajectory_keyframes.tum", ndmin=2)[:, 0].tolist()
        == np.loadtxt(clean / "trajectory_keyframes.tum", ndmin=2)[:, 0].tolist()
    )
    return {
        "keyframes": fig["keyframes"],
        "clean_keyframes": ref["keyframes"],
        "with_depth": fig["keyframes_with_depth"],
        "mapped": fig["keyframes_mapped"],
        "same_ids": float(ids == ref_ids),
        "same_stamps": float(same_stamps),
        "depth_max_abs_diff_m": depth_err,
        "gaussians": n_a,
        "clean_gaussians": n_b,
        "render_psnr_vs_clean_db": float("inf") if mse == 0 else -10 * np.log10(mse),
        "absrel": fig.get("depth", {}).get("absrel", float("nan")),
        "clean_absrel": ref.get("depth", {}).get("absrel", float("nan")),
    }


def check(c: dict[str, float]) -> None:
    assert c["keyframes"] == c["clean_keyframes"] >= 3
    assert c["with_depth"] == c["keyframes"] and c["mapped"] == c["keyframes"]
    assert c["same_ids"] and c["same_stamps"]
    assert c["depth_max_abs_diff_m"] <= DEPTH_ATOL_M
    assert abs(c["gaussians"] - c["clean_gaussians"]) <= COUNT_RTOL * c["clean_gaussians"]
    assert c["render_psnr_vs_clean_db"] >= RENDER_PSNR_DB


def _record(case: str, c: dict[str, float], extra: dict | None = None) -> None:
    line = json.dumps({"case": case, **c, **(extra or {})}, default=float)
    print(line)
    with open(REPO / "runs" / "reliability_kill.jsonl", "a") as f:
        f.write(line + "\n")


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    reuse = os.environ.get("MOGS_KILL_REFERENCE")  # a clean run of the same code and config
    if reuse:
        _BASE.update(yaml.safe_load((Path(reuse) / "launch.yaml").read_text()))
        return Path(reuse)
    out = tmp_path_factory.mktemp("clean")
    run = Run(small_launch(out, f"clean-{uuid.uuid4().hex[:6]}"))
    assert run.wait() == 0, run.log[-4000:]
    fig = json.loads((out / "summary.json").read_text())
    assert fig["keyframes"] >= 4 and fig["keyframes_mapped"] == fig["keyframes"]
    return out


@pytest.mark.slow
@pytest.mark.timeout(TIMEOUT_S)
def test_stop_half_way_and_resume(clean_run: Path, tmp_path: Path) -> None:
    n_kf = json.loads((clean_run / "summary.json").read_text())["keyframes"]
    out = tmp_path / "run"
    path = small_launch(out, f"resume-{uuid.uuid4().hex[:6]}")
    first = Run(path)
    try:
        first.wait_keyframes(max(1, n_kf // 2))
        first.proc.send_signal(signal.SIGINT)  # Ctrl-C: every node stops cleanly
    except BaseException:
        first.proc.kill()
        raise
    assert first.wait() == 0, first.log[-4000:]
    half = json.loads((out / "summary.json").read_text())
    assert half["keyframes"] < n_kf, "the first half must stop before the end"
    second = Run(path, "--resume", str(out))
    assert second.wait() == 0, second.log[-4000:]
    assert "resuming after the journal" in second.log
    c = compare(out, clean_run)
    _record("stop + resume", c, {"keyframes_before_stop": half["keyframes"]})
    check(c)


KILLED = ["mapper", "frontend", "segmentation", "prior", "metrizer", "journal", "player"]


@pytest.mark.slow
@pytest.mark.timeout(TIMEOUT_S)
@pytest.mark.parametrize("victim", KILLED)
def test_sigkill_at_a_random_time(victim: str, clean_run: Path, tmp_path: Path) -> None:
    n_kf = json.loads((clean_run / "summary.json").read_text())["keyframes"]
    rng = random.Random(f"{victim}-{os.environ.get('MOGS_KILL_SEED', '0')}")
    after_kf = rng.randint(1, max(1, n_kf - 2))  # during the replay, not after it
    delay_s = rng.uniform(0.0, 1.0)
    out = tmp_path / "run"
    run = Run(small_launch(out, f"kill-{uuid.uuid4().hex[:6]}"))
    try:
        run.wait_keyframes(after_kf)
        time.sleep(delay_s)
        player_alive = run.pids.get("player") is not None and _alive(run.pids["player"])
        os.kill(run.pids[victim], signal.SIGKILL)
        t_kill = time.monotonic()
    except BaseException:
        run.proc.kill()
        raise
    rc = run.wait()
    assert rc == 0, run.log[-4000:]
    assert f"respawning {victim} (1)" in run.log
    assert player_alive or victim == "player"  # killed while data was still coming
    c = compare(out, clean_run)
    _record(
        f"kill {victim}",
        c,
        {
            "after_keyframes": after_kf,
            "delay_s": round(delay_s, 3),
            "recovery_s": round(time.monotonic() - t_kill, 1),
        },
    )
    check(c)


def _alive(pid: int) -> bool:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, 0)
        return True
    return False
