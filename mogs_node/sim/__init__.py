"""Synthetic driving world with ground truth (DESIGN.md section 6).

Typical use::

    from mogs_node.sim import SimConfig, make_sequence
    seq = make_sequence(SimConfig(seed=0, n_frames=30, width=621, height=188))
    frame = seq.render(0)   # rgb, depth_m, instance_id, instance_kind, T_world_cam, stamp_ns

``simulated_lfm`` is for controlled experiments only; product depth-prior code never imports it.
"""

from mogs_node.sim.imu import ImuNoiseParams, integrate_imu, simulate_imu_noise
from mogs_node.sim.lfm import LfmParams, simulated_lfm, simulated_lfm_with_truth
from mogs_node.sim.sequence import (
    KITTI_CAMERA,
    T_IMU_CAM_DEFAULT,
    SimConfig,
    SimFrame,
    SimSequence,
    make_sequence,
)
from mogs_node.sim.trajectory import GRAVITY_WORLD_M_S2, Trajectory
from mogs_node.sim.world import (
    KIND_BOX,
    KIND_CYLINDER,
    KIND_ELLIPSOID,
    KIND_NAMES,
    KIND_PLANE,
    Box,
    Cylinder,
    Ellipsoid,
    PlaneRect,
    World,
    WorldParams,
)

__all__ = [
    "GRAVITY_WORLD_M_S2",
    "KIND_BOX",
    "KIND_CYLINDER",
    "KIND_ELLIPSOID",
    "KIND_NAMES",
    "KIND_PLANE",
    "KITTI_CAMERA",
    "T_IMU_CAM_DEFAULT",
    "Box",
    "Cylinder",
    "Ellipsoid",
    "ImuNoiseParams",
    "LfmParams",
    "PlaneRect",
    "SimConfig",
    "SimFrame",
    "SimSequence",
    "Trajectory",
    "World",
    "WorldParams",
    "integrate_imu",
    "make_sequence",
    "simulate_imu_noise",
    "simulated_lfm",
    "simulated_lfm_with_truth",
]
