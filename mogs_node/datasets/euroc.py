"""EuRoC MAV (ASL format) reader: ``mav0/cam0``, ``imu0``, ``state_groundtruth_estimate0``.

``cam0/sensor.yaml`` gives the intrinsics ``[fu, fv, cu, cv]``, the radial-tangential distortion and
``T_BS`` (the camera in the body = IMU frame). The ground truth gives body poses (position,
quaternion wxyz), velocity and IMU biases; camera poses are ``T_world_body(t) @ T_BS``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mogs_node.datasets.base import Frame, Sequence, Trajectory, text_lines
from mogs_node.datasets.kitti import load_image, read_euroc_imu_csv
from mogs_node.errors import DatasetError
from mogs_node.geometry import PinholeCamera, make_T, quat_wxyz_to_rotmat, se3_exp, se3_log
from mogs_node.yaml_file import read_yaml

__all__ = [
    "KALIBR_IMU_NOISE",
    "imu_noise_from_kalibr",
    "interpolate_poses",
    "read_euroc",
    "read_euroc_groundtruth",
    "read_sensor_yaml",
]

#: Kalibr / EuRoC ``imu.yaml`` keys -> the frontend's ImuNoise fields (same units)
KALIBR_IMU_NOISE = {
    "gyroscope_noise_density": "gyro_noise_rad_s_rthz",
    "accelerometer_noise_density": "accel_noise_m_s2_rthz",
    "gyroscope_random_walk": "gyro_walk_rad_s2_rthz",
    "accelerometer_random_walk": "accel_walk_m_s3_rthz",
}


def imu_noise_from_kalibr(data: dict, path: Path) -> dict[str, float]:
    """The noise densities of a Kalibr / EuRoC IMU yaml (those present) as ImuNoise fields."""
    out = {}
    for key, name in KALIBR_IMU_NOISE.items():
        if key in data:
            try:
                v = float(data[key])
            except (TypeError, ValueError) as err:
                raise DatasetError(f"{path}: {key} must be a number, got {data[key]!r}") from err
            if not (np.isfinite(v) and v > 0):
                raise DatasetError(f"{path}: {key} must be finite and > 0, got {v}")
            out[name] = v
    return out


def read_sensor_yaml(path: str | Path) -> dict:
    """Parse an EuRoC/Kalibr ``sensor.yaml`` (OpenCV ``%YAML:1.0`` header tolerated)."""
    return read_yaml(Path(path), DatasetError, mapping=True)


def _T_BS(data: dict, path: Path) -> np.ndarray:
    t = data.get("T_BS")
    vals = t.get("data") if isinstance(t, dict) else t
    try:
        T = np.asarray(vals, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError) as err:
        raise DatasetError(f"{path}: T_BS must hold 16 numbers") from err
    return T


def _read_csv(path: Path, ncols: int) -> tuple[np.ndarray, np.ndarray]:
    t, v = [], []
    for i, line in text_lines(path, comments=True):
        parts = line.split(",")
        if len(parts) < ncols:
            raise DatasetError(
                f"{path}:{i}: expected {ncols} comma-separated values, got {len(parts)}"
            )
        try:
            t.append(int(parts[0]))
            v.append([float(x) for x in parts[1:ncols]])
        except ValueError as err:
            raise DatasetError(f"{path}:{i}: bad number ({err})") from err
    if not t:
        raise DatasetError(f"{path}: no data rows")
    return np.asarray(t, dtype=np.int64), np.asarray(v, dtype=np.float64)


def read_euroc_groundtruth(path: str | Path) -> tuple[Trajectory, np.ndarray]:
    """``state_groundtruth_estimate0/data.csv`` -> (body Trajectory, [N, 9] velocity / bg / ba)."""
    p = Path(path)
    t, v = _read_csv(p, 17)
    q = v[:, 3:7]
    if np.any(np.linalg.norm(q, axis=1) < 1e-6):
        raise DatasetError(f"{p}: zero quaternion")
    T = make_T(quat_wxyz_to_rotmat(q), v[:, :3])
    return Trajectory(t, T, "body"), v[:, 7:16]


def interpolate_poses(stamps_ns: np.ndarray, poses: np.ndarray, query_ns: np.ndarray) -> np.ndarray:
    """Poses ``[Q, 4, 4]`` at ``query_ns``: geodesic interpolation between the neighbouring samples
    (clamped at the ends)."""
    i = np.clip(np.searchsorted(stamps_ns, query_ns), 1, len(stamps_ns) - 1)
    t0, t1 = stamps_ns[i - 1], stamps_ns[i]
    f = np.clip((query_ns - t0) / np.maximum(t1 - t0, 1), 0.0, 1.0)
    A, B = poses[i - 1], poses[i]
    rel = np.linalg.inv(A) @ B
    return A @ se3_exp(se3_log(rel) * f[:, None])


def read_euroc(root: str | Path, *, camera: str = "cam0", undistort: bool = True) -> Sequence:
    """Read an EuRoC sequence (``root`` is the folder holding ``mav0`` or ``mav0`` itself).

    With ``undistort`` (default) images are undistorted to the same pinhole intrinsics on loading,
    so
    ``Frame.camera`` is exact; otherwise images are raw and ``Sequence.distortion`` describes them.
    Frames are grey (``mono8``).
    """
    r = Path(root)
    mav = r / "mav0" if (r / "mav0").exists() else r
    cam_dir = mav / camera
    yml = cam_dir / "sensor.yaml"
    s = read_sensor_yaml(yml)
    try:
        fu, fv, cu, cv = (float(x) for x in s["intrinsics"])
        W, H = (int(x) for x in s["resolution"])
        coeffs = [float(x) for x in s.get("distortion_coefficients", [])]
    except (KeyError, TypeError, ValueError) as err:
        raise DatasetError(
            f"{yml}: needs intrinsics [fu, fv, cu, cv] and resolution [w, h] ({err})"
        ) from err
    model = s.get("distortion_model", "radial-tangential")
    if model not in ("radial-tangential", "radtan") and coeffs:
        raise DatasetError(f"{yml}: unsupported distortion_model {model!r}")
    cam = PinholeCamera(fu, fv, cu, cv, W, H)
    T_body_cam = _T_BS(s, yml)
    stamps, _ = _read_csv(cam_dir / "data.csv", 1)
    names = []
    csv_lines = [
        ln
        for ln in (cam_dir / "data.csv").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    ]
    for i, ln in enumerate(csv_lines):
        parts = ln.split(",")
        if len(parts) < 2:
            raise DatasetError(f"{cam_dir / 'data.csv'}:{i + 2}: expected 'timestamp,filename'")
        names.append(parts[1].strip())
    imu_csv = mav / "imu0" / "data.csv"
    imu = read_euroc_imu_csv(imu_csv) if imu_csv.exists() else None
    T_imu_cam = T_body_cam
    imu_yaml = mav / "imu0" / "sensor.yaml"
    imu_noise: dict[str, float] = {}
    if imu_yaml.exists():  # camera in the IMU frame = T_BS_imu^-1 T_BS_cam
        imu_data = read_sensor_yaml(imu_yaml)
        T_body_imu = _T_BS(imu_data, imu_yaml)
        T_imu_cam = np.linalg.inv(T_body_imu) @ T_body_cam
        imu_noise = imu_noise_from_kalibr(imu_data, imu_yaml)
    gt_csv = mav / "state_groundtruth_estimate0" / "data.csv"
    gt, gt_extra = read_euroc_groundtruth(gt_csv) if gt_csv.exists() else (None, None)
    poses: list[np.ndarray | None] = [None] * len(stamps)
    if gt is not None:
        inside = (stamps >= gt.stamps_ns[0]) & (stamps <= gt.stamps_ns[-1])
        P = interpolate_poses(gt.stamps_ns, gt.poses, stamps) @ T_body_cam
        poses = [P[i] if inside[i] else None for i in range(len(stamps))]
    K, D = cam.K, np.asarray(coeffs, dtype=np.float64)
    maps = None
    if undistort and coeffs:
        maps = cv2.initUndistortRectifyMap(K, D, None, K, (W, H), cv2.CV_32FC1)

    def loader(path: Path):
        if maps is None:
            return lambda: load_image(path, grey=True)
        return lambda: cv2.remap(load_image(path, grey=True), maps[0], maps[1], cv2.INTER_LINEAR)

    frames = tuple(
        Frame(
            i,
            int(stamps[i]),
            cam,
            loader(cam_dir / "data" / n),
            "mono8",
            poses[i],
            None,
            str(cam_dir / "data" / n),
        )
        for i, n in enumerate(names)
    )
    meta: dict[str, object] = {
        "groundtruth_velocity_bias": gt_extra,
        "undistorted": maps is not None,
        "imu_noise": imu_noise,
        "calibration": str(yml),
    }
    dist = {"model": "radial-tangential", "coeffs": coeffs}
    return Sequence(mav.parent.name or mav.name, frames, imu, T_imu_cam, gt, dist, meta)
