"""The keyframe policy around standstill (``StandstillKeyframes``, docs/frontend.md round 8)."""

from __future__ import annotations

import numpy as np
import pytest

from mogs_node.errors import ConfigError
from mogs_node.frontend.keyframes import KeyframeParams, StandstillKeyframes

S = 1_000_000_000  # ns per second


class Counter:
    """``count_points`` that records whether it was asked."""

    def __init__(self, n: int) -> None:
        self.n, self.calls = n, 0

    def __call__(self) -> int:
        self.calls += 1
        return self.n


def test_no_keyframe_while_still_whatever_the_parallax_policy_wants():
    gate = StandstillKeyframes(KeyframeParams())
    for k in range(5):
        assert gate.decide(True, True, k * S, np.zeros(3), Counter(500)) == (False, "standstill")
        assert gate.decide(False, True, k * S, np.zeros(3), Counter(500)) == (False, "")
    assert gate.holding


def test_the_first_keyframe_after_a_standstill_waits_for_its_points():
    p = KeyframeParams(first_min_points=100, first_max_motion_m=2.0, first_max_wait_s=2.0)
    gate = StandstillKeyframes(p)
    gate.decide(True, True, 0, np.zeros(3), Counter(0))  # parked at the origin
    few = Counter(99)
    assert gate.decide(True, False, S // 2, np.array([0.5, 0, 0]), few) == (False, "no_parallax")
    assert few.calls == 1
    assert gate.decide(False, False, S, np.array([0.6, 0, 0]), few) == (False, "")
    assert few.calls == 1  # not wanted by the parallax policy: not asked
    assert gate.decide(True, False, S, np.array([0.6, 0, 0]), Counter(100)) == (True, "")
    assert not gate.holding
    # once released, the parallax policy decides alone and nobody counts points
    after = Counter(0)
    assert gate.decide(True, False, 2 * S, np.array([5.0, 0, 0]), after) == (True, "")
    assert gate.decide(False, False, 3 * S, np.array([9.0, 0, 0]), after) == (False, "")
    assert after.calls == 0


@pytest.mark.parametrize(
    ("t_s", "position_m", "released"),
    [
        (1.0, [1.99, 0.0, 0.0], False),
        (1.0, [0.0, 2.0, 0.0], True),  # moved far enough: taken even with few points
        (1.99, [0.1, 0.0, 0.0], False),
        (2.0, [0.1, 0.0, 0.0], True),  # waited long enough (a crawl, a turn on the spot)
    ],
)
def test_the_hold_is_bounded_by_motion_and_time(t_s, position_m, released):
    gate = StandstillKeyframes(KeyframeParams(first_max_motion_m=2.0, first_max_wait_s=2.0))
    gate.parked(0, np.zeros(3))
    taken, _ = gate.decide(True, False, int(t_s * S), np.array(position_m), Counter(0))
    assert taken is released


def test_the_hold_counts_from_the_last_still_frame():
    gate = StandstillKeyframes(KeyframeParams(first_max_motion_m=2.0, first_max_wait_s=2.0))
    gate.parked(0, np.zeros(3))
    gate.decide(False, True, 5 * S, np.array([3.0, 0, 0]), Counter(0))  # still again, elsewhere
    assert gate.decide(True, False, 6 * S, np.array([4.0, 0, 0]), Counter(0))[0] is False
    gate.reset()  # a frontend reset forgets the standstill
    assert gate.decide(True, False, 6 * S, np.array([4.0, 0, 0]), Counter(0)) == (True, "")


def test_switched_off_the_parallax_policy_decides_alone():
    gate = StandstillKeyframes(KeyframeParams(hold_at_standstill=False))
    gate.parked(0, np.zeros(3))
    assert not gate.holding
    for wanted in (True, False):
        assert gate.decide(wanted, True, S, np.zeros(3), Counter(0)) == (wanted, "")


@pytest.mark.parametrize(
    "bad", [{"first_min_points": -1}, {"first_max_motion_m": -0.1}, {"first_max_wait_s": -1.0}]
)
def test_bad_hold_parameters_are_one_clear_error(bad):
    with pytest.raises(ConfigError, match=next(iter(bad))):
        KeyframeParams(**bad)


def _keyframe_with(uv_px, z_m, stamp_ns=7):
    from mogs_node.frontend.frontend import FrameOutput, KeyframeOutput

    n = len(z_m)
    xyz = np.zeros((n, 3), np.float32)
    xyz[:, 2] = z_m
    kf = KeyframeOutput(
        keyframe_id=0,
        stamp_ns=stamp_ns,
        image=np.zeros((20, 30), np.uint8),
        K=np.eye(3),
        T_world_cam=np.eye(4),
        feature_ids=np.arange(n),
        feature_uv_px=np.asarray(uv_px, np.float32),
        feature_xyz_cam_m=xyz,
        feature_cov_cam_m2=np.zeros((n, 3, 3), np.float32),
        feature_weight=np.ones(n, np.float32),
    )
    return FrameOutput(stamp_ns, 0, "tracking", np.eye(4), np.zeros(3), keyframe=kf)


def test_edge_figures_tell_a_silhouette_corner_from_a_straddling_point():
    """A 5 m box (columns < 15) in front of 20 m: points on the box's silhouette with the box's
    or the background's depth are on an edge but right; a depth between the two is wrong."""
    from mogs_node.eval.frontend_runs import keyframe_point_figures

    depth = np.full((20, 30), 20.0)
    depth[:, :15] = 5.0
    uv = [[14, 10], [15, 10], [14, 5], [5, 10], [25, 10]]  # 3 on the silhouette, 2 far from it
    z = [5.1, 19.0, 10.0, 5.0, 30.0]  # right, right, straddling, right, off by 50 % (not an edge)
    fig = keyframe_point_figures([_keyframe_with(uv, z)], lambda t: depth, lambda t: 1.0)
    assert fig["points_near_edges_share"] == pytest.approx(3 / 5)
    assert fig["points_on_edges_share"] == pytest.approx(1 / 5)  # straddling (issue 16)
    assert fig["points_on_edges_weight_share"] == pytest.approx(1 / 5)
    assert fig["points_per_keyframe_median"] == 5 and fig["keyframes_without_points"] == 0


def test_the_bench_replaces_the_points_block_and_its_note_once():
    """``bench/frontend.py --write-points-docs`` keeps the speed tables and replaces the points
    block with the previous run's note (it used to keep every old note)."""
    from bench.frontend_tables import with_new_points

    section = (
        "\n## Frontend\n\nSpeed table.\n\nSparse points block: old run.\n"
        "\nSparse points per keyframe (old)\n\n| old |\n"
        "\nCPU time per tracking frame: old.\n\nRun time against ATE: kept.\n"
    )
    new = with_new_points(section, ["", "Sparse points per keyframe (new)", "", "CPU time: new."])
    assert "old" not in new.replace("Run time against ATE: kept.", "")
    assert new.count("Sparse points per keyframe") == 1 and "Speed table." in new
    assert new.endswith("Run time against ATE: kept.")


def test_a_run_parked_throughout_is_scored_on_every_frame():
    """No keyframe while parked (the EuRoC excerpt hovers): the trajectory is scored on every
    frame instead of failing for want of keyframes."""
    from mogs_node.eval.frontend_runs import RunResult, score_run
    from mogs_node.frontend.frontend import FrameOutput

    stamps = (np.arange(6) * S // 10).astype(np.int64)
    gt = np.stack([np.eye(4)] * 6)
    gt[:, 0, 3] = 0.01 * np.arange(6) ** 2
    gt[:, 1, 3] = 0.002 * np.arange(6)
    outs = [
        FrameOutput(int(t), k, "tracking", gt[k].copy(), np.zeros(3)) for k, t in enumerate(stamps)
    ]
    fig = score_run(RunResult(outs, gt, stamps, {}, 1.0, {}))
    assert fig["scored_on"] == "frames" and fig["poses_scored"] == 6
    assert fig["ate_se3_rmse_m"] == pytest.approx(0.0, abs=1e-9)
