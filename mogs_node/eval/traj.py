"""``mogs eval traj``: run the visual-inertial frontend on a sequence and score it with ``evo``.

:func:`trajectory_metrics` is the pure part (trajectories in, figures out); :func:`evaluate` loads
or simulates the sequence, runs :class:`mogs_node.frontend.frontend.Frontend` and returns the figures
with the keys fixed by DESIGN.md section 7. Ground truth is used only here, for the alignment.
"""

from __future__ import annotations

import argparse
import copy
import logging

import numpy as np
from evo.core import metrics
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D
from numpy.typing import NDArray

from mogs_node.errors import ShapeError
from mogs_node.geometry import check_array

__all__ = ["evaluate", "trajectory_metrics"]

log = logging.getLogger(__name__)


def trajectory_metrics(
    stamps_ns: NDArray, poses_est: NDArray, poses_ref: NDArray, rpe_delta_frames: int = 10
) -> dict[str, float]:
    """ATE (SE(3)- and Sim(3)-aligned, Umeyama), scale error and RPE of ``poses_est`` [N, 4, 4]
    against ``poses_ref`` [N, 4, 4] at the same ``stamps_ns`` [N].

    ``scale_error`` is ``|s - 1|`` with ``s`` the Sim(3) alignment's scale; RPE compares relative
    motions over ``rpe_delta_frames`` frames (RMSE of translation in m and of rotation in degrees).
    """
    est = check_array("poses_est", poses_est, shape=(None, 4, 4), finite=True)
    ref = check_array("poses_ref", poses_ref, shape=(len(est), 4, 4), finite=True)
    t = check_array("stamps_ns", stamps_ns, shape=(len(est),), dtype=np.integer) * 1e-9
    if len(est) < 3:
        raise ShapeError("poses_est: need at least 3 poses")
    traj_ref = PoseTrajectory3D(poses_se3=list(ref), timestamps=t)
    traj_est = PoseTrajectory3D(poses_se3=list(est), timestamps=t)
    se3 = copy.deepcopy(traj_est)
    sim3 = copy.deepcopy(traj_est)
    try:
        se3.align(traj_ref, correct_scale=False)
        _, _, s = sim3.align(traj_ref, correct_scale=True)
    except GeometryException as err:
        raise ShapeError(f"poses_ref: degenerate for alignment ({err})") from err
    out: dict[str, float] = {"path_length_m": float(traj_ref.path_length)}
    for name, tr in (("ate_se3_rmse_m", se3), ("ate_sim3_rmse_m", sim3)):
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((traj_ref, tr))
        out[name] = float(ape.get_statistic(metrics.StatisticsType.rmse))
    out["scale_error"] = float(abs(s - 1.0))
    delta = max(1, min(int(rpe_delta_frames), len(est) - 1))
    for name, rel in (
        ("rpe_trans_m", metrics.PoseRelation.translation_part),
        ("rpe_rot_deg", metrics.PoseRelation.rotation_angle_deg),
    ):
        rpe = metrics.RPE(rel, delta=delta, delta_unit=metrics.Unit.frames, all_pairs=False)
        rpe.process_data((traj_ref, traj_est))
        out[name] = float(rpe.get_statistic(metrics.StatisticsType.rmse))
    return out


def evaluate(args: argparse.Namespace) -> dict:
    """Run the frontend on ``args.dataset`` (sim | oxts | euroc) and score its keyframe poses.

    The sim drive starts with a standstill (``runs.SIM_STATIC_START_S``, overridable by an
    ``args.static_start_s`` attribute) so that the static initialisation fixes the metric scale; the
    OXTS drive has none and uses the dynamic initialisation. On both (a car with a calibrated
    camera height) the road measures translations too, unless ``args.no_ground``."""
    from mogs_node.frontend.runs import run_dataset

    return run_dataset(
        args.dataset,
        seconds=args.seconds,
        seed=args.seed,
        data=args.data,
        out_dir=args.out,
        static_start_s=getattr(args, "static_start_s", None),
        ground=args.dataset in ("sim", "oxts") and not getattr(args, "no_ground", False),
    )
