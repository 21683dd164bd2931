"""The ROS 1 bridge against a real roscore: a bag written by the official rosbag writer and played
with ``rosbag play --clock`` reaches the bus exactly; the pipeline's outputs published on the bus
reach a rospy listener (official genpy classes) as odometry, path, map cloud, 32FC1 depth, tf and
diagnostics; the bridge ends by itself when the camera goes quiet. Skips when ROS 1 is absent
(CI sets MOGS_REQUIRE_ROS1=1 and installs it: .ci/run)."""

from __future__ import annotations

import re
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from _reliability_harness import node_argv
from _ros1 import (
    EPOCH_2011_NS,
    TOPICS,
    camera_info_msg,
    image_msg,
    imu_msg,
    read_listener,
    roscore,
    rospy_or_skip,
    set_param,
    start_listener,
    stop,
    tf_static_msg,
    wait_for_connections,
    wait_for_subscriber,
)

from bridges import ros_convert as rc
from bridges.ros1 import Ros1BridgeParams, raw_message_class, require_rospy
from mogs_node import msgs
from mogs_node.bus import Publisher, Subscriber
from mogs_node.errors import ConfigError, Ros1UnavailableError
from mogs_node.geometry import make_T, quat_wxyz_to_rotmat, so3_exp

N_FRAMES, W, H = 20, 64, 48
T_IMU_CAM = make_T(so3_exp(np.array([1.2, -1.2, 1.2])), np.array([0.05, -0.02, 0.01]))


def _images(n: int) -> list[np.ndarray]:
    """Smooth random images (upsampled 8x6 noise): JPEG keeps them within a few grey levels."""
    rng = np.random.default_rng(5)
    coarse = [rng.uniform(0, 255, (6, 8, 3)).astype(np.float32) for _ in range(n)]
    return [cv2.resize(c, (W, H), interpolation=cv2.INTER_LINEAR).astype(np.uint8) for c in coarse]


def _write_tiny_bag(
    path: Path, encoding: str
) -> tuple[list[int], list[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """20 frames at 10 Hz and IMU at 100 Hz with 2011 stamps, by the official writer (bz2)."""
    rospy = rospy_or_skip()
    import rosbag

    stamps = [EPOCH_2011_NS + i * 100_000_000 for i in range(N_FRAMES)]
    imgs = _images(N_FRAMES)
    imu_t = EPOCH_2011_NS + np.arange(N_FRAMES * 10) * 10_000_000
    imu = np.c_[
        np.sin(np.arange(len(imu_t))), np.cos(np.arange(len(imu_t))), np.arange(len(imu_t)) * 0.01
    ]
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    with rosbag.Bag(str(path), "w", compression=rosbag.Compression.BZ2) as bag:
        tf = tf_static_msg(rospy, EPOCH_2011_NS, T_IMU_CAM, "imu0", "cam0")
        bag.write("/tf_static", tf, _rt(rospy, EPOCH_2011_NS))
        for j, t in enumerate(imu_t):
            bag.write(
                TOPICS["imu"], imu_msg(rospy, int(t), imu[j], imu[j][::-1]), _rt(rospy, int(t))
            )
        for t, img in zip(stamps, imgs):
            bag.write(TOPICS["camera_info"], camera_info_msg(rospy, t, K, W, H), _rt(rospy, t))
            bag.write(TOPICS["image"], image_msg(rospy, t, img, encoding), _rt(rospy, t))
        # malformed input, once each: counted, logged, not forwarded; the bridge goes on
        t_bad = stamps[5] + 50_000_000
        bad = image_msg(rospy, t_bad, imgs[0], encoding)
        if encoding == "jpeg":
            bad.data = b"\xff\xd8 not a jpeg"
        else:
            bad.data = bad.data[:100]  # fewer bytes than height * step
        bag.write(TOPICS["image"], bad, _rt(rospy, t_bad))
        nan_imu = imu_msg(rospy, t_bad, np.array([np.nan, 0, 0]), np.zeros(3))
        bag.write(TOPICS["imu"], nan_imu, _rt(rospy, t_bad))
    return stamps, imgs, (imu_t, imu)


def _rt(rospy, t: int):
    return rospy.Time(t // 1_000_000_000, t % 1_000_000_000)


def _pose(i: int) -> np.ndarray:
    return make_T(so3_exp(np.array([0.01, 0.02 * i, 0.0])), np.array([i * 1.0, 0.1 * i, -0.5]))


def _publish_pipeline_outputs(bus, stamps: list[int]) -> dict:
    """What the pipeline would publish for these frames; returns the ground truth to compare."""
    pub = Publisher(bus)
    time.sleep(1.0)  # slow joiner: the broker forwards subscriptions
    for i, t in enumerate(stamps[:8]):
        pub.publish(
            "/frontend/odometry",
            msgs.Odometry(t, "cam0", i, _pose(i), (1.0, 0.0, 0.0), "tracking"),
        )
        time.sleep(0.02)
    img = np.zeros((H, W), np.uint8)
    for k in range(3):
        time.sleep(0.05)
        pub.publish(
            "/frontend/keyframe",
            msgs.Keyframe(
                stamps[3 * k],
                "cam0",
                k,
                img,
                np.eye(3),
                _pose(3 * k),
                np.zeros(0, np.int64),
                np.zeros((0, 2), np.float32),
                np.zeros((0, 3), np.float32),
                np.zeros(0, np.float32),
            ),
        )
    time.sleep(0.1)  # the window moved keyframe 1: the path follows (within a flush)
    pub.publish("/frontend/refined_pose", msgs.PoseStamped(stamps[3], "world", _pose(4)))
    depth = np.full((H, W), 7.5, np.float32)
    depth[:10] = 0.0  # no value: NaN on ROS
    pub.publish(
        "/metrizer/depth",
        msgs.DepthMap(
            stamps[3], "cam0", 1, "metric", depth, (depth > 0).astype(np.float32), "metrizer"
        ),
    )
    n = 1500
    rng = np.random.default_rng(2)
    means = rng.normal(size=(n, 3)).astype(np.float32) + np.float32([0, 0, 10])
    pub.publish(
        "/mapper/gaussians",
        msgs.GaussianUpdate(
            stamps[3],
            "world",
            1,
            np.arange(n, dtype=np.int64),
            means,
            np.zeros((n, 3), np.float32),
            np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
            np.zeros(n, np.float32),
            rng.uniform(0, 1, (n, 3)).astype(np.float32),
            np.zeros(0, np.int64),
        ),
    )
    pub.publish("/mapper/stats", msgs.MapStats(stamps[3], "world", 1, n, 2, 6, 0.05, 21.5))
    time.sleep(0.5)
    pub.close()
    return {"centroid": means.mean(0), "n": n}


def _run_bridge_case(tmp_path: Path, broker_bus, encoding: str) -> None:
    rospy_or_skip()
    bag = _write_tiny_bag(tmp_path / "tiny.bag", encoding)
    stamps, imgs, (imu_t, imu) = bag
    image_type = "sensor_msgs/CompressedImage" if encoding == "jpeg" else "sensor_msgs/Image"
    with roscore(tmp_path) as env:
        set_param(env, "/use_sim_time", "true")
        listener = start_listener(env, tmp_path / "heard.json", image_type=image_type)
        sub = Subscriber(broker_bus)
        for topic in ("/camera/image", "/imu", "/camera/info"):
            sub.subscribe(topic)
        params = {
            "image_topic": TOPICS["image"],
            "imu_topic": TOPICS["imu"],
            "camera_info_topic": TOPICS["camera_info"],
            "end_after_quiet_s": 3.0,
            "map_period_s": 0.0,
            "image_queue": 64,  # this test checks exact transport; dropping is tested below
        }
        log = (tmp_path / "bridge.log").open("w")
        bridge = subprocess.Popen(
            node_argv("bridges.ros1:Ros1Bridge", "ros1", params, broker_bus),
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        try:
            assert wait_for_subscriber(env, TOPICS["image"], "mogs", 60), (
                tmp_path / "bridge.log"
            ).read_text()
            outs = ["/mogs/odometry", "/mogs/path", "/mogs/depth", "/mogs/map_cloud", "/tf"]
            assert wait_for_connections(env, "/mogs", [*outs, "/diagnostics"], 60)
            truth = _publish_pipeline_outputs(broker_bus, stamps)
            play = subprocess.run(
                ["rosbag", "play", "--clock", "-q", str(tmp_path / "tiny.bag")],
                env=env,
                capture_output=True,
                text=True,
                timeout=120,
            )
            assert play.returncode == 0, play.stderr
            got: dict[str, list] = {"/camera/image": [], "/imu": [], "/camera/info": []}
            got_img, got_imu = got["/camera/image"], got["/imu"]
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and (
                len(got_img) < N_FRAMES or len(got_imu) < len(imu) or not got["/camera/info"]
            ):
                env_ = sub.receive(timeout_ms=200)
                if env_ is not None:
                    got[env_.topic].append(env_.msg)
            # the bridge ends by itself: the camera went quiet for end_after_quiet_s
            rc_bridge = bridge.wait(60)
        finally:
            stop(bridge, 20)
            heard_rc = stop(listener, 20)
            log.close()
            sub.close()
        bridge_log = (tmp_path / "bridge.log").read_text()
        assert rc_bridge == 0, bridge_log
        assert "end of stream" in bridge_log, bridge_log
        assert re.search(r"malformed image from ROS \(\d so far\): data:", bridge_log)
        assert re.search(r"malformed IMU from ROS \(\d so far\): angular_velocity:", bridge_log)
        assert "2 malformed" in bridge_log, bridge_log
        assert heard_rc == 0
    # the calibration: the CameraInfo's intrinsics, T_imu_cam from /tf_static (imu0 -> cam0)
    info = got["/camera/info"][0]
    assert (info.width, info.height, info.frame_id) == (W, H, "cam0")
    np.testing.assert_allclose(info.K, [[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    np.testing.assert_allclose(info.T_imu_cam, T_IMU_CAM, atol=1e-9)
    assert "/tf_static imu0 -> cam0" in info.source
    # in: every frame and IMU sample, exact stamps, exact pixels (jpeg: close)
    assert [m.stamp_ns for m in got_img] == stamps
    assert len(got_imu) == len(imu)
    assert [m.stamp_ns for m in got_imu] == imu_t.tolist()
    np.testing.assert_array_equal([m.gyro_rad_s for m in got_imu], imu)
    for m, rgb in zip(got_img, imgs):
        if encoding == "mono8":
            assert m.encoding == "mono8" and m.data.shape == (H, W)
        elif encoding == "jpeg":
            assert m.encoding == "rgb8" and np.abs(m.data.astype(int) - rgb).mean() < 3
        else:
            assert m.encoding == encoding and np.array_equal(
                m.data, rgb if encoding == "rgb8" else rgb[..., ::-1]
            )
    # out: what the listener heard through the official genpy classes
    heard = read_listener(tmp_path / "heard.json")
    odo = np.array(heard["odometry"])
    assert len(odo) == 8 and heard["odometry_frames"] == ["world", "cam0"]
    for i, row in enumerate(odo):
        T = make_T(quat_wxyz_to_rotmat(row[4:8]), row[1:4])
        assert int(row[0]) == stamps[i]
        np.testing.assert_allclose(T, _pose(i), atol=1e-9)
    path = heard["path"]["poses"]
    assert heard["path"]["frame_id"] == "world" and [int(p[0]) for p in path] == stamps[0:9:3]
    np.testing.assert_allclose(  # keyframe 1 where the window moved it
        np.array(path)[:, 1:4], [_pose(i)[:3, 3] for i in (0, 4, 6)], atol=1e-9
    )
    assert heard["path_first"][str(stamps[3])][:3] == pytest.approx(list(_pose(3)[:3, 3]))
    cloud = heard["map_cloud"]
    assert cloud["width"] * cloud["height"] == truth["n"] >= 1000
    assert cloud["fields"] == [["x", 0, 7, 1], ["y", 4, 7, 1], ["z", 8, 7, 1], ["rgb", 12, 7, 1]]
    assert cloud["point_step"] == 16 and cloud["finite"] and cloud["distinct_colours"] > 1000
    np.testing.assert_allclose(cloud["centroid"], truth["centroid"], atol=1e-4)
    d = heard["depth"]
    assert (d["encoding"], d["height"], d["width"], d["step"]) == ("32FC1", H, W, 4 * W)
    assert d["finite_fraction"] == pytest.approx(1 - 10 / H) and d["min_m"] == d["max_m"] == 7.5
    assert not d["any_zero"]  # REP 118: no value is NaN, never 0
    assert ["world", "cam0"] in heard["tf"]["pairs"] and heard["tf"]["count"] >= 8
    assert "mogs/mapper" in heard["diagnostics"]["names"]
    assert heard["diagnostics"]["last"]["n_gaussians"] == str(truth["n"])


def test_bridge_round_trip_mono8(tmp_path: Path, broker_bus) -> None:
    _run_bridge_case(tmp_path, broker_bus, "mono8")


@pytest.mark.slow
@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "jpeg"])
def test_bridge_round_trip_other_encodings(tmp_path: Path, broker_bus, encoding: str) -> None:
    _run_bridge_case(tmp_path, broker_bus, encoding)


# ------------------------------------------------------------------------- without a roscore


def test_raw_message_class_announces_the_official_type() -> None:
    rospy = rospy_or_skip()
    from nav_msgs.msg import Odometry
    from nav_msgs.msg import Path as RosPath
    from sensor_msgs.msg import PointCloud2
    from tf2_msgs.msg import TFMessage

    for rtype, official in [
        ("nav_msgs/msg/Odometry", Odometry),
        ("nav_msgs/msg/Path", RosPath),
        ("sensor_msgs/msg/PointCloud2", PointCloud2),
        ("tf2_msgs/msg/TFMessage", TFMessage),
    ]:
        cls = raw_message_class(rospy, rtype)
        assert (cls._type, cls._md5sum) == (official._type, official._md5sum)
    # bytes of our conversion decode with the official class
    m = rc.odometry_to_ros(
        msgs.Odometry(EPOCH_2011_NS, "cam0", 0, _pose(2), (1.0, 2.0, 3.0), "ok"),
        distro=rc.Distro.ROS1,
    )
    got = Odometry().deserialize(rc.serialize(m, "nav_msgs/Odometry", rc.Distro.ROS1))
    assert got.child_frame_id == "cam0" and got.pose.pose.position.x == pytest.approx(2.0)


def test_missing_rospy_names_the_apt_line(monkeypatch: pytest.MonkeyPatch) -> None:
    import builtins
    import sys

    real = builtins.__import__

    def no_rospy(name, *a, **k):
        if name == "rospy":
            raise ImportError("No module named 'rospy'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_rospy)
    monkeypatch.delitem(sys.modules, "rospy", raising=False)
    with pytest.raises(Ros1UnavailableError, match="apt-get install -y ros-core python3-rospy"):
        require_rospy()


def test_params_are_checked() -> None:
    with pytest.raises(ConfigError, match="image_queue"):
        Ros1BridgeParams(image_queue=0)
    with pytest.raises(ConfigError, match="image_topic"):
        Ros1BridgeParams(image_topic="")


# ------------------------------------------------------------------------- pure pieces


def test_inbox_drops_old_images_counts_them_and_never_drops_imu() -> None:
    from bridges.ros1 import _Inbox

    box = _Inbox(image_queue=2)
    try:
        for i in range(5):
            box.put_image("sensor_msgs/Image", bytes([i]))
        for i in range(1000):
            box.put_imu(i.to_bytes(2, "little"))
        box.put_tf_static(b"tf")
        imu, images, info, tf = box.take()
        assert [raw for _, raw in images] == [b"\x03", b"\x04"]  # the latest two
        assert (box.frames_in, box.frames_dropped, box.imu_in) == (5, 3, 1000)
        assert [int.from_bytes(b, "little") for b in imu] == list(range(1000)) and info is None
        assert tf == [b"tf"]  # static transforms are never dropped either
        assert box.take() == ([], [], None, [])
    finally:
        box.close()


def _kf(i: int, T: np.ndarray) -> msgs.Keyframe:
    return msgs.Keyframe(
        1000 + i,
        "cam0",
        i,
        np.zeros((4, 4), np.uint8),
        np.eye(3),
        T,
        np.zeros(0, np.int64),
        np.zeros((0, 2), np.float32),
        np.zeros((0, 3), np.float32),
        np.zeros(0, np.float32),
    )


def _update(ids: np.ndarray, removed: np.ndarray, z: float) -> msgs.GaussianUpdate:
    n = len(ids)
    return msgs.GaussianUpdate(
        5,
        "world",
        0,
        ids.astype(np.int64),
        np.c_[ids, ids, np.full(n, z)].astype(np.float32),
        np.zeros((n, 3), np.float32),
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        np.zeros(n, np.float32),
        np.full((n, 3), 0.5, np.float32),
        removed.astype(np.int64),
    )


def test_ros_outputs_path_moves_a_keyframe_seen_again() -> None:
    from bridges.ros_outputs import RosOutputParams, RosOutputs

    out = RosOutputs(RosOutputParams(), rc.Distro.ROS1)
    for i in range(3):
        out.on_keyframe(_kf(i, _pose(i)))
    [(topic, rtype, path)] = out.on_keyframe(_kf(1, _pose(7)))  # keyframe 1 moved
    assert (topic, rtype) == ("/mogs/path", "nav_msgs/msg/Path")
    stamps, Ts = rc.path_from_ros(path)
    assert stamps.tolist() == [1000, 1001, 1002]
    np.testing.assert_allclose(Ts[1], _pose(7), atol=1e-12)


def test_ros_outputs_map_cloud_follows_updates_and_is_throttled() -> None:
    from bridges.ros_outputs import RosOutputParams, RosOutputs

    out = RosOutputs(RosOutputParams(map_period_s=2.0, max_map_points=40), rc.Distro.ROS2)
    stats = msgs.MapStats(5, "world", 0, 10, 1, 1, 0.1, 20.0)
    assert [t for t, _, _ in out.on_stats(stats)] == ["/diagnostics"]
    assert out.on_gaussians(_update(np.zeros(0), np.zeros(0), 1.0), now_s=9.0) == []  # no map
    first = out.on_gaussians(_update(np.arange(100), np.zeros(0), 1.0), now_s=10.0)
    assert [t for t, _, _ in first] == ["/mogs/map_cloud"]
    xyz, _ = rc.pointcloud_from_ros(first[0][2])
    assert len(xyz) == 34  # 100 Gaussians, every 3rd: <= max_map_points
    # 50 removed, 10 changed, 20 added: too soon for a cloud, the flush after 2 s sends it
    assert out.on_gaussians(_update(np.arange(90, 120), np.arange(50), 2.0), now_s=11.0) == []
    assert out.flush(now_s=11.5) == []
    [(_, _, later)] = out.flush(now_s=12.5)
    assert len(out.cloud.ids) == 70 and sorted(out.cloud.ids.tolist()) == list(range(50, 120))
    xyz, _ = rc.pointcloud_from_ros(later)
    assert len(xyz) == 35 and set(xyz[:, 0].tolist()) <= set(range(50, 120))
    assert out.flush(now_s=20.0) == []  # unchanged map: nothing


def test_rviz_config_shows_what_the_bridge_publishes() -> None:
    import yaml

    from bridges.ros_outputs import OUTPUT_TYPES, RosOutputParams

    cfg = yaml.safe_load((Path(__file__).parents[2] / "launch" / "mogs.rviz").read_text())
    shown = {
        d.get("Topic") or d.get("Image Topic"): d["Class"]
        for d in cfg["Visualization Manager"]["Displays"]
    }
    p = RosOutputParams()
    want = {
        "odometry": "rviz/Odometry",
        "path": "rviz/Path",
        "map_cloud": "rviz/PointCloud2",
        "depth": "rviz/Image",
    }
    assert set(want) == set(OUTPUT_TYPES)
    for name, cls in want.items():
        assert shown[p.topic(name)] == cls
    assert cfg["Visualization Manager"]["Global Options"]["Fixed Frame"] == p.world_frame
    assert "rviz/TF" in shown.values() and shown["/camera/image_raw"] == "rviz/Image"


def test_ros_outputs_camera_frame_is_the_images_not_the_worlds() -> None:
    from bridges.ros_outputs import RosOutputParams, RosOutputs

    odo = msgs.Odometry(5, "world", 0, _pose(1), (0.0, 0.0, 0.0), "tracking")  # the frontend's
    depth = np.ones((2, 2), np.float32)
    dm = msgs.DepthMap(5, "world", 0, "metric", depth, depth, "metrizer")
    out = RosOutputs(RosOutputParams(), rc.Distro.ROS1)
    assert out.on_odometry(odo)[0][2].child_frame_id == "camera"  # nothing known: "camera"
    out.input_frame = "cam0"
    (_, _, ros_odo), (_, _, tf) = out.on_odometry(odo)
    assert ros_odo.child_frame_id == "cam0" and ros_odo.header.frame_id == "world"
    assert list(rc.transforms_from_ros(tf)) == [("world", "cam0")]
    assert out.on_depth(dm)[0][2].header.frame_id == "cam0"
    init = msgs.Odometry(4, "world", 0, np.eye(4), (0.0, 0.0, 0.0), "initializing")
    assert out.on_odometry(init) == [] and out.not_estimated == 1  # no pose: nothing on ROS
    fixed = RosOutputs(RosOutputParams(camera_frame="left", world_frame="map"), rc.Distro.ROS2)
    fixed.input_frame = "cam0"
    assert fixed.on_odometry(odo)[0][2].child_frame_id == "left"


def test_a_roscore_that_goes_away_is_logged_once(tmp_path: Path, broker_bus) -> None:
    rospy_or_skip()
    params = {"image_topic": "/cam", "imu_topic": "/imu0", "master_check_s": 0.3}
    log_path = tmp_path / "bridge.log"
    with roscore(tmp_path) as env:
        port = int(env["ROS_MASTER_URI"].rsplit(":", 1)[1])
        log = log_path.open("w")
        bridge = subprocess.Popen(
            node_argv("bridges.ros1:Ros1Bridge", "ros1", params, broker_bus),
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        assert wait_for_subscriber(env, "/cam", "mogs", 60), log_path.read_text()
    time.sleep(3.0)  # ten checks without a roscore
    with roscore(tmp_path, port=port):
        deadline = time.monotonic() + 30
        while "answers again" not in log_path.read_text() and time.monotonic() < deadline:
            time.sleep(0.2)
        code = stop(bridge, 30)  # Ctrl-C: a clean end
    log.close()
    text = log_path.read_text()
    assert code == 0, text
    assert text.count("is gone") == 1 and text.count("answers again") == 1, text
