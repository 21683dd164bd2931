"""KITTI raw and KITTI odometry readers (images, calibration, OXTS, ground-truth depth and poses).

KITTI raw drive folder (``2011_09_26_drive_0001_sync``)::

    image_02/data/0000000000.png ...  image_02/timestamps.txt
    oxts/data/0000000000.txt ...      oxts/timestamps.txt
    proj_depth/{groundtruth,velodyne_raw}/image_02/0000000000.png    (KITTI depth: uint16 / 256 m)
    velodyne_points/data/0000000000.bin                              (float32 x, y, z, reflectance)
    calib_cam_to_cam.txt, calib_velo_to_cam.txt, calib_imu_to_velo.txt   (here or one folder up)

Frames of the rectified colour camera ``image_02`` use ``P_rect_02``; camera-IMU extrinsics follow
the devkit chain ``T_cam2_imu = T2 R_rect_00 T_cam0_velo T_velo_imu`` with ``T2`` the translation
``P_rect_02[:, 3] / f`` (as pykitti).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from mogs_node.datasets.base import Frame, ImuSamples, Sequence, Trajectory, text_lines
from mogs_node.datasets.oxts import OXTS_FIELDS, oxts_to_poses, read_kitti_timestamps, read_oxts
from mogs_node.errors import DatasetError
from mogs_node.geometry import PinholeCamera, make_T, se3_inverse

__all__ = [
    "image_file_frames",
    "kitti_raw_extrinsics",
    "load_image",
    "project_velodyne",
    "read_calib_file",
    "read_depth_png",
    "read_euroc_imu_csv",
    "read_imu_text",
    "stamp_ns_of",
    "read_kitti_odometry",
    "read_kitti_oxts",
    "read_kitti_raw",
    "read_velodyne_bin",
]

log = logging.getLogger(__name__)

KITTI_FRAME_PERIOD_NS = 100_000_000  # 10 Hz, used when a drive has no timestamps.txt


def read_calib_file(path: str | Path) -> dict[str, np.ndarray | str]:
    """Parse a KITTI ``key: v1 v2 ...`` calibration file; numeric values become float64 arrays.

    Non-numeric values are kept as strings only for the known text keys (``calib_time``).
    """
    p = Path(path)
    out: dict[str, np.ndarray | str] = {}
    for i, line in text_lines(p, "calibration"):
        key, sep, rest = line.partition(":")
        if not sep:
            raise DatasetError(f"{p}:{i}: expected 'key: values', got {line!r}")
        key = key.strip()
        if key == "calib_time":
            out[key] = rest.strip()
            continue
        try:
            out[key] = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError as err:
            raise DatasetError(f"{p}:{i}: non-numeric value for {key!r} ({err})") from err
    return out


def _need(calib: dict, key: str, n: int, path: Path) -> np.ndarray:
    v = calib.get(key)
    if not isinstance(v, np.ndarray) or v.size != n:
        got = "missing" if v is None else f"{getattr(v, 'size', v)} values"
        raise DatasetError(f"{path}: key {key!r} needs {n} numbers ({got})")
    return v


def load_image(path: str | Path, *, grey: bool = False) -> np.ndarray:
    """Read a PNG/JPEG as uint8 RGB ``[H, W, 3]`` (or grey ``[H, W]``); errors name the file."""
    p = Path(path)
    img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"{p}: missing or not a readable image")
    return img if grey else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def image_file_frames(
    files: list[Path],
    stamps_ns: np.ndarray,
    camera: PinholeCamera,
    *,
    grey: bool,
    poses: list[np.ndarray | None] | None = None,
    depth_loader: Callable[[Path], Callable[[], np.ndarray] | None] | None = None,
) -> tuple[Frame, ...]:
    """One lazily loaded :class:`Frame` per image file: ``stamps_ns`` int ``[N]``, ``poses`` N
    ``[4, 4]`` ``T_world_cam`` (or None), ``depth_loader(file)`` a loader of its depth or None."""
    return tuple(
        Frame(
            i,
            int(stamps_ns[i]),
            camera,
            (lambda f=f: load_image(f, grey=grey)),
            "mono8" if grey else "rgb8",
            None if poses is None else poses[i],
            None if depth_loader is None else depth_loader(f),
            str(f),
        )
        for i, f in enumerate(files)
    )


def read_depth_png(path: str | Path) -> np.ndarray:
    """KITTI depth PNG (uint16, metres = value / 256, 0 = none) -> float32 ``[H, W]``."""
    p = Path(path)
    raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError(f"{p}: missing or not a readable PNG")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise DatasetError(
            f"{p}: expected a single-channel uint16 depth PNG, got {raw.dtype} {raw.shape}"
        )
    return raw.astype(np.float32) / 256.0


def read_velodyne_bin(path: str | Path) -> np.ndarray:
    """Velodyne scan ``.bin`` -> float32 ``[N, 4]`` (x, y, z, reflectance) in the LiDAR frame."""
    p = Path(path)
    try:
        raw = np.fromfile(p, dtype=np.float32)
    except OSError as err:
        raise DatasetError(f"{p}: cannot read ({err.strerror or err})") from err
    if raw.size % 4:
        raise DatasetError(f"{p}: size {raw.size * 4} bytes is not a multiple of 16")
    return raw.reshape(-1, 4)


def project_velodyne(
    points_velo: np.ndarray,
    T_cam_velo: np.ndarray,
    camera: PinholeCamera,
    *,
    min_depth_m: float = 0.1,
) -> np.ndarray:
    """Project LiDAR points ``[N, >=3]`` into a sparse depth image f32 ``[H, W]`` (0 = none).

    ``T_cam_velo`` maps LiDAR points into the (rectified) camera frame. Where several points land on
    one pixel the nearest wins (as the KITTI depth benchmark).
    """
    P = np.asarray(points_velo, dtype=np.float64)[:, :3]
    Pc = P @ T_cam_velo[:3, :3].T + T_cam_velo[:3, 3]
    Pc = Pc[Pc[:, 2] > min_depth_m]
    uv, _ = camera.project(Pc)
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    ok = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    u, v, z = u[ok], v[ok], Pc[ok, 2]
    order = np.argsort(-z)  # far first, so near points overwrite them
    depth = np.zeros((camera.height, camera.width), dtype=np.float32)
    depth[v[order], u[order]] = z[order]
    return depth


def _find(name: str, folders: list[Path]) -> Path | None:
    for f in folders:
        if (f / name).exists():
            return f / name
    return None


def kitti_raw_extrinsics(
    cam_to_cam: dict,
    velo_to_cam: dict | None,
    imu_to_velo: dict | None,
    cam: int,
    paths: tuple[Path, ...],
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(P_rect [3, 4], T_cam_velo or None, T_cam_imu or None) for rectified camera ``cam``."""
    P = _need(cam_to_cam, f"P_rect_{cam:02d}", 12, paths[0]).reshape(3, 4)
    R0 = np.eye(4)
    R0[:3, :3] = _need(cam_to_cam, "R_rect_00", 9, paths[0]).reshape(3, 3)
    T2 = np.eye(4)
    T2[0, 3] = P[0, 3] / P[0, 0]
    T2[1, 3] = P[1, 3] / P[1, 1]
    T2[2, 3] = P[2, 3]
    T_cam_velo = T_cam_imu = None
    if velo_to_cam is not None:
        R = _need(velo_to_cam, "R", 9, paths[1]).reshape(3, 3)
        t = _need(velo_to_cam, "T", 3, paths[1])
        T_cam_velo = T2 @ R0 @ make_T(R, t)
        if imu_to_velo is not None:
            Ri = _need(imu_to_velo, "R", 9, paths[2]).reshape(3, 3)
            ti = _need(imu_to_velo, "T", 3, paths[2])
            T_cam_imu = T_cam_velo @ make_T(Ri, ti)
    return P, T_cam_velo, T_cam_imu


def stamp_ns_of(text: str, where: str) -> int:
    """Integer nanoseconds, or decimal seconds (a '.' or an exponent) -> nanoseconds."""
    try:
        if any(ch in text for ch in ".eE"):
            sec, _, frac = f"{float(text):.9f}".partition(".")
            return int(sec) * 1_000_000_000 + (int(frac) if not sec.startswith("-") else -int(frac))
        return int(text)
    except ValueError as err:
        raise DatasetError(f"{where}: bad time stamp {text!r}") from err


def read_imu_text(path: str | Path) -> ImuSamples:
    """``t gx gy gz ax ay az`` per line (comma or space separated, ``t`` in ns or s)."""
    p = Path(path)
    t, vals = [], []
    for i, line in text_lines(p, "IMU log", comments=True):
        parts = line.replace(",", " ").split()
        if len(parts) != 7:
            raise DatasetError(
                f"{p}:{i}: expected 7 values (t gx gy gz ax ay az), got {len(parts)}"
            )
        t.append(stamp_ns_of(parts[0], f"{p}:{i}"))
        try:
            vals.append([float(x) for x in parts[1:]])
        except ValueError as err:
            raise DatasetError(f"{p}:{i}: bad number ({err})") from err
    if not t:
        raise DatasetError(f"{p}: no IMU samples")
    v = np.asarray(vals, dtype=np.float64)
    if not np.isfinite(v).all():
        raise DatasetError(f"{p}: non-finite IMU values")
    order = np.argsort(np.asarray(t, dtype=np.int64), kind="stable")
    return ImuSamples(np.asarray(t, dtype=np.int64)[order], v[order, :3], v[order, 3:])


read_euroc_imu_csv = read_imu_text  # EuRoC's csv is one of the text logs read_imu_text takes


def _ground_truth_depth_files(
    d: Path, camera: str, depth: str, T_cam_velo: np.ndarray | None
) -> tuple[dict[str, Path], str]:
    """The drive's ground-truth depth files by frame stem, and their kind (``depth`` as in
    :func:`read_kitti_raw`; "auto" takes the first kind present)."""
    order = {"auto": ["groundtruth", "velodyne_raw", "velodyne_points"]}.get(depth, [depth])
    if depth not in ("auto", "none", "groundtruth", "velodyne_raw", "velodyne_points"):
        raise DatasetError(f"depth: unknown choice {depth!r}")
    for kind in order if depth != "none" else []:
        folder = (
            d / "velodyne_points" / "data"
            if kind == "velodyne_points"
            else d / "proj_depth" / kind / camera
        )
        ext = "*.bin" if kind == "velodyne_points" else "*.png"
        found = {f.stem: f for f in sorted(folder.glob(ext))}
        if found:
            if kind == "velodyne_points" and T_cam_velo is None:
                raise DatasetError(f"{d}: velodyne_points need calib_velo_to_cam.txt")
            return found, kind
    return {}, "none"


def read_kitti_raw(
    drive_dir: str | Path,
    *,
    camera: str = "image_02",
    calib_dir: str | Path | None = None,
    depth: str = "auto",
) -> Sequence:
    """Read a KITTI raw drive (see the module docstring) into a :class:`Sequence`.

    ``depth``: "auto" (proj_depth/groundtruth, else proj_depth/velodyne_raw, else projected
    velodyne_points), "groundtruth", "velodyne_raw", "velodyne_points" or "none". Without
    ``<camera>/timestamps.txt`` frames are stamped at 10 Hz from 0 (``meta["synthetic_stamps"]``).
    With OXTS, ground-truth poses follow the devkit (first OXTS pose = world origin) and the OXTS
    angular rates / accelerations are the IMU; a ``imu/data.csv`` (EuRoC format) overrides them.
    """
    d = Path(drive_dir)
    img_dir = d / camera / "data"
    files = sorted(img_dir.glob("*.png"))
    if not files:
        raise DatasetError(f"{img_dir}: no PNG images (not a KITTI raw drive folder?)")
    try:
        cam = int(camera[-2:])
    except ValueError as err:
        raise DatasetError(f"camera: expected 'image_0X', got {camera!r}") from err
    folders = [Path(calib_dir)] if calib_dir is not None else []
    folders += [d, d.parent]
    c2c = _find("calib_cam_to_cam.txt", folders)
    if c2c is None:
        raise DatasetError(f"{d / 'calib_cam_to_cam.txt'}: missing (also looked in {d.parent})")
    v2c, i2v = _find("calib_velo_to_cam.txt", folders), _find("calib_imu_to_velo.txt", folders)
    cam_to_cam = read_calib_file(c2c)
    P, T_cam_velo, T_cam_imu = kitti_raw_extrinsics(
        cam_to_cam,
        read_calib_file(v2c) if v2c else None,
        read_calib_file(i2v) if i2v else None,
        cam,
        (c2c, v2c or d, i2v or d),
    )
    size = cam_to_cam.get(f"S_rect_{cam:02d}")
    if isinstance(size, np.ndarray) and size.size == 2:
        W, H = int(size[0]), int(size[1])
    else:
        H, W = load_image(files[0]).shape[:2]
    K_cam = PinholeCamera.from_K(P[:, :3], W, H)
    # time stamps
    ts_path = d / camera / "timestamps.txt"
    meta: dict[str, object] = {"calib": str(c2c), "calibration": str(c2c.parent)}
    if ts_path.exists():
        stamps = read_kitti_timestamps(ts_path)
        if len(stamps) != len(files):
            raise DatasetError(
                f"{ts_path}: {len(stamps)} stamps for {len(files)} images in {img_dir}"
            )
    else:
        log.info("%s: no timestamps.txt, stamping frames at 10 Hz", d / camera)
        stamps = np.arange(len(files), dtype=np.int64) * KITTI_FRAME_PERIOD_NS
        meta["synthetic_stamps"] = True
    depth_files, depth_kind = _ground_truth_depth_files(d, camera, depth, T_cam_velo)
    meta["depth"] = depth_kind
    # OXTS -> ground truth and IMU
    T_imu_cam = se3_inverse(T_cam_imu) if T_cam_imu is not None else None
    imu = gt = None
    frame_poses: list[np.ndarray | None] = [None] * len(files)
    if (d / "oxts" / "timestamps.txt").exists():
        o_stamps, packets = read_oxts(d / "oxts")
        T_world_imu = oxts_to_poses(packets)
        gt = Trajectory(o_stamps, T_world_imu, "imu")
        idx = OXTS_FIELDS.index
        imu = ImuSamples(
            o_stamps,
            packets[:, [idx("wx"), idx("wy"), idx("wz")]],
            packets[:, [idx("ax"), idx("ay"), idx("az")]],
        )
        if T_imu_cam is not None:
            if len(o_stamps) == len(files):  # synced drive: packet i belongs to frame i
                nearest = np.arange(len(files))
            else:
                nearest = np.abs(o_stamps[None, :] - stamps[:, None]).argmin(1)
            frame_poses = [T_world_imu[k] @ T_imu_cam for k in nearest]
    if (d / "imu" / "data.csv").exists():
        imu = read_euroc_imu_csv(d / "imu" / "data.csv")
    poses_txt = d / "poses.txt"
    if (
        poses_txt.exists()
    ):  # camera poses written by mogs_node.datasets.writers (KITTI odometry format)
        cam_poses = _read_pose_lines(poses_txt)
        if len(cam_poses) != len(files):
            raise DatasetError(f"{poses_txt}: {len(cam_poses)} poses for {len(files)} images")
        frame_poses = list(cam_poses)
        meta["poses"] = str(poses_txt)

    def depth_loader(stem: str):
        f = depth_files.get(stem)
        if f is None:
            return None
        if depth_kind == "velodyne_points":
            return lambda: project_velodyne(read_velodyne_bin(f), T_cam_velo, K_cam)
        return lambda: read_depth_png(f)

    grey = cam in (0, 1)  # image_00 / image_01 are the grey cameras
    frames = image_file_frames(
        files,
        stamps,
        K_cam,
        grey=grey,
        poses=frame_poses,
        depth_loader=lambda f: depth_loader(f.stem),
    )
    return Sequence(d.name, frames, imu, T_imu_cam, gt, None, meta)


def _read_pose_lines(path: Path) -> np.ndarray:
    """KITTI odometry poses: one line of 12 numbers (3x4 row-major ``T_world_cam``) per frame."""
    out = []
    for i, line in text_lines(path, "poses"):
        try:
            v = np.array([float(x) for x in line.split()])
        except ValueError as err:
            raise DatasetError(f"{path}:{i}: non-numeric pose ({err})") from err
        if v.size != 12:
            raise DatasetError(f"{path}:{i}: expected 12 numbers, got {v.size}")
        T = np.eye(4)
        T[:3, :] = v.reshape(3, 4)
        out.append(T)
    return np.asarray(out).reshape(-1, 4, 4)


def read_kitti_odometry(
    sequence_dir: str | Path, *, camera: str = "image_2", poses_file: str | Path | None = None
) -> Sequence:
    """KITTI odometry ``sequences/XX``: ``image_2/*.png``, ``calib.txt``, ``times.txt``, poses.

    Poses (camera 0, ``T_world_cam0`` per line) are looked up in ``poses_file``, then
    ``sequences/../poses/XX.txt``, then ``XX/poses.txt``; they are moved to the chosen camera
    with its ``P`` baseline. Missing poses mean no ground truth (test sequences).
    """
    d = Path(sequence_dir)
    files = sorted((d / camera).glob("*.png"))
    if not files:
        raise DatasetError(f"{d / camera}: no PNG images (not a KITTI odometry sequence?)")
    calib_path = d / "calib.txt"
    calib = read_calib_file(calib_path)
    cam = int(camera[-1])
    P = _need(calib, f"P{cam}", 12, calib_path).reshape(3, 4)
    H, W = load_image(files[0], grey=True).shape[:2]
    K_cam = PinholeCamera.from_K(P[:, :3], W, H)
    T_cam_cam0 = np.eye(4)
    T_cam_cam0[0, 3] = P[0, 3] / P[0, 0]
    times = d / "times.txt"
    if times.exists():
        try:
            secs = [float(x) for x in times.read_text().split()]
        except ValueError as err:
            raise DatasetError(f"{times}: non-numeric time ({err})") from err
        stamps = np.round(np.asarray(secs) * 1e9).astype(np.int64)
        if len(stamps) != len(files):
            raise DatasetError(f"{times}: {len(stamps)} times for {len(files)} images")
    else:
        stamps = np.arange(len(files), dtype=np.int64) * KITTI_FRAME_PERIOD_NS
    cands = [Path(poses_file)] if poses_file is not None else []
    cands += [d.parent.parent / "poses" / f"{d.name}.txt", d / "poses.txt"]
    pose_path = next((c for c in cands if c.exists()), None)
    poses: list[np.ndarray | None] = [None] * len(files)
    if pose_path is not None:
        T0 = _read_pose_lines(pose_path)
        if len(T0) != len(files):
            raise DatasetError(f"{pose_path}: {len(T0)} poses for {len(files)} images")
        poses = list(T0 @ se3_inverse(T_cam_cam0))
    elif poses_file is not None:
        raise DatasetError(f"{poses_file}: missing")
    grey = camera in ("image_0", "image_1")
    frames = image_file_frames(files, stamps, K_cam, grey=grey, poses=poses)
    meta = {
        "calib": str(calib_path),
        "calibration": str(calib_path),
        "poses": str(pose_path) if pose_path else None,
    }
    return Sequence(d.name, frames, None, None, None, None, meta)


def read_kitti_oxts(drive_dir: str | Path) -> Sequence:
    """A KITTI drive's OXTS only (no images): ground-truth body trajectory and 10 Hz IMU readings.

    Returns a :class:`Sequence` with no frames; ``T_imu_cam`` (image_02) when the calibration
    files are present beside the ``oxts`` folder or one level up.
    """
    d = Path(drive_dir)
    stamps, packets = read_oxts(d / "oxts" if (d / "oxts").exists() else d)
    idx = OXTS_FIELDS.index
    imu = ImuSamples(
        stamps,
        packets[:, [idx("wx"), idx("wy"), idx("wz")]],
        packets[:, [idx("ax"), idx("ay"), idx("az")]],
    )
    folders = [d, d.parent]
    c2c, v2c, i2v = (
        _find(n, folders)
        for n in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt")
    )
    T_imu_cam = None
    if c2c and v2c and i2v:
        _, _, T_cam_imu = kitti_raw_extrinsics(
            read_calib_file(c2c), read_calib_file(v2c), read_calib_file(i2v), 2, (c2c, v2c, i2v)
        )
        T_imu_cam = se3_inverse(T_cam_imu)
    meta: dict[str, object] = {}
    if (d / "image_02_timestamps.txt").exists():
        meta["image_02_stamps_ns"] = read_kitti_timestamps(d / "image_02_timestamps.txt")
    gt = Trajectory(stamps, oxts_to_poses(packets), "imu")
    return Sequence(d.name, (), imu, T_imu_cam, gt, None, meta)
