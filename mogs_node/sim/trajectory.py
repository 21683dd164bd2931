"""Smooth vehicle trajectories with analytic derivatives (the source of the simulated IMU).

A :class:`Trajectory` is a pair of quintic B-splines of time: the IMU (body) position in the world
``p(t)`` and its attitude as KITTI/OXTS Euler angles ``(roll, pitch, yaw)(t)`` with
``R_world_imu = Rz(yaw) Ry(pitch) Rx(roll)``. The body frame is the OXTS one: x forward, y left,
z up. The world frame is z up with gravity ``(0, 0, -9.81)`` m/s^2. Velocities, accelerations and
body
angular rates come from the splines' analytic derivatives, so the IMU is exactly consistent with the
poses (up to the integration scheme a consumer uses).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import BSpline, make_interp_spline, splrep

from mogs_node.errors import ConfigError
from mogs_node.geometry import make_T, rotmat_from_rpy
from mogs_node.shared_data import shared_data_dir

__all__ = [
    "GRAVITY_WORLD_M_S2",
    "CarMotion",
    "Trajectory",
    "WalkMotion",
    "handheld_trajectory",
    "oxts_trajectory",
    "synthetic_trajectory",
]

#: gravity in the world frame (z up), m/s^2
GRAVITY_WORLD_M_S2 = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True)
class Trajectory:
    """Body (IMU) trajectory: position and roll/pitch/yaw splines over ``[t_start_s, t_end_s]``."""

    position: BSpline  # t [s] -> p_world_imu [3] (m); quintic
    rpy: BSpline  # t [s] -> (roll, pitch, yaw) [3] (rad), yaw unwrapped; quintic
    t_start_s: float
    t_end_s: float

    def _t(self, t_s: np.ndarray | float) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        if np.any(t < self.t_start_s - 1e-9) or np.any(t > self.t_end_s + 1e-9):
            raise ConfigError(
                f"t_s: outside the trajectory's span [{self.t_start_s:.3f}, {self.t_end_s:.3f}] s"
            )
        return t

    def T_world_imu(self, t_s: np.ndarray | float) -> np.ndarray:
        """Poses ``[N, 4, 4]`` at times ``t_s`` ``[N]`` (s)."""
        t = self._t(t_s)
        e = self.rpy(t)
        return make_T(rotmat_from_rpy(e[:, 0], e[:, 1], e[:, 2]), self.position(t))

    def velocity_world_m_s(self, t_s: np.ndarray | float) -> np.ndarray:
        """World-frame velocity ``[N, 3]`` of the body origin."""
        return self.position(self._t(t_s), 1)

    def accel_world_m_s2(self, t_s: np.ndarray | float) -> np.ndarray:
        """World-frame acceleration ``[N, 3]`` of the body origin (gravity not included)."""
        return self.position(self._t(t_s), 2)

    def gyro_body_rad_s(self, t_s: np.ndarray | float) -> np.ndarray:
        """Body angular velocity ``[N, 3]`` (``R^T dR/dt = hat(omega)``), from the Euler rates."""
        t = self._t(t_s)
        e, de = self.rpy(t), self.rpy(t, 1)
        r, p = e[:, 0], e[:, 1]
        dr, dp, dy = de[:, 0], de[:, 1], de[:, 2]
        return np.stack(
            [
                dr - dy * np.sin(p),
                dp * np.cos(r) + dy * np.sin(r) * np.cos(p),
                -dp * np.sin(r) + dy * np.cos(r) * np.cos(p),
            ],
            -1,
        )

    def specific_force_body_m_s2(self, t_s: np.ndarray | float) -> np.ndarray:
        """What an ideal accelerometer reads ``[N, 3]``: ``R^T (a - g)`` in the body frame."""
        t = self._t(t_s)
        R = self.T_world_imu(t)[:, :3, :3]
        a = self.position(t, 2) - GRAVITY_WORLD_M_S2
        return np.einsum("nji,nj->ni", R, a)


def _quintic(t: np.ndarray, y: np.ndarray) -> BSpline:
    return make_interp_spline(t, y, k=5, axis=0)


@dataclass(frozen=True)
class CarMotion:
    """How :func:`synthetic_trajectory` drives (defaults: a car at 10 m/s)."""

    speed_m_s: float = 10.0  # mean speed
    speed_variation: float = 0.15  # relative amplitude of the speed's sinusoid
    imu_height_m: float = 0.93  # IMU above the road (plane z = 0)
    min_turn_radius_m: float = 70.0
    margin_s: float = 1.0  # the splines extend this far beyond [0, duration]
    static_start_s: float = 0.0  # standing still (heading +x) from t = 0 until then
    accel_time_s: float = 4.0  # from rest to cruising speed (smootherstep)


@dataclass(frozen=True)
class WalkMotion:
    """How :func:`handheld_trajectory` walks (defaults: a person at 1.4 m/s)."""

    speed_m_s: float = 1.4  # mean walking speed (+-5 %)
    imu_height_m: float = 1.45  # IMU above the ground
    step_hz: float = 1.9  # step frequency (vertical bounce; lateral sway at half of it)
    bounce_m: float = 0.02
    sway_m: float = 0.015
    max_head_rate_deg_s: float = 90.0  # peak head-turn rate (uniform in [0.5, 1] x this)
    head_turn_deg: tuple[float, float] = (20.0, 45.0)  # head-turn amplitude range
    shake_deg: float = 0.4  # hand shake per axis at most
    min_turn_radius_m: float = 25.0
    margin_s: float = 1.0
    static_start_s: float = 0.0  # standing still (heading +x, no shake) until then
    accel_time_s: float = 1.5  # from rest to walking speed


def synthetic_trajectory(
    duration_s: float, *, rng: np.random.Generator, motion: CarMotion | None = None
) -> Trajectory:
    """A car-like drive at about ``motion.speed_m_s``: random smooth curves, speed changes, sway.

    Heading follows a curvature profile made of smooth (raised-cosine) turns of radius at least
    ``min_turn_radius_m``; speed ``v(t) = v0 (1 + speed_variation sin(...))``; pitch and roll follow
    longitudinal / lateral acceleration like a suspended body (about 0.6 deg per m/s^2). The road is
    the plane z = 0 and the IMU rides at ``imu_height_m``. With ``static_start_s > 0`` the vehicle
    stands still (heading +x) until then and reaches its cruising speed ``accel_time_s`` later
    (smootherstep profile), for testing static IMU initialisation.
    """
    mo = motion or CarMotion()
    speed_m_s, speed_variation, static_start_s = mo.speed_m_s, mo.speed_variation, mo.static_start_s
    if duration_s < 0 or speed_m_s <= 0:
        raise ConfigError(f"duration_s/speed_m_s: need >= 0 / > 0, got {duration_s}/{speed_m_s}")
    t0, t1 = -mo.margin_s, duration_s + mo.margin_s
    # speed profile and arc length at dense times (analytic integral of the sinusoid)
    w = 2 * np.pi / rng.uniform(6.0, 10.0)
    phase = rng.uniform(0, 2 * np.pi)
    tk = np.arange(t0 - 0.5, t1 + 0.5 + 1e-9, 0.1)
    if static_start_s > 0:
        if mo.accel_time_s <= 0:
            raise ConfigError(f"accel_time_s: must be positive, got {mo.accel_time_s}")
        td = np.arange(tk[0], tk[-1] + 1e-9, 0.002)
        x = np.clip((td - static_start_s) / mo.accel_time_s, 0.0, 1.0)
        ramp = x**3 * (10.0 - 15.0 * x + 6.0 * x * x)
        vd = speed_m_s * (1.0 + speed_variation * np.sin(w * td + phase)) * ramp
        sd = np.concatenate([[0.0], np.cumsum(0.5 * (vd[1:] + vd[:-1]) * np.diff(td))])
        s_of_t = np.interp(tk, td, sd)
    else:
        s_of_t = speed_m_s * (
            tk - speed_variation / w * (np.cos(w * tk + phase) - np.cos(w * t0 + phase))
        )
    s, heading, x, y = _turning_path(
        float(s_of_t[-1] - s_of_t[0]) + 10.0, rng, mo.min_turn_radius_m
    )
    sk = s_of_t - s_of_t[0]
    pk = np.stack([np.interp(sk, s, x), np.interp(sk, s, y), np.full_like(sk, mo.imu_height_m)], -1)
    # start at the origin heading +x at t = 0
    i0 = int(np.argmin(np.abs(tk)))
    pk = pk - pk[i0] + np.array([0.0, 0.0, mo.imu_height_m])
    position = _quintic(tk, pk)
    v = position(tk, 1)
    a = position(tk, 2)
    if static_start_s > 0:  # the path's heading (the velocity has none while standing)
        yaw = np.interp(sk, s, heading)
    else:
        yaw = np.unwrap(np.arctan2(v[:, 1], v[:, 0]))
    c, s_ = np.cos(yaw), np.sin(yaw)
    a_long = c * a[:, 0] + s_ * a[:, 1]
    a_lat = -s_ * a[:, 0] + c * a[:, 1]
    sway = np.deg2rad(0.6)
    pitch = -sway * a_long  # nose up when accelerating (pitch positive = front down)
    roll = sway * a_lat  # body leans to the outside of a turn (left side down in a right turn)
    rpy = _quintic(tk, np.stack([roll, pitch, yaw], -1))
    return Trajectory(position, rpy, float(t0), float(t1))


def _smootherstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (10.0 - 15.0 * x + 6.0 * x * x)


def _turning_path(
    s_max: float,
    rng: np.random.Generator,
    min_turn_radius_m: float,
    turns_to_last_sample: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Arc length ``s`` (every 5 cm up to ``s_max``), heading and ``x``, ``y`` of a path along
    smooth (raised-cosine) turns of radius at least ``min_turn_radius_m``, at random places. The
    car draws turns up to ``s_max``, the walker up to the last sample (``turns_to_last_sample``):
    a turn past the end changes nothing on the path but moves the generator, so each keeps its
    drives for a given seed."""
    ds = 0.05
    s = np.arange(0.0, s_max, ds)
    stop = s[-1] if turns_to_last_sample else s_max
    kappa = np.zeros_like(s)
    pos = rng.uniform(5.0, 25.0)
    while pos < stop:
        length = rng.uniform(25.0, 60.0)
        k = rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 1.0) / min_turn_radius_m
        m = (s >= pos) & (s < pos + length)
        kappa[m] += k * 0.5 * (1 - np.cos(2 * np.pi * (s[m] - pos) / length))
        pos += length + rng.uniform(15.0, 50.0)
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * ds)])
    x = np.concatenate([[0.0], np.cumsum(0.5 * (np.cos(heading[1:]) + np.cos(heading[:-1])) * ds)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (np.sin(heading[1:]) + np.sin(heading[:-1])) * ds)])
    return s, heading, x, y


def _planar_path(
    t: np.ndarray, speed: np.ndarray, rng: np.random.Generator, min_turn_radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``[T, 2]`` and path heading ``[T]`` at times ``t`` for the speed profile ``speed``
    ``[T]`` (m/s) along raised-cosine turns of radius at least ``min_turn_radius_m``."""
    s_of_t = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t))])
    s_max = float(s_of_t[-1]) + 10.0
    s, heading, x, y = _turning_path(s_max, rng, min_turn_radius_m, turns_to_last_sample=True)
    xy = np.stack([np.interp(s_of_t, s, x), np.interp(s_of_t, s, y)], -1)
    return xy, np.interp(s_of_t, s, heading)


def handheld_trajectory(
    duration_s: float, *, rng: np.random.Generator, motion: WalkMotion | None = None
) -> Trajectory:
    """A person walking with a handheld camera + IMU at about ``motion.speed_m_s`` along a street.

    The path curves like :func:`synthetic_trajectory`'s (gentler speed changes, +-5 %). On top:
    the step bounce (vertical ``bounce_m`` at the step frequency ``step_hz``, lateral ``sway_m``
    at half of it, pitch 0.5 deg with the step), head turns (raised-cosine yaw excursions of
    ``head_turn_deg`` out and back, peak rate uniform in [0.5, 1] x ``max_head_rate_deg_s``, every
    3-8 s) and hand shake (three sinusoids of 1-5 Hz per axis, ``shake_deg`` each at most). With
    ``static_start_s`` the walker stands still (heading +x, no shake) until then and reaches the
    walking speed ``accel_time_s`` later. Body frame as everywhere in the sim: x forward, z up.
    """
    mo = motion or WalkMotion()
    speed_m_s, accel_time_s, static_start_s = mo.speed_m_s, mo.accel_time_s, mo.static_start_s
    if duration_s < 0 or speed_m_s <= 0 or accel_time_s <= 0:
        raise ConfigError(
            f"duration_s/speed_m_s/accel_time_s: need >= 0 / > 0 / > 0, got "
            f"{duration_s}/{speed_m_s}/{accel_time_s}"
        )
    t0, t1 = -mo.margin_s - 0.5, duration_s + mo.margin_s + 0.5
    tk = np.arange(t0, t1 + 1e-9, 0.02)  # knots at 50 Hz: the step and the shake are < 5 Hz
    walk = _smootherstep((tk - static_start_s) / accel_time_s) if static_start_s > 0 else 1.0
    w = 2 * np.pi / rng.uniform(8.0, 14.0)
    speed = speed_m_s * (1.0 + 0.05 * np.sin(w * tk + rng.uniform(0, 2 * np.pi))) * walk
    xy, heading = _planar_path(tk, np.broadcast_to(speed, tk.shape), rng, mo.min_turn_radius_m)
    i0 = int(np.argmin(np.abs(tk)))
    xy -= xy[i0]
    step = 2 * np.pi * mo.step_hz * tk
    left = np.stack([-np.sin(heading), np.cos(heading)], -1)
    xy = xy + (walk * mo.sway_m * np.sin(0.5 * step))[:, None] * left
    z = mo.imu_height_m + walk * mo.bounce_m * np.cos(step)
    position = _quintic(tk, np.c_[xy, z])
    # head turns: out and back, yaw(t) = A (1 - cos(2 pi (t - ts) / T)) / 2, peak rate A pi / T
    head = np.zeros_like(tk)
    ts = max(static_start_s + accel_time_s, 0.0) + rng.uniform(1.0, 3.0)
    while ts < t1:
        amp = np.deg2rad(rng.uniform(*mo.head_turn_deg)) * rng.choice([-1.0, 1.0])
        rate = np.deg2rad(mo.max_head_rate_deg_s) * rng.uniform(0.5, 1.0)
        dur = np.pi * abs(amp) / rate
        m = (tk >= ts) & (tk < ts + dur)
        head[m] += amp * 0.5 * (1 - np.cos(2 * np.pi * (tk[m] - ts) / dur))
        ts += dur + rng.uniform(3.0, 8.0)
    shake = np.zeros((len(tk), 3))
    for axis in range(3):
        for _ in range(3):
            f = rng.uniform(1.0, 5.0)
            a = np.deg2rad(mo.shake_deg) * rng.uniform(0.3, 1.0) / 3.0
            shake[:, axis] += a * np.sin(2 * np.pi * f * tk + rng.uniform(0, 2 * np.pi))
    shake *= np.asarray(walk).reshape(-1, 1) if static_start_s > 0 else 1.0
    pitch_step = walk * np.deg2rad(0.5) * np.sin(step)
    rpy = np.stack(
        [shake[:, 0], pitch_step + shake[:, 1], heading - heading[i0] + head + shake[:, 2]], -1
    )
    return Trajectory(position, _quintic(tk, rpy), float(t0 + 0.5), float(t1 - 0.5))


def default_oxts_dir() -> Path:
    """The KITTI OXTS excerpt in the shared-data folder (``mogs_node.shared_data``)."""
    return shared_data_dir("kitti_raw_2011_09_26_drive_0001_oxts")


def oxts_trajectory(
    oxts_dir: str | Path | None = None,
    *,
    imu_height_m: float = 0.93,
    flatten: bool = True,
    position_sigma_m: float = 0.01,
    angle_sigma_rad: float = 0.001,
) -> Trajectory:
    """The trajectory of a real KITTI drive: OXTS -> devkit poses -> smoothing quintic splines.

    The devkit poses (Mercator metric coordinates) are re-expressed in a z-up world whose origin is
    the first packet's position and whose x axis is the first heading (gravity stays -z). With
    ``flatten`` the altitude is replaced by ``imu_height_m`` (the synthetic road is the plane
    z = 0),
    keeping the real roll, pitch and yaw. Time zero is the first packet.
    """
    from mogs_node.datasets.oxts import oxts_to_poses, read_oxts

    stamps_ns, packets = read_oxts(oxts_dir if oxts_dir is not None else default_oxts_dir())
    T = oxts_to_poses(packets, relative=False)
    t = (stamps_ns - stamps_ns[0]) * 1e-9
    yaw0 = packets[0, 5]
    c, s = np.cos(-yaw0), np.sin(-yaw0)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    p = (T[:, :3, 3] - T[0, :3, 3]) @ Rz.T
    p[:, 2] = imu_height_m if flatten else p[:, 2] + imu_height_m
    roll, pitch = packets[:, 3], packets[:, 4]
    yaw = np.unwrap(packets[:, 5]) - yaw0
    n = len(t)

    def fit(y: np.ndarray, sigma: float) -> BSpline:
        tck = splrep(t, y, k=5, s=n * sigma**2)
        return BSpline(*tck)

    pos_splines = [fit(p[:, i], position_sigma_m) for i in range(3)]
    ang_splines = [fit(a, angle_sigma_rad) for a in (roll, pitch, yaw)]
    # resample onto one multi-dimensional quintic interpolant so Trajectory has one spline per part
    tk = np.linspace(t[0], t[-1], 8 * n)
    pos = _quintic(tk, np.stack([sp(tk) for sp in pos_splines], -1))
    rpy = _quintic(tk, np.stack([sp(tk) for sp in ang_splines], -1))
    return Trajectory(pos, rpy, float(t[0]), float(t[-1]))
