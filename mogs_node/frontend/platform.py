"""Platform profiles: what motion is plausible for a car, a handheld camera or a drone (pure).

A VI initialisation or a window solution that leaves these bounds is not a motion of the platform
but a failure (a wrong scale, an unknown time offset, a diverged solve): initialisation hypotheses
outside them are rejected, and a running window outside them resets the estimator, each with the
bound that was broken named (``docs/frontend.md``, "Platform profiles").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.geometry import check_array, so3_log

__all__ = [
    "PLATFORMS",
    "PlatformBounds",
    "PlatformChooser",
    "PlatformProfile",
    "WalkDetection",
    "detect_walk",
    "motion_violation",
    "platform_profile",
]

log = logging.getLogger(__name__)

#: a person's step cadence (steps per second); a car body's bounce on its suspension is 1-1.5 Hz
#: and weaker, a multicopter's vibration is far above
WALK_CADENCE_HZ = (1.4, 2.6)


@dataclass(frozen=True)
class PlatformProfile:
    """Bounds of a platform's motion (IMU frame, world z up) and its keyframe rate cap."""

    name: str
    max_speed_m_s: float  # norm of the velocity
    max_accel_m_s2: float  # norm of the mean acceleration between two window frames
    max_angular_rate_rad_s: float  # mean angular rate between two window frames
    max_vertical_speed_m_s: float  # |v_z|
    keyframe_min_interval_s: float  # at most one keyframe per this long (the mapper's rate)
    window_interval_s: float = 0.0  # the estimator window's frame spacing when the view does
    # not move (FrontendParams.window_interval_s; 0: every frame stays in the window)
    keep_visual_prior: bool = False  # EstimatorParams.keep_visual_prior when not set
    outlier_reproj_rel: float = 0.0  # EstimatorParams.outlier_reproj_rel when not set

    def __post_init__(self) -> None:
        vals = (
            self.max_speed_m_s,
            self.max_accel_m_s2,
            self.max_angular_rate_rad_s,
            self.max_vertical_speed_m_s,
        )
        if (
            min(vals) <= 0
            or min(self.keyframe_min_interval_s, self.window_interval_s, self.outlier_reproj_rel)
            < 0
        ):
            raise ConfigError(f"platform {self.name!r}: bounds must be positive")


#: car: KITTI, dashcams and the demo (a motorway, hard braking, no flying)
#: handheld: a person walking or running with a camera (head turns up to a few hundred deg/s)
#: drone: a multicopter (EuRoC's MAV) - fast rotations and vertical motion
PLATFORMS: dict[str, PlatformProfile] = {
    "car": PlatformProfile("car", 70.0, 15.0, 2.0, 8.0, 0.09),
    "handheld": PlatformProfile(
        "handheld",
        4.0,
        20.0,
        8.0,
        2.0,
        0.5,
        window_interval_s=0.2,
        keep_visual_prior=True,
        outlier_reproj_rel=4.0,
    ),
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
    window_interval_s: float | None = None


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


@dataclass(frozen=True)
class WalkDetection:
    """Step cadence found in the accelerometer (``platform: auto``)."""

    walking: bool
    cadence_hz: float  # frequency of the strongest component in the cadence band
    amplitude_m_s2: float  # its amplitude (of the specific force's norm)
    band_fraction: float  # the cadence band's share of the 0.5-15 Hz power


def detect_walk(
    stamps_ns: NDArray,
    accel_m_s2: NDArray,
    *,
    min_amplitude_m_s2: float = 0.8,
    min_band_fraction: float = 0.4,
    window_s: float = 4.0,
) -> WalkDetection | None:
    """Whether the last ``window_s`` of IMU is a walk: the norm of the specific force oscillates
    at a step cadence (1.4-2.6 Hz) with at least ``min_amplitude_m_s2`` and that band holds at
    least ``min_band_fraction`` of the 0.5-15 Hz power (a pedometer's test). None: less than
    ``window_s`` of IMU. The norm does not depend on the attitude, so no gravity is needed."""
    t = check_array("stamps_ns", stamps_ns, shape=(None,), dtype=np.integer)
    a = check_array("accel_m_s2", accel_m_s2, shape=(len(t), 3))
    if len(t) < 16 or (t[-1] - t[0]) * 1e-9 < window_s:
        return None
    keep = t >= t[-1] - int(window_s * 1e9)
    ts, norm = (t[keep] - t[keep][0]) * 1e-9, np.linalg.norm(a[keep], axis=1)
    rate_hz = 50.0  # resampled uniformly (IMU stamps jitter, some drivers drop samples)
    grid = np.arange(0.0, ts[-1], 1.0 / rate_hz)
    x = np.interp(grid, ts, norm)
    x = (x - x.mean()) * np.hanning(len(x))
    spec = np.abs(np.fft.rfft(x)) ** 2
    freq = np.fft.rfftfreq(len(x), 1.0 / rate_hz)
    band = (freq >= WALK_CADENCE_HZ[0]) & (freq <= WALK_CADENCE_HZ[1])
    total = float(spec[(freq >= 0.5) & (freq <= 15.0)].sum())
    if total <= 0 or not band.any():
        return WalkDetection(False, 0.0, 0.0, 0.0)
    k = int(np.flatnonzero(band)[np.argmax(spec[band])])
    # a sinusoid of amplitude A under a Hann window: |X| = A N / 4 at its bin
    amp = 4.0 * float(np.sqrt(spec[k])) / len(x)
    frac = float(spec[band].sum()) / total
    ok = amp >= min_amplitude_m_s2 and frac >= min_band_fraction
    return WalkDetection(bool(ok), float(freq[k]), amp, frac)


class PlatformChooser:
    """The profile in use: the named one, or with ``platform: auto`` the ``default`` one until
    the accelerometer shows a walk (:func:`detect_walk`), then ``handheld`` for the rest of the
    run. A bag or a folder says nothing about what carried the camera; a walk's step cadence is
    the one platform signature that is both strong and unambiguous in the IMU."""

    def __init__(
        self, name: str, bounds: PlatformBounds | None = None, default: str = "car"
    ) -> None:
        self.auto = name == "auto"
        self.bounds = bounds
        self.profile = platform_profile(default if self.auto else name, bounds)
        self.detection: WalkDetection | None = None  # the walk that chose 'handheld'
        self._t = np.zeros(0, np.int64)
        self._a = np.zeros((0, 3))
        self._next_check_ns: int | None = None

    def add_imu(self, stamps_ns: NDArray, accel_m_s2: NDArray, *, window_s: float = 4.0) -> bool:
        """New IMU samples (increasing stamps, after the previous ones); True when the profile
        changed. Checks at most twice a second of IMU time."""
        if not self.auto or self.detection is not None or len(stamps_ns) == 0:
            return False
        t = np.asarray(stamps_ns, np.int64).reshape(-1)
        keep = t > (self._t[-1] if self._t.size else np.iinfo(np.int64).min)
        self._t = np.concatenate([self._t, t[keep]])
        self._a = np.concatenate([self._a, np.asarray(accel_m_s2, float).reshape(-1, 3)[keep]])
        old = self._t < self._t[-1] - int(window_s * 1e9)
        self._t, self._a = self._t[~old], self._a[~old]
        if self._next_check_ns is not None and self._t[-1] < self._next_check_ns:
            return False
        self._next_check_ns = int(self._t[-1]) + 500_000_000
        det = detect_walk(self._t, self._a, window_s=window_s - 0.05)
        if det is None or not det.walking:
            return False
        self.detection = det
        self.profile = platform_profile("handheld", self.bounds)
        log.info(
            "platform auto: a walk in the IMU (step cadence %.1f Hz, %.1f m/s^2): handheld",
            det.cadence_hz,
            det.amplitude_m_s2,
        )
        return True
