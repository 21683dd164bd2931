"""Simulated IMU: ideal readings from the trajectory's derivatives plus a MEMS noise model.

Continuous-time model (the one VINS-Mono, OKVIS and Kalibr use), discretised at rate ``f = 1/dt``::

    gyro_k  = omega_k + b_g,k + n_g,k,    n_g,k ~ N(0, sigma_g^2 f)
    accel_k = f_k     + b_a,k + n_a,k,    n_a,k ~ N(0, sigma_a^2 f)
    b_g,k+1 = b_g,k + N(0, sigma_bg^2 dt),   b_a,k+1 = b_a,k + N(0, sigma_ba^2 dt)

with the noise densities ``sigma_*`` of :class:`ImuNoiseParams` and initial biases drawn from
``N(0, initial_bias_std^2)``. ``omega`` is the body angular velocity and ``f = R^T (a - g)`` the
specific force in the body (IMU) frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mogs_node.geometry import check_array, so3_exp

__all__ = ["ImuNoise", "ImuNoiseParams", "integrate_imu", "simulate_imu_noise"]


@dataclass(frozen=True)
class ImuNoiseParams:
    """Noise of a consumer MEMS IMU (defaults near an MPU-9250 / BMI088 datasheet)."""

    enabled: bool = True  # False: exact readings, zero biases
    gyro_noise_density: float = 1.7e-4  # rad/s/sqrt(Hz), white noise on the gyro
    accel_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz), white noise on the accelerometer
    gyro_random_walk: float = 2.0e-5  # rad/s^2/sqrt(Hz), gyro bias diffusion
    accel_random_walk: float = 3.0e-4  # m/s^3/sqrt(Hz), accelerometer bias diffusion
    gyro_bias_std: float = 2.0e-3  # rad/s, std of the initial gyro bias
    accel_bias_std: float = 2.0e-2  # m/s^2, std of the initial accelerometer bias
    white_noise: bool = True  # False: biases only (random walk kept), no white noise


@dataclass(frozen=True)
class ImuNoise:
    """One realisation of the noise: additive terms and the true biases, each ``[M, 3]``."""

    gyro_noise_rad_s: np.ndarray
    accel_noise_m_s2: np.ndarray
    gyro_bias_rad_s: np.ndarray
    accel_bias_m_s2: np.ndarray


def simulate_imu_noise(
    n: int, rate_hz: float, params: ImuNoiseParams, rng: np.random.Generator
) -> ImuNoise:
    """White noise and random-walk biases for ``n`` samples at ``rate_hz`` (see the module doc)."""
    if not params.enabled:
        z = np.zeros((n, 3))
        return ImuNoise(z, z.copy(), z.copy(), z.copy())
    dt = 1.0 / rate_hz

    def walk(b0_std: float, rw: float) -> np.ndarray:
        b0 = rng.normal(0.0, b0_std, 3)
        steps = rng.normal(0.0, rw * np.sqrt(dt), (n, 3))
        steps[0] = 0.0
        return b0 + np.cumsum(steps, axis=0)

    bg = walk(params.gyro_bias_std, params.gyro_random_walk)
    ba = walk(params.accel_bias_std, params.accel_random_walk)
    w = 1.0 if params.white_noise else 0.0
    ng = w * rng.normal(0.0, params.gyro_noise_density * np.sqrt(rate_hz), (n, 3))
    na = w * rng.normal(0.0, params.accel_noise_density * np.sqrt(rate_hz), (n, 3))
    return ImuNoise(ng, na, bg, ba)


def integrate_imu(
    stamps_ns: np.ndarray,
    gyro_rad_s: np.ndarray,
    accel_m_s2: np.ndarray,
    T_world_imu0: np.ndarray,
    velocity0_world_m_s: np.ndarray,
    gravity_world_m_s2: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Dead-reckon IMU samples into poses ``[M, 4, 4]`` and velocities ``[M, 3]`` (reference code).

    Rotation: ``R_k+1 = R_k Exp(dt (w_k + w_k+1) / 2 + dt^2 / 12 w_k x w_k+1)`` (second-order,
    coning-corrected); translation: trapezoid on the world acceleration ``R f + g``, exact for a
    piecewise-linear acceleration. ``stamps_ns`` int64 ``[M]``, ``gyro_rad_s`` / ``accel_m_s2``
    ``[M, 3]`` in the body frame. Biases must already be removed by the caller.
    """
    t = check_array("stamps_ns", stamps_ns, shape=(None,), dtype=np.integer)
    g = check_array("gyro_rad_s", gyro_rad_s, shape=(len(t), 3), finite=True)
    a = check_array("accel_m_s2", accel_m_s2, shape=(len(t), 3), finite=True)
    T0 = check_array("T_world_imu0", T_world_imu0, shape=(4, 4), finite=True)
    dts = np.diff(t) * 1e-9
    m = len(t)
    R = np.empty((m, 3, 3))
    R[0] = T0[:3, :3]
    half = 0.5 * (g[1:] + g[:-1]) * dts[:, None] + np.cross(g[:-1], g[1:]) * (
        dts[:, None] ** 2 / 12
    )
    dR = so3_exp(half)
    for k in range(m - 1):  # sequential by nature (a recursion over samples, not pixels)
        R[k + 1] = R[k] @ dR[k]
    acc_w = np.einsum("nij,nj->ni", R, a) + np.asarray(gravity_world_m_s2, dtype=np.float64)
    dv = 0.5 * (acc_w[1:] + acc_w[:-1]) * dts[:, None]
    v = np.empty((m, 3))
    v[0] = velocity0_world_m_s
    v[1:] = v[0] + np.cumsum(dv, axis=0)
    dp = v[:-1] * dts[:, None] + (2 * acc_w[:-1] + acc_w[1:]) / 6 * dts[:, None] ** 2
    p = np.empty((m, 3))
    p[0] = T0[:3, 3]
    p[1:] = p[0] + np.cumsum(dp, axis=0)
    T = np.zeros((m, 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    return T, v
