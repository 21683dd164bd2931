"""The shared ROS conversions, both ways, for ROS 1 and ROS 2 types, through each wire format
(ROS 1 serialization, CDR) and back, without ROS installed; malformed messages give one error."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridges import ros_convert as rc
from bridges.ros_convert import CameraCalibration, Distro
from mogs_node import msgs
from mogs_node.errors import MessageError
from mogs_node.geometry import PinholeCamera, make_T, so3_exp

DISTROS = [Distro.ROS1, Distro.ROS2]
EPOCH_2011_NS = 1_317_376_934_123_456_789  # a KITTI-era stamp (2011-09-30)


def wire(rmsg, rtype: str, distro: Distro):
    """Through the wire format and back: what a ROS peer would see."""
    return rc.deserialize(rc.serialize(rmsg, rtype, distro), rtype, distro)


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_T(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 10)


# ------------------------------------------------------------------------------ stamps, bytes


@pytest.mark.parametrize("distro", DISTROS)
def test_header_keeps_epoch_nanoseconds_and_ros1_has_seq(distro: Distro) -> None:
    h = wire(
        rc.image_to_ros(
            msgs.Image(EPOCH_2011_NS, "cam", "mono8", np.zeros((2, 2), np.uint8)), distro=distro
        ),
        "sensor_msgs/Image",
        distro,
    ).header
    assert rc.ros_stamp_ns(h) == EPOCH_2011_NS and h.frame_id == "cam"
    assert hasattr(h, "seq") == (distro is Distro.ROS1)


def test_time_range_differs_between_ros1_and_ros2() -> None:
    late = (1 << 31) * 1_000_000_000 + 5  # 2038: unsigned ROS 1 seconds hold it, ROS 2 not
    assert rc.ros_stamp_ns(rc.header(late, "", Distro.ROS1)) == late
    with pytest.raises(MessageError, match="stamp_ns"):
        rc.header(late, "", Distro.ROS2)
    for bad in (-1, 1.5, True, None):
        with pytest.raises(MessageError, match="stamp_ns"):
            rc.header(bad, "", Distro.ROS1)  # type: ignore[arg-type]


@pytest.mark.parametrize("distro", DISTROS)
def test_truncated_bytes_are_one_message_error(distro: Distro) -> None:
    raw = rc.serialize(
        rc.imu_to_ros(msgs.Imu(5, "imu", (1.0, 2.0, 3.0), (4.0, 5.0, 6.0)), distro=distro),
        "sensor_msgs/Imu",
        distro,
    )
    with pytest.raises(MessageError, match="sensor_msgs/msg/Imu"):
        rc.deserialize(raw[:20], "sensor_msgs/Imu", distro)


# ------------------------------------------------------------------------------------ images


@pytest.mark.parametrize("distro", DISTROS)
@pytest.mark.parametrize(
    ("enc", "shape"), [("mono8", (5, 7)), ("rgb8", (4, 6, 3)), ("bgr8", (3, 2, 3))]
)
def test_image_round_trip_is_exact(distro: Distro, enc: str, shape: tuple) -> None:
    data = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
    m = msgs.Image(stamp_ns=EPOCH_2011_NS, frame_id="cam", encoding=enc, data=data)
    r = wire(rc.image_to_ros(m, distro=distro), "sensor_msgs/Image", distro)
    assert (r.encoding, r.height, r.width, r.step) == (enc, shape[0], shape[1], data[0].size)
    assert rc.image_from_ros(r) == m


@pytest.mark.parametrize("distro", DISTROS)
def test_image_from_ros_honours_padding_and_rejects_malformed(distro: Distro) -> None:
    img = np.arange(6, dtype=np.uint8).reshape(2, 3)
    padded = np.zeros((2, 5), np.uint8)
    padded[:, :3] = img
    r = rc.typestore(distro).types["sensor_msgs/msg/Image"](
        header=rc.header(5, "c", distro),
        height=2,
        width=3,
        encoding="8UC1",
        is_bigendian=0,
        step=5,
        data=padded.reshape(-1),
    )
    out = rc.image_from_ros(wire(r, "sensor_msgs/Image", distro))
    assert out.encoding == "mono8" and out.data.tolist() == img.tolist()
    r.data = r.data[:7]
    with pytest.raises(MessageError, match="data"):
        rc.image_from_ros(r)
    r.data, r.step = padded.reshape(-1), 2  # step shorter than a row
    with pytest.raises(MessageError, match="data"):
        rc.image_from_ros(r)
    r.step, r.encoding = 5, "yuv422"
    with pytest.raises(MessageError, match="encoding"):
        rc.image_from_ros(r)


def _smooth_rgb(h: int = 48, w: int = 64) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x * 4, y * 5, (x + y) * 2], -1).clip(0, 255).astype(np.uint8)


@pytest.mark.parametrize("distro", DISTROS)
@pytest.mark.parametrize("enc", ["rgb8", "bgr8", "mono8"])
def test_compressed_jpeg_round_trip_is_close_and_png_exact(distro: Distro, enc: str) -> None:
    rgb = _smooth_rgb()
    data = {"rgb8": rgb, "bgr8": rgb[..., ::-1].copy(), "mono8": rgb[..., 1].copy()}[enc]
    m = msgs.Image(EPOCH_2011_NS, "cam", enc, data)
    r = wire(rc.compressed_image_to_ros(m, distro=distro), "sensor_msgs/CompressedImage", distro)
    assert r.format == "jpeg" and bytes(r.data[:2]) == b"\xff\xd8"  # a JPEG stream
    back = rc.compressed_image_from_ros(r)
    want = rgb if enc != "mono8" else data  # colour comes back as rgb8
    assert back.encoding == ("mono8" if enc == "mono8" else "rgb8")
    assert back.stamp_ns == EPOCH_2011_NS and back.data.shape == want.shape
    assert np.abs(back.data.astype(int) - want).mean() < 2.0
    png = rc.compressed_image_to_ros(m, fmt="png", distro=distro)
    assert np.array_equal(rc.compressed_image_from_ros(png).data, want)


@pytest.mark.parametrize("payload", [b"", b"not a jpeg at all", b"\xff\xd8\xff\xe0" + bytes(40)])
def test_compressed_garbage_is_one_message_error(payload: bytes) -> None:
    r = rc.typestore(Distro.ROS1).types["sensor_msgs/msg/CompressedImage"](
        header=rc.header(1, "c", Distro.ROS1),
        format="jpeg",
        data=np.frombuffer(payload, np.uint8),
    )
    with pytest.raises(MessageError, match="data"):
        rc.compressed_image_from_ros(r)


def test_compressed_16bit_png_is_rejected() -> None:
    ok, buf = cv2.imencode(".png", np.full((4, 4), 1000, np.uint16))
    assert ok
    r = rc.typestore(Distro.ROS2).types["sensor_msgs/msg/CompressedImage"](
        header=rc.header(1, "c", Distro.ROS2), format="png", data=buf.reshape(-1)
    )
    with pytest.raises(MessageError, match="8-bit"):
        rc.compressed_image_from_ros(r)


# ------------------------------------------------------------------------------ calibration


@pytest.mark.parametrize("distro", DISTROS)
@pytest.mark.parametrize(
    ("model", "coeffs"),
    [("none", ()), ("radtan", (-0.28, 0.07, 1e-4, -2e-5)), ("equidistant", (0.1, -0.2, 0.3, -0.4))],
)
def test_camera_info_round_trip(distro: Distro, model: str, coeffs: tuple) -> None:
    cal = CameraCalibration(
        EPOCH_2011_NS,
        "cam0",
        PinholeCamera(458.654, 457.296, 367.215, 248.375, 752, 480),
        model,
        coeffs,
    )
    r = wire(rc.camera_info_to_ros(cal, distro=distro), "sensor_msgs/CameraInfo", distro)
    assert rc.camera_info_from_ros(r) == cal
    _assert_camera_info_reaches_the_bus(r, cal)


@pytest.mark.parametrize("distro", DISTROS)
def test_camera_info_malformed(distro: Distro) -> None:
    cal = CameraCalibration(1, "c", PinholeCamera(100.0, 100.0, 50.0, 40.0, 100, 80))
    key = "K" if distro is Distro.ROS1 else "k"
    bad_k = rc.camera_info_to_ros(cal, distro=distro)
    setattr(bad_k, key, np.zeros(9))  # an uncalibrated camera (all zeros, as ROS drivers send)
    with pytest.raises(MessageError, match="K"):
        rc.camera_info_from_ros(bad_k)
    short = rc.camera_info_to_ros(cal, distro=distro)
    setattr(short, key, np.ones(4))
    with pytest.raises(MessageError, match="K"):
        rc.camera_info_from_ros(short)
    k3 = rc.camera_info_to_ros(
        CameraCalibration(1, "c", cal.camera, "radtan", (0.1, 0.0, 0.0, 0.0)), distro=distro
    )
    getattr(k3, key.replace("K", "D").replace("k", "d"))[4] = 0.01  # k3 is not modelled
    with pytest.raises(MessageError, match="D"):
        rc.camera_info_from_ros(k3)
    sized = rc.camera_info_to_ros(cal, distro=distro)
    sized.width = 0
    with pytest.raises(MessageError, match="K"):
        rc.camera_info_from_ros(sized)


# ------------------------------------------------------------------------------ imu, poses


@pytest.mark.parametrize("distro", DISTROS)
def test_imu_round_trip_and_non_finite(distro: Distro) -> None:
    m = msgs.Imu(EPOCH_2011_NS, "imu0", (0.1, -0.2, 0.3), (0.5, 9.81, -1.0))
    r = wire(rc.imu_to_ros(m, distro=distro), "sensor_msgs/Imu", distro)
    assert r.orientation_covariance[0] == -1.0
    assert rc.imu_from_ros(r) == m
    r.linear_acceleration.y = float("nan")
    with pytest.raises(MessageError, match="linear_acceleration"):
        rc.imu_from_ros(r)


@pytest.mark.parametrize("distro", DISTROS)
def test_odometry_pose_and_tf_round_trip(distro: Distro) -> None:
    T = _pose(3)
    m = msgs.Odometry(EPOCH_2011_NS, "camera", 4, T, (1.0, 2.0, 3.0), "tracking")
    r = wire(rc.odometry_to_ros(m, distro=distro), "nav_msgs/Odometry", distro)
    assert r.header.frame_id == "world" and r.child_frame_id == "camera"
    back = rc.odometry_from_ros(r, frame_index=4, status="tracking")
    np.testing.assert_allclose(back.T_world_cam, T, atol=1e-12)
    np.testing.assert_allclose(back.velocity_world_m_s, (1.0, 2.0, 3.0), atol=1e-12)
    p = wire(rc.pose_to_ros(7, T, distro=distro), "geometry_msgs/PoseStamped", distro)
    np.testing.assert_allclose(rc.pose_from_ros(p).T_world_cam, T, atol=1e-12)
    tf = wire(
        rc.tf_from_pose(7, T, parent="world", child="cam0", distro=distro),
        "tf2_msgs/TFMessage",
        distro,
    )
    got = rc.transforms_from_ros(tf)
    assert list(got) == [("world", "cam0")]
    np.testing.assert_allclose(got["world", "cam0"], T, atol=1e-12)


@pytest.mark.parametrize("distro", DISTROS)
def test_bad_orientation_is_one_message_error(distro: Distro) -> None:
    r = rc.odometry_to_ros(
        msgs.Odometry(1, "c", 0, np.eye(4), (0.0, 0.0, 0.0), "ok"), distro=distro
    )
    q = r.pose.pose.orientation
    q.w = q.x = q.y = q.z = 0.0
    with pytest.raises(MessageError, match="orientation"):
        rc.odometry_from_ros(r)
    q.w = float("nan")
    with pytest.raises(MessageError, match="orientation"):
        rc.odometry_from_ros(r)
    with pytest.raises(MessageError, match="T_world_cam"):
        rc.pose_to_ros(1, np.full((4, 4), np.nan), distro=distro)


@pytest.mark.parametrize("distro", DISTROS)
@pytest.mark.parametrize("n", [0, 1, 6])
def test_path_round_trip(distro: Distro, n: int) -> None:
    stamps = EPOCH_2011_NS + np.arange(n, dtype=np.int64) * 100_000_000
    Ts = np.array([_pose(i) for i in range(n)]).reshape(n, 4, 4)
    r = wire(rc.path_to_ros(stamps, Ts, distro=distro), "nav_msgs/Path", distro)
    assert r.header.frame_id == "world" and len(r.poses) == n
    got_stamps, got_T = rc.path_from_ros(r)
    assert got_stamps.tolist() == stamps.tolist()
    np.testing.assert_allclose(got_T, Ts, atol=1e-12)


def test_path_malformed() -> None:
    with pytest.raises(MessageError, match="T_world_cam"):
        rc.path_to_ros(np.arange(2), np.eye(4)[None])  # two stamps, one pose
    r = rc.path_to_ros(np.arange(3), np.array([_pose(i) for i in range(3)]))
    r.poses[2].pose.position.x = float("inf")
    with pytest.raises(MessageError, match=r"poses\[2\]"):
        rc.path_from_ros(r)


# ------------------------------------------------------------------------------ point clouds


@pytest.mark.parametrize("distro", DISTROS)
def test_pointcloud_layout_is_what_rviz_reads(distro: Distro) -> None:
    xyz = np.array([[1.0, 2.0, 3.0], [-4.0, 5.5, 6.25]], np.float32)
    rgb = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0]], np.float32)
    r = wire(
        rc.pointcloud_to_ros(xyz, rgb, stamp_ns=EPOCH_2011_NS, distro=distro),
        "sensor_msgs/PointCloud2",
        distro,
    )
    assert [(f.name, f.offset, f.datatype, f.count) for f in r.fields] == [
        ("x", 0, 7, 1),
        ("y", 4, 7, 1),
        ("z", 8, 7, 1),
        ("rgb", 12, 7, 1),
    ]
    assert (r.height, r.width, r.point_step, r.row_step) == (1, 2, 16, 32)
    assert not r.is_bigendian and r.header.frame_id == "world"
    raw = np.asarray(r.data, np.uint8)
    assert raw[12:16].view("<u4")[0] == 0xFF0080  # r=255, g=0, b=round(127.5)=128
    got_xyz, got_rgb = rc.pointcloud_from_ros(r)
    np.testing.assert_array_equal(got_xyz, xyz)
    assert got_rgb.tolist() == [[255, 0, 128], [0, 255, 0]]


def _cloud(
    fields: list[tuple[str, int, int]],
    point_step: int,
    rec: bytes,
    h: int,
    w: int,
    row_step: int,
    big: bool = False,
):
    T = rc.typestore(Distro.ROS1).types
    PF = T["sensor_msgs/msg/PointField"]
    return T["sensor_msgs/msg/PointCloud2"](
        header=rc.header(1, "map", Distro.ROS1),
        height=h,
        width=w,
        fields=[PF(name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
        is_bigendian=big,
        point_step=point_step,
        row_step=row_step,
        data=np.frombuffer(rec, np.uint8),
        is_dense=False,
    )


def test_pointcloud_from_ros_reads_other_layouts() -> None:
    # organised 2x3, 32-byte points (padding + an intensity field), fields out of order,
    # float64 coordinates, uint32 rgba, 8 bytes of row padding, one NaN point (dropped)
    dt = np.dtype(
        {
            "names": ["intensity", "z", "y", "x", "rgba"],
            "formats": ["<f4", "<f8", "<f4", "<f4", "<u4"],
            "offsets": [0, 4, 12, 16, 20],
            "itemsize": 32,
        }
    )
    pts = np.zeros((2, 3), dt)
    xyz = np.arange(18, dtype=np.float64).reshape(2, 3, 3) / 4 - 2
    pts["x"], pts["y"], pts["z"] = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    pts["rgba"] = np.arange(6).reshape(2, 3) * 0x010203 | 0xFF000000
    pts["x"][1, 2] = np.nan
    rows = np.zeros((2, 3 * 32 + 8), np.uint8)
    rows[:, : 3 * 32] = pts.view(np.uint8).reshape(2, -1)
    fields = [("intensity", 0, 7), ("z", 4, 8), ("y", 12, 7), ("x", 16, 7), ("rgba", 20, 6)]
    got_xyz, got_rgb = rc.pointcloud_from_ros(_cloud(fields, 32, rows.tobytes(), 2, 3, 104))
    want = xyz.reshape(-1, 3)[:5].astype(np.float32)
    np.testing.assert_array_equal(got_xyz, want)
    packed = np.arange(5) * 0x010203
    assert (
        got_rgb.tolist()
        == np.stack([packed >> 16 & 255, packed >> 8 & 255, packed & 255], 1).tolist()
    )
    # big-endian, x y z only
    be = np.array([(1.5, -2.0, 3.0)], dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4")])
    out, rgb = rc.pointcloud_from_ros(
        _cloud([("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12, be.tobytes(), 1, 1, 12, big=True)
    )
    assert out.tolist() == [[1.5, -2.0, 3.0]] and rgb is None


@pytest.mark.parametrize(
    ("fields", "step", "nbytes", "row_step", "match"),
    [
        ([("x", 0, 7), ("y", 4, 7)], 12, 24, 24, "fields"),  # no z
        ([("x", 0, 7), ("y", 4, 7), ("z", 10, 7)], 12, 24, 24, "fields.z"),  # past point_step
        ([("x", 0, 7), ("y", 4, 7), ("z", 8, 42)], 12, 24, 24, "fields.z"),  # unknown datatype
        ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12, 20, 24, "data"),  # short data
        ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12, 24, 12, "data"),  # row_step < width * step
        ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("rgb", 12, 2)], 16, 32, 32, "rgb"),  # 1-byte rgb
    ],
)
def test_pointcloud_malformed(fields, step, nbytes, row_step, match) -> None:
    with pytest.raises(MessageError, match=match):
        rc.pointcloud_from_ros(_cloud(fields, step, bytes(nbytes), 1, 2, row_step))


def test_pointcloud_to_ros_rejects_bad_arrays() -> None:
    with pytest.raises(MessageError, match="xyz_world_m"):
        rc.pointcloud_to_ros(np.zeros((3, 2)), None, stamp_ns=1)
    with pytest.raises(MessageError, match="xyz_world_m"):
        rc.pointcloud_to_ros(np.array([[0.0, np.inf, 0.0]]), None, stamp_ns=1)
    with pytest.raises(MessageError, match="rgb"):
        rc.pointcloud_to_ros(np.zeros((3, 3)), np.zeros((2, 3)), stamp_ns=1)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 300),
    log_scale=st.floats(-30, 30),
    seed=st.integers(0, 2**16),
    distro=st.sampled_from(DISTROS),
)
def test_pointcloud_round_trip_property(
    n: int, log_scale: float, seed: int, distro: Distro
) -> None:
    """Any number of points (none included), at tiny and huge scales, comes back exactly as
    float32; colours (out-of-range and NaN clipped) come back as their 8-bit values."""
    rng = np.random.default_rng(seed)
    xyz = (rng.normal(size=(n, 3)) * np.exp(log_scale)).astype(np.float32)
    rgb = rng.uniform(-0.5, 1.5, (n, 3))
    if n:
        rgb[0, 0] = np.nan
    r = wire(
        rc.pointcloud_to_ros(xyz, rgb, stamp_ns=0, distro=distro), "sensor_msgs/PointCloud2", distro
    )
    got_xyz, got_rgb = rc.pointcloud_from_ros(r)
    np.testing.assert_array_equal(got_xyz, xyz)
    want = np.round(np.clip(np.nan_to_num(rgb), 0, 1) * 255).astype(np.uint8)
    np.testing.assert_array_equal(got_rgb, want)


# -------------------------------------------------------------------------- depth, stats


@pytest.mark.parametrize("distro", DISTROS)
def test_depth_is_32fc1_metres_with_nan_holes(distro: Distro) -> None:
    d = np.array([[0.0, 1.5], [20.25, 0.0]], np.float32)
    m = msgs.DepthMap(EPOCH_2011_NS, "cam", 3, "metric", d, (d > 0).astype(np.float32), "mogs")
    r = wire(rc.depth_to_ros(m, distro=distro), "sensor_msgs/Image", distro)
    assert (r.encoding, r.step, r.is_bigendian) == ("32FC1", 8, 0)
    raw = np.asarray(r.data, np.uint8).view("<f4").reshape(2, 2)
    assert np.isnan(raw[0, 0]) and np.isnan(raw[1, 1]) and raw[1, 0] == 20.25
    back = rc.depth_from_ros(r, keyframe_id=3, source="mogs")
    np.testing.assert_array_equal(back.depth, d)
    with pytest.raises(MessageError, match="kind"):
        rc.depth_to_ros(msgs.DepthMap(1, "c", 0, "relative_depth", d, d, "x"), distro=distro)


@pytest.mark.parametrize("distro", DISTROS)
def test_mapstats_round_trip(distro: Distro) -> None:
    m = msgs.MapStats(EPOCH_2011_NS, "world", 4, 12345, 4, 60, 0.0123, 24.5, {"ms_per_kf": 812.5})
    r = wire(rc.mapstats_to_ros(m, distro=distro), "diagnostic_msgs/DiagnosticArray", distro)
    assert rc.mapstats_from_ros(r) == m
    r.status[0].values[1].value = "many"
    with pytest.raises(MessageError, match="n_gaussians"):
        rc.mapstats_from_ros(r)


@settings(max_examples=30, deadline=None)
@given(
    h=st.integers(1, 12),
    w=st.integers(1, 12),
    enc=st.sampled_from(["mono8", "rgb8", "bgr8"]),
    stamp_ns=st.integers(0, (1 << 31) * 1_000_000_000 - 1),
    distro=st.sampled_from(DISTROS),
)
def test_image_round_trip_property(h: int, w: int, enc: str, stamp_ns: int, distro: Distro) -> None:
    shape = (h, w) if enc == "mono8" else (h, w, 3)
    data = np.random.default_rng(h * 13 + w).integers(0, 256, shape, dtype=np.uint8)
    m = msgs.Image(stamp_ns, "c", enc, data)
    assert (
        rc.image_from_ros(wire(rc.image_to_ros(m, distro=distro), "sensor_msgs/Image", distro)) == m
    )


@settings(max_examples=40, deadline=None)
@given(
    fx=st.floats(1e-3, 1e6),
    aspect=st.floats(0.5, 2.0),
    w=st.integers(1, 20000),
    h=st.integers(1, 20000),
    coeffs=st.lists(st.floats(-2, 2), min_size=4, max_size=4),
    distro=st.sampled_from(DISTROS),
)
def test_camera_info_round_trip_property(fx, aspect, w, h, coeffs, distro) -> None:
    """Tiny and huge focal lengths and image sizes, any radtan coefficients, come back exactly;
    a NaN anywhere in K is one error naming K."""
    cam = PinholeCamera(fx, fx * aspect, w / 2 - 0.5, h / 2 - 0.5, w, h)
    model = "radtan" if any(coeffs) else "none"
    cal = CameraCalibration(0, "c", cam, model, tuple(coeffs) if any(coeffs) else ())
    r = wire(rc.camera_info_to_ros(cal, distro=distro), "sensor_msgs/CameraInfo", distro)
    assert rc.camera_info_from_ros(r) == cal
    _assert_camera_info_reaches_the_bus(r, cal)
    key = "K" if distro is Distro.ROS1 else "k"
    bad_k = np.array(getattr(r, key), dtype=np.float64)
    bad_k[4] = np.nan
    setattr(r, key, bad_k)
    with pytest.raises(MessageError, match="K"):
        rc.camera_info_from_ros(r)


@settings(max_examples=30, deadline=None)
@given(n=st.integers(0, 40), log_scale=st.floats(-20, 20), distro=st.sampled_from(DISTROS))
def test_path_round_trip_property(n: int, log_scale: float, distro: Distro) -> None:
    """Any number of poses (none included) at tiny and huge translations."""
    stamps = np.arange(n, dtype=np.int64) * 7 + 3
    Ts = np.array([_pose(i) for i in range(n)]).reshape(n, 4, 4)
    Ts[:, :3, 3] *= np.exp(log_scale)
    got_stamps, got_T = rc.path_from_ros(
        wire(rc.path_to_ros(stamps, Ts, distro=distro), "nav_msgs/Path", distro)
    )
    assert got_stamps.tolist() == stamps.tolist()
    np.testing.assert_allclose(got_T, Ts, rtol=1e-12, atol=1e-12 * max(1.0, np.exp(log_scale)))


def _assert_camera_info_reaches_the_bus(r, cal: CameraCalibration) -> None:
    """A ROS CameraInfo onto the bus, with T_imu_cam from /tf_static: what the frontend takes."""
    T = np.eye(4)
    T[:3, 3] = (0.1, -0.02, 0.03)
    c = rc.camera_info_from_ros(r)
    m = c.message(T_imu_cam=T, source="ros1:/cam0/camera_info")
    back = msgs.decode(msgs.encode("/camera/info", m)).msg
    assert (back.width, back.height) == (cal.camera.width, cal.camera.height)
    assert back.distortion_model == c.distortion_model
    np.testing.assert_array_equal(back.K, cal.camera.K)
    np.testing.assert_array_equal(back.distortion_coeffs, np.asarray(c.distortion_coeffs, float))
    np.testing.assert_array_equal(back.T_imu_cam, T)
