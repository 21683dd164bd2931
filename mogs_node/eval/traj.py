"""Trajectory scores with ``evo``: estimated poses against ground truth (ATE, RPE, scale).

:func:`trajectory_metrics` is pure (trajectories in, figures with the keys fixed by DESIGN.md
section 7 out); ``mogs eval traj`` runs the frontend on a sequence in
:mod:`mogs_node.eval.frontend_runs` and scores it here. Ground truth is used only for the alignment.
"""

from __future__ import annotations

import copy
import logging

import numpy as np
from evo.core import metrics
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D
from numpy.typing import NDArray

from mogs_node.errors import ShapeError
from mogs_node.geometry import check_array, nearest_rotation, rotation_defect

__all__ = ["MAX_ROTATION_DEFECT", "orthonormalized", "trajectory_metrics"]

#: a pose whose rotation is further than this from SO(3) (max |R R^T - I|) cannot be scored
MAX_ROTATION_DEFECT = 1e-2

log = logging.getLogger(__name__)


def orthonormalized(name: str, poses: NDArray) -> NDArray:
    """``poses`` [N, 4, 4] with every rotation projected to the nearest rotation.

    evo checks SO(3) to 1e-6; poses chained from a calibration typed with six decimals, or read
    from a text file, miss that by ~1e-6 (issue 28) and would not be scored at all. A rotation
    further than :data:`MAX_ROTATION_DEFECT` from SO(3) is no rounding: :class:`ShapeError` naming
    the poses (index, defect) and why.
    """
    P = np.array(poses, dtype=np.float64)
    defect = rotation_defect(P[:, :3, :3])
    bad = np.flatnonzero(~(defect <= MAX_ROTATION_DEFECT))
    if len(bad):
        shown = ", ".join(f"{int(i)} ({defect[i]:.3g})" for i in bad[:10])
        raise ShapeError(
            f"{name}: {len(bad)} of {len(P)} poses have no rotation matrix (max |R R^T - I| > "
            f"{MAX_ROTATION_DEFECT:g}, or det <= 0): index (defect) {shown}"
            + (" ..." if len(bad) > 10 else "")
        )
    rows = P[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])
    bad = np.flatnonzero(np.abs(rows).max(axis=1) > 1e-9)
    if len(bad):
        raise ShapeError(
            f"{name}: {len(bad)} poses have a last row other than [0, 0, 0, 1]: index "
            + ", ".join(str(int(i)) for i in bad[:10])
        )
    P[:, :3, :3] = nearest_rotation(P[:, :3, :3])
    P[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return P


def trajectory_metrics(
    stamps_ns: NDArray, poses_est: NDArray, poses_ref: NDArray, rpe_delta_frames: int = 10
) -> dict[str, float]:
    """ATE (SE(3)- and Sim(3)-aligned, Umeyama), scale error and RPE of ``poses_est`` [N, 4, 4]
    against ``poses_ref`` [N, 4, 4] at the same ``stamps_ns`` [N].

    ``scale_error`` is ``|s - 1|`` with ``s`` the Sim(3) alignment's scale; RPE compares relative
    motions over ``rpe_delta_frames`` frames (RMSE of translation in m and of rotation in degrees).
    Rotations are re-orthonormalised first (:func:`orthonormalized`); what cannot be scored is a
    :class:`ShapeError` that says which poses and why.
    """
    est = check_array("poses_est", poses_est, shape=(None, 4, 4), finite=True)
    ref = check_array("poses_ref", poses_ref, shape=(len(est), 4, 4), finite=True)
    est, ref = orthonormalized("poses_est", est), orthonormalized("poses_ref", ref)
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
