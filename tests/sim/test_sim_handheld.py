"""The handheld walk (``motion="handheld"``) and the camera-IMU time offset of the simulator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.cli import main
from mogs_node.datasets import read_bag, read_kitti_raw
from mogs_node.errors import ConfigError
from mogs_node.geometry import so3_log
from mogs_node.sim import ImuNoiseParams, SimConfig, integrate_imu, make_sequence
from mogs_node.sim.sequence import HANDHELD_CAMERA_HEIGHT_M


def _walk(**kw) -> object:
    cfg = dict(seed=3, n_frames=301, width=64, height=32, motion="handheld")
    cfg.update(kw)
    return make_sequence(SimConfig(**cfg))


def test_handheld_walk_figures() -> None:
    """Walking speed, step bounce, head turns up to 90 deg/s, camera at about 1.5 m."""
    s = _walk(imu_noise=ImuNoiseParams(enabled=False))
    v = s.imu_velocity_world_m_s
    speed = np.linalg.norm(v[:, :2], axis=1)
    assert 1.2 < float(np.median(speed)) < 1.6
    assert np.abs(v[:, 2]).max() > 0.1  # the step bounce moves the camera up and down
    rate_deg_s = np.degrees(np.abs(s.imu_gyro_true_rad_s[:, 2]))
    assert 40.0 < rate_deg_s.max() <= 90.5  # at least one head turn in 30 s, none faster
    z_cam = s.T_world_cam[:, 2, 3]
    assert np.abs(z_cam - HANDHELD_CAMERA_HEIGHT_M).max() < 0.05
    # hand shake: roll and pitch rates are never zero for long while walking
    assert np.degrees(np.abs(s.imu_gyro_true_rad_s[:, :2])).mean() > 0.5


def test_handheld_imu_integrates_to_the_poses() -> None:
    """Exact IMU readings dead-reckon onto the ground-truth poses (the IMU matches the motion)."""
    s = _walk(n_frames=51, imu_noise=ImuNoiseParams(enabled=False))
    T, _ = integrate_imu(
        s.imu_stamps_ns,
        s.imu_gyro_rad_s,
        s.imu_accel_m_s2,
        s.imu_T_world_imu[0],
        s.imu_velocity_world_m_s[0],
        s.gravity_world_m_s2,
    )
    assert np.linalg.norm(T[:, :3, 3] - s.imu_T_world_imu[:, :3, 3], axis=1).max() < 0.01
    dR = np.einsum("nji,njk->nik", T[:, :3, :3], s.imu_T_world_imu[:, :3, :3])
    assert np.linalg.norm(so3_log(dR), axis=1).max() < 1e-3


def test_handheld_camera_poses_from_the_imu_at_the_camera_stamps() -> None:
    """Exact IMU readings, dead-reckoned from the true state and carried to the camera by the
    sim's own ``T_imu_cam``, land on the true camera poses at each frame's stamp plus the time
    offset to 1 mm / 0.01 deg over 5 s of the walk (head turns about the IMU, the 1.1 m lever arm
    to the camera; docs/frontend.md round 11)."""
    off = 50_000_000
    s = _walk(n_frames=201, imu_noise=ImuNoiseParams(enabled=False), time_offset_ns=off)
    i0 = 150
    k0 = int(np.searchsorted(s.imu_stamps_ns, s.stamps_ns[i0] + off))
    assert s.imu_stamps_ns[k0] == s.stamps_ns[i0] + off
    T, _ = integrate_imu(
        s.imu_stamps_ns[k0:],
        s.imu_gyro_rad_s[k0:],
        s.imu_accel_m_s2[k0:],
        s.T_world_imu[i0],
        s.velocity_world_m_s[i0],
        s.gravity_world_m_s2,
    )
    k = np.searchsorted(s.imu_stamps_ns[k0:], s.stamps_ns[i0:] + off)
    T_cam = T[k] @ s.T_imu_cam
    assert np.abs(np.degrees(s.imu_gyro_true_rad_s[k0:])).max() > 30.0  # a head turn is in it
    assert np.linalg.norm(T_cam[:, :3, 3] - s.T_world_cam[i0:, :3, 3], axis=1).max() < 1e-3
    dR = np.einsum("nji,njk->nik", T_cam[:, :3, :3], s.T_world_cam[i0:, :3, :3])
    assert np.degrees(np.linalg.norm(so3_log(dR), axis=1)).max() < 0.01


def test_handheld_static_start() -> None:
    s = _walk(n_frames=41, static_start_s=2.0, imu_noise=ImuNoiseParams(enabled=False))
    t = (s.imu_stamps_ns - s.stamps_ns[0]) * 1e-9
    rest = t < 1.99
    np.testing.assert_allclose(s.imu_gyro_rad_s[rest], 0.0, atol=1e-3)
    assert np.abs(s.imu_velocity_world_m_s[rest]).max() < 1e-3


@settings(max_examples=8, deadline=None)
@given(offset_ms=st.integers(-200, 200))
def test_time_offset_shifts_only_the_camera_stamps(offset_ms: int) -> None:
    """Same motion, IMU and poses; camera stamps move by -offset: t_imu = t_cam + offset."""
    a = make_sequence(SimConfig(seed=1, n_frames=5, width=32, height=16))
    b = make_sequence(
        SimConfig(seed=1, n_frames=5, width=32, height=16, time_offset_ns=offset_ms * 1_000_000)
    )
    np.testing.assert_array_equal(b.stamps_ns + offset_ms * 1_000_000, a.stamps_ns)
    np.testing.assert_allclose(b.T_world_cam, a.T_world_cam, atol=1e-9)
    # the IMU covers every frame's IMU time with the usual margin either side
    t_imu = b.stamps_ns + offset_ms * 1_000_000
    assert b.imu_stamps_ns[0] <= t_imu[0] - 90_000_000
    assert b.imu_stamps_ns[-1] >= t_imu[-1] + 90_000_000


def test_handheld_errors() -> None:
    with pytest.raises(ConfigError, match="motion"):
        make_sequence(SimConfig(motion="bicycle", n_frames=2))
    with pytest.raises(ConfigError, match="motion"):
        make_sequence(SimConfig(trajectory="oxts", motion="handheld", n_frames=2))


@pytest.mark.parametrize("fmt", ["kitti", "rosbag2"])
def test_mogs_sim_handheld_with_time_offset(tmp_path: Path, fmt: str) -> None:
    out = tmp_path / "walk"
    args = ["sim", "--motion", "handheld", "--time-offset-ms", "50", "--frames", "3"]
    rc = main([*args, "--size", "64x32", "--format", fmt, "--out", str(out)])
    assert rc == 0
    ref = make_sequence(
        SimConfig(n_frames=3, width=64, height=32, motion="handheld", time_offset_ns=50_000_000)
    )
    s = read_kitti_raw(out) if fmt == "kitti" else read_bag(out)
    np.testing.assert_array_equal([f.stamp_ns for f in s.frames], ref.stamps_ns)
    np.testing.assert_array_equal(s[2].image, ref.render(2).rgb)
