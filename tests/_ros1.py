"""ROS 1 test helpers: a real roscore on a free port, bags written by the official ``rosbag``
writer (genpy messages, bz2 chunks), the rospy listener process (``_ros1_listener.py``)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from _reliability_harness import free_tcp_port

from mogs_node.errors import Ros1UnavailableError

REPO = Path(__file__).resolve().parents[1]
EPOCH_2011_NS = 1_317_376_934_000_000_000  # 2011-09-30, a KITTI drive's day

#: the topic names of a EuRoC-style ROS 1 bag (not ours)
TOPICS = {"image": "/cam0/image_raw", "imu": "/imu0", "camera_info": "/cam0/camera_info"}
GT_POSE_TOPIC = "/ground_truth/pose"


def rospy_or_skip() -> Any:
    """rospy, or a skip naming what is missing; with MOGS_REQUIRE_ROS1=1 (CI) a failure."""
    from bridges.ros1 import require_rospy

    try:
        rospy = require_rospy()
        missing = [exe for exe in ("roscore", "rosbag") if shutil.which(exe) is None]
        if missing:
            raise Ros1UnavailableError(f"{missing} not on PATH")
    except Ros1UnavailableError as err:
        if os.environ.get("MOGS_REQUIRE_ROS1") == "1":
            raise
        pytest.skip(f"ROS 1 is not installed here: {err}")
    return rospy


def ros_env(port: int, home: Path) -> dict[str, str]:
    env = dict(os.environ)
    env.update(
        ROS_MASTER_URI=f"http://127.0.0.1:{port}",
        ROS_HOSTNAME="127.0.0.1",
        ROS_HOME=str(home),
        ROS_LOG_DIR=str(home / "log"),
        PYTHONPATH=str(REPO) + os.pathsep + env.get("PYTHONPATH", ""),
        OMP_NUM_THREADS="1",
    )
    return env


def master_up(env: dict[str, str]) -> bool:
    import rosgraph

    old = os.environ.get("ROS_MASTER_URI")
    try:
        rosgraph.Master("/mogs_test", master_uri=env["ROS_MASTER_URI"]).getPid()
        return True
    except Exception:
        return False
    finally:
        if old is not None:
            os.environ["ROS_MASTER_URI"] = old


@contextlib.contextmanager
def roscore(tmp: Path, timeout_s: float = 300.0, port: int = 0) -> Iterator[dict[str, str]]:
    """A real ``roscore`` on ``port`` (0: a free one); yields the environment pointing at it
    (``timeout_s``: a roscore takes a minute or more to answer on a machine shared with other
    runs)."""
    home = tmp / "ros_home"
    home.mkdir(parents=True, exist_ok=True)
    env = ros_env(port or free_tcp_port(), home)
    port_s = env["ROS_MASTER_URI"].rsplit(":", 1)[1]
    log = (tmp / "roscore.log").open("a")
    proc = subprocess.Popen(
        ["roscore", "-p", port_s], env=env, stdout=log, stderr=subprocess.STDOUT
    )
    try:
        deadline = time.monotonic() + timeout_s
        while not master_up(env):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"roscore did not come up: {(tmp / 'roscore.log').read_text()}")
            time.sleep(0.2)
        yield env
    finally:
        stop(proc, 15)
        log.close()


def stop(proc: subprocess.Popen, timeout_s: float = 10.0) -> int | None:
    """SIGINT, then SIGKILL after ``timeout_s``; the exit code (None if it had to be killed)."""
    if proc.poll() is None:
        proc.send_signal(2)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            return None
    return proc.returncode


def rosbag_play_argv(bag: Path, rate: float = 1.0) -> list[str]:
    """``rosbag play --clock`` of ``bag`` at ``rate``, with a deep outgoing queue: rosbag's default
    of 100 drops IMU samples on a crowded machine before they reach the bridge (and an IMU gap
    resets the frontend)."""
    return ["rosbag", "play", "--clock", "-q", "--queue", "10000", "-r", str(rate), str(bag)]


def set_param(env: dict[str, str], name: str, value: str) -> None:
    subprocess.run(["rosparam", "set", name, value], env=env, check=True, timeout=30)


def wait_for_subscriber(env: dict[str, str], topic: str, node: str, timeout_s: float) -> bool:
    """Whether ``node`` subscribes to ``topic`` on the master within ``timeout_s``."""
    import rosgraph

    m = rosgraph.Master("/mogs_test", master_uri=env["ROS_MASTER_URI"])
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        _, subs, _ = m.getSystemState()
        if any(t == topic and any(n.lstrip("/") == node for n in ns) for t, ns in subs):
            return True
        time.sleep(0.2)
    return False


# -------------------------------------------------------------------------------- bag writing


def _time(rospy: Any, stamp_ns: int) -> Any:
    return rospy.Time(int(stamp_ns // 1_000_000_000), int(stamp_ns % 1_000_000_000))


def _header(rospy: Any, stamp_ns: int, frame_id: str) -> Any:
    from std_msgs.msg import Header

    return Header(stamp=_time(rospy, stamp_ns), frame_id=frame_id)


def image_msg(rospy: Any, stamp_ns: int, rgb: np.ndarray, encoding: str) -> Any:
    """A genpy ``sensor_msgs/Image`` (mono8 / rgb8 / bgr8) or ``CompressedImage`` ("jpeg")."""
    from sensor_msgs.msg import CompressedImage, Image

    h = _header(rospy, stamp_ns, "cam0")
    if encoding == "jpeg":
        ok, buf = cv2.imencode(
            ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95]
        )
        assert ok
        return CompressedImage(header=h, format="jpeg", data=buf.tobytes())
    img = {
        "mono8": lambda: cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY),
        "rgb8": lambda: rgb,
        "bgr8": lambda: rgb[..., ::-1],
    }[encoding]()
    img = np.ascontiguousarray(img)
    return Image(
        header=h,
        height=img.shape[0],
        width=img.shape[1],
        encoding=encoding,
        is_bigendian=0,
        step=img.strides[0],
        data=img.tobytes(),
    )


def imu_msg(rospy: Any, stamp_ns: int, gyro: np.ndarray, accel: np.ndarray) -> Any:
    from geometry_msgs.msg import Vector3
    from sensor_msgs.msg import Imu

    m = Imu(header=_header(rospy, stamp_ns, "imu0"))
    m.orientation_covariance[0] = -1.0
    m.angular_velocity = Vector3(*map(float, gyro))
    m.linear_acceleration = Vector3(*map(float, accel))
    return m


def camera_info_msg(rospy: Any, stamp_ns: int, K: np.ndarray, width: int, height: int) -> Any:
    from sensor_msgs.msg import CameraInfo

    return CameraInfo(
        header=_header(rospy, stamp_ns, "cam0"),
        width=width,
        height=height,
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=K.reshape(-1).tolist(),
        R=np.eye(3).reshape(-1).tolist(),
        P=np.c_[K, np.zeros(3)].reshape(-1).tolist(),
    )


def pose_msg(rospy: Any, stamp_ns: int, T: np.ndarray) -> Any:
    from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion

    from mogs_node.geometry import quat_wxyz_from_rotmat

    q = quat_wxyz_from_rotmat(T[:3, :3])
    return PoseStamped(
        header=_header(rospy, stamp_ns, "world"),
        pose=Pose(
            Point(*map(float, T[:3, 3])),
            Quaternion(float(q[1]), float(q[2]), float(q[3]), float(q[0])),
        ),
    )


def tf_static_msg(rospy: Any, stamp_ns: int, T: np.ndarray, parent: str, child: str) -> Any:
    """A genpy ``tf2_msgs/TFMessage`` holding ``T_parent_child`` [4, 4]."""
    from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3
    from tf2_msgs.msg import TFMessage

    from mogs_node.geometry import quat_wxyz_from_rotmat

    q = quat_wxyz_from_rotmat(T[:3, :3])
    tr = TransformStamped(
        header=_header(rospy, stamp_ns, parent),
        child_frame_id=child,
        transform=Transform(
            Vector3(*map(float, T[:3, 3])),
            Quaternion(float(q[1]), float(q[2]), float(q[3]), float(q[0])),
        ),
    )
    return TFMessage(transforms=[tr])


def write_sim_bag_official(path: Path, seq: Any, encoding: str) -> Path:
    """A sim drive as a ROS 1 bag by the official ``rosbag`` writer: bz2 chunks, images on
    ``/cam0/image_raw`` (``encoding``: mono8, rgb8, bgr8 or jpeg), IMU on ``/imu0``, CameraInfo on
    ``/cam0/camera_info``, ``T_imu_cam`` on ``/tf_static`` (imu0 -> cam0), ground truth
    ``T_world_cam`` on ``/ground_truth/pose``; the sequence's own stamps (give it epoch ones)."""
    rospy = rospy_or_skip()
    import rosbag

    with rosbag.Bag(str(path), "w", compression=rosbag.Compression.BZ2) as bag:
        t0 = int(min(seq.imu_stamps_ns[0], seq.stamps_ns[0]))
        bag.write(
            "/tf_static", tf_static_msg(rospy, t0, seq.T_imu_cam, "imu0", "cam0"), _time(rospy, t0)
        )
        for t, kind, k in seq.sensor_events():
            when = _time(rospy, t)
            if kind == "imu":
                m = imu_msg(rospy, t, seq.imu_gyro_rad_s[k], seq.imu_accel_m_s2[k])
                bag.write(TOPICS["imu"], m, when)
                continue
            f = seq.render(k)
            cam = seq.camera
            bag.write(
                TOPICS["camera_info"], camera_info_msg(rospy, t, cam.K, cam.width, cam.height), when
            )
            bag.write(TOPICS["image"], image_msg(rospy, t, f.rgb, encoding), when)
            bag.write(GT_POSE_TOPIC, pose_msg(rospy, t, f.T_world_cam), when)
    return path


# ------------------------------------------------------------------------------- the listener


def start_listener(
    env: dict[str, str], out: Path, *, image_type: str = "sensor_msgs/Image"
) -> subprocess.Popen:
    """The rospy listener process; returns once it has subscribed."""
    log = out.with_suffix(".log").open("w")
    proc = subprocess.Popen(
        [
            sys.executable,
            str(REPO / "tests" / "_ros1_listener.py"),
            str(out),
            "--image-topic",
            TOPICS["image"],
            "--image-type",
            image_type,
        ],
        env=env,
        cwd=REPO,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    deadline = time.monotonic() + 300  # rospy's start takes minutes on a crowded machine
    while not Path(str(out) + ".ready").exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"listener did not start: {out.with_suffix('.log').read_text()}")
        time.sleep(0.1)
    return proc


def read_listener(out: Path) -> dict:
    return json.loads(out.read_text())


def wait_for_connections(
    env: dict[str, str], node: str, topics: list[str], timeout_s: float
) -> bool:
    """Whether ``node`` has an outbound connection on every one of ``topics`` (its publishers
    reach a subscriber) within ``timeout_s``: messages published from then on are delivered."""
    import xmlrpc.client

    import rosgraph

    m = rosgraph.Master("/mogs_test", master_uri=env["ROS_MASTER_URI"])
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            uri = m.lookupNode(node)
            _, _, info = xmlrpc.client.ServerProxy(uri).getBusInfo("/mogs_test")
            out = {c[4] for c in info if c[2] == "o"}
            if set(topics) <= out:
                return True
        except Exception:  # not registered yet
            pass
        time.sleep(0.2)
    return False
