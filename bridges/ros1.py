"""ROS 1 bridge node ``ros1``: a camera, an IMU and a CameraInfo from a ROS 1 graph onto the bus, and
the pipeline's odometry, path, map cloud, depth, map statistics and tf back onto the graph.

Messages cross as bytes: rospy subscriptions of ``rospy.AnyMsg`` deliver the serialized message,
which the (tested, ROS-free) conversions of :mod:`bridges.ros_convert` decode with the rosbags
ROS 1 typestore; outputs are serialized the same way and sent through publishers of a raw message
class carrying the type's md5sum and definition (:func:`raw_message_class`), so rospy never builds a
message object. rospy comes from Debian's ROS 1 packages (:func:`require_rospy`).

Live behaviour:

- a ROS callback never blocks on the pipeline: it appends the bytes to a queue and wakes the bus
  loop through a pipe. Images wait in a queue of ``image_queue`` (older ones are dropped and
  counted: ``frames_dropped``); IMU samples are never dropped. On the bus the frontend keeps only
  its latest image (the live policy: best-effort, latest wins, its drops counted in its own
  diagnostics).
- ``/use_sim_time`` and ``/clock`` (``rosbag play --clock``) are followed by rospy; every output
  carries the stamp of the data it comes from (odometry: its image's; path, cloud, depth and map
  statistics: their keyframe's), so under a bag's clock all of them are on the bag's time.
- the run ends cleanly when no image came for ``end_after_quiet_s`` seconds (wall time: a bag's
  ``/clock`` stops with the bag) or on Ctrl-C; the node's final diagnostics ("stopped") tell the
  report node that the input ended, the mapper writes ``map.ply``.
- a roscore that goes away is logged once (and its return once), not in a loop.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bridges import ros_convert as rc
from bridges.ros_convert import Distro
from bridges.ros_inputs import RosInputParams, RosInputs, calibration_line
from bridges.ros_outputs import RosOutputParams, RosOutputs
from bridges.ros_shell import RosBridgeShell
from mogs_node import msgs
from mogs_node.errors import ConfigError, MessageError, Ros1UnavailableError
from mogs_node.node import Node
from mogs_node.params import group_of

__all__ = [
    "APT_INSTALL",
    "Ros1Bridge",
    "Ros1BridgeParams",
    "raw_message_class",
    "require_rospy",
]

log = logging.getLogger(__name__)

#: what installs ROS 1 on Debian 12 (bookworm), as root
APT_INSTALL = (
    "apt-get install -y ros-core python3-rospy python3-rosbag python3-sensor-msgs "
    "python3-nav-msgs python3-tf2-msgs python3-diagnostic-msgs"
)
DEBIAN_DIST_PACKAGES = Path("/usr/lib/python3/dist-packages")


def require_rospy() -> Any:
    """Import rospy, from Debian's packages when the virtual environment lacks it, or raise
    :class:`Ros1UnavailableError` naming the ``apt-get`` line.

    Debian's ``/usr/lib/python3/dist-packages`` is appended to ``sys.path`` (after the virtual
    environment's own packages, which keep precedence) when this Python's minor version is the
    system's (``/usr/lib/python3.<minor>`` exists): rospy, genpy and the message packages are
    pure Python."""
    try:
        import rospy

        return rospy
    except ImportError as first:
        err: ImportError = first
    minor = f"python3.{sys.version_info.minor}"
    if (DEBIAN_DIST_PACKAGES / "rospy").is_dir() and Path("/usr/lib", minor).is_dir():
        if str(DEBIAN_DIST_PACKAGES) not in sys.path:
            sys.path.append(str(DEBIAN_DIST_PACKAGES))
        try:
            import rospy

            return rospy
        except ImportError as again:
            err = again
    raise Ros1UnavailableError(
        "rospy is not importable: the ROS 1 bridge needs Debian's ROS 1 packages (as root: "
        f"`apt-get update && {APT_INSTALL}`) and a virtual environment of the system's Python "
        f"minor version ({minor} here; Debian 12 has python3.11). ({err})"
    ) from err


def raw_message_class(rospy: Any, rtype: str) -> type:
    """A rospy message class for ROS 1 type ``rtype`` whose instances carry serialized bytes
    (``msg._buff``): a publisher of it announces the real type, md5sum and definition."""
    text, md5 = rc.msgdef_md5(rtype)
    name = rc.rostype(rtype).replace("/msg/", "/")
    return type(
        "Raw" + name.rsplit("/", 1)[1],
        (rospy.AnyMsg,),
        {"_type": name, "_md5sum": md5, "_full_text": text, "_has_header": False, "__slots__": ()},
    )


def _init_node_keeping_logging(rospy: Any, name: str) -> None:
    """``rospy.init_node`` without its signal handlers (the node shell owns SIGINT) and without
    letting it replace the process's logging set-up (rospy loads its own logging config file,
    which swaps the root logger's handlers for a file under ``$ROS_HOME/log``)."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    rospy.init_node(name, disable_signals=True)
    root.handlers[:] = handlers
    root.setLevel(level)
    for chatty in ("rospy", "rosout"):  # a line per connection made or lost
        logging.getLogger(chatty).setLevel(logging.WARNING)


@dataclass(frozen=True)
class Ros1BridgeParams:
    """Parameters of the ROS 1 bridge node."""

    image_topic: str = "/camera/image_raw"  # sensor_msgs/Image (mono8/rgb8/bgr8) or CompressedImage
    imu_topic: str = "/imu"  # sensor_msgs/Imu
    camera_info_topic: str = "/camera/camera_info"  # sensor_msgs/CameraInfo ("" = none)
    tf_static_topic: str = "/tf_static"  # T_imu_cam between the IMU's and the camera's frames
    T_imu_cam: tuple[float, ...] | None = None  # without /tf_static: the camera in the IMU frame
    # (16 numbers, row-major; None: the frontend's own launch value)
    tf_wait_s: float = 1.0  # after the first CameraInfo, wait this long for /tf_static
    camera_info_period_s: float = 2.0  # the calibration on the bus again this often
    bus_camera_info_topic: str = "/camera/info"
    ros_node_name: str = "mogs"  # name of the rospy node
    master_uri: str = ""  # the roscore ("" = $ROS_MASTER_URI)
    prefix: str = "/mogs"  # ROS names of the outputs: <prefix>/odometry, /path, /map_cloud, ...
    world_frame: str = "world"  # parent frame of poses, path, map cloud and tf
    camera_frame: str = ""  # odometry's and tf's child, depth's frame ("" = the images' frame id)
    map_period_s: float = 2.0  # map cloud at most this often (0: after every mapped keyframe)
    max_map_points: int = 200_000  # beyond this many Gaussians the cloud is an even subset
    image_queue: int = 2  # images waiting for the bus loop; older ones are dropped, counted
    end_after_quiet_s: float = 5.0  # no image for this long after the first: end (0 = never)
    master_check_s: float = 2.0  # how often the roscore is looked for
    wait_for_nodes: tuple[str, ...] = ()  # subscribe to the camera once these nodes beat
    wait_for_nodes_s: float = 120.0  # ... or after this long (then with a warning)
    bus_image_topic: str = "/camera/image"
    bus_imu_topic: str = "/imu"

    def __post_init__(self) -> None:
        if self.image_queue < 1 or self.end_after_quiet_s < 0 or self.master_check_s <= 0:
            raise ConfigError("ros1: image_queue >= 1, end_after_quiet_s >= 0, master_check_s > 0")
        if not self.image_topic or not self.imu_topic:
            raise ConfigError("ros1: image_topic and imu_topic are required")
        self.inputs()  # checks T_imu_cam, tf_wait_s

    def inputs(self) -> RosInputParams:
        return group_of(RosInputParams, self, source="ros1")

    def outputs(self) -> RosOutputParams:
        return group_of(RosOutputParams, self)


class _Inbox:
    """What the ROS callbacks hand to the bus loop (thread-safe; callbacks never block)."""

    def __init__(self, image_queue: int) -> None:
        self.lock = threading.Lock()
        self.images: deque[tuple[str, bytes]] = deque()
        self.image_queue = image_queue
        self.imu: deque[bytes] = deque()
        self.camera_info: bytes | None = None
        self.tf_static: list[bytes] = []
        self.frames_in = 0
        self.frames_dropped = 0
        self.imu_in = 0
        self.last_image_s: float | None = None
        self.wake_r, self.wake_w = os.pipe()
        os.set_blocking(self.wake_r, False)
        os.set_blocking(self.wake_w, False)

    def wake(self) -> None:
        with contextlib.suppress(BlockingIOError):  # many wake-ups pending already
            os.write(self.wake_w, b"\0")

    def put_image(self, rtype: str, raw: bytes) -> None:
        with self.lock:
            self.frames_in += 1
            self.last_image_s = time.monotonic()
            if len(self.images) >= self.image_queue:
                self.images.popleft()
                self.frames_dropped += 1
            self.images.append((rtype, raw))
        self.wake()

    def put_imu(self, raw: bytes) -> None:
        with self.lock:
            self.imu_in += 1
            self.imu.append(raw)
        self.wake()

    def put_tf_static(self, raw: bytes) -> None:
        with self.lock:
            self.tf_static.append(raw)
        self.wake()

    def take(self) -> tuple[list[bytes], list[tuple[str, bytes]], bytes | None, list[bytes]]:
        with contextlib.suppress(BlockingIOError):
            while os.read(self.wake_r, 4096):
                pass
        with self.lock:
            imu, images, info = list(self.imu), list(self.images), self.camera_info
            tf = list(self.tf_static)
            self.imu.clear()
            self.images.clear()
            self.tf_static.clear()
            self.camera_info = None
        return imu, images, info, tf

    def close(self) -> None:
        os.close(self.wake_r)
        os.close(self.wake_w)


class Ros1Bridge(RosBridgeShell, Node):
    """The ``ros1`` node: see the module docstring."""

    Params = Ros1BridgeParams

    @property
    def bus_camera_info_topic(self) -> str:
        return self.params.bus_camera_info_topic

    def setup(self) -> None:
        p: Ros1BridgeParams = self.params
        rospy = require_rospy()
        if p.master_uri:
            os.environ["ROS_MASTER_URI"] = p.master_uri
        self._rospy = rospy
        self.inbox = _Inbox(p.image_queue)
        self.outputs = RosOutputs(p.outputs(), Distro.ROS1)
        self.inputs = RosInputs(p.inputs(), Distro.ROS1)
        for k in ("frames_in", "frames_published", "frames_dropped", "imu_in", "imu_published"):
            self.counters[k] = 0
        self.counters.update(ros_malformed=0, ros_published=0, master_lost=0)
        _init_node_keeping_logging(rospy, p.ros_node_name)
        out = p.outputs()
        self._pubs: dict[str, Any] = {}
        for topic, rtype in out.publisher_types().items():
            self._pubs[topic] = self._publisher(topic, rtype, out.latched(topic))
        self._subscribe_outputs()
        self.add_reader(self.inbox.wake_r, self.drain)
        self.every(max(0.1, min(1.0, p.map_period_s)), self.flush_map)  # the map's last change
        self._inputs_started = False
        self._waiting = set(p.wait_for_nodes)
        if self._waiting:  # the pipeline first: a frame before the frontend is up is lost
            self._wait_deadline = time.monotonic() + p.wait_for_nodes_s
            self.subscribe("/diagnostics", self._on_heartbeat, reliable=False, queue_size=256)
            self.every(1.0, self._check_wait)
        else:
            self._start_inputs()
        if p.end_after_quiet_s > 0:
            self.every(min(0.5, p.end_after_quiet_s), self.check_quiet)
        self.every(0.2, self._calibration_due)
        self.every(p.camera_info_period_s, self._republish_calibration)
        self._master_ok = True
        self._watcher = threading.Thread(target=self._watch_master, daemon=True)
        self._watcher.start()
        self.log.info(
            "ROS 1 node %s on %s: %s + %s in, %s/* out",
            rospy.get_name(),
            os.environ.get("ROS_MASTER_URI", "?"),
            p.image_topic,
            p.imu_topic,
            p.prefix,
        )

    def _start_inputs(self) -> None:
        """Subscribe to the ROS camera, IMU and CameraInfo (once)."""
        if self._inputs_started:
            return
        self._inputs_started = True
        p, rospy = self.params, self._rospy
        rospy.Subscriber(
            p.image_topic, rospy.AnyMsg, self._on_ros_image, queue_size=4, buff_size=1 << 26
        )
        rospy.Subscriber(p.imu_topic, rospy.AnyMsg, self._on_ros_imu, queue_size=10_000)
        if p.camera_info_topic:
            rospy.Subscriber(p.camera_info_topic, rospy.AnyMsg, self._on_ros_info, queue_size=1)
        if p.tf_static_topic:
            rospy.Subscriber(p.tf_static_topic, rospy.AnyMsg, self._on_ros_tf, queue_size=100)
        self.log.info("subscribed to %s and %s", p.image_topic, p.imu_topic)

    def _on_heartbeat(self, msg: msgs.Message) -> None:
        if isinstance(msg, msgs.Diagnostics):
            self._waiting.discard(msg.node)
        if not self._waiting:
            self._start_inputs()

    def _check_wait(self) -> None:
        if not self._inputs_started and time.monotonic() > self._wait_deadline:
            self.log.warning("no heartbeat from %s: subscribing anyway", sorted(self._waiting))
            self._start_inputs()

    def _publisher(self, topic: str, rtype: str, latch: bool) -> Any:
        cls = raw_message_class(self._rospy, rtype)
        return self._rospy.Publisher(topic, cls, queue_size=10, latch=latch), cls

    # ----------------------------------------------------------- ROS threads: never block

    def _on_ros_image(self, m: Any) -> None:
        self.inbox.put_image(m._connection_header.get("type", ""), m._buff)

    def _on_ros_imu(self, m: Any) -> None:
        self.inbox.put_imu(m._buff)

    def _on_ros_tf(self, m: Any) -> None:
        self.inbox.put_tf_static(m._buff)

    def _on_ros_info(self, m: Any) -> None:
        if self.inputs.calibration is None:
            with self.inbox.lock:
                self.inbox.camera_info = m._buff
            self.inbox.wake()

    # ------------------------------------------------------------ ROS -> bus (bus thread)

    def drain(self) -> None:
        """Converts what the ROS callbacks queued and publishes it on the bus: IMU first (the
        frontend integrates it up to each image), then the images."""
        p = self.params
        imu, images, info, tf = self.inbox.take()
        self.counters["imu_in"] = self.inbox.imu_in
        self.counters["frames_in"] = self.inbox.frames_in
        self.counters["frames_dropped"] = self.inbox.frames_dropped
        now = time.monotonic()
        for raw in tf:
            try:
                self.inputs.tf_static(raw)
            except MessageError as err:
                self._bad("tf_static", err)
        if info is not None:
            try:
                cal = self.inputs.camera_info(info, now)
            except MessageError as err:
                self._bad("CameraInfo", err)
            else:
                if cal is not None:
                    self._log_calibration(cal)
        for raw in imu:
            try:
                m = self.inputs.imu(raw)
            except MessageError as err:
                self._bad("IMU", err)
                continue
            self.publish(p.bus_imu_topic, m)
            self.counters["imu_published"] += 1
        for rtype, raw in images:
            try:
                img = self.inputs.image(rtype, raw)
            except MessageError as err:
                self._bad("image", err)
                continue
            self.outputs.input_frame = img.frame_id
            self.publish(p.bus_image_topic, img)
            self.counters["frames_published"] += 1

    def _log_calibration(self, cal: rc.CameraCalibration) -> None:
        c = cal.camera
        self.counters.update(
            camera_fx_px=c.fx_px, camera_fy_px=c.fy_px, camera_cx_px=c.cx_px, camera_cy_px=c.cy_px
        )
        self.log.info(*calibration_line(cal, self.params.camera_info_topic))

    # ------------------------------------------------------------ bus -> ROS (bus thread)

    def _send(self, triples: list[tuple[str, str, Any]]) -> None:
        for topic, rtype, rmsg in triples:
            pub, cls = self._pubs[topic]
            m = cls()
            m._buff = rc.serialize(rmsg, rtype, Distro.ROS1)
            try:
                pub.publish(m)
            except self._rospy.ROSException as err:  # shutting down: the topic is closed
                self.log.debug("%s: not published (%s)", topic, err)
                continue
            self.counters["ros_published"] += 1

    def on_odometry(self, msg: msgs.Odometry) -> None:
        self._send(self.outputs.on_odometry(msg))

    def on_keyframe(self, msg: msgs.Keyframe) -> None:
        self._send(self.outputs.on_keyframe(msg))

    def on_keyframe_pose(self, msg: msgs.PoseStamped) -> None:
        self._send(self.outputs.on_keyframe_pose(msg))
        self.counters["path_moves"] = self.outputs.path_moves

    def on_depth(self, msg: msgs.DepthMap) -> None:
        self._send(self.outputs.on_depth(msg))

    def on_gaussians(self, msg: msgs.GaussianUpdate) -> None:
        self._send(self.outputs.on_gaussians(msg, time.monotonic()))

    def flush_map(self) -> None:
        self._send(self.outputs.flush(time.monotonic()))

    def on_stats(self, msg: msgs.MapStats) -> None:
        self._send(self.outputs.on_stats(msg))
        self.counters["map_gaussians"] = msg.n_gaussians

    # ------------------------------------------------------------------- end, roscore

    def check_quiet(self) -> None:
        last = self.inbox.last_image_s
        quiet = self.params.end_after_quiet_s
        if last is not None and time.monotonic() - last > quiet and not self.stopping:
            self.log.info(
                "no image on %s for %.1f s: end of stream (%d frames in, %d dropped here)",
                self.params.image_topic,
                quiet,
                self.inbox.frames_in,
                self.inbox.frames_dropped,
            )
            self.request_stop()

    def _master_alive(self) -> bool:
        import rosgraph

        try:
            rosgraph.Master(self._rospy.get_name()).getPid()
        except Exception:  # ConnectionRefusedError, socket.error, xmlrpc Fault, ...
            return False
        return True

    def _watch_master(self) -> None:
        while not self._stop.wait(self.params.master_check_s):
            ok = self._master_alive()
            if self._master_ok and not ok:
                self.counters["master_lost"] += 1
                self.log.warning(
                    "roscore at %s is gone (logged once): the connections made keep working, "
                    "nothing new can find this node",
                    os.environ.get("ROS_MASTER_URI", "?"),
                )
            elif ok and not self._master_ok:
                # a ROS 1 node does not register again with a restarted master
                self.log.info("a roscore answers again (this node is not registered with it)")
            self._master_ok = ok

    def teardown(self) -> None:
        self._stop.set()
        self.drain()  # what the callbacks queued last still reaches the bus
        self._rospy.signal_shutdown("mogs ros1 bridge stopping")
        self.inbox.close()
        self.log.info(
            "ROS 1 bridge: %d frames in, %d dropped here, %d IMU samples, %d malformed, "
            "%d messages published to ROS",
            self.inbox.frames_in,
            self.inbox.frames_dropped,
            self.inbox.imu_in,
            self.counters["ros_malformed"],
            self.counters["ros_published"],
        )
