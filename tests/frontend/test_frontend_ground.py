"""Road-plane translation (frontend/ground.py) and its distance factor in the window."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_frontend_estimator import CAM, SYNTH, make_scene

from mogs_node.errors import ConfigError
from mogs_node.eval.frontend_runs import DEFAULT_DATA
from mogs_node.frontend.estimator import VioEstimator
from mogs_node.frontend.ground import (
    GroundParams,
    estimate_ground_translation,
    road_normal_from_mount,
    road_scale_of_sfm,
)
from mogs_node.frontend.preintegration import ImuNoise
from mogs_node.geometry import se3_inverse
from mogs_node.sim import T_IMU_CAM_DEFAULT, SimConfig, make_sequence


@pytest.fixture(scope="module")
def drive():
    """A rendered sim drive (synthetic trajectory, 10 m/s, road plane z = 0), grey images."""
    seq = make_sequence(SimConfig(seed=0, n_frames=9, width=621, height=188))
    grays = [cv2.cvtColor(seq.render(i).rgb, cv2.COLOR_RGB2GRAY) for i in range(9)]
    return seq, grays


def pair(seq, i):
    """Ground truth of frames i -> i + 1: R, t of X_cur = R X_prev + t, road normal, height."""
    T = se3_inverse(seq.T_world_cam[i + 1]) @ seq.T_world_cam[i]
    n = seq.T_world_cam[i][:3, :3].T @ np.array([0.0, 0.0, -1.0])
    return T[:3, :3], T[:3, 3], n, float(seq.T_world_cam[i][2, 3])


@pytest.mark.parametrize("guess, search", [(1.0, False), (0.7, True), (1.4, True)])
def test_recovers_the_metric_translation_from_the_road(drive, guess, search):
    seq, grays = drive
    errs = []
    for i in range(8):
        R, t, n, h = pair(seq, i)
        p = GroundParams(camera_height_m=h)
        tau_true = np.linalg.norm(t) / h
        m = estimate_ground_translation(
            grays[i], grays[i + 1], seq.camera.K, R, t, n, guess * tau_true, p, search=search
        )
        assert m is not None
        assert m.distance_m == pytest.approx(m.tau * h)
        assert np.linalg.norm(m.normal_cam) == pytest.approx(1.0)
        assert m.n_pixels >= p.min_pixels and np.isfinite(m.residual)
        errs.append(m.tau / tau_true - 1)
    assert abs(np.median(errs)) < 0.03, errs
    assert np.max(np.abs(errs)) < 0.10, errs


def test_mount_normal_is_the_imu_down_axis():
    n = road_normal_from_mount(T_IMU_CAM_DEFAULT)
    assert n @ (T_IMU_CAM_DEFAULT[:3, :3].T @ np.array([0, 0, -1.0])) == pytest.approx(1.0)


def test_textureless_road_gives_no_measurement(drive):
    seq, _ = drive
    R, t, n, h = pair(seq, 0)
    flat = np.full((188, 621), 128, np.uint8)
    p = GroundParams(camera_height_m=h)
    assert estimate_ground_translation(flat, flat, seq.camera.K, R, t, n, 0.5, p) is None


def test_degenerate_motion_and_bad_input(drive):
    seq, grays = drive
    R, t, n, h = pair(seq, 0)
    p = GroundParams(camera_height_m=h)
    K = seq.camera.K
    assert estimate_ground_translation(grays[0], grays[1], K, R, np.zeros(3), n, 0.5, p) is None
    # moving along the road normal (straight down): not a car on a road
    assert estimate_ground_translation(grays[0], grays[1], K, R, n, n, 0.5, p) is None
    for tau in (0.0, -1.0, np.nan, np.inf):
        assert estimate_ground_translation(grays[0], grays[1], K, R, t, n, tau, p) is None
    with pytest.raises(ConfigError, match="camera_height_m"):
        estimate_ground_translation(grays[0], grays[1], K, R, t, n, 0.5, GroundParams())
    with pytest.raises(ConfigError, match="gray images"):
        estimate_ground_translation(grays[0], grays[1][:-1], K, R, t, n, 0.5, p)
    with pytest.raises(Exception, match="R_cur_prev"):
        estimate_ground_translation(grays[0], grays[1], K, R * np.nan, t, n, 0.5, p)
    for bad in (
        dict(camera_height_m=-1.0),
        dict(camera_height_m=np.nan),
        dict(min_depth_m=30.0),
        dict(levels=0),
        dict(relative_sigma=0.0),
    ):
        with pytest.raises(ConfigError):
            GroundParams(**bad)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    log_tau=st.floats(-20.0, 20.0),
    height=st.floats(1e-3, 1e3),
    scale=st.floats(1e-6, 1e6),
)
def test_any_guess_height_or_scene_scale_gives_a_finite_answer_or_none(
    drive, log_tau, height, scale
):
    """Tiny and huge guesses, heights and translation magnitudes: never NaN, never an exception."""
    seq, grays = drive
    R, t, n, _ = pair(seq, 0)
    m = estimate_ground_translation(
        grays[0],
        grays[1],
        seq.camera.K,
        R,
        t * scale,
        n,
        float(np.exp(log_tau)),
        GroundParams(camera_height_m=height),
    )
    if m is not None:
        assert np.isfinite(m.tau) and m.tau > 0 and np.isfinite(m.distance_m)
        assert np.all(np.isfinite(m.normal_cam))


def test_distance_factor_pulls_a_wrong_speed_back():
    """A window started at 0.7x the true speed (a loose 3 m/s velocity prior, as after an
    uncertain initialisation) keeps that scale on the synthetic drive; the measured camera
    distances (2 % noise) bring it back. (With a tight prior at the wrong speed the accelerometer
    bias absorbs the conflict and the speed overshoots: docs/frontend.md, round 5.)"""
    s = make_scene(4.0)
    rng = np.random.default_rng(0)
    T_ic = T_IMU_CAM_DEFAULT
    ratios = {}
    for use_ground in (False, True):
        est = VioEstimator(SYNTH, CAM, T_ic, ImuNoise())
        ids, uv = s["frames"][0]
        est.initialize(
            s["stamps"][0],
            s["T_wi"][0],
            0.7 * s["v"][0],
            np.zeros(3),
            np.zeros(3),
            ids,
            uv,
            vel_sigma_m_s=3.0,
        )
        for i in range(1, len(s["stamps"])):
            ids, uv = s["frames"][i]
            st_ = est.add_frame(s["stamps"][i], ids, uv, s["imu"], is_keyframe=True)
            if use_ground:
                c0 = (s["T_wi"][i - 1] @ T_ic)[:3, 3]
                c1 = (s["T_wi"][i] @ T_ic)[:3, 3]
                d = np.linalg.norm(c1 - c0) * (1 + 0.02 * rng.standard_normal())
                assert est.add_ground_distance(est.frames[-2].seq, est.frames[-1].seq, d, 0.02 * d)
        ratios[use_ground] = np.linalg.norm(st_.velocity_world_m_s) / np.linalg.norm(s["v"][-1])
    assert abs(ratios[False] - 1) > 0.1, ratios
    assert abs(ratios[True] - 1) < 0.03, ratios
    # not consecutive window frames, or a bad distance
    assert not est.add_ground_distance(est.frames[0].seq, est.frames[-1].seq, 1.0, 0.1)
    with pytest.raises(ConfigError, match="ground distance"):
        est.add_ground_distance(est.frames[-2].seq, est.frames[-1].seq, np.nan, 0.1)


def test_road_scale_of_an_up_to_scale_sfm_window(drive):
    """The dynamic initialisation's use: camera poses known up to scale (here the truth x 0.37)
    and a rough guess of each step (10 m/s) give the metric scale back."""
    seq, grays = drive
    T0_inv = se3_inverse(seq.T_world_cam[0])
    T_c0_ci = np.stack([T0_inv @ T for T in seq.T_world_cam[:9]])
    T_c0_ci[:, :3, 3] *= 0.37
    h = float(seq.T_world_cam[0][2, 3])
    p = GroundParams(camera_height_m=h)
    n = road_normal_from_mount(seq.T_imu_cam)
    steps = np.full(8, 10.0 * 0.1)
    scale = road_scale_of_sfm(grays, T_c0_ci, seq.camera.K, n, p, steps)
    assert scale == pytest.approx(1 / 0.37, rel=0.03)
    # noise images: no road, no scale
    rng = np.random.default_rng(0)
    noise = [rng.integers(0, 255, grays[0].shape, dtype=np.uint8) for _ in grays]
    assert road_scale_of_sfm(noise, T_c0_ci, seq.camera.K, n, p, steps) is None


KITTI = DEFAULT_DATA / "kitti_raw_2011_09_26_78"


@pytest.mark.skipif(not KITTI.exists(), reason=f"{KITTI} absent (../shared/data)")
def test_real_kitti_road_against_lidar_motion():
    """Real images in slow urban traffic (a car 6-10 m ahead in the lane for most frames). The
    reference motion between frames comes from PnP on KLT tracks with the LiDAR depth. A vehicle
    ahead that drives at our speed looks static and would pull tau to 0: those pixels are left
    out (``min_change``) and what stays biased is mostly rejected."""
    from mogs_node.datasets.kitti import read_kitti_raw

    seq = read_kitti_raw(KITTI)
    K, p = seq.camera.K, GroundParams(camera_height_m=1.65)
    n = road_normal_from_mount(seq.T_imu_cam)
    errs, n_pairs = [], 0
    for k in range(35):  # afterwards the car stops (steps < 0.1 m)
        a, b = seq.frames[k], seq.frames[k + 1]
        ga = cv2.cvtColor(a.image, cv2.COLOR_RGB2GRAY)
        gb = cv2.cvtColor(b.image, cv2.COLOR_RGB2GRAY)
        D = a.depth_m()
        pts = cv2.goodFeaturesToTrack(ga, 1500, 0.005, 8)
        p2, st, _ = cv2.calcOpticalFlowPyrLK(ga, gb, pts, None, winSize=(21, 21), maxLevel=3)
        u0, u1 = pts[st[:, 0] == 1, 0], p2[st[:, 0] == 1, 0]
        xi = np.clip(np.round(u0).astype(int), 1, [D.shape[1] - 2, D.shape[0] - 2])
        win = np.stack(
            [D[xi[:, 1] + dy, xi[:, 0] + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 1
        )
        z = np.where(win > 0, win, np.inf).min(1)
        m = np.isfinite(z) & (z < 60)
        X = (np.linalg.inv(K) @ np.c_[u0[m], np.ones(m.sum())].T).T * z[m, None]
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X, u1[m], K, None, reprojectionError=1.5, iterationsCount=300
        )
        assert ok and len(inl) > 100
        R, t = cv2.Rodrigues(rvec)[0], tvec[:, 0]
        d = float(np.linalg.norm(t))
        n_pairs += 1
        meas = estimate_ground_translation(ga, gb, K, R, t, n, d / 1.65, p)
        if meas is not None:
            errs.append(meas.distance_m / d - 1)
    errs = np.abs(np.array(errs))
    assert n_pairs == 35
    assert len(errs) >= 15  # measured: 26 of 35, median |error| 8 %, 77 % within 20 %
    assert np.median(errs) < 0.10, errs
    assert np.mean(errs < 0.2) >= 0.6, errs
