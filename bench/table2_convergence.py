"""Table II's convergence figures in the live pipeline: per keyframe, how many iterations a map
initialised from each depth needs until a held-out view next to the new keyframe reaches the target.

Paper Table II compares how fast a map initialised from each depth converges. In the live drive
the mapper runs ``iters_per_keyframe`` iterations after each keyframe and publishes one map
update, so a fixed view scored at map updates (``bench/pipeline_table2.py``'s first definition)
measured mostly *when* that view entered the map, in steps of ``iters_per_keyframe``. Here the
run's journal (kept by ``bench/pipeline_table2.py``) is replayed through the mapper core
(:func:`bench.mapper_replay.replay`: the live mapper's map, byte for byte, with ``--threads 1``),
with the depth that run's mapper got (random depth regenerated exactly as
:class:`bench.table2_random.RandomDepthNode` published it). After each keyframe's insertion
a copy of the map is optimised by the mapper's own loop (:meth:`GaussianMapper.optimize`, the
same view sampling and learning rates, ``converge_rel`` 0) and scored after every iteration at
the keyframe's held-out view: the nearest frame (within 2 frames) that is not a keyframe and has
an odometry pose (ground truth: the camera image the journal recorded; exposure: the keyframe's),
until it reaches ``stop_db`` or ``cap`` iterations. The replay itself then goes on as the live
mapper did (the copy is dropped), so every keyframe starts from the live run's map.

Per init: ``iters_to_target`` is the median over the scored keyframes of the iterations until
the target (0: the insertion alone reaches it; a keyframe that does not reach it within ``cap``
counts as never, above every count, so the median is ``None`` when half of them never do),
``gaussians_at_target`` the median number of Gaussians in the map at that iteration over the
held-out views that **every** init reaches (:func:`common_view_gaussians`; issue 17: "until a
fixed held-out view reaches 20 dB, Gaussians at that point", i.e. the same views for all). The
median over each init's own reaching views (``gaussians_at_target_own_views``, the headline until
session 17) compared random's early views, the only ones it reaches, with MOGS's late ones, where
every map is larger. Keyframes whose held-out frame is less than ``min_move_m`` from the
keyframe (the static start: the same view) are not scored.

    python bench/table2_convergence.py RUN_DIR --init mogs [--json PATH]
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

if (
    not __package__
):  # run as a script (python bench/table2_convergence.py): the repo root holds bench/
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.mapper_replay import _camera_rgb, mapper_params, read_journal, replay, score  # noqa: E402
from bench.table2_random import RandomDepthParams, random_depth_msg  # noqa: E402
from mogs_node.eval.bench_docs import write_json
from mogs_node.mapper.image_metrics import psnr_db
from mogs_node.mapper.mapper import GaussianMapper
from mogs_node.params import parse_params

STOP_DB = 20.0  # issue 17's target: the copy stops once the view reaches it
CAP = 40  # iterations at most per keyframe (~7x the demo's 6 per keyframe; CPU time)


def heldout_views(
    data: dict[str, list[Any]], min_move_m: float = 0.1, max_frames: int = 2
) -> dict[int, int]:
    """Keyframe id -> the stamp of its held-out frame: of the frames with a camera image and an
    odometry pose that are not keyframes, the nearest to the keyframe within ``max_frames`` frames
    (the later on a tie), if the camera moved at least ``min_move_m`` between the two (before
    that the view is the keyframe's own). Keyframes with no such frame are not scored (the demo
    makes a keyframe at every frame for a while: the next non-keyframe can be 5 frames ahead,
    beyond what the new keyframe sees)."""
    kf_by_stamp = {k.stamp_ns: k for k in data["/frontend/keyframe"]}
    odo = {o.stamp_ns: np.asarray(o.T_world_cam) for o in data["/frontend/odometry"]}
    frames = sorted(odo)
    images = {m.stamp_ns for m in data["/camera/image"]}
    out = {}
    for i, s in enumerate(frames):
        if s not in kf_by_stamp:
            continue
        kf = kf_by_stamp[s]
        near = [
            frames[j]
            for d in range(1, max_frames + 1)
            for j in (i + d, i - d)
            if 0 <= j < len(frames) and frames[j] not in kf_by_stamp and frames[j] in images
        ]
        if near:
            move = np.linalg.norm(odo[near[0]][:3, 3] - np.asarray(kf.T_world_cam)[:3, 3])
            if move >= min_move_m:
                out[kf.keyframe_id] = near[0]
    return out


def random_params(launch: Path) -> RandomDepthParams:
    """The random run's :class:`RandomDepthParams` (its launch file's ``randomizer`` node; the
    defaults where it has none, e.g. the launch file of another init's run)."""

    spec = yaml.safe_load(Path(launch).read_text())
    node = next((n for n in spec.get("nodes", []) if n.get("name") == "randomizer"), {})
    return parse_params(RandomDepthParams, node.get("params") or {}, where="randomizer")


def converge(
    mapper: GaussianMapper,
    T_view: np.ndarray,
    gt: np.ndarray,
    stop_db: float = STOP_DB,
    cap: int = CAP,
) -> dict[str, list[float]]:
    """Optimise a copy of ``mapper`` as its own loop does, scoring the view ``T_view`` (ground
    truth ``gt`` [H, W, 3] float in [0, 1], exposure of the newest keyframe) before the first
    iteration and after each, until the PSNR reaches ``stop_db`` or ``cap`` iterations ran.
    Returns the PSNR [dB] and the map's size per iteration count 0, 1, ..."""
    m = copy.deepcopy(mapper)  # the live replay goes on from the map as it was
    m.params = replace(m.params, converge_rel=0.0)
    curve: dict[str, list[float]] = {"psnr_db": [], "gaussians": []}

    def scored(_it: int = -1) -> bool:
        r = m.render_view(T_view, m.keyframes[-1].exposure_ab).color.numpy()
        curve["psnr_db"].append(round(psnr_db(r, gt), 3))
        curve["gaussians"].append(len(m.map))
        return curve["psnr_db"][-1] >= stop_db

    if not scored() and cap > 0:
        m.optimize(cap, after_iteration=scored)
    return curve


def measure(
    journal: Path,
    launch: Path,
    init: str,
    stop_db: float = STOP_DB,
    cap: int = CAP,
    min_move_m: float = 0.1,
    core: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Replay one run's journal (``launch``: its launch file) with the convergence scoring after
    each keyframe's insertion; per-keyframe curves and the replayed map's held-out figures.
    ``core``: mapper core overrides (``bench/mapper_replay.py``'s ``--core``, e.g.
    ``insertion.patch_px``), for every init alike: a policy measured on recorded runs."""
    torch.set_num_threads(1)  # as the live mapper (launch/demo.yaml threads: 1): the same map
    data = read_journal(journal)
    if init == "random":
        rp = random_params(launch)
        data["/metrizer/depth"] = [random_depth_msg(d, rp) for d in data["/metrizer/depth"]]
    p = mapper_params(str(launch), {})
    views = heldout_views(data, min_move_m)
    images = {m.stamp_ns: m for m in data["/camera/image"]}
    odo = {o.stamp_ns: np.asarray(o.T_world_cam) for o in data["/frontend/odometry"]}
    frames = sorted(odo)
    per_kf: list[dict[str, Any]] = []

    def after_insert(mapper: GaussianMapper) -> None:
        kf_id = mapper.keyframes[-1].keyframe_id
        if kf_id not in views:
            return
        s = views[kf_id]
        gt = _camera_rgb(images[s]).astype(np.float32) / 255.0
        c = converge(mapper, odo[s], gt, stop_db, cap)
        per_kf.append({"keyframe_id": kf_id, "view_frame": frames.index(s), **c})
        print(
            f"[convergence] {init} kf {kf_id}: frame {frames.index(s)}, {c['psnr_db'][0]:.2f} -> "
            f"{c['psnr_db'][-1]:.2f} dB after {len(c['psnr_db']) - 1} iterations",
            flush=True,
        )

    mapper, per = replay(data, p, core=core, after_insert=after_insert)
    q = score(mapper, data)
    return {
        "keyframes": per_kf,
        "stop_db": stop_db,
        "cap": cap,
        "replay_report_heldout_psnr_db": q["report_heldout_psnr_db"],
        "replay_gaussians": len(mapper.map),
        "replay_inserted_pruned": [sum(k["inserted"] for k in per), int(mapper.n_pruned)],
        "iters_per_keyframe": p.iters_per_keyframe,
    }


def iterations_to(curve: list[float], target_db: float) -> int | None:
    """Iterations until ``curve`` (PSNR after 0, 1, ... iterations) reaches ``target_db``."""
    return next((i for i, v in enumerate(curve) if v >= target_db), None)


def figures(conv: dict[str, Any], target_db: float) -> dict[str, Any]:
    """Table II's per-init figures at ``target_db`` from :func:`measure`'s per-keyframe curves."""
    its, gs = [], []
    for k in conv["keyframes"]:
        i = iterations_to(k["psnr_db"], target_db)
        its.append(math.inf if i is None else i)
        if i is not None:
            gs.append(k["gaussians"][i])
    med = float(np.median(its)) if its else math.inf
    return {
        "iters_to_target": None if math.isinf(med) else med,
        "gaussians_at_target": float(np.median(gs)) if gs else None,
        "keyframes_scored": len(its),
        "keyframes_reaching_target": len(gs),
        "psnr_after_insertion_db_median": float(
            np.median([k["psnr_db"][0] for k in conv["keyframes"]])
        )
        if conv["keyframes"]
        else None,
    }


def common_target(convs: dict[str, dict[str, Any]], cap_db: float = STOP_DB) -> float | None:
    """The highest of ``cap_db``, ``cap_db`` - 0.5, ... (down to 10 dB) at which every init's
    median iterations to the target is defined (the same rule for all)."""
    t = cap_db
    while t >= 10.0:
        if all(figures(c, t)["iters_to_target"] is not None for c in convs.values()):
            return t
        t = round(t - 0.5, 6)
    return None


def common_view_gaussians(
    convs: dict[str, dict[str, Any]], target_db: float
) -> tuple[list[int], dict[str, float | None]]:
    """The keyframes whose held-out view every init in ``convs`` reaches at ``target_db``, and per
    init the median Gaussians in its map when it does (``None``: no such keyframe). The same views
    for every init: a fixed view's "Gaussians at that point" (issue 17)."""
    per = {k: {kf["keyframe_id"]: kf for kf in c["keyframes"]} for k, c in convs.items()}
    hit = {
        k: {
            i: n
            for i, kf in p.items()
            if (n := iterations_to(kf["psnr_db"], target_db)) is not None
        }
        for k, p in per.items()
    }
    ids = sorted(set.intersection(*(set(h) for h in hit.values()))) if hit else []
    med = {
        k: float(np.median([per[k][i]["gaussians"][hit[k][i]] for i in ids])) if ids else None
        for k in per
    }
    return ids, med


def _common_views_figures(
    inits: dict[str, dict[str, Any]], convs: dict[str, dict[str, Any]], target_db: float
) -> None:
    """``gaussians_at_target`` of each init in ``inits`` over the views every init reaches (the
    own-views median kept as ``gaussians_at_target_own_views``)."""
    ids, med = common_view_gaussians(convs, target_db)
    for init, r in inits.items():
        r["gaussians_at_target_own_views"] = r["gaussians_at_target"]
        r["gaussians_at_target"] = med.get(init)
        r["keyframes_every_init_reaches"] = ids


def paired_ratios(convs: dict[str, dict[str, Any]], target_db: float) -> dict[str, Any]:
    """Per keyframe both MOGS and random reach the target: median of MOGS / random iterations
    (each + 1: a keyframe reached by its insertion alone counts as one step) and Gaussians."""
    if "mogs" not in convs or "random" not in convs:
        return {}
    ra = {k["keyframe_id"]: k for k in convs["random"]["keyframes"]}
    it, ga = [], []
    for k in convs["mogs"]["keyframes"]:
        r = ra.get(k["keyframe_id"])
        i, j = iterations_to(k["psnr_db"], target_db), r and iterations_to(r["psnr_db"], target_db)
        if i is not None and j is not None:
            it.append((i + 1) / (j + 1))
            ga.append(k["gaussians"][i] / r["gaussians"][j])
    return {
        "keyframes_both_reach": len(it),
        "iters_plus1_mogs_over_random_median": round(float(np.median(it)), 3) if it else None,
        "gaussians_mogs_over_random_median": round(float(np.median(ga)), 3) if ga else None,
    }


FIXED_VIEW_KEYS = ("iters_to_target", "wall_s_to_target", "gaussians_at_target", "curve")


def apply(res: dict[str, Any], convs: dict[str, dict[str, Any]], auto: bool) -> None:
    """Table II's keys of ``res`` (``bench/pipeline_table2.py``'s result) from the convergence
    replays ``convs`` (init -> :func:`measure`): the target is 20 dB when every init's median is
    defined there, else (``auto``) the highest common one (:func:`common_target`); the first
    definition's figures at the fixed view move to ``inits.<init>.fixed_view``."""
    target = STOP_DB
    if auto and any(figures(c, target)["iters_to_target"] is None for c in convs.values()):
        target = common_target(convs) or STOP_DB
    res["fixed_view_target_psnr_db"] = res["target_psnr_db"]
    res["target_psnr_db"] = target
    res["definition"] = "per-keyframe convergence (bench/table2_convergence.py)"
    for init, conv in convs.items():
        r = res["inits"][init]
        r["fixed_view"] = {k: r.pop(k) for k in FIXED_VIEW_KEYS if k in r}
        r["fixed_view"]["view_frame"] = r.pop("view_frame", None)
        r.update(figures(conv, target))
        r["convergence"] = conv
    _common_views_figures(res["inits"], convs, target)
    from bench.pipeline_table2 import ratios  # the same ratios as the first definition's

    res["ratios"] = {
        **ratios(res["inits"]),
        **paired_ratios(convs, target),
        "fixed_view": res.get("ratios", {}),
    }


def policy_table(
    root: Path, core: dict[str, Any], stop_db: float = STOP_DB, cap: int = CAP
) -> dict[str, Any]:
    """Table II's figures under one mapper policy (``core`` overrides, every init alike) from a
    ``bench/pipeline_table2.py`` run folder ``root`` (its ``mogs/`` and ``prior_global/`` runs;
    random depth regenerated from the mogs run as :class:`RandomDepthNode` publishes it): the
    target is ``stop_db`` if every init's median reaches it, else the highest common one."""
    runs = {"mogs": root / "mogs", "prior_global": root / "prior_global", "random": root / "mogs"}
    convs = {
        init: measure(
            r / "journal" / "journal.log", r / "launch.yaml", init, stop_db, cap, 0.1, core
        )
        for init, r in runs.items()
    }
    target = stop_db
    if any(figures(c, target)["iters_to_target"] is None for c in convs.values()):
        target = common_target(convs, stop_db) or stop_db
    inits = {
        init: {
            **figures(c, target),
            "replay_heldout_psnr_db": c["replay_report_heldout_psnr_db"],
            "replay_gaussians": c["replay_gaussians"],
            "replay_inserted_pruned": c["replay_inserted_pruned"],
            "convergence": c,
        }
        for init, c in convs.items()
    }
    _common_views_figures(inits, convs, target)
    m, r, g = inits["mogs"], inits["random"], inits["prior_global"]

    def div(a: float | None, b: float | None) -> float | None:
        return None if a is None or not b else round(a / b, 3)

    return {
        "core": core,
        "target_psnr_db": target,
        "inits": inits,
        "ratios": {
            "iters_to_target_mogs_over_random": div(m["iters_to_target"], r["iters_to_target"]),
            "gaussians_at_target_mogs_over_random": div(
                m["gaussians_at_target"], r["gaussians_at_target"]
            ),
            "replay_heldout_mogs_minus_prior_global_db": round(
                m["replay_heldout_psnr_db"] - g["replay_heldout_psnr_db"], 3
            ),
            **paired_ratios(convs, target),
        },
    }


def _f(v: Any, spec: str = ".2f") -> str:
    return "-" if v is None else format(v, spec)


def markdown(cmd: str, res: dict[str, Any], machine: str, notes: str = "") -> str:
    """The ``pipeline-table2`` section of docs/benchmarks.md; ``notes``: text after the ratios."""
    t = res["target_psnr_db"]
    notes = f"\n{notes.strip()}\n" if notes.strip() else ""
    rows = []
    for k, r in res["inits"].items():
        fv = r.get("fixed_view", {})
        rows.append(
            f"| {k} | {_f(r['iters_to_target'], '.1f')} | "
            f"{r['keyframes_reaching_target']}/{r['keyframes_scored']} | "
            f"{_f(r['gaussians_at_target'], '.0f')} | {_f(r['psnr_after_insertion_db_median'])} | "
            f"{_f(r['psnr_at_budget_db'])} | {_f(r['ssim_at_budget'], '.3f')} | "
            f"{r['gaussians_at_budget']} | {r['gaussians_inserted']} | {r['gaussians_pruned']} | "
            f"{_f(r.get('gaussians_at_target_own_views'), '.0f')} | "
            f"{_f(fv.get('iters_to_target'), 'd')} |"
        )
    rt = res["ratios"]
    conv = next(iter(res["inits"].values()))["convergence"]
    return f"""## Table II in the live pipeline (issue 17)

Command: `{cmd}`

Machine: {machine}; 2 cores shared by all processes. Demo drive ({res["frames"]} frames, 621x188),
the same mapper policy and budget (`launch/demo.yaml`: {res["iters_per_keyframe"]} iterations per
keyframe) for every initialisation; overrides for every init alike: {res.get("overrides") or "none"}.
**Iterations to {t:g} dB**: per keyframe after its insertion, the iterations of the mapper's own
loop until the held-out view next to it (the nearest frame within 2 that is not a keyframe,
ground truth the recorded camera image, pose from the frontend) reaches {t:g} dB, counted iteration by
iteration on a copy of the live map (the run's journal replayed, `bench/table2_convergence.py`;
at most {conv["cap"]}), median over the {next(iter(res["inits"].values()))["keyframes_scored"]}
keyframes after the car drives off. **Gaussians at target**: in the map then, median over the
{len(next(iter(res["inits"].values())).get("keyframes_every_init_reaches", []))} keyframes whose view
every init reaches (the same views for all; over each init's own reaching keyframes in the last
column but one). **At the budget**: the run report's held-out frames after the drive.

| init | iterations to {t:g} dB (median) | keyframes reaching it | Gaussians at target | PSNR after insertion [dB] | held-out PSNR at budget [dB] | held-out SSIM | Gaussians at budget | inserted | pruned | Gaussians at target, own keyframes | first definition: iterations to {res.get("fixed_view_target_psnr_db", 0):g} dB at frame {res.get("view_frame")} |
| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |
{chr(10).join(rows)}

Ratios: MOGS / random iterations to {t:g} dB {_f(rt["iters_to_target_mogs_over_random"], ".3f")}
(goal <= 0.7), Gaussians at target {_f(rt["gaussians_at_target_mogs_over_random"], ".3f")}
(goal <= 0.8); MOGS - prior_global held-out PSNR at budget
{_f(rt["psnr_at_budget_mogs_minus_prior_global_db"])} dB (goal >= 0). Paired over the
{rt.get("keyframes_both_reach", 0)} keyframes both reach: median of (iterations + 1) MOGS /
random {_f(rt.get("iters_plus1_mogs_over_random_median"), ".3f")}, of Gaussians
{_f(rt.get("gaussians_mogs_over_random_median"), ".3f")}.
{notes}
![Table II in the live pipeline](pipeline_table2.png)
"""


def plot(res: dict[str, Any], path: Path) -> None:
    """Per init: the held-out view's PSNR against the iterations after each keyframe (thin) and
    their median (thick), and the Gaussians in the map at each keyframe."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.5))
    for init, r in res["inits"].items():
        kfs = r["convergence"]["keyframes"]
        (line,) = a1.plot([], [], "-", lw=2, label=init)
        n = max((len(k["psnr_db"]) for k in kfs), default=0)
        for k in kfs:
            a1.plot(k["psnr_db"], "-", lw=0.5, alpha=0.5, color=line.get_color())
        # a keyframe that stopped (reached 20 dB) keeps its last value in the median
        pad = [k["psnr_db"] + [k["psnr_db"][-1]] * (n - len(k["psnr_db"])) for k in kfs]
        if pad:
            a1.plot(np.median(np.array(pad), 0), "-", lw=2, color=line.get_color())
        a2.plot([k["keyframe_id"] for k in kfs], [k["gaussians"][0] for k in kfs], ".-", label=init)
    a1.axhline(res["target_psnr_db"], color="k", ls=":", lw=1)
    a1.set_title("a copy stops at 20 dB (the median holds it there)", fontsize=9)
    a1.set_xlabel("iterations after the keyframe's insertion")
    a1.set_ylabel("held-out view next to it: PSNR [dB]")
    a1.legend()
    a2.set_xlabel("keyframe id")
    a2.set_ylabel("Gaussians after its insertion")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("run_dir", help="a bench/pipeline_table2.py run folder (launch.yaml, journal/)")
    ap.add_argument("--init", choices=("mogs", "prior_global", "random"))
    ap.add_argument(
        "--all-inits",
        action="store_true",
        help="run_dir is the bench's folder of runs (mogs/, prior_global/): the three inits' "
        "Table II figures under the --core policy (random from the mogs run)",
    )
    ap.add_argument("--plot", default=None, help="with --all-inits: the curves as a PNG")
    ap.add_argument("--stop-db", type=float, default=STOP_DB)
    ap.add_argument("--cap", type=int, default=CAP)
    ap.add_argument("--json", default=None)
    ap.add_argument(
        "--core",
        action="append",
        default=[],
        help="MapperParams field=JSON value (insertion.FIELD for InsertionParams)",
    )
    args = ap.parse_args(argv)
    run = Path(args.run_dir)
    core = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.core)}
    if args.all_inits:
        res = policy_table(run, core, args.stop_db, args.cap)
        summary = {k: v for k, v in res.items() if k != "inits"}
        for init, r in res["inits"].items():
            summary[init] = {k: v for k, v in r.items() if k != "convergence"}
        print(json.dumps(summary, indent=1))
        write_json(args.json, res)
        if args.plot:
            plot(res, Path(args.plot))
        return 0
    if args.init is None:
        ap.error("--init (or --all-inits)")
    conv = measure(
        run / "journal" / "journal.log",
        run / "launch.yaml",
        args.init,
        args.stop_db,
        args.cap,
        core=core,
    )
    for k, v in figures(conv, args.stop_db).items():
        print(f"{k}: {v}")
    write_json(args.json, conv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
