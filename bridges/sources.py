"""Open what a player streams: a dataset :class:`~mogs_node.datasets.Sequence` or a bus recording.

``open_sequence(kind, ...)`` with ``kind`` one of :data:`SOURCE_KINDS`:

- ``kitti``: KITTI raw drive folder (``image_02/data``; 10 Hz stamps from 0 without timestamps.txt)
- ``kitti_odometry``: KITTI odometry ``sequences/XX`` folder
- ``euroc``: EuRoC ASL folder (holding ``mav0``)
- ``vi_folder``: a generic visual-inertial folder with a Kalibr ``camchain.yaml`` (TUM-VI, Basalt,
  DM-VIO layouts; :mod:`mogs_node.datasets.vi_folder`)
- ``bag``: rosbag1 file, rosbag2 folder (sqlite3 / MCAP) or bare ``.mcap`` with standard messages
- ``sim``: the synthetic world (:class:`mogs_node.sim.SimConfig`), rendered lazily

A recording written by ``mogs record`` (raw bus frames) is opened with
:func:`bridges.recording.read_recording` instead; :func:`is_recording` tells them apart.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from mogs_node import datasets, msgs
from mogs_node.datasets import BagTopics, Sequence
from mogs_node.datasets.base import Frame, ImuSamples, Trajectory
from mogs_node.errors import ConfigError, DatasetError, GeometryError
from mogs_node.geometry import PinholeCamera, rigid_transform
from mogs_node.params import check_choice, parse_params

__all__ = ["SOURCE_KINDS", "camera_info_of", "open_sequence", "sequence_from_sim"]

log = logging.getLogger(__name__)

SOURCE_KINDS = ("kitti", "kitti_odometry", "euroc", "vi_folder", "bag", "sim")
# the kinds read from a folder by path alone ("bag" takes topics and a camera; "sim" no path)
_FOLDER_READERS = {
    "kitti": datasets.read_kitti_raw,
    "kitti_odometry": datasets.read_kitti_odometry,
    "euroc": datasets.read_euroc,
    "vi_folder": datasets.read_vi_folder,
}
# dataset distortion names -> the frontend's (CameraModel) names
_DISTORTION_NAMES = {
    "none": "none",
    "radial-tangential": "radtan",
    "radtan": "radtan",
    "plumb_bob": "radtan",
    "equidistant": "equidistant",
    "equi": "equidistant",
}


def camera_info_of(
    seq: Sequence,
    *,
    stamp_ns: int = 0,
    frame_id: str = "camera",
    camera_height_m: float | None = None,
) -> msgs.CameraInfo:
    """The calibration of ``seq``'s published images as a :class:`~mogs_node.msgs.CameraInfo`.

    Intrinsics and size of the first frame; the distortion left in the images (none when the
    reader undistorts them, ``meta["undistorted"]``); ``T_imu_cam`` and the IMU noise densities
    (``meta["imu_noise"]``) when the source has them; ``camera_height_m`` (None: the source's
    ``meta["camera_height_m"]``, else unknown).
    """
    cam = seq.camera
    model, coeffs = "none", ()
    if seq.distortion is not None and not seq.meta.get("undistorted", False):
        raw = [float(c) for c in seq.distortion.get("coeffs", ()) or ()]  # type: ignore[union-attr]
        name = str(seq.distortion.get("model", "none"))
        if any(raw):
            if name not in _DISTORTION_NAMES:
                raise DatasetError(f"{seq.name}: distortion model {name!r} is not supported")
            model, coeffs = _DISTORTION_NAMES[name], tuple(raw)
    if camera_height_m is None:
        h = seq.meta.get("camera_height_m")
        camera_height_m = float(h) if isinstance(h, int | float) else float("nan")
    noise = seq.meta.get("imu_noise")
    T_imu_cam = None
    if seq.T_imu_cam is not None:  # calibration files print few digits: the nearest rotation
        try:
            T_imu_cam = rigid_transform(seq.T_imu_cam, f"{seq.name}: T_imu_cam")[0]
        except GeometryError as err:
            raise DatasetError(str(err)) from err
    info = msgs.CameraInfo(
        stamp_ns=int(stamp_ns),
        frame_id=frame_id,
        width=int(cam.width),
        height=int(cam.height),
        K=np.asarray(cam.K, dtype=np.float64),
        distortion_model=model,
        distortion_coeffs=np.asarray(coeffs, dtype=np.float64),
        T_imu_cam=T_imu_cam,
        camera_height_m=float(camera_height_m),
        imu_noise=dict(noise) if isinstance(noise, dict) else {},
        source=str(seq.meta.get("calibration", seq.name)),
    )
    info.validate()
    return info


def sequence_from_sim(seq: object) -> Sequence:
    """A :class:`mogs_node.sim.SimSequence` as a dataset Sequence (frames rendered on access).

    Images are RGB, depth is the ground-truth z-depth (0 where the ray hits nothing), poses
    ``T_world_cam``; the IMU is the simulated noisy one; the ground truth is the body trajectory.
    """
    from mogs_node.sim import SimSequence

    if not isinstance(seq, SimSequence):
        raise ConfigError(f"seq: expected a SimSequence, got {type(seq).__name__}")

    # a frame's image and its ground-truth depth come from one ray cast (the player loads both,
    # one after the other): the last rendered frame is kept, which halves the player's CPU
    last: dict[int, object] = {}
    lock = threading.Lock()

    def rendered(i: int):
        with lock:
            f = last.get(i)
            if f is None:
                last.clear()
                f = last[i] = seq.render(i)
            return f

    def image(i: int):
        return lambda: rendered(i).rgb

    def depth(i: int):
        def load() -> np.ndarray:
            d = rendered(i).depth_m
            return np.where(np.isfinite(d), d, 0.0).astype(np.float32)

        return load

    frames = tuple(
        Frame(
            i,
            int(seq.stamps_ns[i]),
            seq.camera,
            image(i),
            "rgb8",
            seq.T_world_cam[i],
            depth(i),
            f"sim:{i}",
        )
        for i in range(len(seq))
    )
    imu = ImuSamples(seq.imu_stamps_ns, seq.imu_gyro_rad_s, seq.imu_accel_m_s2)
    gt = Trajectory(seq.stamps_ns, seq.T_world_imu, "imu")
    return Sequence(
        f"sim_seed{seq.config.seed}", frames, imu, seq.T_imu_cam, gt, None, {"sim": True}
    )


def open_sequence(
    kind: str,
    path: str = "",
    *,
    bag_topics: BagTopics | None = None,
    intrinsics: tuple[float, ...] = (),
    sim: dict[str, object] | None = None,
) -> Sequence:
    """Open a sequence of ``kind`` (see the module docstring); errors name the path or option.

    ``intrinsics`` ``(fx, fy, cx, cy, width, height)``: the camera of a bag without CameraInfo.
    ``sim``: :class:`mogs_node.sim.SimConfig` fields for ``kind == "sim"``.
    """
    check_choice("source", kind, SOURCE_KINDS)
    if kind == "sim":
        from mogs_node.sim import SimConfig, make_sequence

        cfg = parse_params(SimConfig, sim or {}, where="sim")
        return sequence_from_sim(make_sequence(cfg))
    if not path:
        raise ConfigError(f"path: a {kind} source needs a path")
    p = Path(path).expanduser()
    if not p.exists():
        raise DatasetError(f"{p}: no such file or folder")
    if kind in _FOLDER_READERS:
        return _FOLDER_READERS[kind](p)
    camera = None
    if intrinsics:
        if len(intrinsics) != 6:
            raise ConfigError(
                f"intrinsics: expected (fx, fy, cx, cy, width, height), got {intrinsics}"
            )
        fx, fy, cx, cy, w, h = intrinsics
        camera = PinholeCamera(float(fx), float(fy), float(cx), float(cy), int(w), int(h))
    return datasets.read_bag(p, topics=bag_topics, camera=camera)
