"""Export a simulated sequence to disk: KITTI-raw and KITTI-odometry layouts, a generic
visual-inertial folder with a Kalibr calibration, rosbag2 (sqlite3 / MCAP) and ROS1 bags.

KITTI-raw layout written by :func:`write_kitti_raw` (readable by
:func:`mogs_node.datasets.kitti.read_kitti_raw`)::

    image_02/data/%010d.png, image_02/timestamps.txt    rectified RGB frames
    oxts/data/%010d.txt, oxts/timestamps.txt            one packet per frame (devkit Mercator
    oxts/dataformat.txt                                 coordinates around 49 N 8.4 E)
    proj_depth/groundtruth/image_02/%010d.png           z-depth, uint16 = round(256 m), 0 = none
    poses.txt                                           T_world_cam per frame (KITTI odometry rows)
    imu/data.csv                                        full-rate IMU (EuRoC csv; an extension)
    calib_cam_to_cam.txt, calib_velo_to_cam.txt,        P_rect_02 = [K | 0], R_rect_00 = I,
    calib_imu_to_velo.txt                               velodyne frame = IMU frame
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from mogs_node.datasets.bag import BagTopics, BagWriter
from mogs_node.datasets.oxts import EARTH_RADIUS_M, OXTS_FIELDS, format_kitti_timestamps
from mogs_node.errors import DatasetError
from mogs_node.geometry import se3_inverse

if TYPE_CHECKING:
    from mogs_node.sim import SimSequence

__all__ = [
    "FOLDER_FORMATS",
    "depth_to_kitti_png",
    "rpy_from_rotmat",
    "write_kitti_odometry",
    "write_kitti_raw",
    "write_sim_bag",
    "write_vi_folder",
]

log = logging.getLogger(__name__)

ORIGIN_LAT_DEG, ORIGIN_LON_DEG, ORIGIN_ALT_M = 49.0, 8.4, 115.0


def rpy_from_rotmat(R: np.ndarray) -> np.ndarray:
    """Inverse of ``rotmat_from_rpy`` (``Rz(yaw) Ry(pitch) Rx(roll)``), ``[..., 3, 3] -> [..., 3]``.

    Returns (roll, pitch, yaw) ``[..., 3]``.
    """
    R = np.asarray(R, dtype=np.float64)
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], -1)


def depth_to_kitti_png(depth_m: np.ndarray) -> np.ndarray:
    """z-depth f32 ``[H, W]`` (inf/0 = none) -> uint16 KITTI depth (round(256 d), 0 = none/far)."""
    d = np.asarray(depth_m, dtype=np.float64)
    ok = np.isfinite(d) & (d > 0) & (d * 256.0 < 65535.5)
    return np.where(ok, np.round(np.where(ok, d, 0.0) * 256.0), 0).astype(np.uint16)


def _fmt(a: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in np.asarray(a, dtype=np.float64).reshape(-1))  # exact


def _oxts_packets(seq: SimSequence, frame_idx: np.ndarray) -> np.ndarray:
    """Packets whose devkit conversion gives back the world poses up to the first-pose origin."""
    T = seq.T_world_imu[frame_idx]
    scale = np.cos(np.deg2rad(ORIGIN_LAT_DEG))
    mx0 = scale * np.deg2rad(ORIGIN_LON_DEG) * EARTH_RADIUS_M
    my0 = scale * EARTH_RADIUS_M * np.log(np.tan(np.deg2rad(90.0 + ORIGIN_LAT_DEG) / 2.0))
    p = T[:, :3, 3] - T[0, :3, 3]
    mx, my = mx0 + p[:, 0], my0 + p[:, 1]
    lat = np.rad2deg(2.0 * np.arctan(np.exp(my / (scale * EARTH_RADIUS_M)))) - 90.0
    lon = np.rad2deg(mx / (scale * EARTH_RADIUS_M))
    rpy = rpy_from_rotmat(T[:, :3, :3])
    out = np.zeros((len(frame_idx), len(OXTS_FIELDS)))
    idx = OXTS_FIELDS.index
    out[:, idx("lat")], out[:, idx("lon")], out[:, idx("alt")] = lat, lon, ORIGIN_ALT_M + p[:, 2]
    out[:, idx("roll") : idx("yaw") + 1] = rpy
    v_world = seq.velocity_world_m_s[frame_idx]
    v_body = np.einsum("nji,nj->ni", T[:, :3, :3], v_world)
    out[:, idx("vn")], out[:, idx("ve")] = v_world[:, 1], v_world[:, 0]  # world x = east, y = north
    out[:, idx("vf")], out[:, idx("vl")], out[:, idx("vu")] = v_body.T
    k = np.searchsorted(seq.imu_stamps_ns, seq.stamps_ns[frame_idx])
    k = np.clip(k, 0, len(seq.imu_stamps_ns) - 1)
    acc, gyr = seq.imu_accel_m_s2[k], seq.imu_gyro_rad_s[k]
    out[:, idx("ax") : idx("az") + 1] = acc
    out[:, idx("af") : idx("au") + 1] = acc
    out[:, idx("wx") : idx("wz") + 1] = gyr
    out[:, idx("wf") : idx("wu") + 1] = gyr
    out[:, idx("pos_accuracy")], out[:, idx("vel_accuracy")] = 0.01, 0.01
    out[:, idx("navstat") :] = [4, 11, 6, 6, 6]
    return out


def write_kitti_raw(
    seq: SimSequence, out_dir: str | Path, *, frames: list[int] | None = None
) -> Path:
    """Write ``seq`` (all frames or ``frames``) in the KITTI-raw layout of the module docstring."""
    out = Path(out_dir)
    idx = np.arange(len(seq)) if frames is None else np.asarray(frames, dtype=int)
    if len(idx) == 0:
        raise DatasetError("frames: nothing to write")
    for sub in ("image_02/data", "oxts/data", "proj_depth/groundtruth/image_02", "imu"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    stamps = seq.stamps_ns[idx]
    (out / "image_02" / "timestamps.txt").write_text(format_kitti_timestamps(stamps))
    (out / "oxts" / "timestamps.txt").write_text(format_kitti_timestamps(stamps))
    (out / "oxts" / "dataformat.txt").write_text("".join(f"{n}\n" for n in OXTS_FIELDS))
    for n, row in enumerate(_oxts_packets(seq, idx)):
        vals = [repr(float(v)) for v in row[:25]] + [str(int(v)) for v in row[25:]]
        (out / "oxts" / "data" / f"{n:010d}.txt").write_text(" ".join(vals) + "\n")
    K = seq.camera.K
    P = np.c_[K, np.zeros(3)]
    W, H = seq.camera.width, seq.camera.height
    cam_lines = ["calib_time: 01-Jan-2026 00:00:00", "corner_dist: 0.000000e+00"]
    for c in range(4):
        cam_lines += [
            f"S_{c:02d}: {W}.0 {H}.0",
            f"K_{c:02d}: {_fmt(K)}",
            f"D_{c:02d}: {_fmt(np.zeros(5))}",
            f"R_{c:02d}: {_fmt(np.eye(3))}",
            f"T_{c:02d}: {_fmt(np.zeros(3))}",
            f"S_rect_{c:02d}: {W}.0 {H}.0",
            f"R_rect_{c:02d}: {_fmt(np.eye(3))}",
            f"P_rect_{c:02d}: {_fmt(P)}",
        ]
    (out / "calib_cam_to_cam.txt").write_text("\n".join(cam_lines) + "\n")
    T_cam_imu = se3_inverse(seq.T_imu_cam)
    (out / "calib_velo_to_cam.txt").write_text(
        "calib_time: 01-Jan-2026 00:00:00\n"
        f"R: {_fmt(T_cam_imu[:3, :3])}\nT: {_fmt(T_cam_imu[:3, 3])}\n"
        "delta_f: 0.000000e+00 0.000000e+00\ndelta_c: 0.000000e+00 0.000000e+00\n"
    )
    (out / "calib_imu_to_velo.txt").write_text(
        f"calib_time: 01-Jan-2026 00:00:00\nR: {_fmt(np.eye(3))}\nT: {_fmt(np.zeros(3))}\n"
    )
    poses = seq.T_world_cam[idx][:, :3, :].reshape(len(idx), 12)
    (out / "poses.txt").write_text(
        "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in poses)
    )
    imu_lines = [
        "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
        "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
    ]
    for t, g, a in zip(seq.imu_stamps_ns, seq.imu_gyro_rad_s, seq.imu_accel_m_s2, strict=True):
        imu_lines.append(f"{int(t)}," + ",".join(repr(float(v)) for v in (*g, *a)))
    (out / "imu" / "data.csv").write_text("\n".join(imu_lines) + "\n")
    for n, i in enumerate(idx):
        f = seq.render(int(i))
        if not cv2.imwrite(str(out / "image_02" / "data" / f"{n:010d}.png"), f.rgb[..., ::-1]):
            raise DatasetError(f"{out / 'image_02' / 'data'}: cannot write PNG")
        cv2.imwrite(
            str(out / "proj_depth" / "groundtruth" / "image_02" / f"{n:010d}.png"),
            depth_to_kitti_png(f.depth_m),
        )
    log.info("wrote %d frames in KITTI-raw layout to %s", len(idx), out)
    return out


def _frame_indices(seq: SimSequence, frames: list[int] | None) -> np.ndarray:
    idx = np.arange(len(seq)) if frames is None else np.asarray(frames, dtype=int)
    if len(idx) == 0:
        raise DatasetError("frames: nothing to write")
    return idx


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise DatasetError(f"{path}: cannot write the image")


def write_kitti_odometry(
    seq: SimSequence, out_dir: str | Path, *, frames: list[int] | None = None
) -> Path:
    """Write ``seq`` as one KITTI odometry sequence folder (readable by
    :func:`mogs_node.datasets.kitti.read_kitti_odometry`; no IMU, as KITTI odometry)::

        image_2/%06d.png   rectified RGB frames
        times.txt          seconds since the first frame
        calib.txt          P0..P3 = [K | 0] (one camera), Tr = identity
        poses.txt          T_world_cam per frame, 12 numbers, the first pose the identity
    """
    out = Path(out_dir)
    idx = _frame_indices(seq, frames)
    (out / "image_2").mkdir(parents=True, exist_ok=True)
    t = seq.stamps_ns[idx]
    (out / "times.txt").write_text("".join(f"{(s - t[0]) * 1e-9:.6e}\n" for s in t))
    P = _fmt(np.c_[seq.camera.K, np.zeros(3)])
    (out / "calib.txt").write_text(
        "".join(f"P{c}: {P}\n" for c in range(4)) + f"Tr: {_fmt(np.eye(4)[:3])}\n"
    )
    T = se3_inverse(seq.T_world_cam[idx[0]]) @ seq.T_world_cam[idx]
    (out / "poses.txt").write_text("".join(_fmt(p[:3]) + "\n" for p in T))
    for n, i in enumerate(idx):
        _write_rgb(out / "image_2" / f"{n:06d}.png", seq.render(int(i)).rgb)
    log.info("wrote %d frames in KITTI-odometry layout to %s", len(idx), out)
    return out


def _kalibr_yaml(seq: SimSequence, noise: Any) -> tuple[str, str]:
    """``camchain.yaml`` and ``imu.yaml`` of the sim rig, as Kalibr writes them (``noise``: the
    sim's :class:`~mogs_node.sim.imu.ImuNoiseParams`)."""
    c = seq.camera
    T_cam_imu = se3_inverse(seq.T_imu_cam)
    rows = "\n".join("  - [" + ", ".join(repr(float(v)) for v in r) + "]" for r in T_cam_imu)
    camchain = (
        "cam0:\n"
        "  camera_model: pinhole\n"
        f"  intrinsics: [{c.fx_px!r}, {c.fy_px!r}, {c.cx_px!r}, {c.cy_px!r}]\n"
        f"  resolution: [{c.width}, {c.height}]\n"
        "  distortion_model: radtan\n"
        "  distortion_coeffs: [0.0, 0.0, 0.0, 0.0]\n"
        "  T_cam_imu:\n" + rows + "\n"
        "  timeshift_cam_imu: 0.0\n"
        "  rostopic: /cam0/image_raw\n"
    )
    rate = 1e9 / float(np.median(np.diff(seq.imu_stamps_ns)))
    imu = (
        "imu0:\n"
        f"  accelerometer_noise_density: {noise.accel_noise_density!r}\n"
        f"  accelerometer_random_walk: {noise.accel_random_walk!r}\n"
        f"  gyroscope_noise_density: {noise.gyro_noise_density!r}\n"
        f"  gyroscope_random_walk: {noise.gyro_random_walk!r}\n"
        f"  update_rate: {rate:.1f}\n"
        "  rostopic: /imu0\n"
    )
    return camchain, imu


def write_vi_folder(
    seq: SimSequence, out_dir: str | Path, *, frames: list[int] | None = None
) -> Path:
    """Write ``seq`` as a generic visual-inertial folder (EuRoC / TUM-VI / Basalt layout with a
    Kalibr calibration; readable by :func:`mogs_node.datasets.vi_folder.read_vi_folder`)::

        camchain.yaml, imu.yaml   Kalibr calibration (the sim rig; noise of the sim's IMU)
        cam0/data/<t_ns>.png      RGB frames, cam0/data.csv (t_ns,filename)
        depth0/data/<t_ns>.png    ground-truth z-depth (KITTI depth PNG: uint16 = round(256 m))
        imu0/data.csv             every IMU sample from the first to the last frame (+-1.5 s)
        groundtruth.txt           T_world_imu at the frame stamps (TUM)
    """
    from mogs_node.frontend.trajectory_io import write_tum

    out = Path(out_dir)
    idx = _frame_indices(seq, frames)
    for sub in ("cam0/data", "depth0/data", "imu0"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    camchain, imu_yaml = _kalibr_yaml(seq, seq.config.imu_noise)
    (out / "camchain.yaml").write_text(camchain)
    (out / "imu.yaml").write_text(imu_yaml)
    t = seq.stamps_ns[idx]
    names = [f"{int(s)}.png" for s in t]
    (out / "cam0" / "data.csv").write_text(
        "#timestamp [ns],filename\n" + "".join(f"{int(s)},{n}\n" for s, n in zip(t, names))
    )
    m = (seq.imu_stamps_ns >= t[0] - 1_500_000_000) & (seq.imu_stamps_ns <= t[-1] + 1_500_000_000)
    lines = ["#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z"]
    for s, g, a in zip(seq.imu_stamps_ns[m], seq.imu_gyro_rad_s[m], seq.imu_accel_m_s2[m]):
        lines.append(f"{int(s)}," + ",".join(repr(float(v)) for v in (*g, *a)))
    (out / "imu0" / "data.csv").write_text("\n".join(lines) + "\n")
    write_tum(out / "groundtruth.txt", t, seq.T_world_imu[idx])
    for n, i in zip(names, idx):
        f = seq.render(int(i))
        _write_rgb(out / "cam0" / "data" / n, f.rgb)
        cv2.imwrite(str(out / "depth0" / "data" / n), depth_to_kitti_png(f.depth_m))
    log.info("wrote %d frames in the generic VI layout to %s", len(idx), out)
    return out


#: ``mogs sim --format`` values written as folders (the rest are bags, :data:`BAG_FORMATS`)
FOLDER_FORMATS = {"kitti-odometry": write_kitti_odometry, "vi-folder": write_vi_folder}


def write_sim_bag(
    seq: SimSequence,
    path: str | Path,
    *,
    fmt: str = "rosbag2",
    topics: BagTopics | None = None,
    frames: list[int] | None = None,
    compressed: bool = False,
    with_depth: bool = True,
) -> Path:
    """Write ``seq`` to a bag (``fmt`` "rosbag2" (sqlite3), "mcap" or "rosbag1"); a folder format
    of :data:`FOLDER_FORMATS` ("kitti-odometry", "vi-folder") goes to its writer instead, so one
    call writes every ``mogs sim --format`` but KITTI raw.

    Once: ``T_imu_cam`` on tf_static (imu -> camera). Per frame: the image (sensor_msgs/Image
    rgb8, or CompressedImage PNG), CameraInfo, the
    ground-truth camera pose (PoseStamped, ``T_world_cam``) and, with ``with_depth``, the z-depth
    (Image 32FC1, 0 = none); every IMU sample in the frames' time span (sensor_msgs/Imu).
    """
    if fmt in FOLDER_FORMATS:
        return FOLDER_FORMATS[fmt](seq, path, frames=frames)
    tp = topics or BagTopics()
    idx = np.arange(len(seq)) if frames is None else np.asarray(frames, dtype=int)
    t0, t1 = seq.stamps_ns[idx].min(), seq.stamps_ns[idx].max()
    p = Path(path)
    with BagWriter(p, fmt, topics=tp) as w:
        if tp.tf_static is not None and tp.imu is not None:  # the camera-IMU calibration
            w.tf_static(int(t0) - 200_000_000, seq.T_imu_cam, parent="imu", child="camera")
        chosen = set(idx.tolist())
        for t, kind, k in seq.sensor_events():
            if kind == "imu":
                if tp.imu is not None and (t0 - 200_000_000) <= t <= (t1 + 200_000_000):
                    w.imu(t, seq.imu_gyro_rad_s[k], seq.imu_accel_m_s2[k])
                continue
            if k not in chosen:
                continue
            f = seq.render(k)
            if tp.camera_info is not None:
                w.camera_info(t, seq.camera)
            w.image(t, f.rgb, compress="png" if compressed else None)
            if tp.pose is not None:
                w.pose(t, f.T_world_cam)
            if with_depth and tp.depth is not None:
                d = np.where(np.isfinite(f.depth_m), f.depth_m, 0.0).astype(np.float32)
                w.image(t, d, topic=tp.depth)
    log.info("wrote %d frames to %s (%s)", len(idx), p, fmt)
    return p
