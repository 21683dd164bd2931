"""Trajectory files: TUM (``t tx ty tz qx qy qz qw``) and KITTI odometry (12 numbers of the 3x4
``T_world_cam`` per line). Writers and readers round-trip; time stamps are int nanoseconds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import DatasetError
from mogs_node.geometry import check_array, make_T, quat_wxyz_from_rotmat, quat_wxyz_to_rotmat

__all__ = ["read_kitti", "read_tum", "write_kitti", "write_tum"]


def write_tum(path: str | Path, stamps_ns: NDArray, poses_se3: NDArray) -> None:
    """Write ``poses_se3`` [N, 4, 4] at ``stamps_ns`` [N] in TUM format (seconds, 9 decimals)."""
    T = check_array("poses_se3", poses_se3, shape=(None, 4, 4), finite=True)
    t = check_array("stamps_ns", stamps_ns, shape=(len(T),), dtype=np.integer)
    q = quat_wxyz_from_rotmat(T[:, :3, :3])
    lines = [
        f"{int(s) // 1_000_000_000}.{int(s) % 1_000_000_000:09d} "
        + " ".join(f"{v:.9f}" for v in (*p[:3, 3], qq[1], qq[2], qq[3], qq[0]))
        for s, p, qq in zip(t, T, q, strict=True)
    ]
    Path(path).write_text("\n".join(lines) + ("\n" if lines else ""))


def read_tum(path: str | Path) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Read a TUM file -> (stamps_ns [N], poses_se3 [N, 4, 4]). Comment lines start with '#'."""
    stamps, poses = [], []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 8:
            raise DatasetError(f"{path}:{n}: expected 8 columns, got {len(parts)}")
        sec, _, frac = parts[0].partition(".")
        stamps.append(int(sec) * 1_000_000_000 + int((frac + "000000000")[:9]))
        v = np.array([float(x) for x in parts[1:]])
        poses.append(make_T(quat_wxyz_to_rotmat(np.r_[v[6], v[3:6]]), v[:3]))
    return np.array(stamps, np.int64), np.array(poses).reshape(-1, 4, 4)


def write_kitti(path: str | Path, poses_se3: NDArray) -> None:
    """Write ``poses_se3`` [N, 4, 4] as KITTI odometry lines (row-major 3x4)."""
    T = check_array("poses_se3", poses_se3, shape=(None, 4, 4), finite=True)
    lines = [" ".join(f"{v:.9e}" for v in p[:3].ravel()) for p in T]
    Path(path).write_text("\n".join(lines) + ("\n" if lines else ""))


def read_kitti(path: str | Path) -> NDArray[np.float64]:
    """Read KITTI odometry lines -> poses_se3 [N, 4, 4]."""
    out = []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        if not line.strip():
            continue
        v = line.split()
        if len(v) != 12:
            raise DatasetError(f"{path}:{n}: expected 12 numbers, got {len(v)}")
        T = np.eye(4)
        T[:3] = np.array([float(x) for x in v]).reshape(3, 4)
        out.append(T)
    return np.array(out).reshape(-1, 4, 4)
