"""The frontend's refined keyframe poses (``Frontend.window_keyframe_poses``, published by the node
on ``/frontend/refined_pose``; the ROS bridges' path follows them): only keyframes, each moved by
the window's later solves, and the refined keyframe trajectory closer to the truth than the poses
first published (a sim drive with a static start, ground truth by stamp)."""

from __future__ import annotations

from mogs_node.eval.frontend_runs import window_refinement
from mogs_node.frontend.frontend import FrontendParams
from mogs_node.frontend.keyframes import KeyframeParams
from mogs_node.sim import SimConfig, make_sequence


def test_window_refines_the_published_keyframe_poses() -> None:
    seq = make_sequence(SimConfig(seed=0, n_frames=40, width=621, height=188, static_start_s=2.0))
    params = FrontendParams(keyframes=KeyframeParams(min_parallax_px=20.0, max_interval_s=1.0))
    r = window_refinement(seq, params)
    assert r["window_not_keyframe"] == 0  # keyframes only, by camera stamp
    # every keyframe moved by later solves, but the last (the drive ends: no solve after it)
    assert r["keyframes"] >= 4 and r["refined"] >= r["keyframes"] - 1
    assert 1e-3 < r["max_move_m"] < 0.1  # refined by the window, not a jump
    assert r["ate_refined_m"] < r["ate_first_m"], r
