"""Frontend node in one process over an in-process bus: /imu + /camera/image in, odometry and
keyframes out; params validated; frontend counters in /diagnostics."""

from __future__ import annotations

import time

import numpy as np
import pytest

from mogs_node import msgs
from mogs_node.bus import Publisher, Subscriber
from mogs_node.errors import ConfigError
from mogs_node.frontend.frontend import Frontend
from mogs_node.frontend.node import FrontendNode, FrontendNodeParams
from mogs_node.sim import GRAVITY_WORLD_M_S2, SimConfig, make_sequence


def test_params_build_and_validation():
    p = FrontendNodeParams(estimator={"window_size": 5}, tracker={"max_features": 80})
    fp, cam, T = p.build()
    assert fp.estimator.window_size == 5 and fp.tracker.max_features == 80
    assert cam.pinhole.width == 621 and T.shape == (4, 4)
    with pytest.raises(ConfigError, match="estimator"):
        FrontendNodeParams(estimator={"no_such_knob": 1}).build()
    with pytest.raises(ConfigError, match="T_imu_cam"):
        FrontendNodeParams(T_imu_cam=(1.0,) * 16).build()
    with pytest.raises(ConfigError, match="T_imu_cam"):
        FrontendNodeParams(T_imu_cam=(1.0, 2.0))
    fp, _, _ = FrontendNodeParams(ground={"camera_height_m": 1.65}).build()
    assert fp.ground.enabled and fp.ground.camera_height_m == 1.65
    assert not FrontendNodeParams().build()[0].ground.enabled  # off unless the height is given
    with pytest.raises(ConfigError, match="ground"):
        FrontendNodeParams(ground={"height": 1.65}).build()
    with pytest.raises(ConfigError, match="camera_height_m"):
        FrontendNodeParams(ground={"camera_height_m": -1.0}).build()
    # the road needs rectified images: a distorted camera with the road on is refused
    params, cam, T = FrontendNodeParams(
        ground={"camera_height_m": 1.65},
        distortion_model="radtan",
        distortion_coeffs=(0.1, 0.0, 0.0, 0.0),
    ).build()
    with pytest.raises(ConfigError, match="rectified"):
        Frontend(params, cam, T)


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
    }
    node = FrontendNode("frontend", params, bus, context=ctx, diagnostics_period_s=0)
    watcher = Subscriber(bus, context=ctx)
    for topic in ("/frontend/odometry", "/frontend/keyframe"):
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
        got: dict[str, list] = {"/frontend/odometry": [], "/frontend/keyframe": []}
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
