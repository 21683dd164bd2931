"""Messages -> rerun archetypes, logged to a given recording stream (no bus, no files).

Each ``log_*`` function takes the ``rerun`` module (imported by the caller, so that this module
imports without the optional dependency), a ``RecordingStream`` and one message, sets the
``stamp`` timeline to the message's ``stamp_ns`` and logs under :data:`mogs_node.viz.ENTITY_PATHS`.
Works with rerun-sdk 0.18 and later (``set_time`` / ``Scalars`` where they exist, their older
names otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

import numpy as np

from mogs_node import msgs
from mogs_node.errors import MogsError
from mogs_node.viz import ENTITY_PATHS as P

__all__ = [
    "GaussianCloud",
    "Trajectory",
    "log_depth",
    "log_gaussians",
    "log_image",
    "log_keyframe",
    "log_masks",
    "log_odometry",
    "log_render",
    "log_stats",
]


class VizError(MogsError):
    """A message that cannot be visualised (e.g. an image encoding rerun does not take)."""


def set_stamp(rr: ModuleType, rec: Any, stamp_ns: int) -> None:
    """Put the following log calls at ``stamp_ns`` on the ``stamp`` timeline."""
    if hasattr(rr, "set_time"):
        rr.set_time("stamp", timestamp=np.datetime64(int(stamp_ns), "ns"), recording=rec)
    else:  # rerun < 0.23
        rr.set_time_nanos("stamp", int(stamp_ns), recording=rec)


def _rgb(image: np.ndarray, encoding: str) -> np.ndarray:
    """``[H, W]`` mono8 or ``[H, W, 3]`` rgb8/bgr8 uint8 -> what rerun shows as the camera saw it."""
    if encoding == "bgr8":
        return np.ascontiguousarray(image[..., ::-1])
    if encoding in ("rgb8", "mono8"):
        return image
    raise VizError(f"image encoding {encoding!r} is not viewable")


def _transform(rr: ModuleType, T_world_cam: np.ndarray) -> Any:
    T = np.asarray(T_world_cam, dtype=np.float64)
    return rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])


def _pinhole(rr: ModuleType, K: np.ndarray, width: int, height: int) -> Any:
    return rr.Pinhole(image_from_camera=np.asarray(K, dtype=np.float64), resolution=[width, height])


def log_image(rr: ModuleType, rec: Any, msg: msgs.Image) -> None:
    """A camera image under ``world/camera/image``."""
    set_stamp(rr, rec, msg.stamp_ns)
    rr.log(P["camera_image"], rr.Image(_rgb(msg.data, msg.encoding)), recording=rec)


@dataclass
class Trajectory:
    """Camera positions so far (odometry), logged as one line strip."""

    max_points: int = 100_000  # beyond this, older positions are thinned out (memory bound)
    positions_m: list[np.ndarray] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.max_points < 2:
            raise VizError(f"Trajectory.max_points: need >= 2, got {self.max_points}")

    def add(self, T_world_cam: np.ndarray) -> np.ndarray:
        """Append the position of ``T_world_cam`` [4, 4]; all positions kept, ``[N, 3]``.

        Past ``max_points`` the newest ``max_points // 2`` stay as they are and the older ones
        are subsampled evenly (the first one kept) into the rest of the room.
        """
        self.positions_m.append(np.asarray(T_world_cam, dtype=np.float64)[:3, 3].copy())
        n = len(self.positions_m)
        if n > self.max_points:
            n_new = self.max_points // 2
            older, newer = self.positions_m[: n - n_new], self.positions_m[n - n_new :]
            room = self.max_points - n_new
            self.positions_m = older[:: -(-len(older) // room)] + newer
        return np.stack(self.positions_m)


def log_odometry(
    rr: ModuleType,
    rec: Any,
    msg: msgs.Odometry,
    traj: Trajectory,
    K: np.ndarray | None = None,
    size: tuple[int, int] | None = None,
) -> None:
    """The camera pose under ``world/camera`` and the trajectory line under ``world/trajectory``.

    ``K`` [3, 3] / ``size`` (width, height) give the live camera's pinhole once known.
    """
    set_stamp(rr, rec, msg.stamp_ns)
    rr.log(P["camera"], _transform(rr, msg.T_world_cam), recording=rec)
    if K is not None and size is not None:
        rr.log(P["camera_image"], _pinhole(rr, K, *size), recording=rec)
    rr.log(P["trajectory"], rr.LineStrips3D([traj.add(msg.T_world_cam)]), recording=rec)


def sparse_points_world(msg: msgs.Keyframe) -> np.ndarray:
    """The keyframe's metric feature points in the world frame, ``[N, 3]`` float32."""
    T = np.asarray(msg.T_world_cam, dtype=np.float64)
    xyz = np.asarray(msg.feature_xyz_cam_m, dtype=np.float64)
    return (xyz @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def log_keyframe(rr: ModuleType, rec: Any, msg: msgs.Keyframe) -> None:
    """Keyframe pose under ``world/keyframe``, pinhole and image under ``world/keyframe/image``;
    its features, in the world frame,
    under ``world/sparse_points`` (radius from the feature weight)."""
    set_stamp(rr, rec, msg.stamp_ns)
    h, w = msg.image.shape[:2]
    rr.log(P["keyframe"], _transform(rr, msg.T_world_cam), recording=rec)
    rr.log(P["keyframe_image"], _pinhole(rr, msg.K, w, h), recording=rec)
    rr.log(P["keyframe_image"], rr.Image(msg.image), recording=rec)
    rr.log(P["sparse_points"], rr.Points3D(sparse_points_world(msg), radii=0.05), recording=rec)


def log_masks(rr: ModuleType, rec: Any, msg: msgs.Masks) -> None:
    """Instance labels as a segmentation image (label + 1; 0 = no mask)."""
    set_stamp(rr, rec, msg.stamp_ns)
    labels = np.asarray(msg.labels)
    if labels.size and labels.max() >= np.iinfo(np.uint16).max:
        raise VizError(f"/seg/masks: label {labels.max()} does not fit a segmentation image")
    rr.log(P["masks"], rr.SegmentationImage((labels + 1).astype(np.uint16)), recording=rec)


def log_depth(rr: ModuleType, rec: Any, msg: msgs.DepthMap, *, prior: bool = False) -> None:
    """A depth map (0 = none) under the keyframe's pinhole: ``depth`` (metrizer, metric) or
    ``prior_depth`` (the prior, relative unless its kind is metric)."""
    set_stamp(rr, rec, msg.stamp_ns)
    path = P["prior_depth"] if prior else P["depth"]
    meter = 1.0 if msg.kind == "metric" else None
    rr.log(path, rr.DepthImage(np.asarray(msg.depth, dtype=np.float32), meter=meter), recording=rec)


@dataclass
class GaussianCloud:
    """The map's Gaussian centres and colours, kept up to date from incremental updates."""

    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [N]
    means: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))  # [N, 3]
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))  # [N, 3]

    def apply(self, msg: msgs.GaussianUpdate) -> None:
        """Remove ``removed_ids``, then add or replace (by id) the updated Gaussians."""
        drop = np.isin(self.ids, msg.removed_ids) | np.isin(self.ids, msg.ids)
        keep = ~drop
        self.ids = np.concatenate([self.ids[keep], msg.ids])
        self.means = np.concatenate([self.means[keep], np.asarray(msg.means, np.float32)])
        self.colors = np.concatenate([self.colors[keep], np.asarray(msg.colors_rgb, np.float32)])


def log_gaussians(
    rr: ModuleType,
    rec: Any,
    msg: msgs.GaussianUpdate,
    cloud: GaussianCloud,
    max_points: int = 2_000_000,
) -> None:
    """Apply the update to ``cloud`` and log every centre with its colour (``world/gaussians``).

    Beyond ``max_points`` centres an even subset is logged (the viewer's memory, not the map's).
    """
    cloud.apply(msg)
    set_stamp(rr, rec, msg.stamp_ns)
    step = max(1, -(-len(cloud.ids) // max_points))
    colors = (np.clip(cloud.colors[::step], 0.0, 1.0) * 255).astype(np.uint8)
    rr.log(
        P["gaussians"], rr.Points3D(cloud.means[::step], colors=colors, radii=0.02), recording=rec
    )


def log_render(rr: ModuleType, rec: Any, msg: msgs.Render) -> None:
    set_stamp(rr, rec, msg.stamp_ns)
    rr.log(P["render"], rr.Image(msg.image), recording=rec)


def log_stats(rr: ModuleType, rec: Any, msg: msgs.MapStats) -> None:
    """Gaussians, keyframes, loss and PSNR as scalars under ``mapper/stats/<name>``."""
    set_stamp(rr, rec, msg.stamp_ns)
    scalars = getattr(rr, "Scalars", None) or rr.Scalar
    for name in ("n_gaussians", "n_keyframes", "loss", "psnr_db"):
        v = float(getattr(msg, name))
        if np.isfinite(v):
            rr.log(f"{P['stats']}/{name}", scalars(v), recording=rec)
