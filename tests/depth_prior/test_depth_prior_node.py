"""Depth-prior worker node in one process: keyframes in, priors out, keyed by keyframe id."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mogs_node import msgs
from mogs_node.depth_prior.node import DepthPriorNode
from mogs_node.errors import ConfigError, ModelError
from mogs_node.geometry import make_T, so3_exp

sys.path.insert(0, str(Path(__file__).parents[1]))  # tests/: the helpers
from _two_view_scene import CAM, render  # noqa: E402


def keyframe(kid: int, T: np.ndarray) -> tuple[msgs.Keyframe, np.ndarray]:
    grey, depth = render(T)
    rgb = np.repeat(grey[..., None], 3, axis=2)
    # three sparse metric points from the ground truth
    uv = np.array([[100.0, 120.0], [240.0, 140.0], [400.0, 100.0]], np.float32)
    z = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    xyz = CAM.backproject(uv.astype(np.float64), z).astype(np.float32)
    kf = msgs.Keyframe(
        stamp_ns=kid * 100_000_000,
        frame_id="cam",
        keyframe_id=kid,
        image=rgb,
        K=CAM.K,
        T_world_cam=T,
        feature_ids=np.arange(3, dtype=np.int64),
        feature_uv_px=uv,
        feature_xyz_cam_m=xyz,
        feature_weight=np.ones(3, np.float32),
    )
    return kf, depth


def test_flow_node_publishes_prior_per_keyframe(inproc_bus, wired_node) -> None:
    bus, ctx = inproc_bus
    node = DepthPriorNode(
        "prior",
        {"flow": {"far_baseline_m": 0.0}, "metrized_topic": ""},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    w = wired_node(node, ("/frontend/keyframe",), "/prior/depth")
    poses = [np.eye(4), make_T(so3_exp(np.array([0.0, 0.01, 0.0])), np.array([0.05, 0, 0.5]))]
    truth = []
    for kid, T in enumerate(poses, start=7):
        kf, depth = keyframe(kid, T)
        truth.append(depth)
        w.pub.publish("/frontend/keyframe", kf)
    got = w.collect(2, 20)
    assert [m.keyframe_id for m in got] == [7, 8]
    first, second = got
    assert first.kind == "metric" and first.source == "flow"
    assert not first.confidence.any()  # no earlier keyframe: no prior, confidence 0
    m = second.confidence > 0
    assert m.mean() > 0.4
    err = np.abs(second.depth[m] - truth[1][m]) / truth[1][m]
    assert np.median(err) < 0.03
    assert node.counters["handler_errors"] == 0


def test_bad_params_and_missing_model_fail_at_start(inproc_bus, tmp_path) -> None:
    bus, ctx = inproc_bus
    with pytest.raises(ConfigError, match="backend"):
        DepthPriorNode("p", {"backend": "midas"}, bus, context=ctx, diagnostics_period_s=0)
    with pytest.raises(ConfigError, match="flow"):
        DepthPriorNode("p", {"flow": {"min_baseline": 1}}, bus, context=ctx, diagnostics_period_s=0)
    with pytest.raises(ModelError, match="not found"):
        DepthPriorNode(
            "p",
            {"backend": "depth_anything", "onnx": {"model_path": str(tmp_path / "none.onnx")}},
            bus,
            context=ctx,
            diagnostics_period_s=0,
        )


def test_depth_anything_node_publishes_declared_kind(inproc_bus, wired_node, tmp_path) -> None:
    pytest.importorskip("torch")
    import warnings

    import _tiny_onnx

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = _tiny_onnx.export_depth_anything(tmp_path / "da.onnx", dynamic=True)
    bus, ctx = inproc_bus
    node = DepthPriorNode(
        "prior",
        {"backend": "depth_anything", "onnx": {"model_path": model, "input_size": 70}},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    w = wired_node(node, ("/frontend/keyframe",), "/prior/depth")
    kf, _ = keyframe(3, np.eye(4))
    w.pub.publish("/frontend/keyframe", kf)
    got = w.collect_one(10)
    assert got is not None and got.keyframe_id == 3
    assert got.kind == "relative_inverse_depth" and got.source == "depth_anything"
    assert got.depth.shape == kf.image.shape[:2] and np.all(got.confidence == 1)
    assert node.net is not None
    np.testing.assert_allclose(got.depth, node.net.infer(kf.image).value)


def _metrized(kid: int, depth: np.ndarray, kind: str = "metric") -> msgs.DepthMap:
    return msgs.DepthMap(
        stamp_ns=kid * 100_000_000,
        frame_id="cam",
        keyframe_id=kid,
        kind=kind,
        depth=depth.astype(np.float32),
        confidence=np.full(depth.shape, 0.9, np.float32),
        source="metrizer",
    )


def test_flow_node_carries_metrized_depth_into_a_standstill_keyframe(
    inproc_bus, wired_node
) -> None:
    """Standing still: no baseline, but the first keyframe's metrized depth is warped in; a
    metrized depth of a non-metric kind or another size is ignored, and the node goes on."""
    bus, ctx = inproc_bus
    node = DepthPriorNode(
        "prior",
        {"flow": {"far_baseline_m": 0.0}, "road": {"up_world": [0.0, -1.0, 0.0]}},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    w = wired_node(node, ("/frontend/keyframe", "/metrizer/depth"), "/prior/depth")
    kf7, depth = keyframe(7, np.eye(4))
    w.pub.publish("/frontend/keyframe", kf7)
    (first,) = w.collect(1, 20)
    assert not first.confidence.any()  # nothing known yet
    w.pub.publish("/metrizer/depth", _metrized(7, depth, kind="relative_inverse_depth"))
    w.pub.publish("/metrizer/depth", _metrized(7, np.ones((4, 4))))
    w.pub.publish("/metrizer/depth", _metrized(7, depth))
    for _ in range(100):  # the three metrized messages handled
        node.spin_once(50)
        if node.sequence.history and node.sequence.history[-1].metrized is not None:
            break
    kf8, _ = keyframe(8, np.eye(4))  # same place: standing still
    w.pub.publish("/frontend/keyframe", kf8)
    (second,) = w.collect(1, 20)
    assert second.keyframe_id == 8 and second.kind == "metric"
    m = second.confidence > 0
    assert m.mean() > 0.95
    np.testing.assert_allclose(second.depth[m], depth[m], rtol=1e-4)
    assert node.counters["handler_errors"] == 0


@pytest.mark.parametrize("metrized_arrives", [True, False])
def test_a_keyframe_waits_for_the_previous_keyframes_metrized_depth(
    inproc_bus, wired_node, metrized_arrives: bool
) -> None:
    """Keyframe 8's prior is computed only once keyframe 7's metrized depth is in (so it does not
    depend on which message came first), or, when it never comes, after ``metrized_wait_s``
    (counted); keyframes keep their order."""
    bus, ctx = inproc_bus
    wait_s = 30.0 if metrized_arrives else 0.5
    node = DepthPriorNode(
        "prior",
        {"flow": {"far_baseline_m": 0.0}, "metrized_wait_s": wait_s},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    w = wired_node(node, ("/frontend/keyframe", "/metrizer/depth"), "/prior/depth")
    kf7, depth7 = keyframe(7, np.eye(4))
    w.pub.publish("/frontend/keyframe", kf7)
    assert [m.keyframe_id for m in w.collect(1, 20)] == [7]  # nothing before it to wait for
    for kid in (8, 9):
        w.pub.publish("/frontend/keyframe", keyframe(kid, np.eye(4))[0])  # standing still
    if metrized_arrives:
        assert w.collect(1, 1.0) == []  # held back: 7's metrized depth is not in
        w.pub.publish("/metrizer/depth", _metrized(7, depth7))
        (eight,) = w.collect(1, 20)
        assert eight.keyframe_id == 8 and (eight.confidence > 0).mean() > 0.95  # 7's depth in
        assert w.collect(1, 1.0) == []  # 9 now waits for 8's metrized depth
        w.pub.publish("/metrizer/depth", _metrized(8, depth7))
        assert [m.keyframe_id for m in w.collect(1, 20)] == [9]
        assert node.counters.get("metrized_wait_timeouts", 0) == 0
    else:
        got = w.collect(2, 20)
        assert [m.keyframe_id for m in got] == [8, 9]
        assert node.counters["metrized_wait_timeouts"] == 2
    assert node.counters["handler_errors"] == 0


def _heartbeat(node: str, busy_s: float) -> msgs.Diagnostics:
    return msgs.Diagnostics(
        stamp_ns=time.time_ns(),
        frame_id="",
        node=node,
        pid=1,
        uptime_s=1.0,
        status="busy: handler /seg/masks" if busy_s else "ok",
        counters={"busy_s": busy_s},
        topics={},
    )


def test_the_wait_for_metrized_depth_goes_on_while_another_node_is_busy(
    inproc_bus, wired_node
) -> None:
    """A loaded pipeline that works is waited for: while another node's heartbeat says it is
    busy, keyframe 8 stays held back however long past ``metrized_wait_s``; once no node has
    said so for ``metrized_wait_s`` (its own heartbeats do not count), 8 goes without 7's depth
    and the wait is counted. So under any load the prior is the one of an idle machine."""
    bus, ctx = inproc_bus
    wait_s = 0.6
    node = DepthPriorNode(
        "prior",
        {"flow": {"far_baseline_m": 0.0}, "metrized_wait_s": wait_s},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    w = wired_node(node, ("/frontend/keyframe", "/diagnostics"), "/prior/depth")
    w.pub.publish("/frontend/keyframe", keyframe(7, np.eye(4))[0])
    assert [m.keyframe_id for m in w.collect(1, 20)] == [7]
    w.pub.publish("/frontend/keyframe", keyframe(8, np.eye(4))[0])
    t0 = time.monotonic()
    while time.monotonic() - t0 < 6 * wait_s:  # the segmentation computes for a long time
        w.pub.publish("/diagnostics", _heartbeat("segmentation", busy_s=3.0))
        w.pub.publish("/diagnostics", _heartbeat("prior", busy_s=3.0))
        assert w.collect(1, wait_s / 3) == []
    for _ in range(3):  # the pipeline idle (and the prior's own busy heartbeats): it gives up
        w.pub.publish("/diagnostics", _heartbeat("segmentation", busy_s=0.0))
        w.pub.publish("/diagnostics", _heartbeat("prior", busy_s=3.0))
    (eight,) = w.collect(1, 20)
    assert eight.keyframe_id == 8
    assert node.counters["metrized_wait_timeouts"] == 1
    assert node.counters["handler_errors"] == 0


def test_metrized_wait_must_be_finite_and_non_negative(inproc_bus) -> None:
    bus, ctx = inproc_bus
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="metrized_wait_s"):
            DepthPriorNode("prior", {"metrized_wait_s": bad}, bus, context=ctx)


def test_sim_lfm_backend_waits_for_the_truth_and_is_affine_in_inverse_depth(
    inproc_bus, wired_node
) -> None:
    """Evaluation backend: a keyframe published before its ground truth waits for it; the prior
    is the truth's inverse depth up to the LFM's affine map and warp (correlation ~1), with full
    confidence, deterministic per keyframe."""
    bus, ctx = inproc_bus
    node = DepthPriorNode("prior", {"backend": "sim_lfm"}, bus, context=ctx, diagnostics_period_s=0)
    w = wired_node(node, ("/frontend/keyframe", "/groundtruth/depth"), "/prior/depth")
    kf, depth = keyframe(3, np.eye(4))
    w.pub.publish("/frontend/keyframe", kf)
    gt = msgs.DepthMap(
        stamp_ns=kf.stamp_ns,
        frame_id="cam",
        keyframe_id=-1,
        kind="metric",
        depth=depth.astype(np.float32),
        confidence=np.ones_like(depth, np.float32),
        source="groundtruth",
    )
    w.pub.publish("/groundtruth/depth", gt)
    (got,) = w.collect(1, 20)
    assert got.keyframe_id == 3 and got.kind == "relative_inverse_depth"
    assert np.all(got.confidence == 1.0)
    assert np.corrcoef(got.depth.ravel(), 1.0 / depth.ravel())[0, 1] > 0.9
    from mogs_node.depth_prior.sim_lfm import lfm_from_truth

    again, _ = lfm_from_truth(depth, 3)
    np.testing.assert_array_equal(got.depth, again)
    with pytest.raises(ConfigError, match="sim_lfm"):
        DepthPriorNode(
            "p",
            {"backend": "sim_lfm", "sim_lfm": {"sed": 1}},
            bus,
            context=ctx,
            diagnostics_period_s=0,
        )


@pytest.mark.parametrize(
    ("typed", "auto", "expect"),
    [(None, False, 1.21), (1.65, False, 1.65), (0.0, False, 0.0), (0.0, True, 1.21)],
)
def test_flow_camera_height_from_camera_info_unless_typed(
    inproc_bus, wired_node, typed, auto, expect
) -> None:
    """The prior's road bound takes the camera height of the source's ``/camera/info`` (the
    calibration typed once, for the player); a height in the launch file's ``flow`` wins (0: no
    road), except a 0 with ``road.auto_height`` ("measure it": a known height is better); an
    unknown height (NaN) keeps the parameter's."""
    bus, ctx = inproc_bus
    flow = {} if typed is None else {"camera_height_m": typed}
    node = DepthPriorNode(
        "prior",
        {"flow": flow, "road": {"auto_height": auto}, "metrized_topic": ""},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    w = wired_node(node, ("/frontend/keyframe", "/camera/info"), "/prior/depth")
    K = CAM.K
    info = msgs.CameraInfo(1, "cam", CAM.width, CAM.height, K, "none", np.zeros(0))
    w.pub.publish("/camera/info", msgs.CameraInfo(**{**info.__dict__, "camera_height_m": 1.21}))
    w.pub.publish("/camera/info", msgs.CameraInfo(**{**info.__dict__, "stamp_ns": 2}))  # NaN
    kf, _ = keyframe(3, np.eye(4))
    w.pub.publish("/frontend/keyframe", kf)  # reliable topics: in order, the info first
    assert [m.keyframe_id for m in w.collect(1, 20)] == [3]
    assert node.flow_params.camera_height_m == expect
    assert node.sequence.flow.camera_height_m == expect


def test_flow_node_takes_a_tracked_frame_as_reference_of_the_first_keyframe(
    inproc_bus, wired_node
) -> None:
    """``flow.frame_references``: a frame's image and its tracked pose (paired by stamp) are a
    flow reference of the next keyframe, which has no earlier keyframe (the first after a
    standstill); an initialising frame's pose is not used."""
    bus, ctx = inproc_bus
    node = DepthPriorNode(
        "prior",
        {"flow": {"far_baseline_m": 0.0, "frame_references": 4}, "metrized_topic": ""},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    topics = ("/frontend/keyframe", "/camera/image", "/frontend/odometry")
    w = wired_node(node, topics, "/prior/depth")
    T0 = np.eye(4)
    T1 = make_T(so3_exp(np.array([0.0, 0.01, 0.0])), np.array([0.05, 0, 0.5]))
    frame, _ = keyframe(0, T0)
    for stamp, status in ((40_000_000, "initializing"), (50_000_000, "tracking")):
        w.pub.publish("/camera/image", msgs.Image(stamp, "cam", "bgr8", frame.image[..., ::-1]))
        w.pub.publish(
            "/frontend/odometry",
            msgs.Odometry(stamp, "cam", 0, T0, (0.0, 0.0, 0.0), status),
        )
    deadline = time.monotonic() + 10
    while 50_000_000 not in node.sequence.frames and time.monotonic() < deadline:
        node.spin_once(50)
    assert sorted(node.sequence.frames) == [50_000_000]
    kf, depth = keyframe(1, T1)
    w.pub.publish("/frontend/keyframe", kf)
    (got,) = w.collect(1, 20)
    m = got.confidence > 0
    assert m.mean() > 0.4
    assert np.median(np.abs(got.depth[m] - depth[m]) / depth[m]) < 0.03
    assert node.counters["handler_errors"] == 0
    # a reset starts a new world: the frames kept are forgotten
    w.pub.publish("/frontend/odometry", msgs.Odometry(60_000_000, "cam", 0, T0, (0, 0, 0), "reset"))
    deadline = time.monotonic() + 10
    while node.sequence.frames and time.monotonic() < deadline:
        node.spin_once(50)
    assert not node.sequence.frames
