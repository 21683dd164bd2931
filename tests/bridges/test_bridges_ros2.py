"""ROS 2 conversions round-trip without ROS (rosbags typestore + CDR), and `mogs ros2` without rclpy."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from _reliability_harness import run_cli
from hypothesis import given, settings
from hypothesis import strategies as st

from bridges import ros2, ros_convert
from mogs_node import msgs
from mogs_node.errors import MessageError
from mogs_node.geometry import make_T, so3_exp


def cdr(rmsg, rtype: str):
    """Through the wire format and back: what a ROS 2 peer would see."""
    ts = ros2.typestore()
    return ts.deserialize_cdr(ts.serialize_cdr(rmsg, rtype), rtype)


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_T(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 10)


@pytest.mark.parametrize(
    ("enc", "shape"), [("mono8", (5, 7)), ("rgb8", (4, 6, 3)), ("bgr8", (3, 2, 3))]
)
def test_image_round_trip_is_exact(enc: str, shape: tuple) -> None:
    data = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
    m = msgs.Image(stamp_ns=1_700_000_000_123_456_789, frame_id="cam", encoding=enc, data=data)
    r = cdr(ros_convert.image_to_ros(m), "sensor_msgs/msg/Image")
    assert (r.encoding, r.height, r.width, r.step) == (enc, shape[0], shape[1], data[0].size)
    assert (r.header.stamp.sec, r.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert ros_convert.image_from_ros(r) == m


def test_image_from_ros_honours_row_padding_and_rejects_short_data() -> None:
    T = ros2.typestore().types
    img = np.arange(6, dtype=np.uint8).reshape(2, 3)
    padded = np.zeros((2, 5), np.uint8)
    padded[:, :3] = img
    r = T["sensor_msgs/msg/Image"](
        header=ros2._header(5, "c"),
        height=2,
        width=3,
        encoding="8UC1",
        is_bigendian=0,
        step=5,
        data=padded.reshape(-1),
    )
    out = ros_convert.image_from_ros(r)
    assert out.encoding == "mono8" and out.data.tolist() == img.tolist()
    r.data = r.data[:7]
    with pytest.raises(MessageError, match="data"):
        ros_convert.image_from_ros(r)
    r.encoding = "yuv422"
    with pytest.raises(MessageError, match="encoding"):
        ros_convert.image_from_ros(r)


@settings(max_examples=50, deadline=None)
@given(
    st.integers(0, 2**31 * 10**9 - 1),
    st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=6, max_size=6),
)
def test_imu_round_trip_is_exact(stamp: int, v: list[float]) -> None:
    m = msgs.Imu(stamp_ns=stamp, frame_id="imu", gyro_rad_s=tuple(v[:3]), accel_m_s2=tuple(v[3:]))
    r = cdr(ros_convert.imu_to_ros(m), "sensor_msgs/msg/Imu")
    assert r.orientation_covariance[0] == -1.0
    assert ros_convert.imu_from_ros(r) == m


def test_odometry_round_trip_and_twist_in_camera_frame() -> None:
    T = _pose(3)
    v = (1.0, -2.0, 0.5)
    m = msgs.Odometry(
        stamp_ns=42,
        frame_id="camera",
        frame_index=7,
        T_world_cam=T,
        velocity_world_m_s=v,
        status="tracking",
    )
    r = cdr(ros_convert.odometry_to_ros(m), "nav_msgs/msg/Odometry")
    assert r.header.frame_id == "world" and r.child_frame_id == "camera"
    lin = r.twist.twist.linear
    np.testing.assert_allclose([lin.x, lin.y, lin.z], T[:3, :3].T @ np.array(v), atol=1e-12)
    back = ros2.odometry_from_ros(r, frame_index=7, status="tracking")
    np.testing.assert_allclose(back.T_world_cam, T, atol=1e-12)
    np.testing.assert_allclose(back.velocity_world_m_s, v, atol=1e-12)
    assert (back.stamp_ns, back.frame_id, back.frame_index) == (42, "camera", 7)


def test_pose_and_tf() -> None:
    T = _pose(4)
    r = cdr(ros_convert.pose_to_ros(9, T), "geometry_msgs/msg/PoseStamped")
    back = ros_convert.pose_from_ros(r)
    np.testing.assert_allclose(back.T_world_cam, T, atol=1e-12)
    assert back.stamp_ns == 9
    tf = cdr(ros_convert.tf_from_pose(9, T, child="kf"), "tf2_msgs/msg/TFMessage")
    (t,) = tf.transforms
    assert (t.header.frame_id, t.child_frame_id) == ("world", "kf")
    q = t.transform.rotation
    assert [t.transform.translation.x, t.transform.translation.y, t.transform.translation.z] == (
        T[:3, 3].tolist()
    )
    assert (q.x, q.y, q.z, q.w) == (
        r.pose.orientation.x,
        r.pose.orientation.y,
        r.pose.orientation.z,
        r.pose.orientation.w,
    )
    with pytest.raises(MessageError, match="T_world_cam"):
        ros_convert.pose_to_ros(0, np.eye(3))
    with pytest.raises(MessageError, match="stamp_ns"):
        ros_convert.pose_to_ros(-1, T)
    with pytest.raises(MessageError, match="stamp_ns"):
        ros_convert.pose_to_ros(2**31 * 10**9, T)  # beyond int32 seconds (2038)


def test_depth_round_trip_uses_nan_for_missing() -> None:
    d = np.array([[0.0, 1.5], [2.25, 80.0]], np.float32)
    m = msgs.DepthMap(
        stamp_ns=3,
        frame_id="camera",
        keyframe_id=11,
        kind="metric",
        depth=d,
        confidence=(d > 0).astype(np.float32),
        source="ros2",
    )
    r = cdr(ros_convert.depth_to_ros(m), "sensor_msgs/msg/Image")
    assert r.encoding == "32FC1" and r.step == 8
    raw = np.frombuffer(bytes(r.data), "<f4").reshape(2, 2)
    assert np.isnan(raw[0, 0]) and raw[1, 1] == 80.0
    assert ros2.depth_from_ros(r, keyframe_id=11) == m
    rel = msgs.DepthMap(
        stamp_ns=3,
        frame_id="c",
        keyframe_id=1,
        kind="relative_depth",
        depth=d,
        confidence=d,
        source="x",
    )
    with pytest.raises(MessageError, match="kind"):
        ros_convert.depth_to_ros(rel)
    assert ros_convert.to_ros(rel) is None


def test_mapstats_round_trip_as_diagnostics() -> None:
    m = msgs.MapStats(
        stamp_ns=5,
        frame_id="world",
        keyframe_id=4,
        n_gaussians=123456,
        n_keyframes=5,
        iterations=150,
        loss=0.0123456789,
        psnr_db=float("nan"),
        extra={"ms": 12.5, "pruned": 7},
    )
    r = cdr(ros_convert.mapstats_to_ros(m), "diagnostic_msgs/msg/DiagnosticArray")
    assert r.status[0].name == "mogs/mapper"
    assert ros_convert.mapstats_from_ros(r) == m


def test_to_ros_covers_every_bridged_type() -> None:
    from mogs_node.demo_nodes import make_keyframe

    kf = make_keyframe(3, 16, 8, 2)
    rtype, r = ros_convert.to_ros(kf)
    assert rtype == "geometry_msgs/msg/PoseStamped"
    np.testing.assert_allclose(ros_convert.pose_from_ros(r).T_world_cam, kf.T_world_cam)
    diag = msgs.Diagnostics(stamp_ns=0, frame_id="", node="n", pid=1, uptime_s=0.0, status="ok")
    assert ros_convert.to_ros(diag) is None


@pytest.mark.skipif(importlib.util.find_spec("rclpy") is not None, reason="rclpy is installed")
def test_ros2_command_without_rclpy_says_what_is_missing() -> None:
    r = run_cli("ros2")
    assert r.returncode == 1
    assert "rclpy is not importable: `mogs ros2` needs a ROS 2 installation" in r.stderr
