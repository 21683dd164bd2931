"""Camera-only frontend (issue 18): a drive without IMU gets metric poses from the essential
matrix and the road at the calibrated camera height; with the user's poses nothing is estimated
and the keyframes still get their sparse points. On the sim drive against its ground truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mogs_node.errors import ConfigError, DatasetError
from mogs_node.eval.traj import trajectory_metrics
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.ground import GroundParams
from mogs_node.frontend.monocular import MonocularFrontend, MonocularParams, road_aligned_start
from mogs_node.sim import SimConfig, make_sequence


@pytest.fixture(scope="module")
def drive():
    seq = make_sequence(SimConfig(seed=0, n_frames=40, width=621, height=188))
    return seq, [seq.render(i) for i in range(len(seq))]


def _run(seq, frames, *, given: bool):
    # the sim's vehicle calibration: the IMU 0.93 m above the road, the camera above it
    h = 0.93 + float(seq.T_imu_cam[2, 3])
    fe = MonocularFrontend(
        MonocularParams(ground=GroundParams(camera_height_m=h)),
        CameraModel(seq.camera),
        seq.T_imu_cam,
        given_poses=given,
    )
    outs = []
    for i, f in enumerate(frames):
        pose = seq.T_world_cam[i] if given else None
        outs += fe.add_image(int(seq.stamps_ns[i]), f.rgb, pose)
    return fe, outs


def _point_errors(outs, seq, frames) -> list[float]:
    errs = []
    by_stamp = {int(t): i for i, t in enumerate(seq.stamps_ns)}
    for o in outs:
        kf = o.keyframe
        if kf is None or not len(kf.feature_ids):
            continue
        d = frames[by_stamp[kf.stamp_ns]].depth_m
        uv = np.round(kf.feature_uv_px).astype(int)
        g = d[np.clip(uv[:, 1], 0, d.shape[0] - 1), np.clip(uv[:, 0], 0, d.shape[1] - 1)]
        errs.append(float(np.median(np.abs(kf.feature_xyz_cam_m[:, 2] / g - 1))))
    return errs


def test_camera_only_drive_is_metric(drive):
    seq, frames = drive
    fe, outs = _run(seq, frames, given=False)
    posed = [(o.stamp_ns, o.T_world_cam) for o in outs if o.T_world_cam is not None]
    assert len(posed) == len(seq)  # every frame placed (the first at the road-aligned start)
    idx = {int(t): i for i, t in enumerate(seq.stamps_ns)}
    stamps = np.array([s for s, _ in posed], np.int64)
    est = np.stack([T for _, T in posed])
    ref = seq.T_world_cam[[idx[int(s)] for s in stamps]]
    m = trajectory_metrics(stamps, est, ref)
    # issue 18: ATE < 2 % of the path, scale error < 3 % (measured: 0.6 % / 1.6 % on 60 frames)
    assert m["ate_se3_rmse_m"] < 0.02 * m["path_length_m"], m
    assert m["scale_error"] < 0.03, m
    # the road is clear on the sim: it carries the scale (the keyframes' road points find no
    # gross error, so the points never take over)
    assert fe.counters["ground_measurements"] >= 0.7 * len(seq)
    assert fe.counters["road_points_corrections"] == 0 and not fe.points_mode
    kfs = [o.keyframe for o in outs if o.keyframe is not None]
    assert len(kfs) >= 4 and all(len(k.feature_ids) for k in kfs[:3])
    assert np.median(_point_errors(outs, seq, frames)) < 0.12
    # the world is road-aligned: z up, the first camera at its height above the road
    np.testing.assert_allclose(est[0][2, 3], 0.93 + seq.T_imu_cam[2, 3])


def test_given_poses_give_points_and_keep_the_poses(drive):
    seq, frames = drive
    fe, outs = _run(seq, frames, given=True)
    for o in outs:
        i = int(np.flatnonzero(seq.stamps_ns == o.stamp_ns)[0])
        np.testing.assert_array_equal(o.T_world_cam, seq.T_world_cam[i])
    assert fe.counters["poses_given"] == len(seq) - 1 and fe.counters["poses_essential"] == 0
    kfs = [o.keyframe for o in outs if o.keyframe is not None]
    assert len(kfs) >= 4 and min(len(k.feature_ids) for k in kfs) >= 80
    assert np.median(_point_errors(outs, seq, frames)) < 0.03


def test_camera_only_needs_the_camera_height_and_rectified_images(drive):
    seq, _ = drive
    with pytest.raises(ConfigError, match="camera height"):
        MonocularFrontend(MonocularParams(), CameraModel(seq.camera))
    fe = MonocularFrontend(MonocularParams(), CameraModel(seq.camera), given_poses=True)
    out = fe.add_image(5, np.zeros((188, 621), np.uint8))  # a frame without a pose of its own
    assert out[0].status == "no_pose" and out[0].T_world_cam is None
    with pytest.raises(ConfigError, match="rectified"):
        MonocularFrontend(
            MonocularParams(ground=GroundParams(camera_height_m=1.6)),
            CameraModel(seq.camera, "radtan", (0.1, 0.0, 0.0, 0.0)),
        )


def test_the_speed_gate_rejects_an_outlier_but_follows_a_change_of_speed(drive):
    """One road measurement far from the recent ones is gated; ``relock_after`` of them in a row
    on one side are a change of speed and are taken (before, the first median held for the rest
    of a drive). Not the KITTI excerpt's case, as first thought: its road speeds rose from 0.8 to
    ~1.5 m/s while the car decelerated from 2.4 m/s to a stop (the LiDAR-PnP trajectory); the
    road read 3x low under the vehicle ahead (docs/frontend.md, rounds 11 and 12)."""
    seq, _ = drive
    fe = MonocularFrontend(
        MonocularParams(ground=GroundParams(camera_height_m=1.6), relock_after=3),
        CameraModel(seq.camera),
    )
    got = [fe._gate(s) for s in (1.0, 1.1, 0.9, 3.0, 1.0, 2.0, 2.1, 0.5, 2.0, 2.2, 1.9)]
    # the outlier 3.0 and the 0.5 among the faster ones are gated; the run 2.0, 2.1 is broken by
    # the 0.5; 2.0, 2.2, 1.9 (3 in a row above the median) become the recent speeds
    assert got == [1.0, 1.1, 0.9, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.9]
    assert fe.counters["ground_gated"] == 6 and fe.counters["ground_relocked"] == 1
    assert fe._gate(2.05) == 2.05  # the new speed is the reference now
    with pytest.raises(ConfigError, match="relock_after"):
        MonocularParams(relock_after=1)


def test_road_aligned_start_puts_the_camera_above_the_road():
    T = road_aligned_start(np.array([0.0, 1.0, 0.0]), 1.65)
    np.testing.assert_allclose(T[:3, :3] @ [0.0, 1.0, 0.0], [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.0, 1.65])


def test_user_poses_tum_and_kitti(tmp_path, drive):
    from mogs_node.datasets.vi_folder import read_user_poses
    from mogs_node.frontend.trajectory_io import write_kitti, write_tum

    seq, _ = drive
    write_tum(tmp_path / "p.tum", seq.stamps_ns[::2], seq.T_world_cam[::2])
    got = read_user_poses(tmp_path / "p.tum", seq.stamps_ns)
    np.testing.assert_allclose(got[4], seq.T_world_cam[4], atol=1e-8)  # on a line
    assert got[3] is not None and got[-1] is None  # interpolated inside, none outside the span
    np.testing.assert_allclose(got[3][:3, 3], seq.T_world_cam[3][:3, 3], atol=0.02)
    write_kitti(tmp_path / "p.txt", seq.T_world_cam)
    got = read_user_poses(tmp_path / "p.txt", seq.stamps_ns)
    np.testing.assert_allclose(np.stack(got), seq.T_world_cam, atol=1e-8)
    with pytest.raises(DatasetError, match="KITTI poses for"):
        read_user_poses(tmp_path / "p.txt", seq.stamps_ns[:5])
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match="got 3 columns"):
        read_user_poses(tmp_path / "bad.txt", seq.stamps_ns)


def test_given_poses_take_no_keyframe_while_parked():
    """With given poses the keyframes follow ``frontend.keyframes`` (the visual-inertial policy):
    none while the car stands still at the start, then the first once it carries points."""
    from mogs_node.frontend.keyframes import KeyframeParams

    seq = make_sequence(SimConfig(seed=0, n_frames=24, width=621, height=188, static_start_s=1.0))
    kp = KeyframeParams(min_parallax_px=20.0, max_interval_s=0.5)
    fe = MonocularFrontend(
        MonocularParams(keyframes=kp), CameraModel(seq.camera), seq.T_imu_cam, given_poses=True
    )
    taken = []
    for i in range(len(seq)):
        for o in fe.add_image(int(seq.stamps_ns[i]), seq.render(i).rgb, seq.T_world_cam[i]):
            if o.keyframe is not None:
                taken.append((i, len(o.keyframe.feature_ids)))
    moving = np.linalg.norm(np.diff(seq.T_world_cam[:, :3, 3], axis=0), axis=1) >= 0.01
    first_move = int(np.argmax(moving)) + 1
    assert first_move >= 9 and taken, taken  # parked for ~1 s
    assert taken[0][0] > first_move  # none while parked (max_interval_s alone would take 2)
    moved_m = np.linalg.norm(seq.T_world_cam[taken[0][0], :3, 3] - seq.T_world_cam[0, :3, 3])
    assert taken[0][1] >= 100 or moved_m >= 2.0, (taken, moved_m)  # waits for its points


def _frames_with_a_stop(seq, frames, at: int, n_still: int):
    """The drive with a stop: frame ``at`` repeated ``n_still`` times (the car stands, the world
    is static: the same image), the rest of the drive shifted later. Stamps, images, true poses."""
    period = int(seq.stamps_ns[1] - seq.stamps_ns[0])
    order = list(range(at + 1)) + [at] * n_still + list(range(at + 1, len(seq)))
    stamps = int(seq.stamps_ns[0]) + period * np.arange(len(order), dtype=np.int64)
    return stamps, [frames[i].rgb for i in order], seq.T_world_cam[order]


def test_camera_only_stands_still_while_the_car_stops(drive):
    """A stop in the drive (the images stand still): zero motion, not the last speed (before,
    a failed road measurement while parked kept the car driving: 0.56 m/s on KITTI); the drive
    after it stays metric."""
    seq, frames = drive
    at, n_still = 24, 6
    stamps, images, T_true = _frames_with_a_stop(seq, frames, at, n_still)
    h = 0.93 + float(seq.T_imu_cam[2, 3])
    fe = MonocularFrontend(
        MonocularParams(ground=GroundParams(camera_height_m=h)),
        CameraModel(seq.camera),
        seq.T_imu_cam,
    )
    pos = {}
    for t, img in zip(stamps, images):
        for o in fe.add_image(int(t), img):
            pos[o.stamp_ns] = o.T_world_cam[:3, 3]
    assert len(pos) == len(stamps)
    still = np.stack([pos[int(t)] for t in stamps[at : at + n_still + 1]])
    assert np.abs(still - still[0]).max() < 1e-9  # exactly no motion while standing
    assert fe.counters["standstill_frames"] == n_still
    est = np.stack([np.eye(4)] * len(stamps))
    est[:, :3, 3] = np.stack([pos[int(t)] for t in stamps])
    m = trajectory_metrics(stamps, est, T_true)
    assert m["ate_sim3_rmse_m"] < 0.02 * m["path_length_m"], m
    assert m["scale_error"] < 0.03, m


def test_a_road_biased_low_is_caught_by_the_keyframes_road_points(drive, monkeypatch):
    """The road measurement reading 3x low (as under the vehicle ahead on KITTI): a keyframe's
    own road points (their height below the camera against the calibrated one) find the gross
    error, the points carry the scale from there, and the later keyframes' points are metric
    against the sim's true depth; without the check they stay 3x short."""
    import mogs_node.frontend.monocular as mono

    real = mono.estimate_ground_translation

    def biased(*args, **kwargs):
        m = real(*args, **kwargs)
        return None if m is None else replace(m, tau=m.tau / 3, distance_m=m.distance_m / 3)

    monkeypatch.setattr(mono, "estimate_ground_translation", biased)
    seq, frames = drive
    h = 0.93 + float(seq.T_imu_cam[2, 3])
    errs = {}
    for check in (5, 0):
        fe = MonocularFrontend(
            MonocularParams(ground=GroundParams(camera_height_m=h), road_points_min=check),
            CameraModel(seq.camera),
            seq.T_imu_cam,
        )
        outs = []
        for i, f in enumerate(frames):
            outs += fe.add_image(int(seq.stamps_ns[i]), f.rgb)
        errs[check] = _point_errors(outs, seq, frames)
        if check:
            assert fe.counters["road_points_corrections"] >= 1
    assert len(errs[5]) >= 5 and np.median(errs[0]) > 0.5  # 3x short: depth -67 %
    assert errs[5][0] > 0.5 and max(errs[5][2:]) < 0.1, errs[5]  # metric once checked
