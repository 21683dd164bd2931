"""The frontend's refined keyframe poses (``Frontend.window_keyframe_poses``, published by the node
on ``/frontend/refined_pose``; the ROS bridges' path follows them): only keyframes, each moved by
the window's later solves, and the refined keyframe trajectory closer to the truth than the poses
first published (a sim drive with a static start, ground truth by stamp)."""

from __future__ import annotations

import numpy as np

from mogs_node.eval.traj import trajectory_metrics
from mogs_node.frontend.camera import CameraModel
from mogs_node.frontend.frontend import Frontend, FrontendParams
from mogs_node.frontend.keyframes import KeyframeParams
from mogs_node.sim import SimConfig, make_sequence


def test_window_refines_the_published_keyframe_poses() -> None:
    seq = make_sequence(SimConfig(seed=0, n_frames=40, width=621, height=188, static_start_s=2.0))
    params = FrontendParams(keyframes=KeyframeParams(min_parallax_px=20.0, max_interval_s=1.0))
    fe = Frontend(params, CameraModel(seq.camera), seq.T_imu_cam)
    assert fe.window_keyframe_poses() == []  # not initialised
    published: dict[int, np.ndarray] = {}
    refined: dict[int, np.ndarray] = {}
    for t, kind, k in seq.sensor_events():
        if kind == "imu":
            outs = fe.add_imu(int(t), seq.imu_gyro_rad_s[k], seq.imu_accel_m_s2[k])
        else:
            outs = fe.add_image(int(t), seq.render(k).rgb)
        for o in outs:
            if o.keyframe is not None:
                published[o.keyframe.stamp_ns] = o.keyframe.T_world_cam.copy()
        if outs:
            window = fe.window_keyframe_poses()
            assert {s for s, _ in window} <= set(published)  # keyframes only, by camera stamp
            refined.update(window)
    assert len(published) >= 4 and set(refined) == set(published)
    moved = [np.linalg.norm(refined[s][:3, 3] - published[s][:3, 3]) for s in published]
    assert max(moved) > 1e-3 and max(moved) < 0.1  # refined by the window, not a jump
    stamps = np.array(sorted(published), np.int64)
    truth = {int(t): T for t, T in zip(seq.stamps_ns, seq.T_world_cam)}
    gt = np.array([truth[int(s)] for s in stamps])
    first = trajectory_metrics(stamps, np.array([published[s] for s in stamps]), gt)
    final = trajectory_metrics(stamps, np.array([refined[s] for s in stamps]), gt)
    assert final["ate_se3_rmse_m"] < first["ate_se3_rmse_m"], (final, first)
