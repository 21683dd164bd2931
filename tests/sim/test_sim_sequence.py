"""Simulated sequences: multi-view consistency, IMU consistency, determinism, simulated LFM."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from mogs_node.errors import ConfigError
from mogs_node.geometry import se3_inverse, so3_log
from mogs_node.sim import (
    ImuNoiseParams,
    LfmParams,
    SimConfig,
    integrate_imu,
    make_sequence,
    simulate_imu_noise,
    simulated_lfm,
    simulated_lfm_with_truth,
)

SMALL = SimConfig(seed=0, n_frames=6, width=621, height=188)


@pytest.fixture(scope="module")
def seq_small():
    return make_sequence(SMALL)


def test_api_shapes_and_conventions(seq_small) -> None:
    s = seq_small
    assert s.camera.width == 621 and s.camera.height == 188
    assert s.camera.fx_px == pytest.approx(721.5377 * 621 / 1242)
    assert s.stamps_ns.dtype == np.int64 and s.stamps_ns.shape == (6,)
    np.testing.assert_array_equal(np.diff(s.stamps_ns), 100_000_000)
    assert s.T_world_cam.shape == (6, 4, 4)
    np.testing.assert_allclose(s.T_world_cam, s.T_world_imu @ s.T_imu_cam, atol=1e-12)
    # camera looks forward (world +x at t=0), its y axis points down
    R = s.T_world_cam[0, :3, :3]
    assert R[0, 2] > 0.99 and R[2, 1] < -0.99
    assert s.T_world_cam[0, 2, 3] == pytest.approx(0.93 + 0.72, abs=0.05)
    f = s.render(2)
    assert f.rgb.shape == (188, 621, 3) and f.rgb.dtype == np.uint8
    assert f.depth_m.dtype == np.float32 and f.instance_id.dtype == np.int32
    assert f.stamp_ns == s.stamps_ns[2]
    sky = f.instance_id == -1
    assert sky.any() and np.all(np.isinf(f.depth_m[sky])) and np.all(np.isfinite(f.depth_m[~sky]))
    assert (
        f.instance_kind.dtype == np.int8
        and f.instance_kind.max() < 5
        and f.instance_kind.min() >= 1
    )
    ids = np.unique(f.instance_id[~sky])
    assert ids.max() < len(f.instance_kind)
    kinds = set(f.instance_kind[ids].tolist())
    assert {1, 2, 3} <= kinds  # planes, cylinders and ellipsoids in view
    # imu
    M = len(s.imu_stamps_ns)
    assert s.imu_gyro_rad_s.shape == (M, 3) and s.imu_accel_bias.shape == (M, 3)
    assert s.imu_stamps_ns[0] <= s.stamps_ns[0] and s.imu_stamps_ns[-1] >= s.stamps_ns[-1]
    np.testing.assert_array_equal(np.diff(s.imu_stamps_ns), 5_000_000)
    assert np.isin(s.stamps_ns, s.imu_stamps_ns).all()  # frames on the IMU grid


def test_world_along_whole_trajectory() -> None:
    s = make_sequence(SimConfig(seed=4, n_frames=101, width=160, height=48))
    cl = s.world.centerline
    pos = s.T_world_imu[:, :3, 3]
    ss, lat = cl.station(pos[:, :2])
    assert np.all(np.abs(lat + 1.75) < 0.2)  # in the right lane everywhere
    # objects on both sides, every 25 m along the driven stretch
    centres = np.array([p.corners().mean(0) for p in s.world.primitives])
    cs, cl_lat = cl.station(centres[:, :2])
    for a in np.arange(ss.min(), ss.max(), 25.0):
        m = (cs >= a) & (cs < a + 25.0)
        assert np.any(m & (cl_lat > 4)) and np.any(m & (cl_lat < -4))
    assert np.all(np.abs(cl_lat) > 4.0)  # nothing on the carriageway
    # about 10 m/s with curves
    speed = np.linalg.norm(s.velocity_world_m_s, axis=1)
    assert 7.0 < speed.mean() < 13.0
    yaw = np.unwrap(np.arctan2(s.velocity_world_m_s[:, 1], s.velocity_world_m_s[:, 0]))
    assert np.ptp(yaw) > np.deg2rad(5)


def test_deterministic_and_seeded() -> None:
    a = make_sequence(replace(SMALL, n_frames=3))
    b = make_sequence(replace(SMALL, n_frames=3))
    c = make_sequence(replace(SMALL, n_frames=3, seed=1))
    np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
    np.testing.assert_array_equal(a.imu_accel_m_s2, b.imu_accel_m_s2)
    fa, fb = a.render(1), b.render(1)
    np.testing.assert_array_equal(fa.rgb, fb.rgb)
    assert not np.array_equal(a.imu_accel_m_s2, c.imu_accel_m_s2)
    assert not np.array_equal(fa.rgb, c.render(1).rgb)


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    u0, v0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
    return (
        img[v0, u0] * (1 - fu) * (1 - fv)
        + img[v0, u0 + 1] * fu * (1 - fv)
        + img[v0 + 1, u0] * (1 - fu) * fv
        + img[v0 + 1, u0 + 1] * fu * fv
    )


def test_multiview_consistency_of_world_points(seq_small) -> None:
    """A world point projected with the ground-truth poses lands on the same texture feature.

    Corners of frame 0 are located to sub-pixel accuracy, lifted to 3D with the true depth and
    projected into later frames with the true poses; there, the corner detector started 1.5 px away
    from the prediction must converge onto it.
    """
    s = seq_small
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 0.001)
    f0 = s.render(0)
    g0 = cv2.cvtColor(f0.rgb, cv2.COLOR_RGB2GRAY)
    pts = cv2.goodFeaturesToTrack(g0, 1500, 0.005, 5, blockSize=5)[:, 0, :]
    pts = pts[(pts[:, 0] > 12) & (pts[:, 0] < 608) & (pts[:, 1] > 12) & (pts[:, 1] < 175)]
    c0 = cv2.cornerSubPix(g0, pts.astype(np.float32).copy(), (4, 4), (-1, -1), crit).astype(
        np.float64
    )
    # keep well-defined corners: the refinement started 1.5 px away comes back to them
    back = cv2.cornerSubPix(g0, (c0 + 1.5).astype(np.float32), (4, 4), (-1, -1), crit)
    c0 = c0[np.linalg.norm(back - c0, axis=1) < 0.05]
    d = f0.depth_m.astype(np.float64)
    d0 = _bilinear(np.where(np.isfinite(d), d, 1e9), c0)
    # keep corners on smooth depth (not on occlusion edges): the 4 neighbours agree within 2%
    r = np.round(c0).astype(int)
    nb = np.stack([d[r[:, 1] + dy, r[:, 0] + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 1)
    nb = np.where(np.isfinite(nb), nb, 1e9)
    ok0 = np.all(np.isfinite(nb), 1) & (np.ptp(nb, 1) < 0.02 * d0) & (d0 < 40)
    c0, d0 = c0[ok0], d0[ok0]
    X_world = (s.T_world_cam[0] @ np.c_[s.camera.backproject(c0, d0), np.ones(len(d0))].T).T
    id_world = f0.instance_id[np.round(c0[:, 1]).astype(int), np.round(c0[:, 0]).astype(int)]
    n_checked = 0
    for j in (1, 2, 3):
        fj = s.render(j)
        Pc = (se3_inverse(s.T_world_cam[j]) @ X_world.T).T[:, :3]
        uvj, front = s.camera.project(Pc)
        inside = front & (uvj[:, 0] > 12) & (uvj[:, 0] < 608) & (uvj[:, 1] > 12) & (uvj[:, 1] < 175)
        rj = np.round(uvj).astype(int).clip([0, 0], [620, 187])
        visible = inside & (
            np.abs(fj.depth_m[rj[:, 1], rj[:, 0]] - Pc[:, 2]) < 0.02 * Pc[:, 2] + 0.05
        )
        assert visible.sum() > 40
        # same surface: instance ids agree
        assert np.mean(fj.instance_id[rj[visible, 1], rj[visible, 0]] == id_world[visible]) > 0.97
        gj = cv2.cvtColor(fj.rgb, cv2.COLOR_RGB2GRAY)
        start = uvj[visible] + np.random.default_rng(j).choice([-1.5, 1.5], (int(visible.sum()), 2))
        cj = cv2.cornerSubPix(gj, start.astype(np.float32), (4, 4), (-1, -1), crit)
        err = np.linalg.norm(cj - uvj[visible], axis=1)
        assert np.median(err) < 0.4, (j, np.median(err))
        assert np.mean(err < 1.0) > 0.75, (j, np.mean(err < 1.0))
        # and the same colour
        col0 = _bilinear(g0.astype(np.float64), c0[visible])
        colj = _bilinear(gj.astype(np.float64), uvj[visible])
        assert np.median(np.abs(col0 - colj)) < 12
        n_checked += int(visible.sum())
    assert n_checked > 120


def _photometric_residual(s, f0, fj, T_world_camj) -> float:
    """Median |I_0(u) - I_j(proj_j(X(u)))| over frame-0 pixels visible in frame j (grey levels)."""
    g0 = cv2.cvtColor(f0.rgb, cv2.COLOR_RGB2GRAY).astype(np.float64)
    gj = cv2.cvtColor(fj.rgb, cv2.COLOR_RGB2GRAY).astype(np.float64)
    v, u = np.nonzero(np.isfinite(f0.depth_m) & (f0.depth_m < 40))
    uv = np.c_[u, v].astype(np.float64)
    X = (
        s.camera.backproject(uv, f0.depth_m[v, u]) @ s.T_world_cam[0][:3, :3].T
        + s.T_world_cam[0][:3, 3]
    )
    Pc = (X - T_world_camj[:3, 3]) @ T_world_camj[:3, :3]
    uvj, front = s.camera.project(Pc)
    W, H = s.camera.width, s.camera.height
    ok = front & (uvj[:, 0] > 1) & (uvj[:, 0] < W - 2) & (uvj[:, 1] > 1) & (uvj[:, 1] < H - 2)
    rj = np.round(uvj[ok]).astype(int)
    dj = fj.depth_m[rj[:, 1], rj[:, 0]]
    vis = np.abs(dj - Pc[ok, 2]) < 0.02 * Pc[ok, 2]
    return float(np.median(np.abs(g0[v[ok][vis], u[ok][vis]] - _bilinear(gj, uvj[ok][vis]))))


def test_multiview_photometric_consistency(seq_small) -> None:
    """Every pixel of frame 0 re-projected with the true depth and poses has the same brightness."""
    s = seq_small
    f0 = s.render(0)
    for j in (1, 4):
        fj = s.render(j)
        good = _photometric_residual(s, f0, fj, s.T_world_cam[j])
        off = s.T_world_cam[j].copy()
        off[:3, 3] += off[:3, :3] @ np.array([0.1, 0.0, 0.0])  # 10 cm sideways
        bad = _photometric_residual(s, f0, fj, off)
        assert good < 1.5, good
        assert bad > 2.5 * good, (good, bad)


def _integrate_err(seq, gyro, accel) -> np.ndarray:
    T, _ = integrate_imu(
        seq.imu_stamps_ns,
        gyro,
        accel,
        seq.imu_T_world_imu[0],
        seq.imu_velocity_world_m_s[0],
        seq.gravity_world_m_s2,
    )
    return np.linalg.norm(T[:, :3, 3] - seq.imu_T_world_imu[:, :3, 3], axis=1)


@pytest.mark.parametrize("trajectory", ["synthetic", "oxts"])
def test_imu_integration_reproduces_trajectory(trajectory: str) -> None:
    """Biases removed and white noise off: 10 s of dead reckoning stays within 1 cm."""
    from mogs_node.sim.trajectory import default_oxts_dir

    if trajectory == "oxts" and not default_oxts_dir().exists():
        pytest.skip(f"OXTS excerpt not found at {default_oxts_dir()}")
    cfg = SimConfig(
        seed=2,
        n_frames=101,
        width=64,
        height=32,
        trajectory=trajectory,
        imu_noise=ImuNoiseParams(white_noise=False),
    )
    s = make_sequence(cfg)
    assert (s.imu_stamps_ns[-1] - s.imu_stamps_ns[0]) * 1e-9 >= 10.0
    assert np.abs(s.imu_gyro_bias).max() > 1e-4  # biases really are there
    err = _integrate_err(s, s.imu_gyro_rad_s - s.imu_gyro_bias, s.imu_accel_m_s2 - s.imu_accel_bias)
    assert err.max() < 0.01
    # rotation too
    T, _ = integrate_imu(
        s.imu_stamps_ns,
        s.imu_gyro_rad_s - s.imu_gyro_bias,
        s.imu_accel_m_s2 - s.imu_accel_bias,
        s.imu_T_world_imu[0],
        s.imu_velocity_world_m_s[0],
        s.gravity_world_m_s2,
    )
    dR = np.einsum("nji,njk->nik", T[:, :3, :3], s.imu_T_world_imu[:, :3, :3])
    assert np.linalg.norm(so3_log(dR), axis=1).max() < 1e-4
    # without removing the biases the error is far larger
    assert _integrate_err(s, s.imu_gyro_rad_s, s.imu_accel_m_s2).max() > 0.1


def test_imu_noise_is_a_random_walk() -> None:
    """Integrated white gyro noise and the bias both spread like sqrt(t) (random walks)."""
    p = ImuNoiseParams(gyro_bias_std=0.0, accel_bias_std=0.0)
    rate, n, runs = 200.0, 2001, 400
    rng = np.random.default_rng(0)
    ang, bias = [], []
    for _ in range(runs):
        nz = simulate_imu_noise(n, rate, p, rng)
        ang.append(np.cumsum(nz.gyro_noise_rad_s[:, 0]) / rate)
        bias.append(nz.gyro_bias_rad_s[:, 2])
    ang, bias = np.array(ang), np.array(bias)
    k1, k4 = 500, 2000  # 2.5 s and 10 s
    r_ang = ang[:, k4].std() / ang[:, k1].std()
    r_bias = bias[:, k4].std() / bias[:, k1].std()
    assert r_ang == pytest.approx(2.0, rel=0.15) and r_bias == pytest.approx(2.0, rel=0.15)
    # angle random walk magnitude matches the noise density: std = sigma_g sqrt(t)
    assert ang[:, k4].std() == pytest.approx(p.gyro_noise_density * np.sqrt(10.0), rel=0.15)
    assert bias[:, k4].std() == pytest.approx(p.gyro_random_walk * np.sqrt(10.0), rel=0.15)


def test_imu_noise_on_dead_reckoning_drifts() -> None:
    s = make_sequence(SimConfig(seed=5, n_frames=101, width=64, height=32))
    err = _integrate_err(s, s.imu_gyro_rad_s - s.imu_gyro_bias, s.imu_accel_m_s2 - s.imu_accel_bias)
    k1 = np.searchsorted(s.imu_stamps_ns, s.imu_stamps_ns[0] + 1_000_000_000)
    assert err[-1] > 0.01 and err[-1] > 5 * err[k1]


def test_imu_switched_off_is_exact() -> None:
    s = make_sequence(
        SimConfig(seed=1, n_frames=3, width=64, height=32, imu_noise=ImuNoiseParams(enabled=False))
    )
    np.testing.assert_array_equal(s.imu_gyro_rad_s, s.imu_gyro_true_rad_s)
    assert not s.imu_accel_bias.any()
    # at rest along z: the accelerometer reads about +g upwards
    assert s.imu_accel_m_s2[:, 2].mean() == pytest.approx(9.81, abs=0.2)


def test_oxts_trajectory_too_short_raises() -> None:
    from mogs_node.sim.trajectory import default_oxts_dir

    if not default_oxts_dir().exists():
        pytest.skip(f"OXTS excerpt not found at {default_oxts_dir()}")
    with pytest.raises(ConfigError, match="n_frames"):
        make_sequence(SimConfig(n_frames=500, trajectory="oxts"))
    with pytest.raises(ConfigError, match="trajectory"):
        make_sequence(SimConfig(trajectory="circle"))


def test_simulated_lfm(seq_small) -> None:
    f = seq_small.render(0)
    rng = np.random.default_rng(0)
    clean = LfmParams(warp_amplitude=0.0, edge_blur_px=0.0, noise_std=0.0)
    out, truth = simulated_lfm_with_truth(f.depth_m, rng, clean)
    valid = np.isfinite(f.depth_m)
    np.testing.assert_allclose(
        (out[valid] - truth["shift"]) / truth["scale"], 1.0 / f.depth_m[valid], rtol=1e-5
    )
    noisy = simulated_lfm(f.depth_m, np.random.default_rng(1))
    assert noisy.dtype == np.float32 and noisy.shape == f.depth_m.shape
    assert np.all(np.isfinite(noisy)) and noisy.min() >= 0
    # affine-ambiguous but close after the best affine fit in inverse depth (except edges)
    q = 1.0 / f.depth_m[valid]
    A = np.c_[q, np.ones_like(q)]
    coef, *_ = np.linalg.lstsq(A, noisy[valid], rcond=None)
    rel = np.abs(A @ coef - noisy[valid]) / (A @ coef)
    assert np.median(rel) < 0.15 and np.median(rel) > 0.005  # distorted, not identical
    # sky maps to small values
    assert np.median(noisy[~valid]) < np.percentile(noisy[valid], 5)
    # ground truth untouched
    assert np.isinf(f.depth_m).any()


def test_render_arbitrary_pose(seq_small) -> None:
    s = seq_small
    T = s.T_world_cam[2].copy()
    a = s.render(2)
    b = s.world.render(T, s.camera)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    c = s.render_pose(T, s.camera.scaled(310, 94))
    assert c.rgb.shape == (94, 310, 3)


def test_sensor_events_order(seq_small) -> None:
    ev = seq_small.sensor_events()
    stamps = [t for t, _, _ in ev]
    assert stamps == sorted(stamps)
    assert sum(k == "image" for _, k, _ in ev) == len(seq_small)
    assert sum(k == "imu" for _, k, _ in ev) == len(seq_small.imu_stamps_ns)
    pos = {(k, i): n for n, (_, k, i) in enumerate(ev)}
    for i, t in enumerate(seq_small.stamps_ns):  # the IMU sample at the image stamp comes first
        j = int(np.searchsorted(seq_small.imu_stamps_ns, t))
        assert seq_small.imu_stamps_ns[j] == t and pos[("imu", j)] < pos[("image", i)]


def test_static_start_then_drive_off() -> None:
    s = make_sequence(
        SimConfig(
            seed=1,
            n_frames=81,
            width=64,
            height=32,
            static_start_s=2.0,
            imu_noise=ImuNoiseParams(enabled=False),
        )
    )
    t = (s.imu_stamps_ns - s.stamps_ns[0]) * 1e-9
    rest = t < 1.99
    assert np.abs(s.imu_velocity_world_m_s[rest]).max() < 1e-3
    np.testing.assert_allclose(s.imu_accel_m_s2[rest] - [0.0, 0.0, 9.81], 0.0, atol=2e-3)
    np.testing.assert_allclose(s.imu_gyro_rad_s[rest], 0.0, atol=5e-4)  # spline ringing << noise
    np.testing.assert_allclose(s.T_world_cam[0], s.T_world_cam[19], atol=1e-4)  # still at 1.9 s
    speed = np.linalg.norm(s.velocity_world_m_s, axis=1)
    assert speed[-1] > 7.0  # cruising after 8 s
    err = _integrate_err(s, s.imu_gyro_rad_s, s.imu_accel_m_s2)
    assert err.max() < 0.01
    with pytest.raises(ConfigError, match="static_start_s"):
        make_sequence(SimConfig(trajectory="oxts", static_start_s=1.0, n_frames=3))
