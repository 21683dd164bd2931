"""Sliding-window VI estimator and initialisers on the simulator's trajectories with synthetic
landmarks (projected, no rendering: fast). Ground truth is used here only to start and to score."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError
from mogs_node.eval.traj import trajectory_metrics
from mogs_node.frontend.estimator import EstimatorParams, VioEstimator
from mogs_node.frontend.estimator_types import outlier_gate_px
from mogs_node.frontend.initialization import (
    DynamicInitializer,
    InitParams,
    dynamic_init,
    gravity_aligned_rotation,
    is_still,
    static_init,
    visual_sfm,
)
from mogs_node.frontend.keyframes import landmark_covariance, triangulate_midpoint
from mogs_node.frontend.preintegration import ImuNoise, ImuSamples, make_params
from mogs_node.geometry import PinholeCamera, make_T, se3_inverse, so3_exp, so3_log
from mogs_node.sim import GRAVITY_WORLD_M_S2, T_IMU_CAM_DEFAULT, ImuNoiseParams
from mogs_node.sim.imu import simulate_imu_noise
from mogs_node.sim.trajectory import synthetic_trajectory

CAM = PinholeCamera(360.0, 360.0, 310.0, 94.0, 621, 188)
RATE_HZ, IMU_HZ = 10.0, 200.0


def make_scene(duration_s: float, seed: int = 0, px_noise: float = 0.5, standstill: bool = False):
    """Trajectory (moving or parked), noisy biased IMU, and landmarks along the road."""
    rng = np.random.default_rng(seed)
    traj = synthetic_trajectory(duration_s + 1.0, rng=rng)
    t0 = traj.t_start_s + 0.3
    cam_t = t0 + np.arange(int(duration_s * RATE_HZ)) / RATE_HZ
    imu_t = np.arange(t0 - 1.2 if standstill else t0 - 0.1, cam_t[-1] + 0.1, 1.0 / IMU_HZ)
    imu_t = imu_t[imu_t >= traj.t_start_s]
    if standstill:
        T_pose = traj.T_world_imu(np.full_like(cam_t, t0))
        gyro_true = np.zeros((len(imu_t), 3))
        R0 = T_pose[0, :3, :3]
        acc_true = np.tile(R0.T @ -GRAVITY_WORLD_M_S2, (len(imu_t), 1))
        vel = np.zeros((len(cam_t), 3))
    else:
        T_pose = traj.T_world_imu(cam_t)
        gyro_true = traj.gyro_body_rad_s(imu_t)
        acc_true = traj.specific_force_body_m_s2(imu_t)
        vel = traj.velocity_world_m_s(cam_t)
    noise = simulate_imu_noise(len(imu_t), IMU_HZ, ImuNoiseParams(), rng)
    imu = ImuSamples(
        np.round(imu_t * 1e9).astype(np.int64),
        gyro_true + noise.gyro_bias_rad_s + noise.gyro_noise_rad_s,
        acc_true + noise.accel_bias_m_s2 + noise.accel_noise_m_s2,
    )
    dense = traj.T_world_imu(np.linspace(traj.t_start_s, traj.t_end_s, 2000))
    n = 5000
    k = rng.integers(0, len(dense), n)
    side = rng.choice([-1.0, 1.0], n) * rng.uniform(4, 20, n)
    pts = dense[k, :3, 3] + dense[k, :3, 1] * side[:, None]
    pts[:, 2] += rng.uniform(-0.9, 8, n)
    frames = []
    for T in T_pose:
        Tc = se3_inverse(T @ T_IMU_CAM_DEFAULT)
        pc = pts @ Tc[:3, :3].T + Tc[:3, 3]
        uv, front = CAM.project(pc)
        ok = front & (pc[:, 2] > 1) & (pc[:, 2] < 60) & CAM.in_image(uv)
        ids = np.flatnonzero(ok)[:150].astype(np.int64)
        frames.append((ids, uv[ids] + rng.normal(0, px_noise, (len(ids), 2))))
    return dict(
        stamps=np.round(cam_t * 1e9).astype(np.int64),
        T_wi=T_pose,
        v=vel,
        frames=frames,
        imu=imu,
        bg=noise.gyro_bias_rad_s[0],
        ba=noise.accel_bias_m_s2[0],
        pts=pts,
    )


# The synthetic observations have 0.5 px Gaussian noise: the estimator is told so.
SYNTH = EstimatorParams(pixel_sigma_px=1.0)


def run_window(s, params=SYNTH, stationary=False):
    est = VioEstimator(params, CAM, T_IMU_CAM_DEFAULT, ImuNoise())
    ids, uv = s["frames"][0]
    est.initialize(s["stamps"][0], s["T_wi"][0], s["v"][0], np.zeros(3), np.zeros(3), ids, uv)
    Ts, states = [s["T_wi"][0]], []
    for i in range(1, len(s["stamps"])):
        ids, uv = s["frames"][i]
        st = est.add_frame(
            s["stamps"][i], ids, uv, s["imu"], is_keyframe=True, stationary=stationary
        )
        Ts.append(st.T_world_imu)
        states.append(st)
    return est, np.array(Ts), states


def test_window_tracks_a_10s_drive():
    s = make_scene(10.0)
    est, Ts, states = run_window(s)
    m = trajectory_metrics(s["stamps"], Ts, s["T_wi"])
    assert m["path_length_m"] > 80
    assert m["ate_se3_rmse_m"] < 0.01 * m["path_length_m"]
    assert m["scale_error"] < 0.02
    assert np.all(np.isfinite(Ts))
    # Biases are estimated (zero prior): gyro bias to a fraction of its true value.
    assert (
        np.linalg.norm(states[-1].gyro_bias_rad_s - s["bg"]) < 0.5 * np.linalg.norm(s["bg"]) + 2e-4
    )
    # Landmarks of the newest frame: metric points in its camera frame, close to the truth.
    lm = est.newest_landmarks()
    assert len(lm.track_ids) > 30
    assert np.all(lm.xyz_cam_m[:, 2] > 0) and np.all(np.isfinite(lm.cov_cam_m2))
    assert np.all(np.linalg.eigvalsh(lm.cov_cam_m2.astype(float)) > 0)
    Tcw = se3_inverse(s["T_wi"][-1] @ T_IMU_CAM_DEFAULT)
    true_cam = s["pts"][lm.track_ids] @ Tcw[:3, :3].T + Tcw[:3, 3]
    rel = np.linalg.norm(lm.xyz_cam_m - true_cam, axis=1) / true_cam[:, 2]
    assert np.median(rel) < 0.06  # metric sparse points (fresh, up to 60 m deep, 0.5 px noise)


def test_marginalisation_bounds_the_window():
    s = make_scene(3.0)
    est, Ts, _ = run_window(s, EstimatorParams(window_size=4, pixel_sigma_px=1.0))
    assert len(est.frames) == 5  # 4 keyframes + newest
    assert est.values.size() < 5 * 3 + 400
    m = trajectory_metrics(s["stamps"], Ts, s["T_wi"])
    assert m["ate_se3_rmse_m"] < 0.3


def test_standstill_with_zero_motion_factors_does_not_drift():
    s = make_scene(5.0, standstill=True)
    est, Ts, states = run_window(s, stationary=True)
    drift = np.linalg.norm(Ts[:, :3, 3] - s["T_wi"][0, :3, 3], axis=1)
    assert np.all(np.isfinite(Ts))
    assert drift.max() < 0.02
    assert np.linalg.norm(states[-1].velocity_world_m_s) < 0.02


def test_standstill_without_vision_or_zero_motion_is_finite():
    s = make_scene(3.0, standstill=True)
    s["frames"] = [(np.zeros(0, np.int64), np.zeros((0, 2)))] * len(s["frames"])
    est, Ts, _ = run_window(s)
    assert np.all(np.isfinite(Ts))  # IMU-only: drifts, but no NaN and no exception


def test_pure_rotation_no_nan():
    """Camera spinning in place: no parallax, landmarks never triangulate, the IMU carries it."""
    s = make_scene(3.0, standstill=True)
    n = len(s["stamps"])
    t_imu = s["imu"].stamps_ns * 1e-9
    w = np.array([0.0, 0.0, 0.5])  # yaw rate in the IMU frame
    t0 = s["stamps"][0] * 1e-9
    R0 = s["T_wi"][0, :3, :3]
    Rs = R0 @ so3_exp(np.outer(np.clip(t_imu - t0, 0, None), w) * (t_imu >= t0)[:, None])
    acc = np.einsum("nji,j->ni", Rs, -GRAVITY_WORLD_M_S2)
    gyro = np.where((t_imu >= t0)[:, None], w, 0.0)
    s["imu"] = ImuSamples(s["imu"].stamps_ns, gyro, acc)
    cam_t = s["stamps"] * 1e-9
    T_true = make_T(R0 @ so3_exp(np.outer(cam_t - t0, w)), np.tile(s["T_wi"][0, :3, 3], (n, 1)))
    rng = np.random.default_rng(1)
    pts = s["T_wi"][0, :3, 3] + rng.normal(0, 1, (3000, 3)) * np.array([30, 30, 4])
    frames = []
    for T in T_true:
        Tc = se3_inverse(T @ T_IMU_CAM_DEFAULT)
        pc = pts @ Tc[:3, :3].T + Tc[:3, 3]
        uv, front = CAM.project(pc)
        ids = np.flatnonzero(front & (pc[:, 2] > 5) & CAM.in_image(uv))[:100].astype(np.int64)
        frames.append((ids, uv[ids]))
    s["frames"], s["T_wi"] = frames, T_true
    est, Ts, _ = run_window(s)
    assert np.all(np.isfinite(Ts))
    rot_err = np.linalg.norm(so3_log(np.swapaxes(Ts[:, :3, :3], 1, 2) @ T_true[:, :3, :3]), axis=1)
    assert rot_err.max() < 0.01
    assert np.linalg.norm(Ts[:, :3, 3] - T_true[:, :3, 3], axis=1).max() < 0.1


def test_time_must_increase():
    s = make_scene(1.0)
    est = VioEstimator(EstimatorParams(), CAM, T_IMU_CAM_DEFAULT, ImuNoise())
    ids, uv = s["frames"][0]
    est.initialize(s["stamps"][0], s["T_wi"][0], s["v"][0], np.zeros(3), np.zeros(3), ids, uv)
    with pytest.raises(ConfigError, match="t_ns"):
        est.add_frame(s["stamps"][0], ids, uv, s["imu"], is_keyframe=True)


# ----------------------------------------------------------------------------------------- init


def test_static_init_recovers_gravity_and_gyro_bias():
    s = make_scene(2.0, standstill=True)
    p = InitParams()
    t = int(s["stamps"][0])
    assert is_still(p, s["imu"], t, median_flow_px=0.1)
    assert not is_still(p, s["imu"], t, median_flow_px=3.0)
    res = static_init(p, s["imu"], t)
    R_true = s["T_wi"][0, :3, :3]
    up_est = res.T_world_imu[0, :3, :3].T @ np.array([0, 0, 1.0])
    up_true = R_true.T @ np.array([0, 0, 1.0])
    # accelerometer bias (~0.02 m/s^2) limits the tilt to about bias / g
    assert np.degrees(np.arccos(np.clip(up_est @ up_true, -1, 1))) < 0.5
    np.testing.assert_allclose(res.gyro_bias_rad_s, s["bg"], atol=6e-4)  # white noise + walk
    np.testing.assert_allclose(res.velocity_world_m_s, 0.0)


def test_gravity_aligned_rotation_maps_up_to_z():
    rng = np.random.default_rng(3)
    for _ in range(20):
        up = rng.normal(size=3)
        R = gravity_aligned_rotation(up)
        np.testing.assert_allclose(R @ (up / np.linalg.norm(up)), [0, 0, 1], atol=1e-12)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0


def test_visual_sfm_recovers_relative_poses_up_to_scale():
    s = make_scene(1.0, px_noise=0.3)
    T = visual_sfm(s["frames"], CAM)
    assert T is not None
    T_true = se3_inverse(s["T_wi"][0] @ T_IMU_CAM_DEFAULT) @ (s["T_wi"] @ T_IMU_CAM_DEFAULT)
    scale = np.linalg.norm(T_true[-1, :3, 3]) / np.linalg.norm(T[-1, :3, 3])
    pos_err = np.linalg.norm(T[:, :3, 3] * scale - T_true[:, :3, 3], axis=1)
    assert pos_err.max() < 0.02 * np.linalg.norm(T_true[-1, :3, 3])
    rot_err = np.linalg.norm(so3_log(np.swapaxes(T[:, :3, :3], 1, 2) @ T_true[:, :3, :3]), axis=1)
    assert rot_err.max() < 3e-3


def dynamic_run(seconds: float, **init_kw):
    s = make_scene(seconds, px_noise=0.5)
    init = DynamicInitializer(InitParams(**init_kw), SYNTH, CAM, T_IMU_CAM_DEFAULT, ImuNoise())
    est = None
    for i, (ids, uv) in enumerate(s["frames"]):
        est = init.add_frame(int(s["stamps"][i]), ids, uv, np.ones(len(ids), np.int32), s["imu"])
        if est is not None:
            break
    assert est is not None, "initialisation did not complete"
    first = i
    states = {i: est.state()}
    for k in range(i + 1, len(s["stamps"])):
        states[k] = est.add_frame(int(s["stamps"][k]), *s["frames"][k], s["imu"], is_keyframe=True)
    return s, est, first, states


def up_angle_deg(T_est, T_true):
    up_est = T_est[:3, :3].T @ np.array([0, 0, 1.0])
    up_true = T_true[:3, :3].T @ np.array([0, 0, 1.0])
    return np.degrees(np.arccos(np.clip(up_est @ up_true, -1, 1)))


def test_dynamic_init_recovers_gravity_and_scale():
    """Moving start (~10 m/s), no ground truth: SfM + VI alignment candidates scored by the VI
    window over the next 2 s, refined at the vertex of the error parabola. The kept estimator has
    the gravity direction, the gyro bias and the speed of the truth (speed to 15 %: a cruising car
    barely excites the scale; it converges while driving, see the slow test)."""
    s, est, k, states = dynamic_run(3.1)
    st = states[k]
    assert abs(np.linalg.norm(st.velocity_world_m_s) / np.linalg.norm(s["v"][k]) - 1) < 0.15
    assert up_angle_deg(st.T_world_imu, s["T_wi"][k]) < 1.0
    np.testing.assert_allclose(st.gyro_bias_rad_s, s["bg"], atol=3e-3)  # |bias| ~ 5e-3


@pytest.mark.slow
def test_dynamic_init_scale_stays_bounded_while_driving():
    """20 s from a moving start: the metric scale stays within 10 % and gravity within 1.5 deg
    (measured: 6 % speed error and 1.04 deg after 20 s on this drive; the window's scale and tilt
    observability is weak while cruising)."""
    s, est, k, states = dynamic_run(20.0)
    last = max(states)
    assert (
        abs(np.linalg.norm(states[last].velocity_world_m_s) / np.linalg.norm(s["v"][last]) - 1)
        < 0.1
    )
    assert up_angle_deg(states[last].T_world_imu, s["T_wi"][last]) < 1.5


def test_dynamic_init_candidates_include_the_alignment():
    s = make_scene(1.0, px_noise=0.2)
    cands = dynamic_init(
        InitParams(),
        s["frames"],
        s["stamps"],
        s["imu"],
        CAM,
        T_IMU_CAM_DEFAULT,
        make_params(ImuNoise()),
        hypotheses=5,
    )
    assert 5 <= len(cands) <= 6
    for res in cands:
        np.testing.assert_allclose(res.gyro_bias_rad_s, s["bg"], atol=1e-3)
        assert np.all(np.isfinite(res.T_world_imu)) and np.all(np.isfinite(res.velocity_world_m_s))
        assert np.linalg.norm(res.gravity_imu0) == pytest.approx(9.81)
    speeds = sorted(np.linalg.norm(r.velocity_world_m_s[0]) for r in cands)
    assert speeds[0] < 1.0 and speeds[-1] > 30.0


# ----------------------------------------------------------------------------------------- helpers


def test_triangulate_midpoint_and_covariance():
    rng = np.random.default_rng(0)
    P = rng.uniform([-5, -2, 5], [5, 2, 30], (50, 3))
    oa, ob = np.zeros(3), np.array([1.0, 0, 0])
    pts, ang = triangulate_midpoint(np.tile(oa, (50, 1)), P - oa, np.tile(ob, (50, 1)), P - ob)
    np.testing.assert_allclose(pts, P, atol=1e-9)
    assert np.all(ang > 0)
    T = np.stack([np.eye(4), make_T(np.eye(3), ob)])
    cov = landmark_covariance(P, T, np.ones((50, 2), bool), CAM, 1.0)
    # depth uncertainty grows with depth (roughly quadratically for a fixed baseline)
    sd = np.sqrt(cov[:, 2, 2])
    assert np.corrcoef(P[:, 2] ** 2, sd)[0, 1] > 0.9


def test_gtsam_bias_convention():
    """ConstantBias(accel, gyro): the order the estimator relies on."""
    b = gtsam.imuBias.ConstantBias(np.array([1.0, 2, 3]), np.array([4.0, 5, 6]))
    np.testing.assert_allclose(b.accelerometer(), [1, 2, 3])
    np.testing.assert_allclose(b.gyroscope(), [4, 5, 6])


def test_output_positions_agree_with_velocity_states():
    """From the true state, the per-frame output positions advance as far as the velocity states
    say (and as the truth): the previous report of positions advancing ~21 % less than the
    velocities came from comparing a run-wide median step ratio with the last frame's speed."""
    s = make_scene(10.0)
    _, Ts, states = run_window(s)
    v = np.array([s["v"][0]] + [st.velocity_world_m_s for st in states])
    dt = np.diff(s["stamps"]) * 1e-9
    step_est = np.linalg.norm(np.diff(Ts[:, :3, 3], axis=0), axis=1).sum()
    step_vel = (0.5 * np.linalg.norm(v[1:] + v[:-1], axis=1) * dt).sum()
    step_true = np.linalg.norm(np.diff(s["T_wi"][:, :3, 3], axis=0), axis=1).sum()
    assert abs(step_est / step_vel - 1) < 0.02
    assert abs(step_est / step_true - 1) < 0.03


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="open defect: marginalisation of the oldest keyframe drops "
    "its visual information, the window's scale drifts (docs/frontend.md)",
)
def test_scale_holds_with_a_perfect_imu_and_noisy_pixels(monkeypatch):
    """A perfect IMU and 0.5 px pixel noise, from the true state, 15 s: the speed should stay
    within 1 % of the truth. Measured: window 8 loses 4 % (the oldest frame's velocity moves by
    ~3 cm/s per solve, always slower); with no marginalisation (window 300) it holds to 0.1 %."""
    from mogs_node.sim.imu import ImuNoise as SimImuNoise

    monkeypatch.setitem(
        globals(),
        "simulate_imu_noise",
        lambda n, rate, p, rng: SimImuNoise(*[np.zeros((n, 3))] * 4),
    )
    s = make_scene(15.0, seed=1, px_noise=0.5)
    _, _, states = run_window(s)
    speed = np.linalg.norm(states[-1].velocity_world_m_s) / np.linalg.norm(s["v"][-1])
    assert abs(speed - 1) < 0.01


@pytest.mark.slow
def test_visual_prior_holds_the_scale_with_a_perfect_imu_and_noisy_pixels(monkeypatch):
    """The same drive with ``keep_visual_prior``: the oldest keyframe's observations of mature
    landmarks go into the marginalisation prior with the landmarks kept as variables, so the
    window's visual information on scale is not lost; the speed holds to 1 %. (Not the default:
    on the rendered OXTS drive it does worse, see docs/frontend.md.)"""
    from mogs_node.sim.imu import ImuNoise as SimImuNoise

    monkeypatch.setitem(
        globals(),
        "simulate_imu_noise",
        lambda n, rate, p, rng: SimImuNoise(*[np.zeros((n, 3))] * 4),
    )
    s = make_scene(15.0, seed=1, px_noise=0.5)
    est, _, states = run_window(s, EstimatorParams(pixel_sigma_px=1.0, keep_visual_prior=True))
    speed = np.linalg.norm(states[-1].velocity_world_m_s) / np.linalg.norm(s["v"][-1])
    assert abs(speed - 1) < 0.01
    # the prior involves landmarks, and every landmark it involves is still a variable
    prior_keys = set().union(*(set(f.keys()) for f in est._priors))
    lm_keys = {k for k in prior_keys if gtsam.Symbol(k).chr() == ord("l")}
    assert lm_keys and all(est.values.exists(k) for k in lm_keys)


def test_cached_projection_factors_match_a_fresh_graph():
    """The per-frame projection factors are cached and extended between solves; the cached graph
    must equal one built from scratch (same factors, same error) after landmarks came and went."""
    s = make_scene(3.0)
    est, _, _ = run_window(s, EstimatorParams(window_size=4, pixel_sigma_px=1.0))
    cached = est._graph()
    est._factor_cache.clear()
    fresh = est._graph()
    assert cached.size() == fresh.size() > 100
    assert cached.error(est.values) == pytest.approx(fresh.error(est.values), rel=1e-12)
    keys = lambda g: sorted(tuple(g.at(i).keys()) for i in range(g.size()))  # noqa: E731
    assert keys(cached) == keys(fresh)


@settings(max_examples=40, deadline=None)
@given(
    med=st.floats(0.01, 10.0),
    rel=st.floats(0.0, 10.0),
    n=st.integers(0, 60),
)
def test_outlier_gate_follows_the_window_median(med, rel, n):
    """The gate is ``outlier_reproj_px`` when the relative gate is off or the window has too few
    errors, else ``rel x median`` clipped to [floor, outlier_reproj_px]."""
    p = EstimatorParams(outlier_reproj_rel=rel, outlier_reproj_min_px=1.0, outlier_reproj_px=5.0)
    err = np.r_[np.full(n, med), [np.inf]]  # an observation behind the camera does not count
    g = outlier_gate_px(err, p)
    if rel == 0 or n < 20:
        assert g == 5.0
    else:
        assert 1.0 <= g <= 5.0
        assert g == pytest.approx(min(5.0, max(1.0, rel * med)))


def test_outlier_gate_params_are_checked():
    with pytest.raises(ConfigError, match="outlier_reproj_min_px"):
        EstimatorParams(outlier_reproj_min_px=6.0)
    with pytest.raises(ConfigError, match="outlier_reproj_rel"):
        EstimatorParams(outlier_reproj_rel=-1.0)


def test_inaccurate_tracks_are_removed_by_the_relative_gate():
    """Twenty tracks are six times less accurate than the rest (1.2 px against 0.2 px: a KLT
    track sliding on its texture): they stay under the fixed 5 px gate but stand out against the
    window's median error, so the relative gate removes (nearly) all; the accurate ones stay."""
    s = make_scene(3.0, seed=2, px_noise=0.2)
    rng = np.random.default_rng(7)
    bad = np.unique(np.concatenate([ids for ids, _ in s["frames"]]))[::7][:20]
    for ids, uv in s["frames"]:
        m = np.isin(ids, bad)
        uv[m] += rng.normal(0.0, 1.2, (int(m.sum()), 2))
    kept = {}
    for rel in (0.0, 4.0):
        est, _, _ = run_window(s, EstimatorParams(pixel_sigma_px=1.0, outlier_reproj_rel=rel))
        kept[rel] = set(est._lid_of_track) & set(bad.tolist())
        assert len(est._lid_of_track) > 50  # the accurate tracks stay
    assert len(kept[0.0]) >= 5 and len(kept[4.0]) <= 2  # measured: 9 and 2 of 20
