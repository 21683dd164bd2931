"""Platform profiles: motion bounds, rejected initialisations, resets by reason, keyframe cap."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError
from mogs_node.eval.frontend_runs import run_frontend
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.estimator_types import EstimatorParams, outlier_gate_px
from mogs_node.frontend.frontend import Frontend, FrontendParams
from mogs_node.frontend.keyframes import keeps_in_window
from mogs_node.frontend.platform import (
    PLATFORMS,
    PlatformBounds,
    PlatformChooser,
    detect_walk,
    motion_violation,
    platform_profile,
)
from mogs_node.frontend.time_offset import TimeOffsetParams
from mogs_node.geometry import make_T, so3_exp
from mogs_node.sim import SimConfig, make_sequence


def _states(v: np.ndarray, rate_rad_s: float = 0.0, dt_s: float = 0.1):
    """Two window states ``dt_s`` apart with velocities ``v`` [2, 3] and a yaw rate."""
    stamps = np.array([0, int(dt_s * 1e9)], np.int64)
    T = np.stack([np.eye(4), make_T(so3_exp(np.array([0, 0, rate_rad_s * dt_s])), np.zeros(3))])
    return stamps, T, np.asarray(v, float)


def test_each_bound_is_named() -> None:
    hh = PLATFORMS["handheld"]
    walk = np.array([[1.4, 0, 0.1], [1.4, 0, -0.1]])
    assert motion_violation(hh, *_states(walk, rate_rad_s=1.5)) is None
    assert motion_violation(hh, *_states(walk * 4)).startswith("speed: 5.6 m/s > 4 m/s")
    up = np.array([[0.5, 0, 3.0], [0.5, 0, 3.0]])
    assert motion_violation(hh, *_states(up)).startswith("vertical_speed")
    jump = np.array([[0.0, 0, 0], [3.0, 0, 0]])
    assert motion_violation(hh, *_states(jump)).startswith("acceleration: 30.0 m/s^2")
    spin = motion_violation(hh, *_states(walk, rate_rad_s=10.0))
    assert spin.startswith("angular_rate: 573 deg/s")
    # the same spin is a plausible drone, the same speed a plausible car
    assert motion_violation(PLATFORMS["drone"], *_states(walk, rate_rad_s=7.0)) is None
    assert motion_violation(PLATFORMS["car"], *_states(walk * 4)) is None
    nan = walk.copy()
    nan[1, 0] = np.nan
    assert motion_violation(hh, *_states(nan)) == "state: not finite"


@settings(max_examples=40, deadline=None)
@given(speed=st.floats(0.0, 100.0), limit=st.floats(0.1, 80.0))
def test_speed_bound_property(speed: float, limit: float) -> None:
    prof = platform_profile("car", PlatformBounds(max_speed_m_s=limit))
    v = np.array([[speed, 0.0, 0.0], [speed, 0.0, 0.0]])
    r = motion_violation(prof, *_states(v))
    assert (r is not None and r.startswith("speed")) == (speed > limit)


def test_profiles_and_overrides_are_validated() -> None:
    assert platform_profile("drone", PlatformBounds(max_speed_m_s=5)).max_speed_m_s == 5.0
    assert platform_profile("drone").max_speed_m_s == PLATFORMS["drone"].max_speed_m_s
    with pytest.raises(ConfigError, match="frontend.platform"):
        platform_profile("boat")
    with pytest.raises(ConfigError, match="bounds must be positive"):
        platform_profile("car", PlatformBounds(max_accel_m_s2=-1))
    with pytest.raises(ConfigError, match="frontend.platform"):
        Frontend(
            FrontendParams(platform="boat"),
            CameraModel(make_sequence(SimConfig(n_frames=1, width=64, height=32)).camera),
            np.eye(4),
        )


@pytest.fixture(scope="module")
def car_drive():
    """A car at ~10 m/s from the first frame: 7 s at 621x188."""
    seq = make_sequence(SimConfig(seed=0, n_frames=71, width=621, height=188))
    return seq, [seq.render(i).rgb for i in range(len(seq))]


def _run(seq, images, platform: str, **bounds):
    params = FrontendParams(
        platform=platform,
        init_mode="dynamic",
        time_offset=TimeOffsetParams(enabled=False),
        bounds=PlatformBounds(**bounds),
    )
    fe = Frontend(params, CameraModel(seq.camera), seq.T_imu_cam)
    outs = run_frontend(
        fe, seq.stamps_ns, images, seq.imu_stamps_ns, seq.imu_gyro_rad_s, seq.imu_accel_m_s2
    )
    return fe, outs


def test_init_breaking_the_speed_bound_is_rejected_and_the_frontend_waits(
    car_drive, caplog: pytest.LogCaptureFixture
) -> None:
    """A car at 10 m/s under a 4 m/s bound: every chosen hypothesis is rejected with the bound
    named, nothing is published, each next window is tried again; with the car's bounds the same
    drive initialises at its true speed."""
    seq, images = car_drive
    with caplog.at_level(logging.WARNING, logger="mogs_node.frontend"):
        fe, outs = _run(seq, images, "car", max_speed_m_s=4.0)
    rej = fe._dyn_init.rejections
    assert rej.get("speed", 0) >= 2  # rejected, then rejected again on a later window
    assert fe._dyn_init.last_rejection.startswith("speed: ")
    assert "> 4 m/s" in fe._dyn_init.last_rejection
    assert not fe.initialized and fe.counters["dynamic_inits"] == 0
    assert all(o.T_world_cam is None and o.keyframe is None for o in outs)
    msgs = [r.getMessage() for r in caplog.records if "initialisation rejected" in r.getMessage()]
    assert len(msgs) == 1 and "speed" in msgs[0]  # logged once, counted every time
    fe, outs = _run(seq, images, "car")
    assert fe.counters["dynamic_inits"] == 1 and fe._dyn_init.rejections == {}
    speed = np.linalg.norm(fe.estimator.state().velocity_world_m_s)
    true = np.linalg.norm(seq.velocity_world_m_s[-1])
    assert abs(speed / true - 1) < 0.15


def test_keyframe_rate_cap(car_drive) -> None:
    seq, images = car_drive
    fe, outs = _run(seq, images, "car", keyframe_min_interval_s=0.45)
    t = np.array([o.stamp_ns for o in outs if o.keyframe is not None]) * 1e-9
    assert len(t) >= 3 and np.diff(t).min() >= 0.45 - 1e-6
    assert fe.figures()["keyframes_per_s"] <= 1 / 0.45 * 1.01


def test_figures_reach_summary_and_report(car_drive, tmp_path) -> None:
    """The frontend's figures, as the report node receives them from ``/diagnostics``
    (``frontend_<name>``), become ``summary.json``'s ``frontend`` section and a report line."""
    from bridges.sources import camera_info_of, open_sequence
    from mogs_node.frontend.node import FrontendNodeParams
    from mogs_node.report.collect import RunCollector, summarise, write_report

    seq, images = car_drive
    fe, _ = _run(seq, images, "car", max_speed_m_s=4.0)
    fe.counters["resets_speed"] = 2  # as _reset counts them
    diag = {f"frontend_{k}": float(v) for k, v in fe.counters.items()}
    diag.update({f"frontend_{k}": v for k, v in fe.figures().items()})
    c = RunCollector()
    c.frontend_figures = {k[9:]: v for k, v in diag.items()}
    for k in range(5):
        c.gt_poses[k] = c.odometry[k] = make_T(np.eye(3), np.array([k, 0.1 * k * k, 0.0]))
    out = summarise(c)["frontend"]
    assert out["time_offset_ms"] == 0.0 and out["resets"] == {"speed": 2}
    assert out["init_rejected"]["speed"] >= 1
    assert out["keyframes_per_s"] == 0.0  # never initialised: no keyframe
    write_report(tmp_path / "report.md", summarise(c))
    assert "Camera-IMU time offset 0.0 ms" in (tmp_path / "report.md").read_text()
    # the launch parameters of the node build the same groups
    # the sim rig's calibration as the player publishes it
    info = camera_info_of(open_sequence("sim", sim={"n_frames": 2, "width": 621, "height": 188}))
    p, _, _ = FrontendNodeParams(
        platform="handheld",
        bounds={"max_speed_m_s": 3},
        time_offset={"enabled": False, "search_ms": 80},
    ).build(info=info)
    assert p.platform == "handheld" and p.bounds.max_speed_m_s == 3.0
    assert not p.time_offset.enabled and p.time_offset.search_ms == 80.0
    with pytest.raises(ConfigError, match="frontend.time_offset"):
        FrontendNodeParams(time_offset={"search": 1}).build(info=info)


def _imu(kind: str, seconds: float = 6.0, rate_hz: float = 200.0, seed: int = 0):
    """Specific force [N, 3] (IMU frame, z up at rest) of a walk, a car on a bumpy road or a
    hovering multicopter, with white noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    a = np.tile([0.0, 0.0, 9.81], (len(t), 1)) + rng.normal(0, 0.05, (len(t), 3))
    if kind == "walk":  # 2 cm step bounce at 1.8 Hz: a vertical (2 pi f)^2 0.02 = 2.6 m/s^2
        a[:, 2] += (2 * np.pi * 1.8) ** 2 * 0.02 * np.cos(2 * np.pi * 1.8 * t)
    elif kind == "car":  # body bounce at 1.2 Hz, road noise, braking and accelerating
        a[:, 2] += 0.4 * np.sin(2 * np.pi * 1.2 * t) + rng.normal(0, 0.3, len(t))
        a[:, 0] += 2.0 * np.sin(2 * np.pi * 0.1 * t)
    elif kind == "drone":  # rotor vibration (aliased to 40 Hz at 200 Hz) and slow manoeuvres
        a += 1.5 * np.sin(2 * np.pi * 40.0 * t)[:, None] + rng.normal(0, 0.3, (len(t), 3))
        a[:, 1] += 1.0 * np.sin(2 * np.pi * 0.3 * t)
    return (t * 1e9).astype(np.int64), a


@pytest.mark.parametrize("kind", ["walk", "car", "drone", "still"])
def test_walk_detected_only_in_a_walk(kind: str) -> None:
    t, a = _imu(kind)
    det = detect_walk(t, a)
    assert det is not None and det.walking == (kind == "walk")
    if kind == "walk":
        assert abs(det.cadence_hz - 1.8) <= 0.25 and abs(det.amplitude_m_s2 - 2.56) < 0.5
    assert detect_walk(t[t < 3e9], a[t < 3e9]) is None  # less than the 4 s window


@settings(max_examples=25, deadline=None)
@given(
    cadence=st.floats(1.5, 2.5),
    bounce_m=st.floats(0.0, 0.04),
    yaw=st.floats(-np.pi, np.pi),
)
def test_walk_detection_property(cadence: float, bounce_m: float, yaw: float) -> None:
    """Any attitude (the norm of the specific force), any cadence in the band: a walk exactly
    when the bounce's acceleration amplitude clears the threshold (away from it)."""
    t = np.arange(0.0, 5.0, 1 / 200.0)
    amp = (2 * np.pi * cadence) ** 2 * bounce_m
    up = np.array([np.sin(yaw) * 0.3, np.cos(yaw) * 0.3, 1.0])
    up /= np.linalg.norm(up)
    a = np.outer(9.81 + amp * np.cos(2 * np.pi * cadence * t), up)
    det = detect_walk((t * 1e9).astype(np.int64), a)
    if amp > 1.2:
        assert det.walking
    elif amp < 0.5:
        assert not det.walking


def test_auto_platform_switches_to_handheld_on_a_walk() -> None:
    car = PlatformChooser("car")
    assert not car.auto and car.profile.name == "car"
    t, a = _imu("walk", seconds=8.0)
    assert not car.add_imu(t, a) and car.profile.name == "car"  # a named platform stays
    for kind, expect in (("walk", "handheld"), ("car", "car"), ("drone", "car")):
        ch = PlatformChooser("auto", PlatformBounds(max_speed_m_s=3.0), default="car")
        t, a = _imu(kind, seconds=8.0)
        changed = [ch.add_imu(t[i : i + 20], a[i : i + 20]) for i in range(0, len(t), 20)]
        assert ch.profile.name == expect and sum(changed) == (expect == "handheld")
        if expect == "handheld":
            assert ch.profile.max_speed_m_s == 3.0  # the launch's overrides are kept
            assert 4.0 <= (t[changed.index(True) * 20 + 19]) * 1e-9 <= 4.6  # after one window
    with pytest.raises(ConfigError, match="frontend.platform"):
        PlatformChooser("auto", default="boat")


def test_auto_platform_in_the_frontend_on_the_sim_walk() -> None:
    """``platform: auto`` on the sim's handheld walk: the frontend takes the handheld bounds and
    keyframe cap once 4 s of IMU show the step cadence; on the car drive it keeps the car's."""
    for motion, expect in (("handheld", "handheld"), ("car", "car")):
        seq = make_sequence(SimConfig(motion=motion, n_frames=45, width=64, height=32))
        fe = Frontend(FrontendParams(platform="auto"), CameraModel(seq.camera), seq.T_imu_cam)
        assert fe.estimator.params.keep_visual_prior is False  # the car's until a walk shows
        imgs = [np.zeros((32, 64, 3), np.uint8)] * len(seq)
        run_frontend(
            fe, seq.stamps_ns, imgs, seq.imu_stamps_ns, seq.imu_gyro_rad_s, seq.imu_accel_m_s2
        )
        assert fe.profile.name == expect and fe._dyn_init.profile.name == expect
        walk = expect == "handheld"  # the walk's estimator settings go to both
        assert fe.estimator.params.keep_visual_prior is walk
        assert fe._dyn_init.estimator_params.keep_visual_prior is walk
        assert fe.figures()["platform_walk_detected"] == float(expect == "handheld")


@pytest.mark.parametrize("interval", [0.0, 0.3])
def test_window_spacing(car_drive, interval: float) -> None:
    """``window_interval_s``: the frames between published keyframes stay in the window one per
    interval (parallax and track loss not triggering here); 0 keeps every frame."""
    seq, images = car_drive
    params = FrontendParams(
        platform="car",
        init_mode="dynamic",
        time_offset=TimeOffsetParams(enabled=False),
        bounds=PlatformBounds(keyframe_min_interval_s=1.5),
        window_interval_s=interval,
        window_parallax_px=1e9,
        window_tracked_ratio=0.0,
    )
    fe = Frontend(params, CameraModel(seq.camera), seq.T_imu_cam)
    outs = run_frontend(
        fe, seq.stamps_ns, images, seq.imu_stamps_ns, seq.imu_gyro_rad_s, seq.imu_accel_m_s2
    )
    published = {o.stamp_ns for o in outs if o.keyframe is not None}
    frames = fe.estimator.frames[:-1]  # the newest frame is always on top
    assert len(frames) == fe.params.estimator.window_size
    dt = np.diff([f.t_ns for f in frames]) * 1e-9
    later = [f.t_ns in published for f in frames[1:]]
    if interval == 0.0:
        assert np.allclose(dt, 0.1, atol=2e-3)
    else:
        assert all(d >= interval - 2e-3 or kf for d, kf in zip(dt, later, strict=True))
        assert dt.max() < interval + 0.1 + 2e-3  # the first frame past the interval stays
        assert sum(not kf for kf in later) >= 3


def test_window_interval_from_the_platform() -> None:
    """None takes the profile's spacing: the handheld walk spreads its window, car and drone
    keep every frame."""
    assert platform_profile("car").window_interval_s == 0.0
    assert platform_profile("drone").window_interval_s == 0.0
    assert platform_profile("handheld").window_interval_s > 0.0
    hand = platform_profile("handheld", PlatformBounds(window_interval_s=0.0))
    assert hand.window_interval_s == 0.0


def test_estimator_settings_from_the_platform() -> None:
    """Unset (None) estimator settings take the profile's: the walk keeps its
    visual prior, car and drone do not; a launch value wins over the profile's (``platform: auto``
    hands the walk's to the estimator: test_auto_platform_in_the_frontend_on_the_sim_walk)."""
    params = FrontendParams()
    for name, keep in (("car", False), ("drone", False), ("handheld", True)):
        assert params.estimator_for(platform_profile(name)).keep_visual_prior is keep
    off = replace(params, estimator=replace(params.estimator, keep_visual_prior=False))
    assert off.estimator_for(platform_profile("handheld")).keep_visual_prior is False
    # the window's outlier gate relative to its median error: the walk's only (round 11)
    for name, rel in (("car", 0.0), ("drone", 0.0), ("handheld", 4.0)):
        assert params.estimator_for(platform_profile(name)).outlier_reproj_rel == rel
    fixed = replace(params, estimator=replace(params.estimator, outlier_reproj_rel=0.0))
    assert fixed.estimator_for(platform_profile("handheld")).outlier_reproj_rel == 0.0


def test_outlier_gate_from_the_platform() -> None:
    """The gate relative to the window's median error (docs/frontend.md round 11) is the walk's:
    car and drone keep the fixed 5 px gate; an estimator no platform set (None) uses the fixed
    gate too."""
    assert platform_profile("handheld").outlier_reproj_rel == 4.0
    assert platform_profile("car").outlier_reproj_rel == 0.0
    assert platform_profile("drone").outlier_reproj_rel == 0.0
    est = EstimatorParams()
    assert est.outlier_reproj_rel is None
    err = np.full(50, 0.2)
    assert outlier_gate_px(err, est) == est.outlier_reproj_px
    assert outlier_gate_px(err, replace(est, outlier_reproj_rel=4.0)) == 1.0  # the floor


def test_keeps_in_window_rule() -> None:
    """Interval, parallax and track loss each keep a frame; none of them: dropped."""
    ids = np.arange(100)
    uv = np.random.default_rng(0).uniform(0, 600, (100, 2))
    rule = (0.2, 10.0, 0.7)
    assert not keeps_in_window(*rule, ids, uv, ids, uv + 2.0, 0.1)  # 2.8 px, all tracks, 0.1 s
    assert keeps_in_window(*rule, ids, uv, ids, uv + 2.0, 0.2)  # the interval
    assert keeps_in_window(*rule, ids, uv, ids, uv + 8.0, 0.1)  # 11.3 px of parallax
    assert keeps_in_window(*rule, ids, uv, ids[:60], uv[:60] + 2.0, 0.1)  # 60 % of the tracks
