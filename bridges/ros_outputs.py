"""What a ROS bridge publishes for each bus output: pure state + conversions, no ROS, no bus.

:class:`RosOutputs` turns the pipeline's bus messages into ``(ros topic, ros type, message)``
triples with the conversions of :mod:`bridges.ros_convert` (for ROS 1 or ROS 2), keeping the little
state that needs: the keyframe path, the Gaussian map (from the incremental ``/mapper/gaussians``
updates) and the map cloud's throttle. The ROS 1 bridge (:mod:`bridges.ros1`) moves the triples
onto a ROS graph; a test checks them without one.

| bus | ROS (``prefix`` = ``/mogs``) |
| --- | --- |
| ``/frontend/odometry`` | ``<prefix>/odometry`` (``nav_msgs/Odometry``) and ``/tf`` world -> camera, for estimated frames |
| ``/frontend/keyframe`` | ``<prefix>/path`` (``nav_msgs/Path`` of every keyframe pose so far) |
| ``/frontend/refined_pose`` | a keyframe's pose moved by the window's solve: the path again (:meth:`RosOutputs.flush`, at most every flush) |
| ``/metrizer/depth`` | ``<prefix>/depth`` (32FC1 metres, REP 118) |
| ``/mapper/gaussians`` | the map is updated; at most every ``map_period_s`` ``<prefix>/map_cloud`` (``sensor_msgs/PointCloud2``, Gaussian centres + rgb; :meth:`RosOutputs.flush` sends the last change) |
| ``/mapper/stats`` | ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``, status ``mogs/mapper``) |
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bridges import ros_convert as rc
from bridges.ros_convert import Distro
from mogs_node import msgs
from mogs_node.errors import ConfigError
from mogs_node.report.node import NOT_ESTIMATED
from mogs_node.viz.rerun_log import GaussianCloud

__all__ = [
    "DIAGNOSTICS_TYPE",
    "OUTPUT_TYPES",
    "TF_TOPIC",
    "TF_TYPE",
    "RosOutputParams",
    "RosOutputs",
]

#: output name (after the prefix) -> ROS type
OUTPUT_TYPES = {
    "odometry": "nav_msgs/msg/Odometry",
    "path": "nav_msgs/msg/Path",
    "depth": "sensor_msgs/msg/Image",
    "map_cloud": "sensor_msgs/msg/PointCloud2",
}
TF_TOPIC = "/tf"
TF_TYPE = "tf2_msgs/msg/TFMessage"
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"

Triple = tuple[str, str, Any]


@dataclass(frozen=True)
class RosOutputParams:
    """How the pipeline's outputs appear on a ROS graph."""

    prefix: str = "/mogs"  # ROS names: <prefix>/odometry, /path, /depth, /map_cloud
    diagnostics_topic: str = "/diagnostics"  # map statistics (DiagnosticArray, "mogs/mapper")
    world_frame: str = "world"  # parent frame of poses, the path, the cloud and tf
    camera_frame: str = ""  # frame of the camera: odometry's child, tf's child, depth images
    # ("" = the frame id of the images coming in, see RosOutputs.input_frame)
    map_period_s: float = 2.0  # map cloud at most this often (0 = after every keyframe)
    max_map_points: int = 200_000  # beyond this many Gaussians an even subset is sent

    def __post_init__(self) -> None:
        if not self.prefix.startswith("/") or self.map_period_s < 0 or self.max_map_points < 1:
            raise ConfigError(
                "ros outputs: prefix starts with /, map_period_s >= 0, max_map_points >= 1"
            )

    def topic(self, name: str) -> str:
        return f"{self.prefix.rstrip('/')}/{name}"

    def publisher_types(self) -> dict[str, str]:
        """Every ROS topic the outputs go out on, with its type (the outputs, tf and the map
        statistics): what a bridge advertises."""
        topics = {self.topic(n): t for n, t in OUTPUT_TYPES.items()}
        topics[TF_TOPIC] = TF_TYPE
        topics[self.diagnostics_topic] = DIAGNOSTICS_TYPE
        return topics

    def latched(self, topic: str) -> bool:
        """Whether ``topic`` is latched on ROS 1: RViz started later still sees the map."""
        return topic in (self.topic("path"), self.topic("map_cloud"))


class RosOutputs:
    """Bus message in, ROS messages out (see the module docstring); ``now_s`` is a monotonic time
    the caller passes (the throttle's clock), so this stays pure and testable."""

    def __init__(self, params: RosOutputParams, distro: Distro) -> None:
        self.params = params
        self.distro = distro
        self.path_stamps_ns: list[int] = []
        self.path_T_world_cam: list[np.ndarray] = []
        self._path_index: dict[int, int] = {}  # keyframe id -> position in the path
        self._path_by_stamp: dict[int, int] = {}  # keyframe stamp -> position in the path
        self._path_dirty = False  # a keyframe moved since the path was last sent
        self.path_moves = 0  # keyframe poses moved by the window (refinements applied)
        self.cloud = GaussianCloud()
        self._last_cloud_s: float | None = None
        self._cloud_dirty = False
        self._cloud_stamp_ns = 0
        self.input_frame = ""  # frame id of the camera images coming in (the bridge sets it)
        self.not_estimated = 0  # odometry messages without an estimate, not sent

    def _child(self, frame_id: str) -> str:
        """The camera frame: the parameter, else the input images' frame id, else the message's
        own when it is not the world frame (the frontend labels its poses "world")."""
        p = self.params
        own = frame_id if frame_id != p.world_frame else ""
        return p.camera_frame or self.input_frame or own or "camera"

    def on_odometry(self, msg: msgs.Odometry) -> list[Triple]:
        """Odometry + tf of an estimated frame; none for a frame without an estimate (the
        frontend initialising, reset, a rejected or dropped frame: its pose means nothing)."""
        if msg.status in NOT_ESTIMATED:
            self.not_estimated += 1
            return []
        p, d = self.params, self.distro
        child = self._child(msg.frame_id)
        odo = rc.odometry_to_ros(msg, world_frame=p.world_frame, child_frame=child, distro=d)
        tf = rc.tf_from_pose(
            msg.stamp_ns, msg.T_world_cam, parent=p.world_frame, child=child, distro=d
        )
        return [(p.topic("odometry"), OUTPUT_TYPES["odometry"], odo), (TF_TOPIC, TF_TYPE, tf)]

    def on_keyframe(self, msg: msgs.Keyframe) -> list[Triple]:
        """Adds (or, for a keyframe id seen before, moves) the keyframe's pose; the whole path."""
        i = self._path_index.get(msg.keyframe_id)
        if i is None:
            self._path_index[msg.keyframe_id] = len(self.path_stamps_ns)
            self._path_by_stamp[int(msg.stamp_ns)] = len(self.path_stamps_ns)
            self.path_stamps_ns.append(int(msg.stamp_ns))
            self.path_T_world_cam.append(np.asarray(msg.T_world_cam, np.float64))
        else:
            self.path_T_world_cam[i] = np.asarray(msg.T_world_cam, np.float64)
        return [self.path()]

    def on_keyframe_pose(self, msg: msgs.PoseStamped) -> list[Triple]:
        """A keyframe's pose refined by the frontend's window (matched by stamp; a keyframe not
        on the path, e.g. shed, is ignored): the path is sent again from :meth:`flush`."""
        i = self._path_by_stamp.get(int(msg.stamp_ns))
        if i is not None:
            self.path_T_world_cam[i] = np.asarray(msg.T_world_cam, np.float64)
            self._path_dirty = True
            self.path_moves += 1
        return []

    def path(self) -> Triple:
        """The keyframe path now (``nav_msgs/Path``, every keyframe's latest pose)."""
        self._path_dirty = False
        path = rc.path_to_ros(
            np.asarray(self.path_stamps_ns, np.int64),
            np.asarray(self.path_T_world_cam).reshape(-1, 4, 4),
            world_frame=self.params.world_frame,
            distro=self.distro,
        )
        return (self.params.topic("path"), OUTPUT_TYPES["path"], path)

    def on_depth(self, msg: msgs.DepthMap) -> list[Triple]:
        if msg.kind != "metric":
            return []
        ros = rc.depth_to_ros(msg, distro=self.distro)
        ros.header.frame_id = self._child(msg.frame_id)  # an image is in the camera's frame
        return [(self.params.topic("depth"), OUTPUT_TYPES["depth"], ros)]

    def on_gaussians(self, msg: msgs.GaussianUpdate, now_s: float) -> list[Triple]:
        """Applies the update; the whole map as a cloud when ``map_period_s`` has passed since
        the last one (else later, from :meth:`flush`)."""
        self.cloud.apply(msg)
        self._cloud_dirty = True
        self._cloud_stamp_ns = int(msg.stamp_ns)
        return self.flush(now_s)

    def flush(self, now_s: float) -> list[Triple]:
        """The path if a keyframe moved since it was sent; the map cloud if it changed since the
        last one and ``map_period_s`` has passed (call it now and then: the last change of a run
        is sent too)."""
        p = self.params
        out = [self.path()] if self._path_dirty else []
        due = self._last_cloud_s is None or now_s - self._last_cloud_s >= p.map_period_s
        empty = len(self.cloud.ids) == 0 and self._last_cloud_s is None  # nothing to show yet
        if not (self._cloud_dirty and due) or empty:
            return out
        self._last_cloud_s = now_s
        self._cloud_dirty = False
        return [*out, self.map_cloud(self._cloud_stamp_ns)]

    def on_stats(self, msg: msgs.MapStats) -> list[Triple]:
        ros = rc.mapstats_to_ros(msg, distro=self.distro)
        return [(self.params.diagnostics_topic, DIAGNOSTICS_TYPE, ros)]

    def map_cloud(self, stamp_ns: int) -> Triple:
        """The whole map now: Gaussian centres with their colours (an even subset beyond
        ``max_map_points``)."""
        n = len(self.cloud.ids)
        step = max(1, -(-n // self.params.max_map_points))
        ros = rc.pointcloud_to_ros(
            self.cloud.means[::step],
            self.cloud.colors[::step],
            stamp_ns=stamp_ns,
            frame_id=self.params.world_frame,
            distro=self.distro,
        )
        return (self.params.topic("map_cloud"), OUTPUT_TYPES["map_cloud"], ros)
