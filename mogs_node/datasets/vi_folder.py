"""A generic visual-inertial folder with a Kalibr calibration (TUM-VI, Basalt, DM-VIO layouts).

What a user with a Kalibr-calibrated camera + IMU rig has: images, their time stamps, an IMU log
and Kalibr's ``camchain.yaml`` (+ ``imu.yaml``). :func:`read_vi_folder` accepts (docs/bridges.md
"A folder of your own"):

- calibration: ``camchain.yaml`` (or ``*camchain*.yaml``; also in ``dso/``), Kalibr's ``cam0``:
  ``intrinsics`` [fu, fv, cu, cv] (``camera_model: pinhole``), ``resolution`` [w, h],
  ``distortion_model`` (``radtan`` / ``equidistant`` / ``none``), ``distortion_coeffs``,
  ``T_cam_imu`` (4x4, the IMU in the camera frame) and ``timeshift_cam_imu`` (s,
  ``t_imu = t_cam + shift``; the images are stamped on the IMU clock with it). IMU noise from
  ``imu.yaml`` (or ``*imu*.yaml``; Kalibr ``imu0:`` or top-level keys), when present.
- images: ``cam0/data/`` (EuRoC / TUM-VI / Basalt, also under ``mav0/``), ``images/`` or ``cam0/``
  (DM-VIO); PNG or JPEG.
- image stamps: ``cam0/data.csv`` (``t_ns,filename``), ``times.txt`` (DM-VIO: ``name t_s
  [exposure]`` per line), else the file names are the nanosecond stamps (``1403715273262142976.png``).
- IMU: ``imu0/data.csv`` or ``imu.txt`` / ``imu.csv``: ``t gx gy gz ax ay az`` per line, comma or
  space separated, ``t`` integer nanoseconds or decimal seconds; ``#`` comments.
- ground-truth depth (optional): ``depth0/data/<image name>.png``, KITTI depth PNGs (uint16,
  metres = value / 256, 0 = none), z-depth in the camera of the same-named image.
- ground truth (optional): ``groundtruth.txt`` (TUM ``t tx ty tz qx qy qz qw``, the IMU/body in
  the world) or EuRoC's ``state_groundtruth_estimate0/data.csv``; camera poses are
  ``T_world_imu(t) @ T_imu_cam`` interpolated at the image stamps.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mogs_node.datasets.base import Sequence, Trajectory
from mogs_node.datasets.euroc import (
    imu_noise_from_kalibr,
    interpolate_poses,
    read_euroc_groundtruth,
)
from mogs_node.datasets.kitti import image_file_frames, read_depth_png, read_imu_text, stamp_ns_of
from mogs_node.errors import DatasetError
from mogs_node.geometry import PinholeCamera, se3_inverse
from mogs_node.yaml_file import read_yaml

__all__ = ["read_kalibr_camchain", "read_user_poses", "read_vi_folder"]

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_KALIBR_MODELS = {"radtan": "radtan", "equidistant": "equidistant", "none": "none"}


def read_kalibr_camchain(path: str | Path, camera: str = "cam0") -> dict:
    """Kalibr ``camchain.yaml`` -> ``{"camera": PinholeCamera, "distortion": {"model", "coeffs"},
    "T_imu_cam": [4, 4] | None, "time_shift_ns": int}`` of ``camera``."""
    p = Path(path)
    data = read_yaml(p, DatasetError, mapping=True)
    c = data.get(camera)
    if not isinstance(c, dict):
        raise DatasetError(f"{p}: no {camera!r} (cameras: {sorted(data)})")
    model = c.get("camera_model", "pinhole")
    if model != "pinhole":
        raise DatasetError(f"{p}: {camera}.camera_model {model!r}: only 'pinhole' is supported")
    try:
        fu, fv, cu, cv = (float(x) for x in c["intrinsics"])
        w, h = (int(x) for x in c["resolution"])
    except (KeyError, TypeError, ValueError) as err:
        raise DatasetError(
            f"{p}: {camera} needs intrinsics [fu, fv, cu, cv] and resolution [w, h] ({err})"
        ) from err
    dmodel = str(c.get("distortion_model", "none"))
    if dmodel not in _KALIBR_MODELS:
        raise DatasetError(
            f"{p}: {camera}.distortion_model {dmodel!r} not in {sorted(_KALIBR_MODELS)}"
        )
    try:
        coeffs = [float(x) for x in c.get("distortion_coeffs", []) or []]
    except (TypeError, ValueError) as err:
        raise DatasetError(f"{p}: {camera}.distortion_coeffs must be numbers") from err
    T_imu_cam = None
    if "T_cam_imu" in c:
        try:
            T_cam_imu = np.asarray(c["T_cam_imu"], dtype=np.float64).reshape(4, 4)
        except (TypeError, ValueError) as err:
            raise DatasetError(f"{p}: {camera}.T_cam_imu must be a 4x4 matrix") from err
        T_imu_cam = se3_inverse(T_cam_imu)
    try:
        shift_s = float(c.get("timeshift_cam_imu", 0.0))
    except (TypeError, ValueError) as err:
        raise DatasetError(f"{p}: {camera}.timeshift_cam_imu must be a number (s)") from err
    return {
        "camera": PinholeCamera(fu, fv, cu, cv, w, h),
        "distortion": {"model": _KALIBR_MODELS[dmodel], "coeffs": coeffs},
        "T_imu_cam": T_imu_cam,
        "time_shift_ns": int(round(shift_s * 1e9)),
    }


def _first(root: Path, candidates: list[str]) -> Path | None:
    for c in candidates:
        hits = sorted(root.glob(c))
        if hits:
            return hits[0]
    return None


def _images(root: Path) -> tuple[Path, list[tuple[int, Path]]]:
    """The image folder and its (stamp_ns, file) list, in time order."""
    img_dir = _first(root, ["mav0/cam0/data", "cam0/data", "images", "cam0"])
    if img_dir is None or not img_dir.is_dir():
        raise DatasetError(
            f"{root}: no image folder (cam0/data, mav0/cam0/data, images or cam0; "
            "docs/bridges.md 'A folder of your own')"
        )
    files = {f.name: f for f in img_dir.iterdir() if f.suffix.lower() in _IMAGE_SUFFIXES}
    if not files:
        raise DatasetError(f"{img_dir}: no PNG or JPEG images")
    csv = img_dir.parent / "data.csv" if img_dir.name == "data" else None
    times = _first(root, ["times.txt"])
    out: list[tuple[int, Path]] = []
    if csv is not None and csv.exists():
        for i, line in enumerate(csv.read_text().splitlines(), 1):
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            parts = [x.strip() for x in line.split(",")]
            if len(parts) < 2 or parts[1] not in files:
                raise DatasetError(f"{csv}:{i}: expected 't_ns,filename' of an image in {img_dir}")
            out.append((stamp_ns_of(parts[0], f"{csv}:{i}"), files[parts[1]]))
    elif times is not None:
        stems = {f.stem: f for f in files.values()}
        for i, line in enumerate(times.read_text().splitlines(), 1):
            parts = line.split()
            if not parts or line.lstrip().startswith("#"):
                continue
            if len(parts) < 2 or parts[0] not in stems:
                raise DatasetError(
                    f"{times}:{i}: expected 'name t_s [exposure]' of an image in {img_dir}"
                )
            out.append((stamp_ns_of(parts[1], f"{times}:{i}"), stems[parts[0]]))
    else:
        for f in files.values():
            if not f.stem.isdigit():
                raise DatasetError(
                    f"{f}: no cam0/data.csv or times.txt, and the file name is no ns stamp"
                )
            out.append((int(f.stem), f))
    out.sort(key=lambda x: x[0])
    return img_dir, out


def _ground_truth(root: Path) -> Trajectory | None:
    tum = _first(root, ["groundtruth.txt", "gt.txt"])
    if tum is not None:
        from mogs_node.frontend.trajectory_io import read_tum

        stamps, poses = read_tum(tum)
        return Trajectory(stamps, poses, "imu")
    csv = _first(root, ["mav0/state_groundtruth_estimate0/data.csv"])
    return read_euroc_groundtruth(csv)[0] if csv is not None else None


def read_vi_folder(root: str | Path, *, camera: str = "cam0") -> Sequence:
    """Read a generic visual-inertial folder (module docstring); errors name the file."""
    r = Path(root)
    if not r.is_dir():
        raise DatasetError(f"{r}: not a folder")
    chain = _first(r, ["camchain.yaml", "*camchain*.yaml", "dso/camchain.yaml"])
    if chain is None:
        raise DatasetError(
            f"{r}: no Kalibr camchain.yaml (the camera calibration; docs/bridges.md)"
        )
    cal = read_kalibr_camchain(chain, camera)
    img_dir, images = _images(r)
    shift = cal["time_shift_ns"]
    stamps = np.array([t + shift for t, _ in images], dtype=np.int64)
    if np.any(np.diff(stamps) <= 0):
        raise DatasetError(f"{img_dir}: image stamps are not strictly increasing")
    imu_file = _first(r, ["mav0/imu0/data.csv", "imu0/data.csv", "imu.txt", "imu.csv"])
    imu = read_imu_text(imu_file) if imu_file is not None else None
    imu_yaml = _first(r, ["imu.yaml", "*imu*.yaml", "dso/imu_config.yaml"])
    noise: dict[str, float] = {}
    if imu_yaml is not None:
        data = read_yaml(imu_yaml, DatasetError, mapping=True)
        noise = imu_noise_from_kalibr(data.get("imu0", data), imu_yaml)
    gt = _ground_truth(r)
    poses: list[np.ndarray | None] = [None] * len(stamps)
    if gt is not None and cal["T_imu_cam"] is not None and len(gt):
        inside = (stamps >= gt.stamps_ns[0]) & (stamps <= gt.stamps_ns[-1])
        P = interpolate_poses(gt.stamps_ns, gt.poses, stamps) @ cal["T_imu_cam"]
        poses = [P[i] if inside[i] else None for i in range(len(stamps))]
    first = cv2.imread(str(images[0][1]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise DatasetError(f"{images[0][1]}: unreadable image")
    cam: PinholeCamera = cal["camera"]
    if first.shape[:2] != (cam.height, cam.width):
        raise DatasetError(
            f"{images[0][1]}: {first.shape[1]}x{first.shape[0]} image, but {chain} says "
            f"{cam.width}x{cam.height}"
        )
    grey = first.ndim == 2
    depth_dir = img_dir.parents[1] / "depth0" / "data" if img_dir.name == "data" else r / "depth0"

    def depth_of(f: Path):
        d = depth_dir / (f.stem + ".png")
        return (lambda: read_depth_png(d)) if d.exists() else None

    frames = image_file_frames(
        [f for _, f in images], stamps, cam, grey=grey, poses=poses, depth_loader=depth_of
    )
    meta: dict[str, object] = {
        "calibration": str(chain),
        "imu_noise": noise,
        "time_shift_ns": shift,
    }
    return Sequence(r.name, frames, imu, cal["T_imu_cam"], gt, cal["distortion"], meta)


def read_user_poses(path: str | Path, frame_stamps_ns: np.ndarray) -> list[np.ndarray | None]:
    """The user's camera poses ``T_world_cam`` for frames at ``frame_stamps_ns`` [F].

    TUM (``t tx ty tz qx qy qz qw``, 8 columns): interpolated on SE(3) at the frame stamps inside
    the file's time span (None outside); KITTI odometry (12 numbers of the 3x4 pose per line):
    one line per frame, in order (the counts must agree). Rotations are made orthonormal.
    """
    from mogs_node.frontend.trajectory_io import read_kitti, read_tum
    from mogs_node.geometry import nearest_rotation

    p = Path(path)
    try:
        first = next((ln for ln in p.read_text().splitlines() if ln.strip() and ln[0] != "#"), "")
    except OSError as err:
        raise DatasetError(f"{p}: cannot read poses ({err.strerror or err})") from err
    n = len(first.split())
    stamps = np.asarray(frame_stamps_ns, dtype=np.int64)
    if n == 8:
        t, P = read_tum(p)
        if len(t) < 2 or np.any(np.diff(t) <= 0):
            raise DatasetError(f"{p}: TUM poses need >= 2 lines with increasing stamps")
        P[:, :3, :3] = nearest_rotation(P[:, :3, :3])
        Q = interpolate_poses(t, P, stamps)
        inside = (stamps >= t[0]) & (stamps <= t[-1])
        return [Q[i] if inside[i] else None for i in range(len(stamps))]
    if n == 12:
        P = read_kitti(p)
        if len(P) != len(stamps):
            raise DatasetError(f"{p}: {len(P)} KITTI poses for {len(stamps)} frames")
        P[:, :3, :3] = nearest_rotation(P[:, :3, :3])
        return list(P)
    raise DatasetError(
        f"{p}: expected TUM (8 columns: t tx ty tz qx qy qz qw) or KITTI (12 numbers) lines, "
        f"got {n} columns"
    )
