"""Platform profiles: what motion is plausible for a car, a handheld camera or a drone (pure).

A VI initialisation or a window solution that leaves these bounds is not a motion of the platform
but a failure (a wrong scale, an unknown time offset, a diverged solve): initialisation hypotheses
outside them are rejected, and a running window outside them resets the estimator, each with the
bound that was broken named (``docs/frontend.md``, "Platform profiles").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.geometry import check_array, so3_log

__all__ = [
    "PLATFORMS",
    "PlatformBounds",
    "PlatformProfile",
    "motion_violation",
    "platform_profile",
]


@dataclass(frozen=True)
class PlatformProfile:
    """Bounds of a platform's motion (IMU frame, world z up) and its keyframe rate cap."""

    name: str
    max_speed_m_s: float  # norm of the velocity
    max_accel_m_s2: float  # norm of the mean acceleration between two window frames
    max_angular_rate_rad_s: float  # mean angular rate between two window frames
    max_vertical_speed_m_s: float  # |v_z|
    keyframe_min_interval_s: float  # at most one keyframe per this long (the mapper's rate)

    def __post_init__(self) -> None:
        vals = (
            self.max_speed_m_s,
            self.max_accel_m_s2,
            self.max_angular_rate_rad_s,
            self.max_vertical_speed_m_s,
        )
        if min(vals) <= 0 or self.keyframe_min_interval_s < 0:
            raise ConfigError(f"platform {self.name!r}: bounds must be positive")


#: car: KITTI, dashcams and the demo (a motorway, hard braking, no flying)
#: handheld: a person walking or running with a camera (head turns up to a few hundred deg/s)
#: drone: a multicopter (EuRoC's MAV) - fast rotations and vertical motion
PLATFORMS: dict[str, PlatformProfile] = {
    "car": PlatformProfile("car", 70.0, 15.0, 2.0, 8.0, 0.09),
    "handheld": PlatformProfile("handheld", 4.0, 20.0, 8.0, 2.0, 0.5),
    "drone": PlatformProfile("drone", 20.0, 25.0, 8.0, 8.0, 0.25),
}


@dataclass(frozen=True)
class PlatformBounds:
    """Launch overrides of the profile's bounds (``frontend.bounds``); None keeps the profile's."""

    max_speed_m_s: float | None = None
    max_accel_m_s2: float | None = None
    max_angular_rate_rad_s: float | None = None
    max_vertical_speed_m_s: float | None = None
    keyframe_min_interval_s: float | None = None


def platform_profile(name: str, bounds: PlatformBounds | None = None) -> PlatformProfile:
    """The named profile with the bounds given in ``bounds`` replaced."""
    if name not in PLATFORMS:
        raise ConfigError(f"frontend.platform: {name!r} not in {tuple(PLATFORMS)}")
    base = PLATFORMS[name]
    fields = {k: getattr(base, k) for k in base.__dataclass_fields__}
    if bounds is not None:
        over = {k: getattr(bounds, k) for k in bounds.__dataclass_fields__}
        fields.update({k: float(v) for k, v in over.items() if v is not None})
    return PlatformProfile(**fields)


def motion_violation(
    profile: PlatformProfile,
    stamps_ns: NDArray,
    T_world_imu: NDArray,
    velocity_world_m_s: NDArray,
) -> str | None:
    """The first bound a motion breaks, as ``"<bound>: <value> > <limit>"``, or None.

    ``stamps_ns`` [F] (IMU time, increasing), ``T_world_imu`` [F, 4, 4], ``velocity_world_m_s``
    [F, 3]: states of consecutive window frames (one frame checks speeds only)."""
    t = check_array("stamps_ns", stamps_ns, shape=(None,), dtype=np.integer)
    T = check_array("T_world_imu", T_world_imu, shape=(len(t), 4, 4))
    v = check_array("velocity_world_m_s", velocity_world_m_s, shape=(len(t), 3))
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(v))):
        return "state: not finite"
    p = profile
    speed = np.linalg.norm(v, axis=1)
    k = int(np.argmax(speed))
    if speed[k] > p.max_speed_m_s:
        return f"speed: {speed[k]:.1f} m/s > {p.max_speed_m_s:g} m/s"
    vz = float(np.max(np.abs(v[:, 2])))
    if vz > p.max_vertical_speed_m_s:
        return f"vertical_speed: {vz:.1f} m/s > {p.max_vertical_speed_m_s:g} m/s"
    if len(t) < 2:
        return None
    dt = np.diff(t) * 1e-9
    if np.any(dt <= 0):
        raise ConfigError("stamps_ns: must increase")
    acc = float(np.max(np.linalg.norm(np.diff(v, axis=0), axis=1) / dt))
    if acc > p.max_accel_m_s2:
        return f"acceleration: {acc:.1f} m/s^2 > {p.max_accel_m_s2:g} m/s^2"
    R = T[:, :3, :3]
    dR = np.einsum("nji,njk->nik", R[:-1], R[1:])
    rate = float(np.max(np.linalg.norm(so3_log(dR), axis=1) / dt))
    if rate > p.max_angular_rate_rad_s:
        return (
            f"angular_rate: {np.degrees(rate):.0f} deg/s > "
            f"{np.degrees(p.max_angular_rate_rad_s):.0f} deg/s"
        )
    return None
