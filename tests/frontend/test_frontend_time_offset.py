"""Camera-IMU time offset from rotation rates (frontend/time_offset.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError
from mogs_node.frontend.preintegration import ImuSamples
from mogs_node.frontend.time_offset import (
    TimeOffsetEstimator,
    TimeOffsetParams,
    estimate_time_offset,
    gyro_integral,
    gyro_variation,
    rotation_from_tracks,
)
from mogs_node.geometry import so3_exp

RATE_HZ = 200.0


def _omega(t_s: np.ndarray, amp: float = 1.0) -> np.ndarray:
    """A head-turn-like angular velocity [T, 3] (rad/s), smooth and changing."""
    t = np.asarray(t_s)[:, None]
    f = np.array([0.3, 0.5, 0.7])
    return (
        amp
        * np.c_[
            0.2 * np.sin(2 * np.pi * f[0] * t),
            0.3 * np.sin(2 * np.pi * f[1] * t + 1),
            1.2 * np.sin(2 * np.pi * f[2] * t + 2),
        ]
    )


def _omega_integral(t0_s: np.ndarray, t1_s: np.ndarray, amp: float = 1.0) -> np.ndarray:
    """Exact integral of :func:`_omega` over [t0, t1] per row."""
    f = np.array([0.3, 0.5, 0.7])
    a = np.array([0.2, 0.3, 1.2])
    ph = np.array([0.0, 1.0, 2.0])
    w = 2 * np.pi * f
    t0, t1 = np.asarray(t0_s)[:, None], np.asarray(t1_s)[:, None]
    return amp * a * (np.cos(w * t0 + ph) - np.cos(w * t1 + ph)) / w


def _imu(seconds: float, amp: float = 1.0, bias=(0.0, 0.0, 0.0)) -> ImuSamples:
    t = np.arange(-1.0, seconds + 1.0, 1 / RATE_HZ)
    stamps = np.round(t * 1e9).astype(np.int64)
    g = _omega(t, amp) + np.asarray(bias)
    return ImuSamples(stamps, g, np.tile([0.0, 0.0, 9.81], (len(t), 1)))


@settings(max_examples=30, deadline=None)
@given(t0=st.floats(0.0, 5.0), span=st.floats(0.001, 2.0))
def test_gyro_integral_matches_the_analytic_integral(t0: float, span: float) -> None:
    imu = _imu(8.0)
    q = np.array([int(t0 * 1e9), int((t0 + span) * 1e9)])
    G = gyro_integral(imu, q)
    exact = _omega_integral(np.array([q[0] * 1e-9]), np.array([q[1] * 1e-9]))[0]
    # trapezoids over 200 Hz samples of a ~1-3 Hz signal: error up to ~2e-5 per half second
    np.testing.assert_allclose(G[1] - G[0], exact, atol=4e-5 * max(1.0, 2.0 * span))


def test_gyro_integral_is_nan_outside_the_samples() -> None:
    imu = _imu(1.0)
    G = gyro_integral(imu, np.array([imu.stamps_ns[0] - 1, imu.stamps_ns[-1] + 1]))
    assert np.all(np.isnan(G))


def _pairs(offset_ms: float, n: int = 100, noise: float = 0.0, amp: float = 1.0, seed: int = 0):
    """Visual rotation vectors of frame pairs at 10 Hz (camera time) for a true offset."""
    rng = np.random.default_rng(seed)
    t_cam = np.arange(n + 1) * 0.1
    t0, t1 = t_cam[:-1] + offset_ms * 1e-3, t_cam[1:] + offset_ms * 1e-3
    r = _omega_integral(t0, t1, amp) + rng.normal(0, noise, (n, 3))
    return t_cam, r


@settings(max_examples=15, deadline=None)
@given(offset_ms=st.floats(-120.0, 120.0), bias=st.floats(-0.02, 0.02))
def test_offset_and_bias_recovered_from_rotation_rates(offset_ms: float, bias: float) -> None:
    t_cam, r = _pairs(offset_ms, noise=1e-4)
    imu = _imu(12.0, bias=(bias, -bias, 0.5 * bias))
    offs = np.arange(-150, 151) * 1_000_000
    ts = np.round(t_cam * 1e9).astype(np.int64)
    G = gyro_integral(imu, ts[:, None] + offs[None])  # [F, D, 3]
    est = estimate_time_offset(np.diff(t_cam), r, G[1:] - G[:-1], offs)
    assert est is not None
    assert abs(est.offset_ns / 1e6 - offset_ms) < 0.3
    assert est.sigma_ns < 1e6
    np.testing.assert_allclose(est.gyro_bias_rad_s, [bias, -bias, 0.5 * bias], atol=1e-3)


def test_gross_outliers_are_dropped() -> None:
    t_cam, r = _pairs(40.0, noise=1e-4)
    r[::10] += 0.3  # every tenth essential matrix wrong
    imu = _imu(12.0)
    offs = np.arange(-150, 151) * 1_000_000
    ts = np.round(t_cam * 1e9).astype(np.int64)
    G = gyro_integral(imu, ts[:, None] + offs[None])
    est = estimate_time_offset(np.diff(t_cam), r, G[1:] - G[:-1], offs)
    assert abs(est.offset_ns / 1e6 - 40.0) < 0.3 and est.pairs == 90


def test_without_rotation_changes_the_offset_is_not_used() -> None:
    """A constant turn rate (or none) says nothing about the offset: large error, not accepted."""
    n = 120
    t_cam = np.arange(n + 1) * 0.1
    t = np.arange(-1.0, 14.0, 1 / RATE_HZ)
    imu = ImuSamples(
        np.round(t * 1e9).astype(np.int64),
        np.tile([0.0, 0.0, 0.1], (len(t), 1))
        + np.random.default_rng(1).normal(0, 1e-3, (len(t), 3)),
        np.tile([0.0, 0.0, 9.81], (len(t), 1)),
    )
    est = TimeOffsetEstimator(TimeOffsetParams(min_pairs=20), 0, np.eye(3), np.eye(3))
    # feed the estimator's pairs directly: rotation about z by 0.01 rad per frame
    est._waiting = [
        (int(t_cam[i] * 1e9), int(t_cam[i + 1] * 1e9), np.array([0.0, 0.0, 0.01])) for i in range(n)
    ]
    est._integrate_waiting(imu)
    assert est.pairs == n
    res = estimate_time_offset(np.full(n, 0.1), np.stack(est._r), np.stack(est._G), est.offsets_ns)
    assert res.sigma_ns > TimeOffsetParams().max_sigma_ms * 1e6


@settings(max_examples=10, deadline=None)
@given(rx=st.floats(-0.1, 0.1), ry=st.floats(-0.2, 0.2), rz=st.floats(-0.1, 0.1))
def test_rotation_from_tracks_recovers_the_rotation(rx: float, ry: float, rz: float) -> None:
    rng = np.random.default_rng(3)
    K = np.array([[360.0, 0, 310], [0, 360.0, 94], [0, 0, 1]])
    P0 = np.c_[rng.uniform(-8, 8, 150), rng.uniform(-3, 2, 150), rng.uniform(4, 40, 150)]
    R = so3_exp(np.array([rx, ry, rz]))  # R_c1_c0
    t = np.array([0.02, 0.0, 0.15])
    P1 = P0 @ R.T + t
    uv0 = (P0 / P0[:, 2:]) @ K.T
    uv1 = (P1 / P1[:, 2:]) @ K.T
    R_est = rotation_from_tracks(uv0[:, :2], uv1[:, :2], K)
    assert R_est is not None
    # the 0.15 m step at 4-40 m biases a rotation-only fit by up to ~4e-3 (a grid over this
    # range); a rotation rate off by that much moves the rate correlation's peak by far less
    np.testing.assert_allclose(R_est, R, atol=8e-3)


def test_params_are_validated() -> None:
    with pytest.raises(ConfigError, match="time_offset"):
        TimeOffsetParams(step_ms=0.0)
    with pytest.raises(ConfigError, match="time_offset"):
        TimeOffsetParams(min_pairs=2)


def test_gyro_variation_tells_rotation_changes_apart() -> None:
    """A steady turn has no variation (the offset is unobservable and harmless: no waiting);
    head-turn-like rates have plenty."""
    steady = ImuSamples(
        np.arange(0, 3_000_000_000, 5_000_000, dtype=np.int64),
        np.tile([0.0, 0.0, 0.3], (600, 1)),
        np.tile([0.0, 0.0, 9.81], (600, 1)),
    )
    assert gyro_variation(steady, 2_900_000_000) == pytest.approx(0.0, abs=1e-12)
    assert gyro_variation(_imu(4.0), 3_000_000_000) > TimeOffsetParams().init_wait_gyro_std_rad_s
    assert gyro_variation(steady, -5_000_000_000) == 0.0  # no samples in the span
