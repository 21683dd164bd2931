"""Readers on the real excerpts in ../shared/data (skipped, with the reason, when absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mogs_node.datasets.euroc import read_euroc
from mogs_node.datasets.kitti import read_kitti_oxts, read_kitti_raw
from mogs_node.geometry import so3_log

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
KITTI78 = DATA / "kitti_raw_2011_09_26_78"
OXTS = DATA / "kitti_raw_2011_09_26_drive_0001_oxts"
EUROC = DATA / "euroc_v1_01_micro"

pytestmark = pytest.mark.shared_data


def _need(p: Path) -> None:
    if not p.exists():
        pytest.skip(f"real data excerpt not found: {p} (a user checkout has no ../shared/data)")


def test_kitti_raw_78_frames_depth_and_calibration() -> None:
    _need(KITTI78)
    s = read_kitti_raw(KITTI78)
    assert len(s) == 78
    cam = s.camera
    assert (cam.width, cam.height) == (1242, 375)
    assert cam.fx_px == pytest.approx(721.5377) and cam.cx_px == pytest.approx(609.5593)
    assert cam.cy_px == pytest.approx(172.854)
    assert s.meta["depth"] == "velodyne_raw" and s.meta.get("synthetic_stamps")
    np.testing.assert_array_equal(np.diff(s.stamps_ns), 100_000_000)
    img = s[10].image
    assert img.shape == (375, 1242, 3) and img.dtype == np.uint8
    d = s[10].depth_m()
    assert d.shape == (375, 1242) and d.dtype == np.float32
    n = int((d > 0).sum())
    assert 10_000 < n < 25_000  # ~16k LiDAR returns
    assert d[d > 0].min() > 2.0 and d.max() < 90.0
    # camera-IMU extrinsics from the devkit chain: camera ~1.08 m ahead, 0.73 m above the IMU
    T = s.T_imu_cam
    np.testing.assert_allclose(T[:3, 3], [1.08, -0.25, 0.73], atol=0.03)
    np.testing.assert_allclose(
        T[:3, :3] @ [0, 0, 1.0], [1, 0, 0], atol=0.02
    )  # optical axis = forward
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-5)
    # LiDAR depth lands on image structure: more returns in the lower half (road) than the sky
    assert (d[:100] > 0).sum() < (d[200:] > 0).sum()


def test_kitti_oxts_trajectory_length_and_imu() -> None:
    _need(OXTS)
    s = read_kitti_oxts(OXTS)
    gt = s.ground_truth
    assert len(gt) == 108 and len(s.frames) == 0
    assert gt.path_length_m() == pytest.approx(107.0, abs=2.0)
    np.testing.assert_allclose(gt.poses[0], np.eye(4), atol=1e-9)
    duration = (gt.stamps_ns[-1] - gt.stamps_ns[0]) * 1e-9
    assert duration == pytest.approx(11.0, abs=0.2)
    # speed ~9.7 m/s; the devkit pose's forward axis points along the motion
    v = np.diff(gt.poses[:, :3, 3], axis=0) / np.diff(gt.stamps_ns)[:, None] * 1e9
    assert np.linalg.norm(v, axis=1).mean() == pytest.approx(9.7, abs=0.6)
    fwd = gt.poses[:-1, :3, 0]
    cosang = np.einsum("ij,ij->i", fwd, v) / np.linalg.norm(v, axis=1)
    assert np.median(cosang) > 0.99
    # IMU: accelerometer z reads ~ +g (specific force), yaw rate integrates to the heading change
    assert s.imu.accel_m_s2[:, 2].mean() == pytest.approx(9.81, abs=0.6)
    dyaw = so3_log(gt.poses[0, :3, :3].T @ gt.poses[-1, :3, :3])[2]
    yaw_int = np.sum(
        0.5 * (s.imu.gyro_rad_s[1:, 2] + s.imu.gyro_rad_s[:-1, 2]) * np.diff(s.imu.stamps_ns) * 1e-9
    )
    assert yaw_int == pytest.approx(dyaw, abs=0.02)
    assert s.T_imu_cam is not None and len(s.meta["image_02_stamps_ns"]) > 0


def test_euroc_frames_imu_groundtruth() -> None:
    _need(EUROC)
    s = read_euroc(EUROC)
    assert len(s) == 95
    assert (s.camera.width, s.camera.height) == (752, 480)
    assert s.camera.fx_px == pytest.approx(458.654)
    assert s.distortion["coeffs"][0] == pytest.approx(-0.28340811)
    img = s[0].image
    assert img.shape == (480, 752) and img.dtype == np.uint8 and s[0].encoding == "mono8"
    raw = read_euroc(EUROC, undistort=False)[0].image
    assert not np.array_equal(img, raw)  # undistortion changed the pixels
    np.testing.assert_allclose(np.diff(s.stamps_ns), 50_000_000, atol=1000)  # 20 Hz
    assert len(s.imu) > 2000
    dt = np.diff(s.imu.stamps_ns)
    assert np.median(dt) == pytest.approx(5_000_000, abs=1000)  # 200 Hz
    assert s.imu.stamps_ns[0] <= s.stamps_ns[0] and s.imu.stamps_ns[-1] >= s.stamps_ns[-1]
    # nearly static: |accel| ~ g, ground truth moves ~2 cm
    assert np.linalg.norm(s.imu.accel_m_s2, axis=1).mean() == pytest.approx(9.81, abs=0.3)
    T = s.T_world_cam
    assert T is not None
    assert np.linalg.norm(T[-1, :3, 3] - T[0, :3, 3]) < 0.05
    # T_BS of cam0: camera z axis roughly along body x... compare with the published matrix
    np.testing.assert_allclose(
        s.T_imu_cam[0, :3], [0.0148655429818, -0.999880929698, 0.00414029679422], atol=1e-9
    )
    assert s.ground_truth.frame == "body" and len(s.ground_truth) > 90
