"""IMU preintegration: a thin layer over GTSAM's ``PreintegratedCombinedMeasurements``.

Forster et al. on-manifold preintegration as used by VINS-Mono (paper's frontend). The layer adds
what GTSAM leaves to the caller: noise parameters with units, integration between two arbitrary
time stamps with linear interpolation of the samples at the interval ends and midpoint (trapezoid)
averaging of consecutive samples, and checks of the sample stream.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields

import gtsam
import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError, ShapeError
from mogs_node.geometry import check_array, so3_exp

__all__ = ["ImuBuffer", "ImuNoise", "ImuSamples", "make_params", "preintegrate", "zero_bias"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise model (Kalibr / EuRoC conventions) and gravity.

    Defaults: twice the datasheet densities of a consumer MEMS IMU (EuRoC's ADIS16448 class), the
    usual inflation that absorbs unmodelled vibration and integration error."""

    gyro_noise_rad_s_rthz: float = 3.4e-4  # gyroscope white noise density
    accel_noise_m_s2_rthz: float = 4.0e-3  # accelerometer white noise density
    gyro_walk_rad_s2_rthz: float = 4.0e-5  # gyroscope bias random walk
    accel_walk_m_s3_rthz: float = 6.0e-4  # accelerometer bias random walk
    integration_sigma: float = 1e-4  # position integration uncertainty (GTSAM)
    gravity_m_s2: float = 9.81  # magnitude of gravity; world z is up

    def __post_init__(self) -> None:
        vals = {f.name: getattr(self, f.name) for f in fields(self)}  # every field is a density
        bad = {k: v for k, v in vals.items() if not (np.isfinite(v) and v > 0)}
        if bad:
            raise ConfigError(f"imu noise: every value must be finite and > 0, got {bad}")


@dataclass
class ImuSamples:
    """A time-ordered IMU stream: ``stamps_ns`` [N] int64, ``gyro_rad_s`` [N, 3], ``accel_m_s2`` [N, 3]."""

    stamps_ns: NDArray[np.int64]
    gyro_rad_s: NDArray[np.float64]
    accel_m_s2: NDArray[np.float64]

    def __post_init__(self) -> None:
        self.stamps_ns = check_array("stamps_ns", self.stamps_ns, shape=(None,), dtype=np.integer)
        n = len(self.stamps_ns)
        self.gyro_rad_s = check_array("gyro_rad_s", self.gyro_rad_s, shape=(n, 3), finite=True)
        self.accel_m_s2 = check_array("accel_m_s2", self.accel_m_s2, shape=(n, 3), finite=True)
        if n > 1 and np.any(np.diff(self.stamps_ns) <= 0):
            raise ShapeError("stamps_ns: must be strictly increasing")


def zero_bias() -> gtsam.imuBias.ConstantBias:
    return gtsam.imuBias.ConstantBias(np.zeros(3), np.zeros(3))


def make_params(
    noise: ImuNoise, T_imu_cam: NDArray | None = None
) -> gtsam.PreintegrationCombinedParams:
    """GTSAM parameters (world z up, gravity ``-g z``). Covariances are continuous-time densities
    squared, as GTSAM expects. ``T_imu_cam`` is not used here: poses in the graph are IMU poses."""
    del T_imu_cam
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(noise.gravity_m_s2)
    I3 = np.eye(3)
    p.setGyroscopeCovariance(noise.gyro_noise_rad_s_rthz**2 * I3)
    p.setAccelerometerCovariance(noise.accel_noise_m_s2_rthz**2 * I3)
    p.setBiasOmegaCovariance(noise.gyro_walk_rad_s2_rthz**2 * I3)
    p.setBiasAccCovariance(noise.accel_walk_m_s3_rthz**2 * I3)
    p.setIntegrationCovariance(noise.integration_sigma**2 * I3)
    return p


def _interp(samples: ImuSamples, t_ns: NDArray[np.int64]) -> tuple[NDArray, NDArray]:
    t = samples.stamps_ns.astype(np.float64)
    q = t_ns.astype(np.float64)
    g = np.stack([np.interp(q, t, samples.gyro_rad_s[:, k]) for k in range(3)], -1)
    a = np.stack([np.interp(q, t, samples.accel_m_s2[:, k]) for k in range(3)], -1)
    return g, a


def preintegrate(
    samples: ImuSamples,
    t0_ns: int,
    t1_ns: int,
    params: gtsam.PreintegrationCombinedParams,
    bias: gtsam.imuBias.ConstantBias | None = None,
) -> gtsam.PreintegratedCombinedMeasurements:
    """Preintegrate ``samples`` over ``[t0_ns, t1_ns]``.

    The sub-intervals are the sample stamps inside ``(t0, t1)`` plus both ends (values at the ends
    linearly interpolated, held constant outside the stream); each sub-interval integrates the mean
    of its two end samples, applied at the sub-interval's midpoint attitude. Raises :class:`ShapeError` when ``t1_ns <= t0_ns`` or there is no sample.
    """
    if t1_ns <= t0_ns:
        raise ShapeError(f"t1_ns: must be after t0_ns ({t0_ns} >= {t1_ns})")
    if len(samples.stamps_ns) == 0:
        raise ShapeError("samples: empty IMU stream")
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias if bias is not None else zero_bias())
    s = samples.stamps_ns
    inner = s[(s > t0_ns) & (s < t1_ns)]
    knots = np.concatenate([[t0_ns], inner, [t1_ns]]).astype(np.int64)
    g, a = _interp(samples, knots)
    gm = 0.5 * (g[1:] + g[:-1])
    am = 0.5 * (a[1:] + a[:-1])
    dts = np.diff(knots) * 1e-9
    # GTSAM rotates each acceleration by the attitude at the start of its sub-interval; pre-rotate
    # it by half the sub-interval's rotation so that it is applied at the midpoint attitude.
    am = (so3_exp(gm * (0.5 * dts[:, None])) @ am[:, :, None])[:, :, 0]
    for k in range(len(dts)):
        pim.integrateMeasurement(am[k], gm[k], dts[k])
    return pim


class ImuBuffer:
    """Append-only IMU stream with amortised O(1) appends and trimming of old samples."""

    def __init__(self) -> None:
        self.t = np.zeros(0, np.int64)
        self.g = np.zeros((0, 3))
        self.a = np.zeros((0, 3))
        self._pending: list[tuple[int, tuple, tuple]] = []

    def append(self, t_ns: int, g: tuple, a: tuple) -> None:
        self._pending.append((t_ns, g, a))

    def flush(self) -> None:
        if self._pending:
            t, g, a = zip(*self._pending, strict=True)
            self.t = np.concatenate([self.t, np.asarray(t, np.int64)])
            self.g = np.concatenate([self.g, np.asarray(g, float).reshape(-1, 3)])
            self.a = np.concatenate([self.a, np.asarray(a, float).reshape(-1, 3)])
            self._pending = []

    @property
    def last_ns(self) -> int | None:
        if self._pending:
            return self._pending[-1][0]
        return int(self.t[-1]) if len(self.t) else None

    def trim(self, before_ns: int) -> None:
        self.flush()
        k = int(np.searchsorted(self.t, before_ns))
        if k > 0:
            self.t, self.g, self.a = self.t[k:], self.g[k:], self.a[k:]

    def samples(self) -> ImuSamples:
        self.flush()
        return ImuSamples(self.t, self.g, self.a)

    def max_gap_s(self, t0_ns: int, t1_ns: int) -> float:
        self.flush()
        inner = self.t[(self.t > t0_ns) & (self.t < t1_ns)]
        knots = np.concatenate([[t0_ns], inner, [t1_ns]])
        return float(np.max(np.diff(knots))) * 1e-9
