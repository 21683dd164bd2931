"""Issue 28: the keyframe chain waits for late inputs, sheds whole keyframes, names failures."""

from __future__ import annotations

import functools
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node import msgs
from mogs_node.errors import ConfigError
from mogs_node.frontend.backlog import BacklogParams, KeyframeBacklog
from mogs_node.geometry import make_T
from mogs_node.keyframe_chain import failed_masks, failed_prior, failure_reason
from mogs_node.launch import _child_setup, parse_launch, usable_cpus
from mogs_node.metrizer.node import KeyframeMatcher
from mogs_node.worker_budget import ScaleBudget, ScaleBudgetParams

sys.path.insert(0, str(Path(__file__).parents[1]))  # tests/: the helpers
from _two_view_scene import CAM, render  # noqa: E402


def keyframe_pose(kid: int) -> np.ndarray:
    return make_T(np.eye(3), np.array([0.05 * kid, 0.0, 0.3 * kid]))


def keyframe(kid: int) -> msgs.Keyframe:
    """Keyframe ``kid`` of a camera moving forward 0.3 m per keyframe in the two-view scene."""
    T = keyframe_pose(kid)
    grey, depth = render(T)
    uv = np.array([[100.0, 120.0], [240.0, 140.0], [400.0, 100.0], [300.0, 60.0]], np.float32)
    z = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    xyz = CAM.backproject(uv.astype(np.float64), z).astype(np.float32)
    return msgs.Keyframe(
        stamp_ns=kid * 100_000_000,
        frame_id="cam",
        keyframe_id=kid,
        image=np.repeat(grey[..., None], 3, axis=2),
        K=CAM.K,
        T_world_cam=T,
        feature_ids=np.arange(len(uv), dtype=np.int64),
        feature_uv_px=uv,
        feature_xyz_cam_m=xyz,
        feature_weight=np.ones(len(uv), np.float32),
    )


# ------------------------------------------------------------------ the metrizer's wait


def test_a_late_prior_is_waited_for_while_its_worker_advances():
    """A prior worker with a backlog of 3 keyframes, 1.5 s each: no keyframe goes without its
    prior although every prior comes long after the 2 s that used to be the fixed wait."""
    m = KeyframeMatcher(max_wait_s=2.0)
    for kid in range(4):
        m.add("keyframe", kid, f"K{kid}", 0.0)
        m.add("masks", kid, f"M{kid}", 0.1)
    released = []
    for kid in range(4):
        t = 1.5 * (kid + 1)
        for tick in np.arange(t - 1.4, t, 0.05):  # the timer between the priors
            assert m.expire(float(tick)) == []
        released += m.add("prior", kid, f"P{kid}", t)
    assert [e.keyframe_id for e in released] == [0, 1, 2, 3]
    assert all(e.complete and not e.missing for e in released)
    assert m.counters["partial"] == 0 and m.counters["complete"] == 4


def test_a_silent_worker_is_given_up_after_its_backlog_and_named():
    m = KeyframeMatcher(max_wait_s=2.0, stall_factor=2.0)
    for kid in range(3):  # the prior worker answers every 1 s, then falls silent
        m.add("keyframe", kid, "K", float(kid))
        m.add("masks", kid, "M", float(kid))
        m.add("prior", kid, "P", float(kid) + 1.0)
    m.add("keyframe", 3, "K", 3.0)
    m.add("masks", 3, "M", 3.0)
    m.add("keyframe", 4, "K", 3.0)
    m.add("masks", 4, "M", 3.0)
    # last prior at 3.0 s, interval 1 s: keyframe 3 waits 2 + 2 * 1 * 1 s, keyframe 4 2 + 2 * 2 s
    assert m.expire(6.99) == []
    out = m.expire(7.0)
    assert [e.keyframe_id for e in out] == [3]
    assert out[0].missing == {"prior": "prior worker silent for 4.0 s"}
    assert [e.keyframe_id for e in m.expire(9.0)] == [4]
    assert m.counters["stalled_inputs"] == 2 and m.counters["partial"] == 2
    assert m.add("prior", 3, "P", 9.5) == [] and m.counters["dropped"] == 1  # too late now


def test_a_worker_whose_heartbeat_goes_on_is_waited_for():
    """A prior that takes 40 s on a loaded machine: its worker's heartbeats keep the keyframe
    waiting; once they stop (a dead worker), the keyframe goes without it."""
    m = KeyframeMatcher(max_wait_s=2.0)
    m.add("prior", 0, "P", 0.0)  # the worker's first output
    m.add("keyframe", 1, "K", 1.0)
    m.add("masks", 1, "M", 1.0)
    for t in np.arange(1.0, 41.0, 1.0):
        m.worker_alive("prior", float(t))
        assert m.expire(float(t) + 0.5) == []
    assert [e.keyframe_id for e in m.add("prior", 1, "P", 41.0)] == [1]
    m.add("keyframe", 2, "K", 42.0)
    m.add("masks", 2, "M", 42.0)
    m.worker_alive("prior", 43.0)  # its last heartbeat
    assert m.expire(44.9) == []
    assert m.expire(45.0 + 2.0 * m.pace["prior"].interval_s)[0].missing == {
        "prior": f"prior worker silent for {2.0 + 2.0 * m.pace['prior'].interval_s:.1f} s"
    }


def test_before_the_first_output_a_worker_gets_the_start_up_wait_once():
    m = KeyframeMatcher(max_wait_s=2.0, first_wait_s=30.0)
    m.add("keyframe", 0, "K", 0.0)
    m.add("masks", 0, "M", 0.0)
    assert m.expire(29.9) == []
    assert m.expire(30.0)[0].missing == {"prior": "prior worker silent for 30.0 s"}
    m.add("keyframe", 1, "K", 31.0)
    m.add("masks", 1, "M", 31.0)
    assert [e.keyframe_id for e in m.expire(33.0)] == [1]  # no worker: no start-up wait again


def test_a_failure_notice_releases_the_keyframe_at_once_with_its_reason():
    m = KeyframeMatcher(max_wait_s=100.0)
    kf = keyframe(5)
    m.add("keyframe", 5, kf, 0.0)
    m.add("masks", 5, "M", 0.0)
    notice = failed_prior(kf, RuntimeError("out of memory"))
    out = m.add("prior", 5, notice, 0.1, failure_reason(notice))
    assert [e.keyframe_id for e in out] == [5] and out[0].prior is None
    assert out[0].missing == {"prior": "prior backend failed: RuntimeError: out of memory"}
    assert m.counters["failed_inputs"] == 1 and m.counters["partial"] == 1


def test_failure_notices_carry_nothing_but_the_reason():
    kf = keyframe(3)
    masks = failed_masks(kf, "SAM session died")
    prior = failed_prior(kf, ValueError("bad\n  shape"))
    assert failure_reason(masks) == "SAM session died"
    assert failure_reason(prior) == "ValueError: bad shape"
    assert masks.labels.shape == kf.image.shape[:2] and np.all(masks.labels == -1)
    assert not prior.confidence.any() and prior.keyframe_id == 3
    for m in (masks, prior):  # valid on the wire
        env = msgs.decode(msgs.encode("/x", m))
        assert failure_reason(env.msg) == failure_reason(m)
    ordinary = msgs.Masks(**kf.result_header(), labels=masks.labels, backend="graph")
    assert failure_reason(ordinary) is None


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 7), st.sampled_from(("keyframe", "masks", "prior"))),
        max_size=40,
    ),
    st.floats(0.0, 5.0),
)
def test_every_keyframe_is_released_once_and_complete_sets_at_once(arrivals, max_wait_s):
    """Any arrival order: a set is released the moment it is complete, every keyframe at most
    once, and after the workers fall silent long enough every keyframe is released."""
    m = KeyframeMatcher(max_wait_s=max_wait_s)
    seen: dict[int, set[str]] = {}
    released: list[int] = []
    for i, (kid, slot) in enumerate(arrivals):
        seen.setdefault(kid, set()).add(slot)
        out = m.add(slot, kid, slot, 0.01 * i)
        released += [e.keyframe_id for e in out]
        if seen[kid] == {"keyframe", "masks", "prior"} and kid not in released:
            pytest.fail(f"keyframe {kid} complete but not released")
    released += [e.keyframe_id for e in m.expire(1e6)]
    assert len(released) == len(set(released))
    assert set(released) == {k for k, s in seen.items() if "keyframe" in s}
    assert len(m) == 0


# ------------------------------------------------------------------ shedding whole keyframes


def test_backlog_sheds_whole_keyframes_and_counts_them():
    b = KeyframeBacklog(BacklogParams(max_backlog=2))
    assert b.admit(0) is None and b.admit(1) is None
    assert b.admit(2) == "backlog: 2 keyframes in the chain (max 2)"
    assert b.admit(3) is not None and b.shed == {"backlog": 2}
    b.done(0)  # keyframe 0 through the chain: room for one
    assert b.backlog == 1 and b.admit(4) is None and b.admit(5) is not None
    b.done(4)  # the chain works in order: 1 and 4 are through
    assert b.backlog == 0 and b.shed_total == 3
    off = KeyframeBacklog(BacklogParams())
    assert all(off.admit(k) is None for k in range(100)) and off.shed_total == 0
    with pytest.raises(ConfigError, match="max_backlog"):
        BacklogParams(max_backlog=-1)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.booleans(), max_size=60), st.integers(1, 4))
def test_backlog_never_exceeds_its_bound(events, cap):
    """Keyframes (True) and chain completions (False, in order) in any interleaving: never more
    than ``cap`` in flight, and every keyframe is either in flight, through, or shed."""
    b = KeyframeBacklog(BacklogParams(max_backlog=cap))
    published: list[int] = []
    done = -1
    kid = 0
    for is_keyframe in events:
        if is_keyframe:
            if b.admit(kid) is None:
                published.append(kid)
            kid += 1
        elif [k for k in published if k > done]:
            done = min(k for k in published if k > done)
            b.done(done)
        assert b.backlog <= cap
    assert len(published) + b.shed_total == kid
    assert b.backlog == len([k for k in published if k > done])


def test_backlog_in_time_sheds_a_keyframe_whose_depth_would_come_too_late():
    b = KeyframeBacklog(BacklogParams(max_backlog=3, max_latency_s=2.0, deviations=0.0))
    assert b.admit(0, 0.0, 0.0) is None  # nothing measured yet: only the count bounds it
    b.done(0, 1.0)
    assert b.service_s == 1.0 and b.measured == 1
    assert b.admit(1, 1.2, 1.1) is None  # an empty chain: always admitted
    # keyframe 1 started at 1.2 and takes 1.0: keyframe 2 (image at 1.4) would be done at 3.2
    assert b.predicted_latency_s(1.5, 1.4) == pytest.approx(1.8)
    assert b.admit(2, 1.5, 1.4) is None
    # keyframe 3 (image at 1.5): behind 1 and 2, done at 4.2, 2.7 s after its image
    reason = b.admit(3, 1.6, 1.5)
    assert reason is not None and reason.startswith("latency: depth predicted 2.7 s")
    assert b.shed == {"latency": 1} and b.backlog == 2
    b.done(1, 2.4)  # 1.2 s from its start: the chain got slower
    assert b.service_s == pytest.approx(1.0 + 0.3 * 0.2)
    b.done(2, 3.6)  # started when 1 was through (2.4), not when published (1.5): 1.2 s again
    assert b.service_s == pytest.approx(1.06 + 0.3 * 0.14)
    assert b.backlog == 0 and b.admit(4, 5.0, 4.9) is None
    with pytest.raises(ConfigError, match="max_latency_s"):
        BacklogParams(max_latency_s=-1.0)


def test_backlog_in_time_never_sheds_into_an_empty_chain():
    b = KeyframeBacklog(BacklogParams(max_latency_s=0.5))
    b.admit(0, 0.0)
    b.done(0, 10.0)  # a chain far slower than the budget
    assert b.admit(1, 11.0, 10.5) is None  # alone in the chain: shedding it gains nothing
    assert b.admit(2, 11.1, 11.1) is not None and b.shed == {"latency": 1}


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(0.01, 2.0), min_size=1, max_size=40),
    st.floats(0.1, 1.5),
    st.floats(0.5, 4.0),
    st.integers(0, 3),
)
def test_backlog_in_time_bounds_the_latency_of_a_steady_chain(gaps, service_s, budget_s, cap):
    """A chain that takes ``service_s`` per keyframe, in order, and keyframes at any times: once
    the chain is measured, every keyframe admitted gets its depth within the budget (or within
    one service time, when it found the chain empty), and every keyframe is admitted or shed."""
    b = KeyframeBacklog(BacklogParams(max_backlog=cap, max_latency_s=budget_s, deviations=0.0))
    done_at: list[tuple[float, int]] = []  # pending completions (time, id), in order
    last_done = 0.0
    t = 0.0
    admitted = 0
    for kid, gap in enumerate(gaps):
        t += gap
        while done_at and done_at[0][0] <= t:
            b.done(done_at[0][1], done_at[0][0])
            done_at.pop(0)
        measured, empty = b.measured > 0, not done_at
        if b.admit(kid, t, t) is None:
            admitted += 1
            last_done = max(t, last_done) + service_s
            done_at.append((last_done, kid))
            if measured:
                assert last_done - t <= max(budget_s, service_s) + 1e-9
                assert not empty or last_done - t == pytest.approx(service_s)
    assert admitted + b.shed_total == len(gaps)


# ------------------------------------------------------------------ a worker's scale from its budget


def test_a_worker_over_budget_takes_the_largest_scale_that_fits_at_once():
    b = ScaleBudget(ScaleBudgetParams(budget_s=1.0, scales=(1.0, 0.75, 0.5), hold_keyframes=2))
    assert b.scale == 1.0
    # 2 s at full scale: 0.75 would take 1.125 s, 0.5 takes 0.5 s
    assert b.observe(2.0) == 0.5 and b.unit_cost_s == 2.0 and b.changes == 1
    assert b.observe(0.5) == 0.5  # as predicted: stays
    # the machine gets 5x faster (0.4 s per full image): the running mean falls 2.0 -> 1.52,
    # 1.18 (0.75 within 0.8 s: up), 0.95 (1.0 fits, but 0.75 served 1 keyframe), 0.78 (up)
    scales = [b.observe(0.4 * b.scale**2) for _ in range(4)]
    assert scales == [0.5, 0.75, 0.75, 1.0]
    assert b.unit_cost_s == pytest.approx(0.4 + 1.6 * 0.7**4) and b.changes == 3


def test_a_worker_without_budget_keeps_full_scale_and_bad_budgets_are_named():
    b = ScaleBudget(ScaleBudgetParams())
    assert [b.observe(c) for c in (5.0, 0.1, 9.0)] == [1.0, 1.0, 1.0]
    for bad, key in (
        ({"budget_s": -1.0}, "budget_s"),
        ({"scales": (0.5, 1.0)}, "scales"),
        ({"scales": (1.0, 0.0)}, "scales"),
        ({"headroom": 1.5}, "headroom"),
    ):
        with pytest.raises(ConfigError, match=key):
            ScaleBudgetParams(**bad)


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_the_prior_at_a_budget_scale_is_metric_and_right(inproc_bus, scale):
    """The flow prior computed at half scale (a budget its full-scale cost cannot meet) is
    published at that scale, in metres, as right as at full scale where it is confident."""
    from mogs_node.depth_prior.node import DepthPriorNode

    bus, ctx = inproc_bus
    params = {"metrized_topic": "", "scale_budget": {"budget_s": 1e-9, "scales": [scale]}}
    node = DepthPriorNode("prior", params, bus, context=ctx, diagnostics_period_s=0)
    try:
        for kid in range(3):
            depth, conf, kind, _ = node._flow(keyframe(kid))
        H, W = CAM.height, CAM.width
        assert kind == "metric" and depth.shape == conf.shape == (H * scale, W * scale)
        assert node.counters["prior_scale"] == scale
        _, truth = render(keyframe_pose(2), CAM.scaled(*depth.T.shape))
        ok = conf > 0.1  # measured: coverage 0.68 / 0.46, median AbsRel 0.013 / 0.028
        assert ok.mean() > 0.4
        absrel = np.median(np.abs(depth[ok] - truth[ok]) / truth[ok])
        assert absrel < 0.05, absrel
        # the keyframe's metrized depth (full size) joins the history at the prior's size
        full = np.full((H, W), 9.0, np.float32)
        node.on_metrized(
            msgs.DepthMap(
                **keyframe(2).result_header(),
                kind="metric",
                depth=full,
                confidence=full,
                source="t",
            )
        )
        assert node.sequence.history[-1].metrized[0].shape == depth.shape
    finally:
        node.close()


# ------------------------------------------------------------------ CPU priority in launch files


def _node(extra: dict) -> dict:
    return {"nodes": [{"name": "a", "class": "m:C", **extra}]}


def test_launch_file_nice_and_cpus_are_checked():
    spec = parse_launch(_node({"nice": 10, "cpus": [0, 1]})).nodes[0]
    assert (spec.nice, spec.cpus) == (10, (0, 1))
    assert parse_launch(_node({})).nodes[0].nice == 0
    for bad, key in (({"nice": 25}, "nice"), ({"nice": "low"}, "nice"), ({"cpus": [-1]}, "cpus")):
        with pytest.raises(ConfigError, match=rf"nodes\[0\]\.{key}"):
            parse_launch(_node(bad))


def test_a_child_runs_at_its_niceness_and_on_its_cpus():
    cpus = usable_cpus((0,))
    code = "import os; print(os.nice(0), sorted(os.sched_getaffinity(0)))"
    out = subprocess.run(
        [sys.executable, "-c", code],
        preexec_fn=functools.partial(_child_setup, 7, cpus),
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout.split(" ", 1)
    assert int(out[0]) == os.nice(0) + 7
    if cpus:
        assert out[1].strip() == "[0]"
    assert usable_cpus((10_000,)) == ()  # a CPU this machine lacks: none of them


def test_real_time_launch_files_run_the_mapper_below_the_chain():
    from mogs_node.launch import load_launch_file

    root = Path(__file__).parents[2]
    for name in ("kitti.yaml", "euroc.yaml", "live.yaml", "ros1.yaml"):
        nodes = {n.name: n for n in load_launch_file(root / "launch" / name).nodes}
        chain = max(nodes[n].nice for n in ("frontend", "segmentation", "prior", "metrizer"))
        assert nodes["mapper"].nice > chain, name
        assert nodes["frontend"].params["backlog"]["max_backlog"] > 0, name


# ------------------------------------------------------------------ a backend that fails


def test_a_prior_backend_that_raises_on_one_keyframe_costs_only_that_keyframe_its_prior(
    inproc_bus, wired_node, caplog
):
    from mogs_node.depth_prior.node import DepthPriorNode
    from mogs_node.metrizer.node import MetrizerNode
    from mogs_node.segmentation.node import SegmentationNode

    bus, ctx = inproc_bus
    kw = {"context": ctx, "diagnostics_period_s": 0}
    prior = DepthPriorNode("prior", {"metrized_topic": ""}, bus, **kw)
    flow = prior._flow

    def backend(kf):  # the backend fails on keyframe 2 only
        if kf.keyframe_id == 2:
            raise RuntimeError("flow backend out of memory")
        return flow(kf)

    prior._flow = backend
    seg = SegmentationNode("segmentation", {}, bus, **kw)
    # a long fixed wait: keyframe 2 must be released by the failure notice, not by a timeout
    met = MetrizerNode("metrizer", {"max_wait_s": 300.0, "metrizer": {"d_max_m": 60.0}}, bus, **kw)
    kf_topic = "/frontend/keyframe"
    w = wired_node(met, (kf_topic, "/seg/masks", "/prior/depth"), "/metrizer/depth")
    wired_node(seg, (kf_topic,), "/seg/masks")
    wired_node(prior, (kf_topic,), "/prior/depth")
    for kid in range(4):
        w.pub.publish(kf_topic, keyframe(kid))
    got: list[msgs.DepthMap] = []
    deadline = time.monotonic() + 120
    with caplog.at_level(logging.WARNING, logger="mogs.metrizer"):
        while len(got) < 4 and time.monotonic() < deadline:
            for node in (seg, prior, met):
                node.spin_once(20)
            env = w.watcher.receive(timeout_ms=10)
            if env is not None:
                got.append(env.msg)
    assert sorted(m.keyframe_id for m in got) == [0, 1, 2, 3]
    warnings = [r.getMessage() for r in caplog.records if r.name == "mogs.metrizer"]
    assert warnings == [
        "keyframe 2: metrized without prior "
        "(prior backend failed: RuntimeError: flow backend out of memory)"
    ]
    c = met.matcher.counters
    assert (c["complete"], c["partial"], c["failed_inputs"], c["stalled_inputs"]) == (3, 1, 1, 0)
    assert prior.counters["handler_errors"] == 1 and seg.counters["handler_errors"] == 0


def test_summary_and_report_carry_shed_keyframes_and_missing_inputs(tmp_path):
    from mogs_node.report.collect import RunCollector, summarise, write_report

    c = RunCollector()
    c.node_counters = {
        "frontend": {"keyframes_shed": 3.0, "keyframes_shed_backlog": 3.0, "dropped": 4.0},
        "metrizer": {"metrized_without_inputs": 1.0, "match_failed_inputs": 1.0},
    }
    figures = summarise(c)
    assert figures["realtime"] == {
        "keyframes_shed": 3,
        "shed_reasons": {"backlog": 3},
        "metrized_without_inputs": 1,
        "inputs_failed": 1,
        "inputs_stalled": 0,
    }
    write_report(tmp_path / "report.md", figures)
    assert (
        "Keyframes shed whole: 3 (backlog 3); metrized without masks or prior: 1 "
        "(1 failed, 0 silent worker)." in (tmp_path / "report.md").read_text()
    )


def test_the_metrizer_takes_a_worker_s_heartbeat_for_life(inproc_bus):
    from mogs_node.metrizer.node import MetrizerNode

    bus, ctx = inproc_bus
    met = MetrizerNode("metrizer", {}, bus, context=ctx, diagnostics_period_s=0)
    met.clock = lambda: 12.5
    try:

        def beat(topics, status="ok"):
            met.on_heartbeat(
                msgs.Diagnostics(
                    stamp_ns=1,
                    frame_id="",
                    node="w",
                    pid=1,
                    uptime_s=1.0,
                    status=status,
                    counters={},
                    topics=topics,
                )
            )

        beat({"/prior/depth": {"received": 4}})  # a consumer of priors (journal, viz): not it
        beat({"/prior/depth": {"published": 0}, "/seg/masks": "junk"})
        beat({"/prior/depth": {"published": 3}}, status="stopped")
        assert met.matcher.pace["prior"].alive_s == -np.inf
        assert met.matcher.pace["masks"].alive_s == -np.inf
        beat({"/prior/depth": {"published": 3}})
        assert met.matcher.pace["prior"].alive_s == 12.5
        assert met.matcher.pace["masks"].alive_s == -np.inf
    finally:
        met.close()
