"""Frontend node in one process over an in-process bus: /imu + /camera/image in, odometry and
keyframes out; params validated; frontend counters in /diagnostics."""

from __future__ import annotations

import time

import numpy as np
import pytest

from bridges.sources import camera_info_of, open_sequence
from mogs_node import msgs
from mogs_node.bus import Publisher, Subscriber
from mogs_node.errors import ConfigError
from mogs_node.frontend.frontend import Frontend
from mogs_node.frontend.node import FrontendNode, FrontendNodeParams
from mogs_node.frontend.preintegration import ImuNoise
from mogs_node.geometry import make_T, so3_exp
from mogs_node.sim import GRAVITY_WORLD_M_S2, SimConfig, make_sequence


def _sim_info(**over: object) -> msgs.CameraInfo:
    """The sim rig's calibration at 621x188 as the player publishes it."""
    seq = open_sequence("sim", sim={"n_frames": 2, "width": 621, "height": 188})
    info = camera_info_of(seq)
    return msgs.CameraInfo(**{**info.__dict__, **over})


def test_params_build_and_validation():
    info = _sim_info()
    p = FrontendNodeParams(estimator={"window_size": 5}, tracker={"max_features": 80})
    fp, cam, T = p.build(info=info)
    assert fp.estimator.window_size == 5 and fp.tracker.max_features == 80
    assert cam.pinhole.width == 621 and T.shape == (4, 4)
    np.testing.assert_array_equal(T, info.T_imu_cam)
    with pytest.raises(ConfigError, match="estimator"):
        FrontendNodeParams(estimator={"no_such_knob": 1}).build(info=info)
    with pytest.raises(ConfigError, match="T_imu_cam"):
        FrontendNodeParams(T_imu_cam=(1.0,) * 16).build(info=info)
    with pytest.raises(ConfigError, match="T_imu_cam"):
        FrontendNodeParams(T_imu_cam=(1.0, 2.0))
    fp, _, _ = FrontendNodeParams(ground={"camera_height_m": 1.65}).build(info=info)
    assert fp.ground.enabled and fp.ground.camera_height_m == 1.65
    # off unless the height is given (the sim's CameraInfo carries none)
    assert not FrontendNodeParams().build(info=info)[0].ground.enabled
    with pytest.raises(ConfigError, match="ground"):
        FrontendNodeParams(ground={"height": 1.65}).build(info=info)
    with pytest.raises(ConfigError, match="camera_height_m"):
        FrontendNodeParams(ground={"camera_height_m": -1.0}).build(info=info)
    # the road needs rectified images: a distorted camera with the road on is refused
    params, cam, T = FrontendNodeParams(
        ground={"camera_height_m": 1.65},
        distortion_model="radtan",
        distortion_coeffs=(0.1, 0.0, 0.0, 0.0),
    ).build(info=info)
    with pytest.raises(ConfigError, match="rectified"):
        Frontend(params, cam, T)


def test_calibration_from_the_camera_info_and_launch_overrides():
    info = _sim_info(
        camera_height_m=1.65,
        imu_noise={"gyro_noise_rad_s_rthz": 1e-4, "accel_walk_m_s3_rthz": 2e-3},
    )
    # nothing typed: everything from the message; noise densities times the inflation (2)
    fp, cam, T = FrontendNodeParams().build("fe", info)
    K = info.K
    assert (cam.pinhole.fx_px, cam.pinhole.cy_px) == (K[0, 0], K[1, 2])
    assert fp.ground.camera_height_m == 1.65
    assert fp.imu.gyro_noise_rad_s_rthz == pytest.approx(2e-4)
    assert fp.imu.accel_walk_m_s3_rthz == pytest.approx(4e-3)
    assert fp.imu.accel_noise_m_s2_rthz == ImuNoise().accel_noise_m_s2_rthz  # not in the message
    # a launch value overrides the message's, field by field
    T_launch = np.eye(4)
    T_launch[:3, 3] = (0.1, 0.2, 0.3)
    fp, cam, T = FrontendNodeParams(
        fx_px=400.0,
        T_imu_cam=tuple(T_launch.ravel()),
        imu={"gyro_noise_rad_s_rthz": 5e-4},
        ground={"camera_height_m": 0.0},
    ).build("fe", info)
    assert cam.pinhole.fx_px == 400.0 and cam.pinhole.fy_px == K[1, 1]
    np.testing.assert_array_equal(T, T_launch)
    assert fp.imu.gyro_noise_rad_s_rthz == 5e-4 and not fp.ground.enabled
    # what neither gives is one error naming the value
    with pytest.raises(ConfigError, match=r"fe\.T_imu_cam: not in the launch file.*unknown to"):
        FrontendNodeParams().build("fe", _sim_info(T_imu_cam=None, source="a bag"))
    with pytest.raises(ConfigError, match=r"fe\.fx_px: .*no /camera/info"):
        FrontendNodeParams().build("fe")
    assert not FrontendNodeParams(fx_px=1.0).overrides_all()


def test_typed_T_imu_cam_is_cleaned_or_refused():
    """Issue 28: six decimals are accepted and made orthonormal; 1e-2 off is one clear error."""
    info = _sim_info()
    R = so3_exp(np.array([0.3, -0.2, 1.1]))
    typed = np.round(make_T(R, [1.08, -0.25, 0.73]), 6)
    assert np.abs(typed[:3, :3] @ typed[:3, :3].T - np.eye(3)).max() > 1e-7  # not orthonormal
    _, _, T = FrontendNodeParams(T_imu_cam=tuple(typed.ravel())).build("frontend", info)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(T, typed, atol=2e-6)
    bad = typed.copy()
    bad[0, 1] += 1e-2
    with pytest.raises(ConfigError, match=r"frontend\.T_imu_cam: the rotation is not orthonormal"):
        FrontendNodeParams(T_imu_cam=tuple(bad.ravel())).build("frontend", info)


def test_node_streams_odometry_and_keyframes(inproc_bus):
    bus, ctx = inproc_bus
    seq = make_sequence(SimConfig(seed=0, n_frames=2, width=621, height=188))
    img = seq.render(0).rgb
    c = seq.camera
    params = {
        "fx_px": c.fx_px,
        "fy_px": c.fy_px,
        "cx_px": c.cx_px,
        "cy_px": c.cy_px,
        "width": c.width,
        "height": c.height,
        "T_imu_cam": [float(x) for x in seq.T_imu_cam.ravel()],
        "mode": "vi",
        # parked: keyframes only when asked for at standstill (round 8), to check their messages
        "keyframes": {"hold_at_standstill": False},
    }
    node = FrontendNode("frontend", params, bus, context=ctx, diagnostics_period_s=0)
    watcher = Subscriber(bus, context=ctx)
    for topic in ("/frontend/odometry", "/frontend/keyframe", "/frontend/refined_pose"):
        watcher.subscribe(topic)
    pub = Publisher(bus, context=ctx)
    try:
        assert pub.wait_for_subscriber("/imu", 5) and pub.wait_for_subscriber("/camera/image", 5)
        assert node._pub.wait_for_subscriber("/frontend/odometry", 5)
        # a parked car: 0.5 s of IMU, then 20 frames at 10 Hz with IMU in between; the static
        # initialisation needs 1 s of IMU, so the first frames are acknowledged as 'initializing'
        rng = np.random.default_rng(0)
        f_true = seq.T_world_imu[0, :3, :3].T @ -GRAVITY_WORLD_M_S2
        t_imu = 1_000_000_000 + np.arange(int(2.8 * 200)) * 5_000_000
        t_img = t_imu[0] + 500_000_000 + np.arange(20) * 100_000_000
        got: dict[str, list] = {t: [] for t in watcher.topics}
        k = 0

        def drain() -> None:
            env = watcher.receive(timeout_ms=5)
            while env is not None:
                got[env.topic].append(env.msg)
                env = watcher.receive(timeout_ms=5)

        for i, t in enumerate(t_img):
            while k < len(t_imu) and t_imu[k] <= t:
                g = tuple(float(x) for x in rng.normal(0, 2e-3, 3))
                a = tuple(float(x) for x in f_true + rng.normal(0, 0.03, 3))
                pub.publish(
                    "/imu",
                    msgs.Imu(stamp_ns=int(t_imu[k]), frame_id="imu", gyro_rad_s=g, accel_m_s2=a),
                )
                k += 1
            pub.publish(
                "/camera/image",
                msgs.Image(stamp_ns=int(t), frame_id="cam", encoding="rgb8", data=img),
            )
            deadline = time.monotonic() + 10
            while node.frontend.counters["frames"] < i + 1 and time.monotonic() < deadline:
                node.spin_once(20)
                drain()
        for _ in range(20):
            node.spin_once(10)
            drain()
        diag = node.diagnostics()
    finally:
        watcher.close()
        pub.close(0)
        node.close()
    odo, kfs = got["/frontend/odometry"], got["/frontend/keyframe"]
    assert node.frontend.counters["static_inits"] == 1
    # one odometry per image, with its stamp, also while initialising (flow control)
    assert [o.stamp_ns for o in odo] == [int(t) for t in t_img]
    status = [o.status for o in odo]
    assert status[0] == "initializing" and status[-1] == "tracking"
    n_init = status.index("tracking")
    assert 3 <= n_init <= 8 and all(s == "tracking" for s in status[n_init:])
    np.testing.assert_allclose(odo[0].T_world_cam, np.eye(4))  # no pose yet: identity
    assert all(np.all(np.isfinite(o.T_world_cam)) for o in odo)
    assert kfs and kfs[0].image.shape == img.shape and kfs[0].K.shape == (3, 3)
    assert diag.counters["frontend_static_inits"] == 1
    # refined keyframe poses: keyframes' stamps only, each sent when the window moved it
    first = {kf.stamp_ns: kf.T_world_cam for kf in kfs}
    for m in got["/frontend/refined_pose"]:
        assert m.stamp_ns in first and m.frame_id == "world" and np.isfinite(m.T_world_cam).all()
        assert np.linalg.norm(m.T_world_cam[:3, 3] - first[m.stamp_ns][:3, 3]) < 0.02  # parked


def test_node_waits_for_the_camera_info(inproc_bus):
    """No calibration typed: images before /camera/info are acknowledged 'no_calibration' and
    counted, IMU samples wait; the CameraInfo starts the frontend with the source's values."""
    bus, ctx = inproc_bus
    info = _sim_info()
    node = FrontendNode("frontend", {}, bus, context=ctx, diagnostics_period_s=0)
    watcher = Subscriber(bus, context=ctx)
    watcher.subscribe("/frontend/odometry")
    pub = Publisher(bus, context=ctx)
    img = np.zeros((188, 621, 3), np.uint8)

    def spin_until(cond) -> None:
        deadline = time.monotonic() + 10
        while not cond() and time.monotonic() < deadline:
            node.spin_once(20)

    try:
        for topic in ("/imu", "/camera/image", "/camera/info"):
            assert pub.wait_for_subscriber(topic, 5)
        assert node._pub.wait_for_subscriber("/frontend/odometry", 5)
        imu = msgs.Imu(stamp_ns=10, frame_id="imu", gyro_rad_s=(0.0,) * 3, accel_m_s2=(0, 0, 9.8))
        pub.publish("/imu", imu)
        pub.publish("/camera/image", msgs.Image(20, "cam", "rgb8", img))
        spin_until(lambda: node.counters["frames_without_calibration"] == 1)
        env = watcher.receive(timeout_ms=2000)
        assert node.frontend is None and len(node._imu_waiting) == 1
        pub.publish("/camera/info", info)
        spin_until(lambda: node._calibrated)
        assert node.frontend is None  # built at the first image: its mode depends on the inputs
        pub.publish("/camera/image", msgs.Image(30, "cam", "rgb8", img))
        spin_until(lambda: node.frontend is not None)
        assert node.mode == "vi"  # IMU came before the image
        assert node.frontend is not None and not node._imu_waiting
        assert node.frontend.counters["imu_samples"] == 1  # the waiting sample went in
        assert node.frontend.camera.pinhole.fx_px == info.K[0, 0]
        np.testing.assert_array_equal(node.frontend.T_imu_cam, info.T_imu_cam)
        # the same calibration again (the player repeats it) changes nothing, a new one is ignored
        pub.publish("/camera/info", info)
        pub.publish("/camera/info", _sim_info(width=620))
        spin_until(lambda: node.counters["camera_info_ignored"] == 1)
        assert node.counters["camera_info_ignored"] == 1
    finally:
        watcher.close()
        pub.close(0)
        node.close()
    assert env is not None and env.msg.status == "no_calibration" and env.msg.stamp_ns == 20


def test_camera_only_needs_no_T_imu_cam():
    """KITTI odometry: no IMU, no T_imu_cam; the camera-only frontend builds without it."""
    info = _sim_info(T_imu_cam=None, camera_height_m=1.65, source="calib.txt")
    fe = FrontendNodeParams(camera_only={"min_parallax_px": 30.0}).build_monocular(
        "fe", info, given_poses=False
    )
    assert fe.T_imu_cam is None and fe.params.ground.camera_height_m == 1.65
    assert fe.params.min_parallax_px == 30.0 and fe.params.points.max_reproj_px == 1.5
    np.testing.assert_allclose(fe.normal_cam, [0.0, 1.0, 0.0])  # a level rectified camera
    with pytest.raises(ConfigError, match=r"fe\.T_imu_cam: not in the launch file"):
        FrontendNodeParams().build("fe", info)
    with pytest.raises(ConfigError, match="camera_only.ground"):
        FrontendNodeParams(camera_only={"ground": {}}).build_monocular(
            "fe", info, given_poses=False
        )
