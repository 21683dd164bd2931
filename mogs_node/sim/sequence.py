"""A simulated drive: trajectory + world + camera + IMU, with ground truth for everything.

Frames ``i`` are at ``t = i / frame_rate_hz`` (s), stamps ``start_ns + round(t * 1e9) -
time_offset_ns`` (the camera clock's offset against the IMU's, 0 by default). The camera
rides on the vehicle: ``T_world_cam = T_world_imu(t) @ T_imu_cam``. IMU samples cover
``[t_0 - imu_margin_s, t_last + imu_margin_s]`` on a grid aligned with the frames.
World frame: z up, gravity ``(0, 0, -9.81)`` m/s^2, road plane z = 0. IMU (body) frame: x forward,
y left, z up (as the KITTI OXTS unit). Camera frame: x right, y down, z forward.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from mogs_node.errors import ConfigError
from mogs_node.geometry import PinholeCamera, make_T
from mogs_node.params import check_choice
from mogs_node.sim.imu import ImuNoise, ImuNoiseParams, simulate_imu_noise
from mogs_node.sim.trajectory import (
    GRAVITY_WORLD_M_S2,
    CarMotion,
    Trajectory,
    WalkMotion,
    handheld_trajectory,
    oxts_trajectory,
    synthetic_trajectory,
)
from mogs_node.sim.world import KIND_NAMES, SimFrame, World, WorldParams, generate_world

__all__ = [
    "KITTI_CAMERA",
    "T_IMU_CAM_DEFAULT",
    "SimConfig",
    "SimFrame",
    "SimSequence",
    "make_sequence",
]

log = logging.getLogger(__name__)

#: KITTI raw 2011_09_26 P_rect_02 intrinsics at 1242x375
KITTI_CAMERA = PinholeCamera(721.5377, 721.5377, 609.5593, 172.854, 1242, 375)

#: camera in the IMU frame, KITTI-like: 0.81 m ahead, 0.32 m right, 0.72 m above the IMU
T_IMU_CAM_DEFAULT = make_T(
    np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.array([0.81, -0.32, 0.72])
)

#: the vehicle drives in the right lane: the road centre is this far to its left
EGO_LANE_OFFSET_M = 1.75

MOTIONS = ("car", "handheld")
#: handheld walk: the camera about 1.5 m above the ground (the IMU sits T_imu_cam[2, 3] below it)
HANDHELD_CAMERA_HEIGHT_M = 1.5


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated sequence (deterministic for a given value)."""

    seed: int = 0  # world layout, trajectory curves and IMU noise
    n_frames: int = 30  # number of camera frames
    width: int = 1242  # image width (px); intrinsics are KITTI's scaled to this size
    height: int = 375  # image height (px)
    frame_rate_hz: float = 10.0  # camera rate
    speed_m_s: float | None = None  # mean speed of the synthetic trajectory (ignored for "oxts");
    # None: 10 m/s for the car, 1.4 m/s for the handheld walk
    trajectory: str = "synthetic"  # "synthetic" (random smooth curves) or "oxts" (real KITTI drive)
    oxts_dir: str | None = None  # OXTS folder for "oxts" (default ../shared/data/..._0001_oxts)
    imu_rate_hz: float = 200.0  # IMU rate
    imu_margin_s: float = 0.1  # IMU samples before the first and after the last frame
    imu_noise: ImuNoiseParams = field(default_factory=ImuNoiseParams)  # noise model (switchable)
    T_imu_cam: tuple[tuple[float, ...], ...] | None = (
        None  # 4x4 camera-IMU extrinsics (default KITTI-like)
    )
    world: WorldParams = field(default_factory=WorldParams)  # layout of the world
    start_ns: int = 1_000_000_000  # stamp of frame 0
    static_start_s: float = 0.0  # synthetic only: seconds at rest (from t = 0) before driving off
    motion: str = "car"  # synthetic only: "car" (a drive) or "handheld" (a walk, see
    # trajectory.handheld_trajectory; speed_m_s None means 1.4 m/s then)
    time_offset_ns: int = 0  # camera clock against the IMU's: a frame taken at IMU time t is
    # stamped t - time_offset_ns, so the frontend's t_imu = t_cam + time_offset_ns holds
    # (ground truth keeps the true pose of each frame)


@dataclass(frozen=True)
class SimSequence:
    """A generated sequence. Images are rendered lazily by :meth:`render`."""

    config: SimConfig
    camera: PinholeCamera
    world: World
    trajectory: Trajectory
    stamps_ns: np.ndarray  # [F] int64
    T_world_cam: np.ndarray  # [F, 4, 4] f64, ground truth
    T_world_imu: np.ndarray  # [F, 4, 4] f64, ground truth body poses
    velocity_world_m_s: np.ndarray  # [F, 3] f64, body (IMU) velocity
    T_imu_cam: np.ndarray  # [4, 4]
    imu_stamps_ns: np.ndarray  # [M] int64
    imu_gyro_rad_s: np.ndarray  # [M, 3] measured (noisy, biased), body frame
    imu_accel_m_s2: np.ndarray  # [M, 3] measured specific force, body frame
    imu_gyro_bias: np.ndarray  # [M, 3] true gyro bias (rad/s)
    imu_accel_bias: np.ndarray  # [M, 3] true accelerometer bias (m/s^2)
    imu_gyro_true_rad_s: np.ndarray  # [M, 3] noiseless, bias-free
    imu_accel_true_m_s2: np.ndarray  # [M, 3] noiseless, bias-free
    imu_T_world_imu: np.ndarray  # [M, 4, 4] ground-truth body poses at the IMU stamps
    imu_velocity_world_m_s: np.ndarray  # [M, 3]
    gravity_world_m_s2: np.ndarray = field(default_factory=lambda: GRAVITY_WORLD_M_S2.copy())

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def n_frames(self) -> int:
        return len(self.stamps_ns)

    @cached_property
    def instance_kind(self) -> np.ndarray:
        return self.world.instance_kind

    def render(self, i: int) -> SimFrame:
        """Render frame ``i`` (about 0.3-1 s at 1242x375 on one core)."""
        if not 0 <= i < len(self.stamps_ns):
            raise ConfigError(f"i: frame index {i} outside [0, {len(self.stamps_ns)})")
        return self.world.render(
            self.T_world_cam[i], self.camera, stamp_ns=int(self.stamps_ns[i]), index=i
        )

    def sensor_events(self) -> list[tuple[int, str, int]]:
        """Time-ordered ``(stamp_ns, "imu" | "image", index)`` of every IMU sample and frame.

        At equal stamps the IMU sample comes first (a filter has the IMU up to the image time).
        This is the order a live sensor driver or a bag replay publishes in.
        """
        ev = [(int(t), 0, "imu", k) for k, t in enumerate(self.imu_stamps_ns)]
        ev += [(int(t), 1, "image", i) for i, t in enumerate(self.stamps_ns)]
        ev.sort()
        return [(t, kind, k) for t, _, kind, k in ev]

    def render_pose(
        self, T_world_cam: np.ndarray, camera: PinholeCamera | None = None, stamp_ns: int = 0
    ) -> SimFrame:
        """Render an arbitrary (e.g. held-out) view of the same world."""
        return self.world.render(T_world_cam, camera or self.camera, stamp_ns=stamp_ns)


def make_sequence(config: SimConfig | None = None) -> SimSequence:
    """Build the trajectory, the world along it, the camera poses and the IMU stream."""
    cfg = config or SimConfig()
    if cfg.n_frames < 1 or cfg.frame_rate_hz <= 0 or cfg.imu_rate_hz <= 0:
        raise ConfigError("n_frames/frame_rate_hz/imu_rate_hz: must be positive")
    if cfg.width < 8 or cfg.height < 8:
        raise ConfigError(f"width/height: too small ({cfg.width}x{cfg.height})")
    duration_s = (cfg.n_frames - 1) / cfg.frame_rate_hz
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 1]))
    check_choice("motion", cfg.motion, MOTIONS)
    T_imu_cam = (
        T_IMU_CAM_DEFAULT.copy()
        if cfg.T_imu_cam is None
        else np.asarray(cfg.T_imu_cam, dtype=np.float64)
    )
    margin_s = cfg.imu_margin_s + 0.5
    if cfg.trajectory == "synthetic" and cfg.motion == "handheld":
        walk = WalkMotion(
            speed_m_s=1.4 if cfg.speed_m_s is None else cfg.speed_m_s,
            imu_height_m=HANDHELD_CAMERA_HEIGHT_M - float(T_imu_cam[2, 3]),
            margin_s=margin_s,
            static_start_s=cfg.static_start_s,
        )
        traj = handheld_trajectory(duration_s, rng=rng, motion=walk)
    elif cfg.trajectory == "synthetic":
        car = CarMotion(
            speed_m_s=10.0 if cfg.speed_m_s is None else cfg.speed_m_s,
            margin_s=margin_s,
            static_start_s=cfg.static_start_s,
        )
        traj = synthetic_trajectory(duration_s, rng=rng, motion=car)
    elif cfg.trajectory == "oxts":
        if cfg.static_start_s > 0 or cfg.motion != "car":
            raise ConfigError("static_start_s / motion: only for the synthetic trajectory")
        traj = oxts_trajectory(cfg.oxts_dir)
        if duration_s + cfg.imu_margin_s > traj.t_end_s - traj.t_start_s:
            raise ConfigError(
                f"n_frames: {cfg.n_frames} frames at {cfg.frame_rate_hz} Hz need "
                f"{duration_s:.2f} s "
                f"(+{cfg.imu_margin_s} s IMU margin) but the OXTS drive lasts "
                f"{traj.t_end_s - traj.t_start_s:.2f} s"
            )
        # shift time so that frame 0 is at t = 0 with room for the IMU margin before it
        traj = Trajectory(traj.position, traj.rpy, traj.t_start_s, traj.t_end_s)
    else:
        raise ConfigError(f"trajectory: expected 'synthetic' or 'oxts', got {cfg.trajectory!r}")
    t_offset = cfg.imu_margin_s if cfg.trajectory == "oxts" else 0.0  # trajectory time of frame 0
    t_frames = t_offset + np.arange(cfg.n_frames) / cfg.frame_rate_hz
    stamps_ns = (
        cfg.start_ns
        + np.round((t_frames - t_offset) * 1e9).astype(np.int64)
        - int(cfg.time_offset_ns)
    )
    T_world_imu = traj.T_world_imu(t_frames)
    T_world_cam = T_world_imu @ T_imu_cam
    # IMU grid aligned with frame 0
    dt_imu = 1.0 / cfg.imu_rate_hz
    k0 = int(np.floor(cfg.imu_margin_s / dt_imu + 1e-9))
    k1 = int(np.floor((duration_s + cfg.imu_margin_s) / dt_imu + 1e-9))
    k = np.arange(-k0, k1 + 1)
    t_imu = t_offset + k * dt_imu
    t_imu = t_imu[(t_imu >= traj.t_start_s) & (t_imu <= traj.t_end_s)]
    imu_stamps_ns = cfg.start_ns + np.round((t_imu - t_offset) * 1e9).astype(np.int64)
    gyro = traj.gyro_body_rad_s(t_imu)
    accel = traj.specific_force_body_m_s2(t_imu)
    noise: ImuNoise = simulate_imu_noise(
        len(t_imu),
        cfg.imu_rate_hz,
        cfg.imu_noise,
        np.random.default_rng(np.random.SeedSequence([cfg.seed, 2])),
    )
    # world along the driven path, extended beyond both ends
    ts = np.linspace(
        traj.t_start_s, traj.t_end_s, max(int((traj.t_end_s - traj.t_start_s) * 20), 20)
    )
    pos = traj.position(ts)[:, :2]
    vel = traj.position(ts, 1)[:, :2]
    hd = vel / np.maximum(np.linalg.norm(vel, axis=1, keepdims=True), 1e-9)
    left = np.stack([-hd[:, 1], hd[:, 0]], -1)
    center = pos + EGO_LANE_OFFSET_M * left
    ext = cfg.world.extend_m
    steps = np.linspace(0.0, ext, max(int(ext / 2), 2))[1:, None]
    center = np.concatenate([center[0] - steps[::-1] * hd[0], center, center[-1] + steps * hd[-1]])
    world = generate_world(center, cfg.seed, cfg.world)
    camera = (
        KITTI_CAMERA
        if (cfg.width, cfg.height) == (1242, 375)
        else KITTI_CAMERA.scaled(cfg.width, cfg.height)
    )
    log.debug(
        "sim world: %d primitives (%s)",
        len(world.primitives),
        ", ".join(f"{KIND_NAMES[k]}={int(np.sum(world.instance_kind == k))}" for k in KIND_NAMES),
    )
    return SimSequence(
        config=cfg,
        camera=camera,
        world=world,
        trajectory=traj,
        stamps_ns=stamps_ns,
        T_world_cam=T_world_cam,
        T_world_imu=T_world_imu,
        velocity_world_m_s=traj.velocity_world_m_s(t_frames),
        T_imu_cam=T_imu_cam,
        imu_stamps_ns=imu_stamps_ns,
        imu_gyro_rad_s=gyro + noise.gyro_bias_rad_s + noise.gyro_noise_rad_s,
        imu_accel_m_s2=accel + noise.accel_bias_m_s2 + noise.accel_noise_m_s2,
        imu_gyro_bias=noise.gyro_bias_rad_s,
        imu_accel_bias=noise.accel_bias_m_s2,
        imu_gyro_true_rad_s=gyro,
        imu_accel_true_m_s2=accel,
        imu_T_world_imu=traj.T_world_imu(t_imu),
        imu_velocity_world_m_s=traj.velocity_world_m_s(t_imu),
    )
