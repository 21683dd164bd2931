"""The ``frontend`` section of docs/benchmarks.md as bench/frontend.py writes it: the speed, sweep,
sparse-points and accuracy tables, and the blocks a partial run keeps from the current section."""

from __future__ import annotations

import json
from pathlib import Path

from mogs_node.eval.bench_docs import machine_line


def speed_lines(cmd: str, frames: int, load: float, rows: list[tuple[str, dict]]) -> list[str]:
    """The head of the docs' ``frontend`` section: the command and the speed table."""
    lines = [
        "## Frontend (`bench/frontend.py`)",
        "",
        f"Command: `{cmd}`",
        "",
        f"Sim drive, {frames} frames at 10 Hz, one core; {machine_line()}; "
        f"1-min load average {load:.1f} during the run "
        "(the machine is shared: absolute times are inflated by the load).",
        "",
        "| resolution | tracking ms/frame | estimation ms/frame | road ms/frame "
        "| p50 total ms | p95 total ms | frames/s |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for tag, t in rows:
        lines.append(
            f"| {tag} | {t['tracking_ms_per_frame']:.1f} | "
            f"{t['estimation_ms_per_frame']:.1f} | {t['ground_ms_per_frame']:.1f} | "
            f"{t['total_ms_per_frame_p50']:.1f} | "
            f"{t['total_ms_per_frame_p95']:.1f} | {t['frames_per_s']:.1f} |"
        )
    return lines


def sweep_lines(sweep: list[tuple]) -> list[str]:
    """The knob sweep's table for the docs (none without a sweep)."""
    if not sweep:
        return []
    return [
        "",
        "Run time against ATE (621x188, keyframes, SE(3)-aligned), one knob at a "
        "time from the defaults; the sweep starts from the true state at frame 0 "
        "(benchmark harness only) so that the initialisation's scale choice does not "
        "drown the knob's effect:",
        "",
        "| knob | value | ms/frame (p50) | frames/s | ATE m | ATE % of path |",
        "| --- | --- | --- | --- | --- | --- |",
        *(
            f"| {n} | {v} | {ms:.1f} | {fps:.1f} | {a:.3f} | {p:.2f} |"
            for n, v, ms, fps, a, p in sweep
        ),
    ]


def points_lines(out: dict[str, float], seed: int, frames: int, repeats: int) -> list[str]:
    """The docs' sparse-points block from :func:`bench.frontend.points_figures`' figures
    (``out``): the points per variant on the demo drive and the CPU time with / without them."""
    lines = [
        "",
        "Sparse points per keyframe (demo drive: sim seed "
        f"{seed}, parked 2 s then ~4 s of driving, 621x188, launch/demo.yaml's keyframe policy; "
        "against ground truth at the points' pixels; \"on a depth edge\" (issue 16's "
        "definition: the point straddles one): within 2 px of a 4-neighbour depth jump > 10 % "
        "(sky included) and more than 10 % off the truth of every pixel within 1 px, i.e. "
        'neither side\'s depth; "near a depth edge": within 2 px of such a jump at all (the '
        "geometric share reported before round 9); docs/frontend.md rounds 6 to 9):",
        "",
        "| points | per moving keyframe (median) | rel. depth error (median) | on depth edges "
        "(straddling) | the same by omega | near depth edges "
        "| keyframes (without points) | CPU per frame parked / driving |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for tag, name in (
        ("landmarks_", "estimator window's landmarks (before)"),
        ("", "**the demo's (launch/demo.yaml `points`)**"),
        (
            "defaults_",
            "dense tracks (code default, round 8: 900 tracks >= 5 px apart, 3 keyframes "
            "re-observed)",
        ),
        ("round9_", "dense tracks, round 9 (3000 tracks >= 2 px apart, 6 keyframes re-observed)"),
        (
            "round13_",
            "dense tracks, round 13 (round 9, a quarter of the tracks within 10 deg of the motion)",
        ),
        (
            "round14_",
            "dense tracks, round 14 (round 13, re-observed points at ZNCC 0.55 that keep "
            "half their contrast)",
        ),
    ):
        lines.append(
            f"| {name} | {out[tag + 'points_per_keyframe_median']:.1f} | "
            f"{100 * out[tag + 'points_rel_err_median']:.2f} % | "
            f"{100 * out[tag + 'points_on_edges_share']:.2f} % | "
            f"{100 * out[tag + 'points_on_edges_weight_share']:.1f} % | "
            f"{100 * out[tag + 'points_near_edges_share']:.1f} % | "
            f"{out[tag + 'keyframes']:.0f} ({out[tag + 'keyframes_without_points']:.0f}) | "
            f"{out[tag + 'cpu_ms_per_frame_standstill']:.1f} / "
            f"{out[tag + 'cpu_ms_per_frame_moving']:.1f} ms |"
        )
    lines += [
        "",
        f"CPU time per tracking frame at 621x188 ({frames} frames, moving start, one core, "
        "`time.process_time`, the call that completes the initialisation left out, the least of "
        f"{repeats} interleaved runs per setting): "
        f"{out['cpu_ms_per_frame_621x188_no_points']:.1f} ms without the dense points "
        f"({out['cpu_frames_per_s_621x188_no_points']:.1f} frames/s), "
        f"{out['cpu_ms_per_frame_621x188']:.1f} ms with them "
        f"({out['cpu_frames_per_s_621x188']:.1f} frames/s, x"
        f"{out['cpu_ms_per_frame_621x188'] / out['cpu_ms_per_frame_621x188_no_points']:.2f}), "
        f"{out['cpu_ms_per_frame_621x188_round9']:.1f} ms with round 9's "
        f"({out['cpu_frames_per_s_621x188_round9']:.1f} frames/s, x"
        f"{out['cpu_ms_per_frame_621x188_round9'] / out['cpu_ms_per_frame_621x188_no_points']:.2f}"
        ")"
        + "".join(
            f", {out[f'cpu_ms_per_frame_621x188_round{r}']:.1f} ms with round {r}'s "
            f"({out[f'cpu_frames_per_s_621x188_round{r}']:.1f} frames/s, x"
            f"{out[f'cpu_ms_per_frame_621x188_round{r}'] / out['cpu_ms_per_frame_621x188_no_points']:.2f})"
            for r in (13, 14)
        )
        + "; on a loaded machine the ratios hold better than the times.",
    ]
    return lines


def traj_lines(paths: list[str]) -> list[str]:
    """Accuracy table from ``mogs eval traj --json`` files (goals of issue 6)."""
    if not paths:
        return []
    out = [
        "",
        "Accuracy (`mogs eval traj --dataset D --json PATH`; keyframes; goals: ATE SE(3) < 1 % "
        "of the path and scale error < 2 % on sim and oxts, end drift < 2 cm on euroc):",
        "",
        "| dataset | road | path m | ATE SE(3) m | % of path | ATE Sim(3) m | scale error "
        "| end drift m | resets |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for path in paths:
        f = json.loads(Path(path).read_text())
        out.append(
            f"| {f['dataset']} | {'yes' if f.get('ground') else 'no'} | "
            f"{f['path_length_m']:.1f} | {f['ate_se3_rmse_m']:.3f} | "
            f"{f['ate_se3_percent_of_path']:.2f} | {f['ate_sim3_rmse_m']:.3f} | "
            f"{100 * f['scale_error']:.1f} % | {f['end_drift_m']:.4f} | {f['resets']} |"
        )
    out += [
        "",
        "The sim drive starts parked for 2 s (static initialisation); the OXTS drive starts "
        "moving (dynamic initialisation); the EuRoC excerpt is near stationary (7 mm path): its "
        "% of path and scale error mean nothing, its goal is the end drift. Road: translations "
        "also measured on the road at the calibrated camera height (docs/frontend.md, round 5; "
        "`--no-ground` gives camera + IMU only: OXTS 6.2 % of the path, scale error 26 %).",
    ]
    return out


SWEEP_HEAD = "Run time against ATE"
ACCURACY_HEAD = "Accuracy (`mogs eval traj"


def kept_tables(section: str, *, sweep: bool, accuracy: bool) -> list[str]:
    """The knob sweep and / or the accuracy tables of the current ``frontend`` section of
    docs/benchmarks.md (``section``: its text), for a run that does not redo them (--no-sweep,
    no --traj-json); their first line says they come from an earlier run."""
    out: list[str] = []
    for wanted, head, stop in (
        (sweep, SWEEP_HEAD, ACCURACY_HEAD),
        (accuracy, ACCURACY_HEAD, None),
    ):
        if not wanted or head not in section:
            continue
        part = section[section.index(head) :]
        if stop is not None and stop in part:
            part = part[: part.index(stop)]
        lines = part.rstrip().splitlines()
        if "kept from" not in lines[0]:
            lines[0] = lines[0].replace(head, head + " (kept from an earlier run, not re-run)", 1)
        out += ["", *lines]
    return out


def current_section(name: str = "frontend") -> str:
    """Text of section ``name`` of docs/benchmarks.md ('' if absent)."""
    p = Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"
    text = p.read_text() if p.exists() else ""
    begin, end = f"<!-- BEGIN {name} -->", f"<!-- END {name} -->"
    if begin not in text or end not in text:
        return ""
    return text.split(begin, 1)[1].split(end, 1)[0]


POINTS_HEAD = "\nSparse points per keyframe"
POINTS_END = "\nCPU time per tracking frame"
POINTS_NOTE = "\nSparse points block:"


def with_new_points(section: str, point_lines: list[str]) -> str | None:
    """``section`` (the current ``frontend`` section's text) with its sparse-points block
    replaced by ``point_lines`` and the rest (speed, sweep, accuracy tables) kept as it is; None
    if it has no such block."""
    if POINTS_HEAD not in section or POINTS_END not in section:
        return None
    head, rest = section.split(POINTS_HEAD, 1)
    head = head.rstrip()
    if POINTS_NOTE in head:  # the previous run's note goes with its block
        head = head.rsplit(POINTS_NOTE, 1)[0]
    tail = rest.split(POINTS_END, 1)[1]
    tail = tail.split("\n\n", 1)[1] if "\n\n" in tail else ""
    return head.rstrip() + "\n" + "\n".join(point_lines) + "\n\n" + tail.strip("\n")
