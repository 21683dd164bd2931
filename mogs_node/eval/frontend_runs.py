"""Offline runs of the frontend on a whole sequence (sim, sim along the KITTI OXTS drive, EuRoC):
``mogs eval traj`` (:func:`evaluate`) and ``bench/frontend.py``. Ground truth is read here only to
score (with :mod:`mogs_node.eval.traj`)."""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import DatasetError
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.frontend import FrameOutput, Frontend, FrontendParams
from mogs_node.frontend.trajectory_io import write_kitti, write_tum
from mogs_node.geometry import se3_inverse
from mogs_node.shared_data import shared_data_dir

if TYPE_CHECKING:
    from mogs_node.sim.sequence import SimSequence

__all__ = [
    "RunResult",
    "evaluate",
    "keyframe_point_figures",
    "load_dataset",
    "run_dataset",
    "run_frontend",
    "score_run",
]

log = logging.getLogger(__name__)

DEFAULT_DATA = shared_data_dir()


@dataclass
class RunResult:
    """Per-frame outputs of a run with the ground truth at the same frames."""

    outputs: list[FrameOutput]
    gt_T_world_cam: NDArray[np.float64]  # [F, 4, 4] for every input frame
    stamps_ns: NDArray[np.int64]  # [F]
    counters: dict[str, int]
    wall_s: float
    timings_ms: dict[str, float] = field(default_factory=dict)  # mean per frame


def run_frontend(
    frontend: Frontend,
    stamps_ns: NDArray,
    images: Iterable[NDArray],
    imu_stamps_ns: NDArray,
    gyro_rad_s: NDArray,
    accel_m_s2: NDArray,
) -> list[FrameOutput]:
    """Stream a recorded sequence into ``frontend`` in time order (IMU up to each frame first)."""
    outs: list[FrameOutput] = []
    k = 0
    n_imu = len(imu_stamps_ns)
    for t, img in zip(np.asarray(stamps_ns).tolist(), images, strict=True):
        t_imu = t + frontend.params.time_offset_ns
        while k < n_imu and imu_stamps_ns[k] <= t_imu:
            outs += frontend.add_imu(int(imu_stamps_ns[k]), gyro_rad_s[k], accel_m_s2[k])
            k += 1
        outs += frontend.add_image(int(t), img)
    return outs


SIM_IMU_HEIGHT_M = 0.93  # mogs_node.sim.trajectory's default IMU height above the road
SIM_STATIC_START_S = 2.0  # default standstill before the sim drive: the static initialisation
# (gravity from the accelerometer, zero velocity) fixes the metric scale


def load_dataset(
    dataset: str,
    *,
    seconds: float | None = None,
    seed: int = 0,
    data: str | Path | None = None,
    size: tuple[int, int] = (621, 188),
    static_start_s: float | None = None,
) -> dict:
    """Sequence as plain arrays: stamps, image loader, IMU, camera model, ``T_imu_cam`` and GT.

    ``static_start_s``: seconds the sim vehicle stands still before driving off (``sim`` only;
    default :data:`SIM_STATIC_START_S`, 0 for a moving start). The OXTS drive and EuRoC are
    replayed as recorded."""
    if dataset in ("sim", "oxts"):
        from mogs_node.sim import SimConfig, make_sequence

        kw = {}
        if dataset == "oxts":
            oxts_dir = Path(data) if data else DEFAULT_DATA / "kitti_raw_2011_09_26_drive_0001_oxts"
            kw = {"trajectory": "oxts", "oxts_dir": str(oxts_dir)}
            seconds = min(seconds or 10.5, 10.5)
            if static_start_s:
                raise DatasetError("static_start_s: the OXTS drive has no standstill")
        else:
            seconds = seconds or 60.0
            kw = {
                "static_start_s": SIM_STATIC_START_S
                if static_start_s is None
                else float(static_start_s)
            }
            if seconds < kw["static_start_s"] + 1.0:
                raise DatasetError(
                    f"seconds: {seconds} s leaves the sim parked "
                    f"(static_start_s {kw['static_start_s']} s); use >= "
                    f"{kw['static_start_s'] + 1.0} s or static_start_s=0"
                )
        cfg = SimConfig(
            seed=seed, n_frames=int(round(seconds * 10.0)) + 1, width=size[0], height=size[1], **kw
        )
        seq = make_sequence(cfg)
        return dict(
            stamps_ns=seq.stamps_ns,
            image=lambda i: seq.render(i).rgb,
            imu=(seq.imu_stamps_ns, seq.imu_gyro_rad_s, seq.imu_accel_m_s2),
            camera=CameraModel(seq.camera),
            T_imu_cam=seq.T_imu_cam,
            # vehicle calibration: the IMU rides SIM_IMU_HEIGHT_M above the road (z up), the
            # camera T_imu_cam[2, 3] above it (KITTI's 1.65 m)
            camera_height_m=SIM_IMU_HEIGHT_M + float(seq.T_imu_cam[2, 3]),
            gt=seq.T_world_cam,
            velocity=seq.velocity_world_m_s,
            name=f"{dataset} seed {seed} {seconds:.1f}s",
        )
    if dataset == "euroc":
        from mogs_node.datasets.euroc import read_euroc

        root = Path(data) if data else DEFAULT_DATA / "euroc_v1_01_micro"
        if not root.exists():
            raise DatasetError(f"{root}: EuRoC excerpt not found")
        seq = read_euroc(root, undistort=False)
        frames = list(seq.frames)
        if seconds:
            t0 = frames[0].stamp_ns
            frames = [f for f in frames if f.stamp_ns - t0 <= seconds * 1e9]
        if any(f.T_world_cam is None for f in frames):
            raise DatasetError(f"{root}: ground truth does not cover every frame")
        dist = seq.distortion or {"model": "radial-tangential", "coeffs": []}
        cam = CameraModel(
            frames[0].camera,
            "radtan" if dist["coeffs"] else "none",
            tuple(float(c) for c in dist["coeffs"]),
        )
        return dict(
            stamps_ns=np.array([f.stamp_ns for f in frames], np.int64),
            image=lambda i: frames[i].image,
            imu=(seq.imu.stamps_ns, seq.imu.gyro_rad_s, seq.imu.accel_m_s2),
            camera=cam,
            T_imu_cam=seq.T_imu_cam,
            gt=np.stack([f.T_world_cam for f in frames]),
            name=f"euroc {root.name}",
        )
    raise DatasetError(f"dataset: unknown {dataset!r} (sim, oxts, euroc)")


def run_dataset_frames(
    d: dict,
    params: FrontendParams | None = None,
    on_frame: Callable[[FrameOutput], None] | None = None,
) -> RunResult:
    fe = Frontend(params or FrontendParams(), d["camera"], d["T_imu_cam"])
    t0 = time.perf_counter()
    images = (d["image"](i) for i in range(len(d["stamps_ns"])))
    outs = run_frontend(fe, d["stamps_ns"], images, *d["imu"])
    wall = time.perf_counter() - t0
    if on_frame:
        for o in outs:
            on_frame(o)
    timings = {
        k: float(np.mean([o.timings_ms.get(k, 0.0) for o in outs]))
        for k in ("tracking", "estimation", "ground")
    }
    return RunResult(outs, d["gt"], d["stamps_ns"], dict(fe.counters), wall, timings)


def score_run(run: RunResult, *, keyframes_only: bool = True) -> dict:
    """Figures of DESIGN.md section 7 (on keyframes by default) plus run facts. A run with fewer
    than 3 keyframes (parked throughout: no keyframe while still, docs/frontend.md round 8) is
    scored on every frame (``scored_on``)."""
    from mogs_node.eval.traj import trajectory_metrics

    stamp_index = {int(t): i for i, t in enumerate(run.stamps_ns)}
    posed = [o for o in run.outputs if o.T_world_cam is not None]
    sel = [o for o in posed if o.keyframe is not None or not keyframes_only]
    scored_on = "keyframes" if keyframes_only else "frames"
    if len(sel) < 3 and keyframes_only:
        sel, scored_on = posed, "frames"
    if len(sel) < 3:
        raise DatasetError(f"run: only {len(sel)} estimated poses, cannot score")
    idx = np.array([stamp_index[o.stamp_ns] for o in sel])
    est = np.stack([o.T_world_cam for o in sel])
    ref = run.gt_T_world_cam[idx]
    rate = (len(run.stamps_ns) - 1) / max((run.stamps_ns[-1] - run.stamps_ns[0]) * 1e-9, 1e-9)
    per_s = max(1, int(round(len(sel) / max((sel[-1].stamp_ns - sel[0].stamp_ns) * 1e-9, 1e-9))))
    out = trajectory_metrics(run.stamps_ns[idx], est, ref, rpe_delta_frames=per_s)
    E = se3_inverse(se3_inverse(ref[0]) @ ref[-1]) @ (se3_inverse(est[0]) @ est[-1])
    out.update(
        {
            "end_drift_m": float(np.linalg.norm(E[:3, 3])),
            "ate_se3_percent_of_path": 100.0
            * out["ate_se3_rmse_m"]
            / max(out["path_length_m"], 1e-9),
            "poses_scored": len(sel),
            "scored_on": scored_on,
            "frames": len(run.stamps_ns),
            "first_pose_s": float((sel[0].stamp_ns - run.stamps_ns[0]) * 1e-9),
            "frame_rate_hz": float(rate),
            "tracking_ms_per_frame": run.timings_ms.get("tracking", 0.0),
            "estimation_ms_per_frame": run.timings_ms.get("estimation", 0.0),
            "ground_ms_per_frame": run.timings_ms.get("ground", 0.0),
            "resets": int(
                run.counters.get("divergence_resets", 0) + run.counters.get("imu_gap_resets", 0)
            ),
            # road measurements used / without a result / left out by the tracking gate
            **{
                f"{k}_frames": int(run.counters.get(k, 0))
                for k in (
                    "ground_measurements",
                    "ground_rejected",
                    "ground_gated",
                    "ground_implausible",
                )
            },
        }
    )
    return out


EDGE_JUMP = 0.10  # "on a depth edge": a 4-neighbour ground-truth depth jump above 10 % ...
EDGE_RADIUS_PX = 2  # ... within 2 px of the point's pixel (sky counts as a jump)
# an edge point is a wrong one when its depth is more than EDGE_JUMP off the true depth of every
# pixel within this radius of its own (neither side's depth: straddling, or slid along the edge)
EDGE_MATCH_RADIUS_PX = 1


def _matches_a_surface(depth_m: NDArray, uv: NDArray, z_m: NDArray, radius_px: int) -> NDArray:
    """Whether each depth ``z_m`` [N] is within :data:`EDGE_JUMP` (relative) of the true depth of
    some pixel within ``radius_px`` of its pixel ``uv`` [N, 2] (int, in the image)."""
    r = int(radius_px)
    pad = np.pad(np.where(np.isfinite(depth_m), depth_m, np.inf), r, constant_values=np.inf)
    best = np.full(len(z_m), np.inf)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            t = pad[uv[:, 1] + r + dy, uv[:, 0] + r + dx]
            with np.errstate(invalid="ignore"):
                rel = np.where(np.isfinite(t) & (t > 0), np.abs(z_m - t) / t, np.inf)
            best = np.minimum(best, rel)
    return best <= EDGE_JUMP


def keyframe_point_figures(
    outputs: Iterable[FrameOutput],
    depth_m_of: Callable[[int], NDArray],
    speed_m_s_of: Callable[[int], float],
    *,
    min_speed_m_s: float = 0.5,
) -> dict[str, float]:
    """The keyframes' sparse points against ground truth (docs/frontend.md, round 6).

    ``depth_m_of(stamp_ns)``: the true z-depth [H, W] of the frame (inf on sky);
    ``speed_m_s_of(stamp_ns)``: the vehicle's speed, a keyframe faster than ``min_speed_m_s`` is
    a moving one. Figures: the median point count per moving keyframe, the median relative depth
    error at the points' pixels (pixels with a finite truth), and the share of points that
    straddle a depth edge (issue 16's "on depth edges", round 9): on an edge (:data:`EDGE_JUMP`
    within :data:`EDGE_RADIUS_PX`) and more than :data:`EDGE_JUMP` off the truth of every pixel
    within :data:`EDGE_MATCH_RADIUS_PX` (neither side's depth; a corner on a silhouette with
    the foreground's depth is a right point), also weighted by omega; and the share of points
    near an edge at all (the geometric definition of rounds 6 to 8)."""
    from mogs_node.eval.depth_sim import _depth_edge_free

    counts, errors, on_edge, weights, n_kf, n_empty = [], [], [], [], 0, 0
    wrong_side = []
    for o in outputs:
        kf = o.keyframe
        if kf is None:
            continue
        n_kf += 1
        n_empty += len(kf.feature_ids) == 0
        depth = depth_m_of(kf.stamp_ns)
        H, W = depth.shape
        if speed_m_s_of(kf.stamp_ns) > min_speed_m_s:
            counts.append(len(kf.feature_ids))
        uv = np.clip(np.round(kf.feature_uv_px).astype(np.int64), 0, [W - 1, H - 1])
        truth = depth[uv[:, 1], uv[:, 0]]
        finite = np.isfinite(truth) & (truth > 0)
        z = kf.feature_xyz_cam_m[:, 2].astype(np.float64)
        errors.append(np.abs(z[finite] - truth[finite]) / truth[finite])
        edge_free = _depth_edge_free(depth, EDGE_JUMP, EDGE_RADIUS_PX)
        on_edge.append(~edge_free[uv[:, 1], uv[:, 0]])
        wrong_side.append(on_edge[-1] & ~_matches_a_surface(depth, uv, z, EDGE_MATCH_RADIUS_PX))
        weights.append(kf.feature_weight.astype(np.float64))
    err = np.concatenate(errors) if errors else np.zeros(0)
    edge = np.concatenate(on_edge) if on_edge else np.zeros(0, bool)
    w = np.concatenate(weights) if weights else np.zeros(0)
    straddle = np.concatenate(wrong_side) if wrong_side else np.zeros(0, bool)
    return {
        "points_per_keyframe_median": float(np.median(counts)) if counts else 0.0,
        "points_rel_err_median": float(np.median(err)) if len(err) else float("nan"),
        "points_on_edges_share": float(np.mean(straddle)) if len(edge) else 0.0,
        # the same share counted by omega: what a weighted consumer (the metrizer) sees
        "points_on_edges_weight_share": float(w[straddle].sum() / w.sum()) if w.sum() > 0 else 0.0,
        "points_near_edges_share": float(np.mean(edge)) if len(edge) else 0.0,
        "points_total": float(len(edge)),
        "keyframes": float(n_kf),
        "keyframes_moving": float(len(counts)),
        "keyframes_without_points": float(n_empty),
    }


def run_dataset(
    dataset: str,
    *,
    seconds: float | None = None,
    seed: int = 0,
    data: str | Path | None = None,
    out_dir: str | Path | None = None,
    params: FrontendParams | None = None,
    static_start_s: float | None = None,
    ground: bool = False,
) -> dict:
    """Run the frontend on ``dataset`` and score it; optionally write TUM/KITTI trajectories.

    ``ground``: measure translations on the road at the dataset's calibrated camera height (sim
    and OXTS only): the dynamic initialisation's scale and a distance factor per frame
    (docs/frontend.md, round 5)."""
    d = load_dataset(dataset, seconds=seconds, seed=seed, data=data, static_start_s=static_start_s)
    if ground:
        if "camera_height_m" not in d:
            raise DatasetError(f"ground: {dataset} has no camera height above a road")
        params = params or FrontendParams()
        params = replace(
            params, ground=replace(params.ground, camera_height_m=d["camera_height_m"])
        )
    log.info("running the frontend on %s (%d frames)", d["name"], len(d["stamps_ns"]))
    run = run_dataset_frames(d, params)
    figures = {"dataset": dataset, **score_run(run), "ground": bool(ground)}
    if dataset == "sim":
        figures["static_start_s"] = SIM_STATIC_START_S if static_start_s is None else static_start_s
    all_frames = score_run(run, keyframes_only=False)
    figures["ate_se3_rmse_m_all_frames"] = all_frames["ate_se3_rmse_m"]
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        sel = [o for o in run.outputs if o.T_world_cam is not None]
        idx = {int(t): i for i, t in enumerate(run.stamps_ns)}
        stamps = np.array([o.stamp_ns for o in sel], np.int64)
        est = np.stack([o.T_world_cam for o in sel])
        ref = run.gt_T_world_cam[[idx[int(t)] for t in stamps]]
        write_tum(out / "estimate_tum.txt", stamps, est)
        write_tum(out / "groundtruth_tum.txt", stamps, ref)
        write_kitti(out / "estimate_kitti.txt", est)
        write_kitti(out / "groundtruth_kitti.txt", ref)
    return figures


def evaluate(args: argparse.Namespace) -> dict:
    """Run the frontend on ``args.dataset`` (sim | oxts | euroc) and score its keyframe poses.

    The sim drive starts with a standstill (:data:`SIM_STATIC_START_S`, overridable by an
    ``args.static_start_s`` attribute) so that the static initialisation fixes the metric scale; the
    OXTS drive has none and uses the dynamic initialisation. On both (a car with a calibrated
    camera height) the road measures translations too, unless ``args.no_ground``."""
    return run_dataset(
        args.dataset,
        seconds=args.seconds,
        seed=args.seed,
        data=args.data,
        out_dir=args.out,
        static_start_s=getattr(args, "static_start_s", None),
        ground=args.dataset in ("sim", "oxts") and not getattr(args, "no_ground", False),
    )


def window_refinement(seq: SimSequence, params: FrontendParams) -> dict:
    """A sim sequence through the frontend, keeping each
    keyframe's pose as first published and as the window's solves last left it
    (``Frontend.window_keyframe_poses``, what ``/frontend/refined_pose`` carries); scored against
    the sequence's ground truth by stamp: ``keyframes``, ``ate_first_m``, ``ate_refined_m``
    (SE(3)-aligned keyframe ATE), ``max_move_m``, ``refined`` (keyframes moved by the window),
    ``window_not_keyframe`` (window poses of stamps never published as keyframes: must be 0)."""
    from mogs_node.eval.traj import trajectory_metrics

    fe = Frontend(params, CameraModel(seq.camera), seq.T_imu_cam)
    published: dict[int, NDArray] = {}
    refined: dict[int, NDArray] = {}
    strays = 0
    for t, kind, k in seq.sensor_events():
        if kind == "imu":
            outs = fe.add_imu(int(t), seq.imu_gyro_rad_s[k], seq.imu_accel_m_s2[k])
        else:
            outs = fe.add_image(int(t), seq.render(k).rgb)
        for o in outs:
            if o.keyframe is not None:
                published[o.keyframe.stamp_ns] = o.keyframe.T_world_cam.copy()
        if outs:
            window = fe.window_keyframe_poses()
            strays += sum(s not in published for s, _ in window)
            refined.update(window)
    stamps = np.array(sorted(published), np.int64)
    truth = {int(t): T for t, T in zip(seq.stamps_ns, seq.T_world_cam)}
    gt = np.array([truth[int(s)] for s in stamps])
    final = {s: refined.get(s, published[s]) for s in published}
    moves = [float(np.linalg.norm(final[s][:3, 3] - published[s][:3, 3])) for s in published]
    first = trajectory_metrics(stamps, np.array([published[s] for s in stamps]), gt)
    last = trajectory_metrics(stamps, np.array([final[s] for s in stamps]), gt)
    return {
        "keyframes": len(stamps),
        "refined": sum(m > 0 for m in moves),
        "max_move_m": max(moves, default=0.0),
        "ate_first_m": first["ate_se3_rmse_m"],
        "ate_refined_m": last["ate_se3_rmse_m"],
        "window_not_keyframe": strays,
    }
