"""The common interface of every dataset reader: a :class:`Sequence` of lazily loaded frames.

A reader returns a :class:`Sequence`: frames (image loaded on access, stamp, pinhole intrinsics,
optional ground-truth camera pose and depth), optional IMU samples as arrays, optional camera-IMU
extrinsics ``T_imu_cam`` and an optional ground-truth body trajectory. Images are RGB ``uint8
[H, W, 3]`` or grey ``uint8 [H, W]`` (``Frame.encoding`` says which); depth is float32 metres with 0
where there is no value.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mogs_node.errors import DatasetError
from mogs_node.geometry import PinholeCamera

__all__ = ["Frame", "ImuSamples", "Sequence", "Trajectory", "text_lines"]


def text_lines(path: Path, what: str = "", *, comments: bool = False) -> list[tuple[int, str]]:
    """The non-blank lines of a text file with their 1-based numbers (for errors naming
    ``file:line``); with ``comments`` lines starting with ``#`` are skipped too. A file that cannot
    be read raises :class:`DatasetError` naming it and ``what`` it should hold."""
    try:
        lines = path.read_text().splitlines()
    except OSError as err:
        label = f" {what}" if what else ""
        raise DatasetError(f"{path}: cannot read{label} ({err.strerror or err})") from err
    return [
        (i, line)
        for i, line in enumerate(lines, 1)
        if line.strip() and not (comments and line.lstrip().startswith("#"))
    ]


@dataclass(frozen=True)
class Frame:
    """One camera frame; ``image`` and ``depth_m`` are loaded from disk (or a bag) when accessed."""

    index: int
    stamp_ns: int
    camera: PinholeCamera
    load_image: Callable[[], np.ndarray] = field(repr=False)
    encoding: str = "rgb8"  # "rgb8" ([H, W, 3]) or "mono8" ([H, W])
    T_world_cam: np.ndarray | None = None  # [4, 4] f64 ground truth, if the dataset has it
    load_depth: Callable[[], np.ndarray] | None = field(default=None, repr=False)
    source: str = ""  # file (or bag topic) the image comes from, for error messages

    @property
    def image(self) -> np.ndarray:
        """The image, uint8 ``[H, W, 3]`` RGB or ``[H, W]`` grey (loaded now, not cached)."""
        return self.load_image()

    @property
    def has_depth(self) -> bool:
        return self.load_depth is not None

    def depth_m(self) -> np.ndarray | None:
        """Ground-truth depth f32 ``[H, W]`` (0 = no value), or None if the dataset has none."""
        return None if self.load_depth is None else self.load_depth()


@dataclass(frozen=True)
class ImuSamples:
    """IMU readings in the IMU (body) frame: stamps int64 ``[M]``, gyro / accel f64 ``[M, 3]``."""

    stamps_ns: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray

    def __post_init__(self) -> None:
        m = len(self.stamps_ns)
        if self.gyro_rad_s.shape != (m, 3) or self.accel_m_s2.shape != (m, 3):
            raise DatasetError(
                f"imu: stamps {m}, gyro {self.gyro_rad_s.shape}, "
                f"accel {self.accel_m_s2.shape} disagree"
            )

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def between(self, t0_ns: int, t1_ns: int) -> ImuSamples:
        """Samples with ``t0_ns <= stamp <= t1_ns``."""
        m = (self.stamps_ns >= t0_ns) & (self.stamps_ns <= t1_ns)
        return ImuSamples(self.stamps_ns[m], self.gyro_rad_s[m], self.accel_m_s2[m])


@dataclass(frozen=True)
class Trajectory:
    """Ground-truth poses at their own stamps: int64 ``[N]`` and ``T_world_x`` f64 ``[N, 4, 4]``."""

    stamps_ns: np.ndarray
    poses: np.ndarray
    frame: str = "imu"  # which frame the poses place in the world ("imu"/"body" or "cam")

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def path_length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.poses[:, :3, 3], axis=0), axis=1).sum())


@dataclass(frozen=True)
class Sequence:
    """A recorded (or simulated) sequence read from disk."""

    name: str
    frames: tuple[Frame, ...]
    imu: ImuSamples | None = None
    T_imu_cam: np.ndarray | None = None  # [4, 4] camera pose in the IMU/body frame
    ground_truth: Trajectory | None = None  # body (or camera) trajectory, at its own rate
    distortion: dict[str, object] | None = None  # {"model": ..., "coeffs": [...]} of the raw images
    meta: dict[str, object] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> Frame:
        return self.frames[i]

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)

    @property
    def camera(self) -> PinholeCamera:
        if not self.frames:
            raise DatasetError(f"{self.name}: no frames")
        return self.frames[0].camera

    @property
    def stamps_ns(self) -> np.ndarray:
        return np.array([f.stamp_ns for f in self.frames], dtype=np.int64)

    @property
    def T_world_cam(self) -> np.ndarray | None:
        """Ground-truth camera poses ``[F, 4, 4]`` if every frame has one, else None."""
        if not self.frames or any(f.T_world_cam is None for f in self.frames):
            return None
        return np.stack([f.T_world_cam for f in self.frames])
