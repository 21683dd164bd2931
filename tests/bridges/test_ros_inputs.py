"""The ROS bridges' shared input side (``bridges/ros_inputs.py``) for ROS 1 and ROS 2 wire bytes,
without ROS installed: camera (Image, CompressedImage), IMU, CameraInfo and /tf_static become the
bus's messages and its calibration (T_imu_cam from /tf_static, else the launch value, else
unknown after the wait); malformed input raises one MessageError naming what is wrong. Also the
output side's path following the frontend's window refinements (``/frontend/refined_pose``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from bridges import ros_convert as rc
from bridges.ros_convert import CameraCalibration, Distro
from bridges.ros_inputs import RosInputParams, RosInputs
from bridges.ros_outputs import RosOutputParams, RosOutputs
from mogs_node import msgs
from mogs_node.errors import ConfigError, MessageError
from mogs_node.geometry import PinholeCamera, make_T, se3_inverse, so3_exp

DISTROS = [Distro.ROS1, Distro.ROS2]
T0 = 1_317_376_934_000_000_000  # 2011 epoch stamps
CAL = CameraCalibration(T0, "cam0", PinholeCamera(458.6, 457.3, 367.2, 248.4, 64, 48), "none")


def _T(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_T(so3_exp(rng.normal(size=3) * 0.3), rng.normal(size=3) * 0.1)


def _info(distro: Distro) -> bytes:
    return rc.serialize(rc.camera_info_to_ros(CAL, distro=distro), "sensor_msgs/CameraInfo", distro)


def _tf(distro: Distro, T: np.ndarray, parent: str, child: str) -> bytes:
    ros = rc.tf_from_pose(T0, T, parent=parent, child=child, distro=distro)
    return rc.serialize(ros, "tf2_msgs/TFMessage", distro)


def _imu(distro: Distro, gyro_x: float = 0.1) -> bytes:
    ros = rc.imu_to_ros(msgs.Imu(T0, "imu0", (0.1, 0.2, 0.3), (0.0, 0.0, 9.81)), distro=distro)
    ros.angular_velocity.x = gyro_x
    return rc.serialize(ros, "sensor_msgs/Imu", distro)


@pytest.mark.parametrize("distro", DISTROS)
def test_calibration_takes_t_imu_cam_from_tf_static_through_a_base_frame(distro: Distro) -> None:
    T_base_imu, T_base_cam = _T(1), _T(2)
    inp = RosInputs(RosInputParams(camera_info_topic="/cam0/camera_info"), distro)
    inp.tf_static(_tf(distro, T_base_imu, "base_link", "imu0"))
    inp.tf_static(_tf(distro, T_base_cam, "/base_link", "/cam0"))  # leading slashes: ROS 1 style
    assert inp.imu(_imu(distro)).gyro_rad_s == (0.1, 0.2, 0.3)
    assert inp.calibration_due(now_s=0.0) is None  # no CameraInfo yet
    assert inp.camera_info(_info(distro), now_s=5.0) == CAL
    assert inp.camera_info(_info(distro), now_s=5.1) is None  # the first one is kept
    info, where = inp.calibration_due(now_s=5.0)
    assert where == "/tf_static imu0 -> cam0"
    np.testing.assert_allclose(info.T_imu_cam, se3_inverse(T_base_imu) @ T_base_cam, atol=1e-12)
    np.testing.assert_array_equal(info.K, CAL.camera.K)
    assert (info.width, info.height, info.frame_id) == (64, 48, "cam0")
    assert info.source == "ros:/cam0/camera_info + /tf_static imu0 -> cam0"
    assert inp.calibration_due(now_s=9.0) is None  # once


@pytest.mark.parametrize("distro", DISTROS)
def test_calibration_without_tf_static_waits_then_uses_the_launch_value_or_none(
    distro: Distro,
) -> None:
    T = _T(3)
    typed = RosInputs(RosInputParams(T_imu_cam=tuple(T.reshape(-1)), source="ros2"), distro)
    typed.camera_info(_info(distro), now_s=0.0)
    info, where = typed.calibration_due(now_s=0.0)  # a typed value: no need to wait
    assert where == "the launch file" and info.source.startswith("ros2:")
    np.testing.assert_allclose(info.T_imu_cam, T, atol=1e-12)
    bare = RosInputs(RosInputParams(tf_wait_s=1.0), distro)
    bare.camera_info(_info(distro), now_s=10.0)
    assert bare.calibration_due(now_s=10.5) is None  # /tf_static may still come
    info, where = bare.calibration_due(now_s=11.0)
    assert where == "" and info.T_imu_cam is None  # the frontend's own launch value


def test_input_params_are_checked() -> None:
    with pytest.raises(ConfigError, match="ros1.T_imu_cam"):
        RosInputParams(T_imu_cam=(1.0,) * 16, source="ros1")
    with pytest.raises(ConfigError, match="tf_wait_s"):
        RosInputParams(tf_wait_s=-1.0)


@pytest.mark.parametrize("distro", DISTROS)
@pytest.mark.parametrize("enc", ["mono8", "rgb8", "bgr8", "jpeg"])
def test_camera_messages_of_either_type_and_spelling(distro: Distro, enc: str) -> None:
    rng = np.random.default_rng(0)
    rgb = cv2.resize(rng.uniform(0, 255, (6, 8, 3)).astype(np.float32), (64, 48)).astype(np.uint8)
    inp = RosInputs(RosInputParams(), distro)
    if enc == "jpeg":
        rtype = "sensor_msgs/CompressedImage"
        ros = rc.compressed_image_to_ros(msgs.Image(T0, "cam0", "rgb8", rgb), distro=distro)
    else:
        rtype = "sensor_msgs/msg/Image"
        data = {"mono8": rgb[..., 0], "rgb8": rgb, "bgr8": rgb[..., ::-1]}[enc]
        ros = rc.image_to_ros(
            msgs.Image(T0, "cam0", enc, np.ascontiguousarray(data)), distro=distro
        )
    img = inp.image(rtype, rc.serialize(ros, rtype, distro))
    assert img.stamp_ns == T0 and inp.image_frame == "cam0"
    if enc == "jpeg":
        assert img.encoding == "rgb8" and np.abs(img.data.astype(int) - rgb).mean() < 3
    else:
        assert img.encoding == enc


@pytest.mark.parametrize("distro", DISTROS)
def test_malformed_inputs_are_one_message_error_each(distro: Distro) -> None:
    inp = RosInputs(RosInputParams(), distro)
    with pytest.raises(MessageError, match="type"):
        inp.image("sensor_msgs/PointCloud2", b"")
    ros = rc.image_to_ros(msgs.Image(T0, "c", "mono8", np.zeros((48, 64), np.uint8)), distro=distro)
    ros.data = ros.data[:100]  # fewer bytes than height * step
    with pytest.raises(MessageError, match="data"):
        inp.image("sensor_msgs/Image", rc.serialize(ros, "sensor_msgs/Image", distro))
    with pytest.raises(MessageError, match="Image"):
        inp.image("sensor_msgs/Image", b"\x01\x02")  # truncated bytes
    with pytest.raises(MessageError, match="angular_velocity"):
        inp.imu(_imu(distro, float("nan")))
    with pytest.raises(MessageError, match="TFMessage"):
        inp.tf_static(b"\x05")
    bad = rc.camera_info_to_ros(CAL, distro=distro)
    setattr(bad, "K" if distro is Distro.ROS1 else "k", np.zeros(9))  # uncalibrated driver
    with pytest.raises(MessageError, match="K"):
        inp.camera_info(rc.serialize(bad, "sensor_msgs/CameraInfo", distro), now_s=0.0)
    assert inp.calibration is None  # a bad CameraInfo is not kept: the next good one is
    assert inp.camera_info(_info(distro), now_s=1.0) == CAL
    lines = [inp.count_malformed("image", MessageError("short", field="data")) for _ in range(5)]
    assert inp.malformed == 5 and [x is not None for x in lines] == [1, 1, 0, 1, 0]
    assert lines[0] == "malformed image from ROS (1 so far): data: short"


def _kf(i: int, T: np.ndarray) -> msgs.Keyframe:
    z = np.zeros
    return msgs.Keyframe(
        1000 + i, "world", i, z((4, 4), np.uint8), np.eye(3), T,
        z(0, np.int64), z((0, 2), np.float32), z((0, 3), np.float32), z(0, np.float32),
    )  # fmt: skip


@pytest.mark.parametrize("distro", DISTROS)
def test_path_follows_the_windows_refinements(distro: Distro) -> None:
    out = RosOutputs(RosOutputParams(map_period_s=100.0), distro)
    for i in range(3):
        assert [t for t, _, _ in out.on_keyframe(_kf(i, _T(i)))] == ["/mogs/path"]
    assert out.flush(now_s=0.0) == []  # nothing moved
    # the window moved keyframes 1 and 2; a pose of a keyframe not on the path (shed) is ignored
    for stamp, T in ((1001, _T(11)), (1002, _T(12)), (1001, _T(21)), (5555, _T(9))):
        assert out.on_keyframe_pose(msgs.PoseStamped(stamp, "world", T)) == []
    assert out.path_moves == 3
    [(topic, rtype, path)] = out.flush(now_s=1.0)  # once, with the latest poses
    assert (topic, rtype) == ("/mogs/path", "nav_msgs/msg/Path")
    stamps, Ts = rc.path_from_ros(rc.deserialize(rc.serialize(path, rtype, distro), rtype, distro))
    assert stamps.tolist() == [1000, 1001, 1002]
    for got, want in zip(Ts, (_T(0), _T(21), _T(12))):
        np.testing.assert_allclose(got, want, atol=1e-12)
    assert out.flush(now_s=2.0) == []
