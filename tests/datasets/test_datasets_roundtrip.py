"""Writers and readers round-trip a simulated sequence; bad files raise DatasetError naming them."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from mogs_node.datasets.bag import BagTopics, BagWriter, read_bag
from mogs_node.datasets.euroc import read_euroc, read_sensor_yaml
from mogs_node.datasets.kitti import (
    project_velodyne,
    read_calib_file,
    read_depth_png,
    read_kitti_odometry,
    read_kitti_raw,
    read_velodyne_bin,
)
from mogs_node.datasets.oxts import (
    format_kitti_timestamp,
    parse_kitti_timestamp,
    read_kitti_timestamps,
    read_oxts,
)
from mogs_node.datasets.writers import (
    depth_to_kitti_png,
    rpy_from_rotmat,
    write_kitti_raw,
    write_sim_bag,
)
from mogs_node.errors import DatasetError
from mogs_node.geometry import PinholeCamera, rotmat_from_rpy
from mogs_node.sim import SimConfig, make_sequence


@pytest.fixture(scope="module")
def seq():
    return make_sequence(SimConfig(seed=3, n_frames=4, width=160, height=64))


@pytest.fixture(scope="module")
def renders(seq):
    return [seq.render(i) for i in range(len(seq))]


def test_kitti_raw_roundtrip(seq, renders, tmp_path: Path) -> None:
    out = write_kitti_raw(seq, tmp_path / "drive")
    s = read_kitti_raw(out)
    assert len(s) == len(seq)
    assert s.camera == seq.camera
    np.testing.assert_array_equal(s.stamps_ns, seq.stamps_ns)
    np.testing.assert_array_equal(s.T_world_cam, seq.T_world_cam)
    np.testing.assert_allclose(s.T_imu_cam, seq.T_imu_cam, atol=1e-12)
    for f, r in zip(s, renders, strict=True):
        np.testing.assert_array_equal(f.image, r.rgb)
        d = f.depth_m()
        np.testing.assert_array_equal(d, depth_to_kitti_png(r.depth_m).astype(np.float32) / 256)
        fin = np.isfinite(r.depth_m) & (r.depth_m < 255)
        assert np.abs(d[fin] - r.depth_m[fin]).max() <= 1 / 512 + 1e-6
        assert np.all(d[~np.isfinite(r.depth_m)] == 0)
    # OXTS -> devkit poses = the true body poses relative to the first one
    rel = np.linalg.inv(seq.T_world_imu[0]) @ seq.T_world_imu
    np.testing.assert_allclose(s.ground_truth.poses, rel, atol=1e-6)
    # the full-rate IMU comes back exactly
    np.testing.assert_array_equal(s.imu.stamps_ns, seq.imu_stamps_ns)
    np.testing.assert_array_equal(s.imu.gyro_rad_s, seq.imu_gyro_rad_s)
    np.testing.assert_array_equal(s.imu.accel_m_s2, seq.imu_accel_m_s2)


@pytest.mark.parametrize("fmt", ["rosbag2", "mcap", "rosbag1"])
def test_bag_roundtrip(seq, renders, tmp_path: Path, fmt: str) -> None:
    path = write_sim_bag(seq, tmp_path / ("seq.bag" if fmt == "rosbag1" else "seq"), fmt=fmt)
    b = read_bag(path)
    assert len(b) == len(seq)
    assert b.camera == seq.camera
    np.testing.assert_array_equal(b.stamps_ns, seq.stamps_ns)
    np.testing.assert_allclose(b.T_world_cam, seq.T_world_cam, atol=1e-12)
    for f, r in zip(b, renders, strict=True):
        np.testing.assert_array_equal(f.image, r.rgb)
        np.testing.assert_array_equal(f.depth_m(), np.where(np.isfinite(r.depth_m), r.depth_m, 0))
    m = np.isin(seq.imu_stamps_ns, b.imu.stamps_ns)
    assert (
        m.sum() == len(b.imu) and len(b.imu) >= (seq.stamps_ns[-1] - seq.stamps_ns[0]) // 5_000_000
    )
    np.testing.assert_array_equal(b.imu.gyro_rad_s, seq.imu_gyro_rad_s[m])
    np.testing.assert_array_equal(b.imu.accel_m_s2, seq.imu_accel_m_s2[m])


def test_bag_custom_topics_compressed_and_encodings(tmp_path: Path) -> None:
    topics = BagTopics(
        image="/cam/compressed", camera_info=None, imu="/my_imu", pose=None, depth=None
    )
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (12, 20, 3), dtype=np.uint8)
    with BagWriter(tmp_path / "c", "mcap", topics=topics) as w:
        w.image(1_000, img, compress="png")
        w.image(2_000, img[..., 0], compress="png")
        w.image(3_000, img, topic="/other")
        w.imu(1_500, np.array([0.1, 0.2, 0.3]), np.array([1.0, 2.0, 9.8]))
    cam = PinholeCamera(10.0, 10.0, 9.5, 5.5, 20, 12)
    b = read_bag(tmp_path / "c", topics=topics, camera=cam)
    assert len(b) == 2 and b.camera == cam
    np.testing.assert_array_equal(b[0].image, img)
    np.testing.assert_array_equal(b[1].image, img[..., 0])
    np.testing.assert_array_equal(b.imu.gyro_rad_s, [[0.1, 0.2, 0.3]])
    with pytest.raises(DatasetError, match="no CameraInfo"):
        read_bag(tmp_path / "c", topics=topics)
    with pytest.raises(DatasetError, match="no image topic '/nope'"):
        read_bag(tmp_path / "c", topics=BagTopics(image="/nope"), camera=cam)


def test_bgr8_and_mono8_images_decode(tmp_path: Path) -> None:
    from mogs_node.datasets.bag import decode_image_msg

    class Msg:
        def __init__(self, enc: str, arr: np.ndarray) -> None:
            self.encoding, self.height, self.width = enc, arr.shape[0], arr.shape[1]
            self.step = arr.strides[0] + 4  # padded rows
            pad = np.zeros((arr.shape[0], self.step), np.uint8)
            pad[:, : arr[0].nbytes] = arr.reshape(arr.shape[0], -1).view(np.uint8)
            self.data, self.is_bigendian = pad.reshape(-1), 0

    rgb = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    out, enc = decode_image_msg(Msg("bgr8", rgb[..., ::-1].copy()))
    assert enc == "rgb8"
    np.testing.assert_array_equal(out, rgb)
    out, enc = decode_image_msg(Msg("mono8", rgb[..., 0].copy()))
    assert enc == "mono8"
    np.testing.assert_array_equal(out, rgb[..., 0])
    with pytest.raises(DatasetError, match="unsupported image encoding"):
        decode_image_msg(Msg("yuv422", rgb[..., 0].copy()))


def test_kitti_odometry_reader(seq, renders, tmp_path: Path) -> None:
    d = tmp_path / "sequences" / "07"
    (d / "image_2").mkdir(parents=True)
    K = seq.camera.K
    b = 0.06  # as KITTI: P2[0, 3] = f b puts camera 2 b metres left of camera 0
    P0 = np.c_[K, np.zeros(3)]
    P2 = P0.copy()
    P2[0, 3] = K[0, 0] * b
    lines = [
        f"P{i}: " + " ".join(repr(float(v)) for v in (P2 if i == 2 else P0).ravel())
        for i in range(4)
    ]
    lines.append("Tr: " + " ".join(repr(float(v)) for v in np.eye(4)[:3].ravel()))
    (d / "calib.txt").write_text("\n".join(lines) + "\n")
    (d / "times.txt").write_text(
        "".join(f"{(t - seq.stamps_ns[0]) * 1e-9:.6e}\n" for t in seq.stamps_ns)
    )
    for i, r in enumerate(renders):
        cv2.imwrite(str(d / "image_2" / f"{i:06d}.png"), r.rgb[..., ::-1])
    T_cam0 = seq.T_world_cam.copy()
    (tmp_path / "poses").mkdir()
    (tmp_path / "poses" / "07.txt").write_text(
        "".join(" ".join(repr(float(v)) for v in T[:3].ravel()) + "\n" for T in T_cam0)
    )
    s = read_kitti_odometry(d)
    assert len(s) == 4 and s.camera == PinholeCamera.from_K(K, 160, 64)
    np.testing.assert_array_equal(s[2].image, renders[2].rgb)
    np.testing.assert_array_equal(
        s.stamps_ns, np.round((seq.stamps_ns - seq.stamps_ns[0]) * 1.0).astype(np.int64)
    )
    # camera 2 pose = camera 0 pose moved by the baseline along camera x
    expect = T_cam0.copy()
    expect[:, :3, 3] -= b * T_cam0[:, :3, 0]
    np.testing.assert_allclose(s.T_world_cam, expect, atol=1e-12)
    (tmp_path / "poses" / "07.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match=r"07\.txt:1: expected 12 numbers"):
        read_kitti_odometry(d)


def test_velodyne_projection(tmp_path: Path) -> None:
    cam = PinholeCamera(100.0, 100.0, 49.5, 29.5, 100, 60)
    # LiDAR frame = camera frame rotated: x forward, y left, z up
    T_cam_velo = np.eye(4)
    T_cam_velo[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    pts = np.array(
        [[10.0, 0.0, 0.0, 1.0], [5.0, 0.0, 0.0, 1.0], [-3.0, 0.0, 0.0, 1.0], [8.0, 1.0, 0.5, 1.0]],
        dtype=np.float32,
    )
    pts.tofile(tmp_path / "0.bin")
    got = read_velodyne_bin(tmp_path / "0.bin")
    np.testing.assert_array_equal(got, pts)
    d = project_velodyne(got, T_cam_velo, cam)
    assert d[30, 50] == pytest.approx(5.0)  # the nearer of the two points on the axis wins
    assert d[round(29.5 - 100 * 0.5 / 8), round(49.5 - 100 * 1 / 8)] == pytest.approx(8.0)
    assert (d > 0).sum() == 2  # the point behind is dropped
    (tmp_path / "bad.bin").write_bytes(b"\x00" * 10)
    with pytest.raises(DatasetError, match="bad.bin"):
        read_velodyne_bin(tmp_path / "bad.bin")


def test_timestamps_and_rpy_roundtrip() -> None:
    t = 1317042145964389445
    s = format_kitti_timestamp(t)
    assert s == "2011-09-26 13:02:25.964389445"
    assert parse_kitti_timestamp(s) == t
    rng = np.random.default_rng(0)
    rpy = rng.uniform([-1, -1.4, -3], [1, 1.4, 3], (50, 3))
    np.testing.assert_allclose(rpy_from_rotmat(rotmat_from_rpy(*rpy.T)), rpy, atol=1e-12)


def test_bad_files_name_file_and_line(tmp_path: Path) -> None:
    (tmp_path / "ts.txt").write_text("2011-09-26 13:02:25.964389445\nnot a time\n")
    with pytest.raises(DatasetError, match=r"ts\.txt:2: bad timestamp"):
        read_kitti_timestamps(tmp_path / "ts.txt")
    (tmp_path / "calib.txt").write_text("P_rect_02: 1 2 x\n")
    with pytest.raises(DatasetError, match=r"calib\.txt:1: non-numeric"):
        read_calib_file(tmp_path / "calib.txt")
    with pytest.raises(DatasetError, match="missing.txt"):
        read_calib_file(tmp_path / "missing.txt")
    o = tmp_path / "oxts"
    (o / "data").mkdir(parents=True)
    (o / "timestamps.txt").write_text("2011-09-26 13:02:25.964389445\n")
    (o / "data" / "0000000000.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match=r"0000000000\.txt:1: expected 30 values"):
        read_oxts(o)
    cv2.imwrite(str(tmp_path / "d8.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(DatasetError, match=r"d8\.png: expected a single-channel uint16"):
        read_depth_png(tmp_path / "d8.png")
    with pytest.raises(DatasetError, match="no PNG images"):
        read_kitti_raw(tmp_path)
    (tmp_path / "s.yaml").write_text("%YAML:1.0\nintrinsics: [1, 2\n")
    with pytest.raises(DatasetError, match=r"s\.yaml"):
        read_sensor_yaml(tmp_path / "s.yaml")
    cam0 = tmp_path / "mav0" / "cam0"
    cam0.mkdir(parents=True)
    (cam0 / "sensor.yaml").write_text("%YAML:1.0\nresolution: [4, 4]\n")
    with pytest.raises(DatasetError, match=r"sensor\.yaml: needs intrinsics"):
        read_euroc(tmp_path)
    with pytest.raises(DatasetError, match="no such bag"):
        read_bag(tmp_path / "nothing.bag")


def test_kitti_writer_depth_png_encoding() -> None:
    d = np.array([[np.inf, 0.0, 1.0], [255.0, 300.0, 1 / 256]], dtype=np.float32)
    np.testing.assert_array_equal(depth_to_kitti_png(d), [[0, 0, 256], [65280, 0, 1]])


def test_kitti_raw_velodyne_points_through_calibration(seq, renders, tmp_path: Path) -> None:
    """LiDAR scans in the velodyne frame come back as the true depth through the calib chain."""
    import shutil

    out = write_kitti_raw(seq, tmp_path / "drive", frames=[0, 1])
    shutil.rmtree(out / "proj_depth")
    (out / "velodyne_points" / "data").mkdir(parents=True)
    rng = np.random.default_rng(1)
    picks = []
    for n in range(2):
        d = renders[n].depth_m
        v, u = np.nonzero(np.isfinite(d))
        k = rng.choice(len(u), 300, replace=False)
        uv = np.c_[u[k], v[k]].astype(np.float64)
        Pc = seq.camera.backproject(uv, d[v[k], u[k]])
        # the writer's velodyne frame is the IMU frame: T_velo_cam = T_imu_cam
        Pv = Pc @ seq.T_imu_cam[:3, :3].T + seq.T_imu_cam[:3, 3]
        np.c_[Pv, np.ones(len(Pv))].astype(np.float32).tofile(
            out / "velodyne_points" / "data" / f"{n:010d}.bin"
        )
        picks.append((u[k], v[k], d[v[k], u[k]]))
    s = read_kitti_raw(out)
    assert s.meta["depth"] == "velodyne_points"
    for n, (u, v, z) in enumerate(picks):
        got = s[n].depth_m()
        assert (got > 0).sum() == len(np.unique(np.c_[u, v], axis=0))
        np.testing.assert_allclose(got[v, u], z, rtol=1e-5)
    # the 10 Hz OXTS IMU is the sequence's IMU at the frame stamps when no imu/data.csv exists
    (out / "imu" / "data.csv").unlink()
    s = read_kitti_raw(out)
    k = np.searchsorted(seq.imu_stamps_ns, seq.stamps_ns[:2])
    np.testing.assert_array_equal(s.imu.stamps_ns, seq.stamps_ns[:2])
    np.testing.assert_allclose(s.imu.gyro_rad_s, seq.imu_gyro_rad_s[k], rtol=1e-15)
    np.testing.assert_allclose(s.imu.accel_m_s2, seq.imu_accel_m_s2[k], rtol=1e-15)


# ------------------------------------------------------------ generic VI folder, KITTI odometry


def _small_sim():
    from mogs_node.sim import SimConfig, make_sequence

    return make_sequence(SimConfig(seed=3, n_frames=4, width=96, height=40))


def test_vi_folder_round_trip_with_a_kalibr_calibration(tmp_path):
    from bridges.sources import camera_info_of
    from mogs_node.datasets import read_vi_folder, write_sim_bag

    seq = _small_sim()
    d = write_sim_bag(seq, tmp_path / "walk", fmt="vi-folder")
    got = read_vi_folder(d)
    assert len(got) == len(seq) and np.array_equal(got.stamps_ns, seq.stamps_ns)
    assert got.camera == seq.camera
    np.testing.assert_allclose(got.T_imu_cam, seq.T_imu_cam, atol=1e-15)
    np.testing.assert_allclose(got.T_world_cam, seq.T_world_cam, atol=1e-8)  # TUM, 9 decimals
    np.testing.assert_array_equal(got.frames[2].image, seq.render(2).rgb)
    m = (seq.imu_stamps_ns >= seq.stamps_ns[0] - 1_500_000_000) & (
        seq.imu_stamps_ns <= seq.stamps_ns[-1] + 1_500_000_000
    )
    np.testing.assert_array_equal(got.imu.gyro_rad_s, seq.imu_gyro_rad_s[m])
    info = camera_info_of(got)  # what the player publishes: no value typed anywhere
    noise = seq.config.imu_noise
    assert info.imu_noise["gyro_noise_rad_s_rthz"] == noise.gyro_noise_density
    assert info.imu_noise["accel_walk_m_s3_rthz"] == noise.accel_random_walk
    assert info.distortion_model == "none"  # all-zero radtan coefficients


def test_vi_folder_dmvio_layout_and_kalibr_time_shift(tmp_path):
    """DM-VIO: images/ + times.txt (name, seconds) + imu.txt (seconds, spaces); Kalibr's
    timeshift_cam_imu moves the images onto the IMU clock; equidistant distortion is kept."""
    import cv2

    from bridges.sources import camera_info_of
    from mogs_node.datasets import read_vi_folder

    (tmp_path / "images").mkdir()
    for i in range(3):
        cv2.imwrite(str(tmp_path / "images" / f"{i:05d}.png"), np.full((40, 96), 10 * i, np.uint8))
    (tmp_path / "times.txt").write_text(
        "".join(f"{i:05d} {100.0 + 0.05 * i:.6f} 8.0\n" for i in range(3))
    )
    (tmp_path / "imu.txt").write_text(
        "# t gx gy gz ax ay az\n"
        + "".join(f"{99.9 + 0.005 * k:.6f} 0.01 0 0 0 0 9.8\n" for k in range(60))
    )
    (tmp_path / "camchain.yaml").write_text(
        "cam0:\n  camera_model: pinhole\n  intrinsics: [50.0, 51.0, 48.0, 20.0]\n"
        "  resolution: [96, 40]\n  distortion_model: equidistant\n"
        "  distortion_coeffs: [0.01, -0.002, 0.0003, 0.0]\n"
        "  T_cam_imu:\n  - [1, 0, 0, 0.1]\n  - [0, 1, 0, 0]\n  - [0, 0, 1, 0]\n  - [0, 0, 0, 1]\n"
        "  timeshift_cam_imu: -0.0125\n"
    )
    seq = read_vi_folder(tmp_path)
    assert list(seq.stamps_ns) == [100_000_000_000 - 12_500_000 + 50_000_000 * i for i in range(3)]
    assert seq.frames[1].encoding == "mono8" and seq.frames[1].image[0, 0] == 10
    assert seq.imu.stamps_ns[1] - seq.imu.stamps_ns[0] == 5_000_000 and len(seq.imu) == 60
    np.testing.assert_allclose(seq.T_imu_cam[:3, 3], [-0.1, 0.0, 0.0])
    info = camera_info_of(seq)
    assert info.distortion_model == "equidistant" and info.imu_noise == {}
    np.testing.assert_allclose(info.distortion_coeffs, [0.01, -0.002, 0.0003, 0.0])


def test_vi_folder_errors_name_the_file(tmp_path):
    from mogs_node.datasets import read_vi_folder

    with pytest.raises(DatasetError, match="camchain.yaml"):
        read_vi_folder(tmp_path)
    (tmp_path / "camchain.yaml").write_text("cam0:\n  intrinsics: [1, 2]\n")
    with pytest.raises(DatasetError, match=r"camchain\.yaml: cam0 needs intrinsics"):
        read_vi_folder(tmp_path)
    (tmp_path / "camchain.yaml").write_text(
        "cam0:\n  intrinsics: [1, 1, 1, 1]\n  resolution: [4, 4]\n  distortion_model: fov\n"
    )
    with pytest.raises(DatasetError, match="distortion_model 'fov'"):
        read_vi_folder(tmp_path)


def test_kitti_odometry_writer_round_trip(tmp_path):
    from mogs_node.datasets import read_kitti_odometry, write_sim_bag
    from mogs_node.geometry import se3_inverse

    seq = _small_sim()
    d = write_sim_bag(seq, tmp_path / "00", fmt="kitti-odometry")
    got = read_kitti_odometry(d)
    assert got.imu is None and got.camera == seq.camera
    np.testing.assert_allclose(
        got.T_world_cam, se3_inverse(seq.T_world_cam[0]) @ seq.T_world_cam, atol=1e-12
    )
    np.testing.assert_array_equal(got.stamps_ns, seq.stamps_ns - seq.stamps_ns[0])
    np.testing.assert_array_equal(got.frames[3].image, seq.render(3).rgb)


def test_vi_folder_carries_ground_truth_depth(tmp_path):
    from mogs_node.datasets import read_vi_folder, write_vi_folder

    seq = _small_sim()
    got = read_vi_folder(write_vi_folder(seq, tmp_path / "d"))
    d_true = seq.render(1).depth_m
    d = got.frames[1].depth_m()
    ok = np.isfinite(d_true) & (d_true * 256 < 65535)
    np.testing.assert_allclose(d[ok], d_true[ok], atol=1 / 512 + 1e-6)  # 1/256 m steps
