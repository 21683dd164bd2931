"""The player node's parameters and the image encodings it converts between
(:mod:`bridges.player`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from bridges.sources import SOURCE_KINDS
from mogs_node.datasets import BagTopics
from mogs_node.errors import ConfigError
from mogs_node.params import check_choice

__all__ = ["ENCODINGS", "PLAYER_SOURCES", "PlayerParams", "convert_encoding"]

PLAYER_SOURCES = (*SOURCE_KINDS, "recording")
ENCODINGS = ("", "mono8", "rgb8", "bgr8")


@dataclass(frozen=True)
class PlayerParams:
    """Parameters of the player node."""

    source: str = "sim"  # kitti | kitti_odometry | euroc | vi_folder | bag | sim | recording
    path: str = ""  # dataset folder, bag or recording (unused for sim)
    rate: float = 1.0  # replay speed: 1 = recorded rate, N = N times faster, 0 = no clock
    fast: bool = False  # as fast as the pipeline accepts (flow control below); ignores rate
    start_s: float = 0.0  # first frame played: this many seconds after the first frame
    end_s: float | None = None  # last frame played: this many seconds after the first (None: all)
    imu_lead_s: float = 1.2  # IMU samples this long before the first played frame are played
    # (where the source has them): a start at rest initialises statically from them (issue 23:
    # the static init inspects the 1 s before a frame, so a little more than 1 s)
    camera_info_topic: str = "/camera/info"  # the source's calibration (msgs.CameraInfo)
    camera_info_period_s: float = 2.0  # ... published before the first image and this often
    poses: str = ""  # your camera poses T_world_cam (TUM or KITTI file): published on
    # pose_topic before each image; the frontend maps with them (mode poses) instead of estimating
    pose_topic: str = "/camera/pose"
    camera_height_m: float | None = None  # camera above the road (a car's calibration; None:
    # the source's own value if it has one, else unknown), published in the CameraInfo
    image_topic: str = "/camera/image"  # output images (best effort)
    imu_topic: str = "/imu"  # output IMU samples (reliable)
    groundtruth: bool = True  # publish ground-truth camera poses when the dataset has them
    groundtruth_depth: bool = False  # also publish ground-truth depth maps (large)
    gt_pose_topic: str = "/groundtruth/pose"  # output ground-truth poses
    gt_depth_topic: str = "/groundtruth/depth"  # output ground-truth depth
    encoding: str = ""  # "" keeps the dataset's encoding; mono8 | rgb8 | bgr8 converts
    camera_frame_id: str = "camera"  # frame_id of images and ground truth
    imu_frame_id: str = "imu"  # frame_id of IMU samples
    bag_image_topic: str = "/camera/image_raw"  # bag: sensor_msgs Image or CompressedImage
    bag_imu_topic: str = "/imu"  # bag: sensor_msgs/Imu ("" = none)
    bag_camera_info_topic: str = "/camera/camera_info"  # bag: CameraInfo ("" = none)
    bag_pose_topic: str = "/ground_truth/pose"  # bag: geometry_msgs/PoseStamped ("" = none)
    bag_depth_topic: str = "/ground_truth/depth"  # bag: 32FC1 / 16UC1 depth ("" = none)
    bag_tf_static_topic: str = "/tf_static"  # bag: T_imu_cam between the IMU and image frames
    intrinsics: tuple[float, ...] = ()  # bag without CameraInfo: (fx, fy, cx, cy, width, height)
    sim: dict[str, Any] = field(default_factory=dict)  # source sim: SimConfig fields
    ack_topic: str = "/frontend/odometry"  # fast: a message here acknowledges images <= its stamp
    max_frames_in_flight: int = 1  # fast: images published and not yet acknowledged (>= 1);
    # > 1 only for a consumer that queues images (the frontend keeps only the latest one)
    keyframe_topic: str = "/frontend/keyframe"  # fast: keyframes produced (watched if below > 0)
    keyframe_done_topic: str = "/metrizer/depth"  # fast: a keyframe is done when this arrives
    max_keyframes_in_flight: int = 0  # keyframes waiting for keyframe_done (0 = unwatched)
    ack_timeout_s: float = 30.0  # fast: give up waiting after this long (counted; 0 = never)
    wait_for_subscriber_s: float = 10.0  # before streaming, wait for a subscriber of image_topic
    wait_for_nodes: tuple[str, ...] = ()  # before streaming, wait for a heartbeat of these nodes
    wait_for_nodes_s: float = 60.0  # ... at most this long (their subscriptions exist by then)
    prefetch: int = 4  # images loaded ahead in a worker thread
    progress_period_s: float = 2.0  # seconds between progress lines (0 = none)
    tick_s: float = 0.002  # scheduling period of the player loop
    linger_s: float = 0.5  # after the last message: keep running this long
    exit_when_done: bool = True  # stop the node (exit code 0) once everything is played

    def __post_init__(self) -> None:
        check_choice("player.source", self.source, PLAYER_SOURCES)
        check_choice("player.encoding", self.encoding, ENCODINGS)
        if not (self.rate >= 0 and np.isfinite(self.rate)):
            raise ConfigError(f"player.rate: expected a finite number >= 0, got {self.rate}")
        if self.max_frames_in_flight < 1 or self.max_keyframes_in_flight < 0:
            raise ConfigError(
                "player.max_frames_in_flight: >= 1 and max_keyframes_in_flight: >= 0, got "
                f"{self.max_frames_in_flight}, {self.max_keyframes_in_flight}"
            )
        if self.tick_s <= 0 or self.prefetch < 0 or self.linger_s < 0 or self.ack_timeout_s < 0:
            raise ConfigError(
                "player: tick_s > 0, prefetch >= 0, linger_s >= 0, ack_timeout_s >= 0"
            )
        if self.camera_info_period_s <= 0 or self.imu_lead_s < 0:
            raise ConfigError(
                "player.camera_info_period_s: > 0 and imu_lead_s: >= 0, got "
                f"{self.camera_info_period_s}, {self.imu_lead_s}"
            )
        if self.camera_height_m is not None and not (
            np.isfinite(self.camera_height_m) and self.camera_height_m >= 0
        ):
            raise ConfigError(
                f"player.camera_height_m: a finite height >= 0, got {self.camera_height_m}"
            )
        if self.start_s < 0 or (self.end_s is not None and self.end_s < self.start_s):
            raise ConfigError(
                f"player.start_s/end_s: need 0 <= start_s <= end_s, got {self.start_s}, {self.end_s}"
            )

    def bag_topics(self) -> BagTopics:
        return BagTopics(
            image=self.bag_image_topic,
            camera_info=self.bag_camera_info_topic or None,
            imu=self.bag_imu_topic or None,
            pose=self.bag_pose_topic or None,
            depth=self.bag_depth_topic or None,
            tf_static=self.bag_tf_static_topic or None,
        )


def convert_encoding(image: np.ndarray, encoding: str, target: str) -> tuple[np.ndarray, str]:
    """uint8 image ``[H, W]`` (mono8) or ``[H, W, 3]`` (rgb8 / bgr8) -> ``target`` encoding
    (``""`` keeps it)."""
    if not target or target == encoding:
        return image, encoding
    if encoding == "mono8":
        rgb = np.repeat(image[..., None], 3, axis=2)
    elif encoding == "bgr8":
        rgb = np.ascontiguousarray(image[..., ::-1])
    elif encoding == "rgb8":
        rgb = image
    else:
        raise ConfigError(f"encoding: cannot convert from {encoding!r}")
    if target == "mono8":
        return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), "mono8"
    if target == "bgr8":
        return np.ascontiguousarray(rgb[..., ::-1]), "bgr8"
    return rgb, "rgb8"
