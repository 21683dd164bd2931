"""Saying why a run makes no keyframe or no depth (mogs_node/diagnosis.py, issue 18): each cause
from the observations that reveal it, once, with what to do; the coverage and stillness helpers
at their edges."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from mogs_node import msgs
from mogs_node.diagnosis import DoctorParams, RunDoctor, depth_coverage, imu_is_still
from mogs_node.errors import ShapeError


def _beat(doc: RunDoctor, now: float, *, images: int, imu: int = 0, **frontend: float) -> None:
    topics = {"/camera/image": {"published": images}, "/imu": {"published": imu}}
    doc.on_diagnostics("player", {}, topics, now)
    if frontend:
        doc.on_diagnostics("frontend", {f"frontend_{k}": v for k, v in frontend.items()}, {}, now)


def _run(
    doc: RunDoctor, t0: int, t1: int, *, status: str | None = "dropped", step_m: float = 0.0, **kw
) -> list[str]:
    """Seconds t0..t1 of a 10 Hz stream: heartbeats each second and, unless ``status`` is None,
    one odometry per frame (data time = wall time); every line said."""
    said = []
    for t in range(t0, t1 + 1):
        if status is not None:
            for k in range(10):
                stamp = t * 10**9 + k * 10**8
                doc.on_odometry(status, np.array([step_m * (10 * t + k), 0.0, 0.0]), stamp)
        _beat(doc, float(t), images=10 * (t + 1), **kw)
        said += doc.check(float(t))
    return said


def _run_until(doc: RunDoctor, t_end: float, **kw) -> list[str]:
    return _run(doc, 0, int(t_end), **kw)


def test_no_imu_is_said_once_ten_seconds_after_the_first_image() -> None:
    doc = RunDoctor()
    assert _run_until(doc, 9.0, frames=0) == []  # < 10 s since the first image
    said = _run_until(doc, 30.0, frames=0)
    assert len(said) == 1
    assert said[0].startswith("no keyframe yet after")
    assert "no IMU" in said[0] and "0 IMU samples" in said[0] and "What to do" in said[0]
    assert doc.at_end() == []  # already said


def test_at_end_says_why_a_short_run_made_no_keyframe() -> None:
    doc = RunDoctor()
    _beat(doc, 0.0, images=78)
    assert doc.check(5.0) == []
    (line,) = doc.at_end()
    assert line.startswith("the run made no keyframe from 78 images: no IMU")


def test_a_back_pressured_pipeline_is_not_a_stall() -> None:
    """Wall time passes without a keyframe, but the frontend handled little data (the player
    waits for the mapper): nothing to say."""
    doc = RunDoctor()
    doc.on_keyframe(0, 200, 0, 0.0)
    for t in range(60):  # one frame every 10 s of wall time, 0.1 s of data each
        doc.on_odometry("tracking", np.zeros(3), t * 10**8)
        _beat(doc, 10.0 * t, images=t + 1, imu=20 * t, frames=t)
        assert doc.check(10.0 * t) == []


def test_no_images_seen_says_nothing() -> None:
    doc = RunDoctor()
    assert doc.check(100.0) == [] and doc.at_end() == []


def test_images_waiting_for_imu_mean_the_clocks_disagree() -> None:
    doc = RunDoctor()
    said = _run_until(
        doc, 12.0, status=None, imu=500, frames=0, imu_samples=500, frames_dropped_waiting_imu=40
    )
    assert len(said) == 1 and "camera and IMU stamps do not overlap" in said[0]


def test_a_still_sensor_is_no_motion() -> None:
    rng = np.random.default_rng(0)
    doc = RunDoctor()
    for _ in range(200):  # 1 mrad/s, 0.02 m/s^2 of noise: standing
        doc.on_imu(
            tuple(rng.normal(0, 1e-3, 3)), tuple(np.array([0, 0, 9.81]) + rng.normal(0, 0.02, 3))
        )
    said = _run_until(doc, 12.0, status="initializing", imu=2000, frames=120, imu_samples=2000)
    assert len(said) == 1 and "no motion" in said[0]


def test_a_moving_sensor_still_initialising_points_at_the_calibration() -> None:
    rng = np.random.default_rng(1)
    doc = RunDoctor()
    for _ in range(200):  # swinging: 0.5 rad/s, 3 m/s^2
        doc.on_imu(tuple(rng.normal(0, 0.5, 3)), tuple(rng.normal(0, 3.0, 3)))
    said = _run_until(doc, 12.0, status="initializing", imu=2000, frames=120, imu_samples=2000)
    assert len(said) == 1 and "still initialising" in said[0] and "fx_px" in said[0]


def test_resets_are_tracking_lost_and_tracking_without_travel_is_no_motion() -> None:
    doc = RunDoctor()
    doc.on_keyframe(0, 200, 0, 0.0)
    said = _run(
        doc, 0, 12, status="reset", imu=2000, frames=120, imu_samples=2000, divergence_resets=2
    )
    assert len(said) == 1 and "tracking lost" in said[0]
    assert said[0].startswith("no keyframe for 11 s of data")  # 0 .. 10.9 s
    doc.on_keyframe(1, 200, 13 * 10**9, 13.0)  # a keyframe: a later stall is said again
    later = _run(
        doc, 13, 30, status="tracking", step_m=0.001, imu=2000, frames=300, imu_samples=2000
    )
    assert len(later) == 1 and "no motion" in later[0]


def test_an_empty_depth_says_whether_the_prior_was_empty() -> None:
    doc = RunDoctor()
    doc.on_keyframe(3, 150, 0, 0.0)
    doc.on_prior(3, 0.0)
    (line,) = doc.on_depth(3, 0.0)
    assert line.startswith("keyframe 3 got no depth: its depth prior is empty")
    doc.on_keyframe(4, 150, 1, 1.0)
    doc.on_prior(4, 0.0)
    assert doc.on_depth(4, 0.0) == []  # said once per run
    doc.on_keyframe(5, 3, 2, 2.0)
    doc.on_prior(5, 0.3)
    (line,) = doc.on_depth(5, 0.0)
    assert "only 3 sparse metric points" in line
    assert doc.on_depth(6, 0.25) == []  # a depth: nothing to say


def test_observe_feeds_messages() -> None:
    doc = RunDoctor(DoctorParams(no_keyframe_s=1.0))
    d = np.zeros((4, 5), np.float32)
    doc.observe(
        "/diagnostics",
        msgs.Diagnostics(
            stamp_ns=1,
            frame_id="",
            node="player",
            pid=1,
            uptime_s=1.0,
            status="ok",
            counters={},
            topics={"/camera/image": {"published": 4}},
        ),
        0.0,
    )
    depth = msgs.DepthMap(
        stamp_ns=1,
        frame_id="c",
        keyframe_id=7,
        kind="metric",
        depth=d,
        confidence=d.copy(),
        source="x",
    )
    doc.observe("/prior/depth", depth, 0.5)
    (line,) = doc.observe("/metrizer/depth", depth, 0.6)
    assert "keyframe 7 got no depth: its depth prior is empty" in line
    assert doc.check(2.0)[0].startswith("no keyframe yet after 4 images: no IMU")


def test_depth_coverage_counts_finite_positive_confident_pixels() -> None:
    d = np.array([[1.0, 0.0, np.nan], [np.inf, -1.0, 2.0]], np.float32)
    assert depth_coverage(d) == pytest.approx(2 / 6)
    c = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 0.0]], np.float32)
    assert depth_coverage(d, c) == pytest.approx(1 / 6)
    with pytest.raises(ShapeError, match="depth_m"):
        depth_coverage(np.zeros((0, 3)))
    with pytest.raises(ShapeError, match="confidence"):
        depth_coverage(d, c[:1])


@settings(max_examples=50, deadline=None)
@given(
    arrays(
        np.float32,
        st.tuples(st.integers(1, 8), st.integers(1, 8)),
        elements=st.floats(allow_nan=True, allow_infinity=True, width=32),
    )
)
def test_depth_coverage_is_a_fraction(d: np.ndarray) -> None:
    c = depth_coverage(d)
    assert 0.0 <= c <= 1.0
    assert c == pytest.approx(np.count_nonzero(np.isfinite(d) & (d > 0)) / d.size)


@settings(max_examples=50, deadline=None)
@given(scale=st.floats(1e-9, 1e9), n=st.integers(2, 50))
def test_imu_stillness_scales_with_the_spread(scale: float, n: int) -> None:
    rng = np.random.default_rng(n)
    g, a = rng.normal(0, 1, (n, 3)) * scale, rng.normal(0, 1, (n, 3)) * scale
    still = imu_is_still(g, a, gyro_std=0.1, accel_std=1.5)
    assert still == (np.std(g, axis=0).max() < 0.1 and np.std(a, axis=0).max() < 1.5)


def test_imu_stillness_edges() -> None:
    z = np.zeros((5, 3))
    assert imu_is_still(z, z, gyro_std=0.1, accel_std=1.5)
    bad = z.copy()
    bad[2, 1] = np.nan
    assert not imu_is_still(bad, z, gyro_std=0.1, accel_std=1.5)
    with pytest.raises(ShapeError, match="gyro_rad_s"):
        imu_is_still(np.zeros((1, 3)), np.zeros((1, 3)), gyro_std=0.1, accel_std=1.5)
    with pytest.raises(ShapeError, match="gyro_rad_s"):
        imu_is_still(np.zeros((4, 2)), np.zeros((4, 2)), gyro_std=0.1, accel_std=1.5)
