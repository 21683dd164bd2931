"""The frontend core on rendered sim images: tracking quality at 10 Hz, the stream guards (time
going backwards, IMU gaps, late IMU, dropped frames, bad samples) and keyframe output."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from mogs_node.errors import ConfigError
from mogs_node.eval.frontend_runs import DEFAULT_DATA
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.frontend import Frontend, FrontendParams
from mogs_node.frontend.initialization import InitParams
from mogs_node.frontend.keyframes import KeyframeParams
from mogs_node.frontend.tracker import FeatureTracker, TrackerParams
from mogs_node.geometry import se3_inverse
from mogs_node.sim import GRAVITY_WORLD_M_S2, SimConfig, make_sequence


@cache
def sim(n_frames: int = 12, width: int = 621, height: int = 188):
    seq = make_sequence(SimConfig(seed=0, n_frames=n_frames, width=width, height=height))
    frames = [seq.render(i) for i in range(n_frames)]
    return seq, frames


OXTS = DEFAULT_DATA / "kitti_raw_2011_09_26_drive_0001_oxts"


def test_tracker_keeps_80_percent_of_trackable_features_on_sim_at_10hz():
    """Of the features whose true position stays in the image (ground-truth depth and poses), at
    least 80 % are kept frame to frame, and kept tracks are accurate."""
    seq, frames = sim()
    cam = seq.camera
    tr = FeatureTracker(TrackerParams(), CameraModel(cam))
    kept = trackable = 0
    errs = []
    prev = None
    for i, fr in enumerate(frames):
        res = tr.track(fr.rgb)
        if prev is not None:
            ids0, uv0, d0 = prev
            P = cam.backproject(uv0, np.where(np.isfinite(d0), d0, 1.0))  # sky: masked below
            T = se3_inverse(seq.T_world_cam[i]) @ seq.T_world_cam[i - 1]
            uv_true, front = cam.project(P @ T[:3, :3].T + T[:3, 3])
            inside = front & cam.in_image(uv_true) & np.isfinite(d0)
            inside &= (uv_true[:, 0] > 3) & (uv_true[:, 0] < cam.width - 4)
            inside &= (uv_true[:, 1] > 3) & (uv_true[:, 1] < cam.height - 4)
            is_kept = np.isin(ids0, res.ids)
            kept += np.count_nonzero(inside & is_kept)
            trackable += np.count_nonzero(inside)
            _, ia, ib = np.intersect1d(ids0, res.ids, return_indices=True)
            errs.append(np.linalg.norm(uv_true[ia] - res.uv_px[ib], axis=1)[inside[ia]])
        r = np.clip(np.round(res.uv_px).astype(int), 0, [cam.width - 1, cam.height - 1])
        prev = (res.ids, res.uv_px, fr.depth_m[r[:, 1], r[:, 0]].astype(float))
    assert trackable > 500
    assert kept / trackable >= 0.8
    assert np.median(np.concatenate(errs)) < 0.5


def parked_stream(seconds: float, rate_hz: float = 10.0, imu_hz: float = 200.0, seed: int = 0):
    """A parked car: one rendered view repeated, IMU reading gravity plus noise and bias."""
    seq, frames = sim()
    rng = np.random.default_rng(seed)
    R = seq.T_world_imu[0, :3, :3]
    t_img = (1_000_000_000 + np.arange(int(seconds * rate_hz)) * 1e9 / rate_hz).astype(np.int64)
    t_imu = t_img[0] - 1_100_000_000 + np.arange(int((seconds + 1.2) * imu_hz)) * 1e9 / imu_hz
    t_imu = t_imu.astype(np.int64)
    gyro = np.array([1e-3, -2e-3, 5e-4]) + rng.normal(0, 2.4e-3, (len(t_imu), 3))
    acc = R.T @ -GRAVITY_WORLD_M_S2 + rng.normal(0, 0.03, (len(t_imu), 3))
    return seq, frames[0].rgb, t_img, t_imu, gyro, acc


def feed(fe, t_img, image, t_imu, gyro, acc, *, skip=()):
    outs, k = [], 0
    for i, t in enumerate(t_img.tolist()):
        while k < len(t_imu) and t_imu[k] <= t:
            outs += fe.add_imu(int(t_imu[k]), gyro[k], acc[k])
            k += 1
        if i not in skip:
            outs += fe.add_image(t, image)
    return outs


def test_parked_static_init_and_no_drift():
    seq, img, t_img, t_imu, gyro, acc = parked_stream(3.0)
    fe = Frontend(FrontendParams(), CameraModel(seq.camera), seq.T_imu_cam)
    outs = feed(fe, t_img, img, t_imu, gyro, acc)
    assert fe.counters["static_inits"] == 1 and fe.counters["dynamic_inits"] == 0
    poses = np.array([o.T_world_cam for o in outs if o.T_world_cam is not None])
    assert len(poses) >= len(t_img) - 2
    assert np.all(np.isfinite(poses))
    assert np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1).max() < 0.02
    # gravity: the camera's world-up is the truth's (the world frame's yaw is arbitrary)
    up_est = poses[-1, :3, :3].T @ np.array([0, 0, 1.0])
    up_true = seq.T_world_cam[0, :3, :3].T @ np.array([0, 0, 1.0])
    assert np.degrees(np.arccos(np.clip(up_est @ up_true, -1, 1))) < 1.0
    # parked: nothing new to map and no parallax for points, so no keyframe (round 8) ...
    assert not any(o.keyframe is not None for o in outs)
    assert fe.counters["keyframes_skipped_standstill"] >= 3  # 3 s at max_interval_s 0.5
    # ... unless asked for (the policy before round 8): then every keyframe is well formed
    params = FrontendParams(keyframes=KeyframeParams(hold_at_standstill=False))
    fe = Frontend(params, CameraModel(seq.camera), seq.T_imu_cam)
    kfs = [o.keyframe for o in feed(fe, t_img, img, t_imu, gyro, acc) if o.keyframe is not None]
    assert len(kfs) >= 4 and all(k.image.shape == img.shape for k in kfs)
    assert [k.keyframe_id for k in kfs] == list(range(len(kfs)))


def test_time_going_backwards_and_bad_samples_are_rejected_and_counted():
    seq, img, t_img, t_imu, gyro, acc = parked_stream(1.5)
    fe = Frontend(FrontendParams(), CameraModel(seq.camera), seq.T_imu_cam)
    feed(fe, t_img, img, t_imu, gyro, acc)
    n_frames = fe.counters["frames"]
    assert fe.add_image(int(t_img[-1]), img) == []  # same stamp
    assert fe.add_image(int(t_img[0]), img) == []  # back in time
    assert fe.counters["image_time_backwards"] == 2
    assert fe.add_imu(int(t_imu[5]), gyro[5], acc[5]) == []
    assert fe.counters["imu_time_backwards"] == 1
    assert fe.add_imu(int(t_imu[-1]) + 5_000_000, (np.nan, 0, 0), acc[0]) == []
    assert fe.add_imu(int(t_imu[-1]) + 5_000_000, (0, 0), acc[0]) == []
    assert fe.counters["bad_input"] == 2
    assert fe.counters["frames"] == n_frames


def test_frame_waits_for_its_imu():
    seq, img, t_img, t_imu, gyro, acc = parked_stream(1.0)
    fe = Frontend(FrontendParams(), CameraModel(seq.camera), seq.T_imu_cam)
    k = int(np.searchsorted(t_imu, t_img[0]))
    fe.add_imu_batch(t_imu[: k - 3], gyro[: k - 3], acc[: k - 3])
    assert fe.add_image(int(t_img[0]), img) == []  # IMU not there yet
    outs = fe.add_imu_batch(t_imu[k - 3 : k + 1], gyro[k - 3 : k + 1], acc[k - 3 : k + 1])
    assert len(outs) == 1 and outs[0].stamp_ns == t_img[0]


def test_imu_gap_resets_and_recovers_without_nan():
    seq, img, t_img, t_imu, gyro, acc = parked_stream(4.0)
    hole = (t_imu > t_img[20]) & (t_imu < t_img[22])  # 200 ms without IMU after init
    fe = Frontend(FrontendParams(), CameraModel(seq.camera), seq.T_imu_cam)
    outs = feed(fe, t_img, img, t_imu[~hole], gyro[~hole], acc[~hole])
    assert fe.counters["imu_gap_resets"] == 1
    assert fe.counters["static_inits"] == 2  # re-initialised after the gap
    assert any(o.status == "reset" for o in outs)
    assert all(np.all(np.isfinite(o.T_world_cam)) for o in outs if o.T_world_cam is not None)
    assert outs[-1].T_world_cam is not None


def test_dropped_frames_keep_tracking():
    seq, img, t_img, t_imu, gyro, acc = parked_stream(3.0)
    fe = Frontend(FrontendParams(), CameraModel(seq.camera), seq.T_imu_cam)
    outs = feed(fe, t_img, img, t_imu, gyro, acc, skip=set(range(15, 25)))
    assert fe.counters["imu_gap_resets"] == 0
    poses = np.array([o.T_world_cam for o in outs if o.T_world_cam is not None])
    assert np.all(np.isfinite(poses))
    assert np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1).max() < 0.02


def test_params_are_validated():
    with pytest.raises(ConfigError):
        FrontendParams(init_mode="magic")
    with pytest.raises(ConfigError):
        InitParams(dyn_frames=2)


def test_driving_off_is_not_taken_for_standstill():
    """Parked, then accelerating at 1 m/s^2 with (almost) no image flow: the zero-motion factors
    must let go (gravity-compensated acceleration), the velocity follows the IMU, no reset."""
    seq, img, t_img, t_imu, gyro, acc = parked_stream(3.0)
    R = seq.T_world_imu[0, :3, :3]
    t_go = int(t_img[15])
    a_world = R @ np.array([1.0, 0.0, 0.0])  # along the IMU's x axis, level
    a_world[2] = 0.0
    moving = t_imu > t_go
    acc = acc.copy()
    acc[moving] += R.T @ a_world
    fe = Frontend(FrontendParams(), CameraModel(seq.camera), seq.T_imu_cam)
    outs = feed(fe, t_img, img, t_imu, gyro, acc)
    assert fe.counters["divergence_resets"] == 0 and fe.counters["static_inits"] == 1
    v_true = np.linalg.norm(a_world) * (t_img[-1] - t_go) * 1e-9
    v_est = np.linalg.norm(outs[-1].velocity_world_m_s)
    assert abs(v_est - v_true) < 0.25 * v_true


def test_sim_evaluation_starts_parked_by_default():
    """``mogs eval traj --dataset sim`` starts with a standstill (static initialisation fixes the
    metric scale); a moving start stays available, the OXTS drive has no standstill."""
    from mogs_node.errors import DatasetError
    from mogs_node.eval.frontend_runs import SIM_STATIC_START_S, load_dataset

    d = load_dataset("sim", seconds=3.0)
    parked = d["stamps_ns"] - d["stamps_ns"][0] < (SIM_STATIC_START_S - 0.1) * 1e9
    assert SIM_STATIC_START_S >= 1.5 and np.any(parked)
    assert np.abs(d["velocity"][parked]).max() < 1e-3
    assert np.linalg.norm(d["velocity"][-1]) > 0.1
    moving = load_dataset("sim", seconds=3.0, static_start_s=0.0)
    assert np.linalg.norm(moving["velocity"][0]) > 5.0
    with pytest.raises(DatasetError, match="standstill"):
        load_dataset("oxts", static_start_s=2.0)
    with pytest.raises(DatasetError, match="parked"):
        load_dataset("sim", seconds=1.0)


@pytest.mark.skipif(not OXTS.exists(), reason=f"{OXTS} absent (../shared/data)")
def test_oxts_drive_meets_the_issue_bounds():
    """Issue 6 goal on the drive along the real KITTI OXTS trajectory (dynamic initialisation, the
    road measured at the camera's calibrated height): ATE after SE(3) alignment under 1 % of the
    distance and metric scale error under 2 %, with the scale set at the initialisation from the
    road (the first pose within 1 s). Camera + IMU alone: test below."""
    from mogs_node.eval.frontend_runs import run_dataset

    f = run_dataset("oxts", ground=True)
    assert f["resets"] == 0
    assert f["first_pose_s"] < 1.0
    assert f["ate_se3_percent_of_path"] < 1.0
    assert f["scale_error"] < 0.02


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="camera + IMU alone (no road): the metric scale is not observable on the "
    "decelerating OXTS drive without a standstill (docs/frontend.md, rounds 3-5)",
)
def test_oxts_drive_without_the_road_meets_the_issue_bounds():
    """The same bounds with the visual-inertial estimate only. Measured: 6.2 % and 26 %."""
    from mogs_node.eval.frontend_runs import run_dataset

    f = run_dataset("oxts")
    assert f["resets"] == 0
    assert f["ate_se3_percent_of_path"] < 1.0
    assert f["scale_error"] < 0.02


def test_image_of_another_size_is_rejected_and_counted():
    seq, img, t_img, t_imu, gyro, acc = parked_stream(1.0)
    fe = Frontend(FrontendParams(), CameraModel(seq.camera), seq.T_imu_cam)
    feed(fe, t_img, img, t_imu, gyro, acc)
    n_frames = fe.counters["frames"]
    t_next = int(t_img[-1]) + 100_000_000
    assert fe.add_image(t_next, img[::2, ::2]) == []
    assert fe.add_image(t_next + 1, img[:, :, 0].ravel()) == []
    assert fe.counters["image_wrong_size"] == 2 and fe.counters["frames"] == n_frames
    assert fe.pending_stamps_ns == []  # nothing queued for the KLT
