"""Metrizer node: keyframe / masks / prior matching with a bounded wait (no process needed)."""

from __future__ import annotations

import numpy as np
import pytest

from mogs_node import msgs
from mogs_node.errors import ConfigError
from mogs_node.metrizer.node import (
    KeyframeMatcher,
    MatchedKeyframe,
    MetrizerNodeParams,
    metrizer_inputs,
)
from mogs_node.metrizer.pipeline import metrize_depth


def test_complete_set_is_released_in_any_arrival_order():
    m = KeyframeMatcher(max_wait_s=1.0)
    assert m.add("prior", 7, "P", 0.0) == []
    assert m.add("keyframe", 7, "K", 0.1) == []
    ready = m.add("masks", 7, "M", 0.2)
    assert len(ready) == 1 and ready[0].complete
    assert (ready[0].keyframe, ready[0].masks, ready[0].prior) == ("K", "M", "P")
    assert len(m) == 0 and m.counters["complete"] == 1


def test_interleaved_keyframes_match_by_id():
    m = KeyframeMatcher()
    m.add("keyframe", 1, "K1", 0.0)
    m.add("keyframe", 2, "K2", 0.0)
    m.add("masks", 2, "M2", 0.0)
    m.add("masks", 1, "M1", 0.0)
    r2 = m.add("prior", 2, "P2", 0.0)
    r1 = m.add("prior", 1, "P1", 0.0)
    assert [(e.keyframe, e.masks, e.prior) for e in r2 + r1] == [
        ("K2", "M2", "P2"),
        ("K1", "M1", "P1"),
    ]


def test_bounded_wait_releases_partial_and_drops_orphans():
    m = KeyframeMatcher(max_wait_s=2.0)
    m.add("keyframe", 3, "K3", 10.0)
    m.add("masks", 3, "M3", 10.5)
    m.add("prior", 4, "P4", 10.0)  # its keyframe never comes
    assert m.expire(11.9) == []
    out = m.expire(12.0)
    assert len(out) == 1 and out[0].keyframe_id == 3 and out[0].prior is None
    c = m.counters
    assert (c["complete"], c["partial"], c["dropped"], c["duplicates"]) == (0, 1, 1, 0)
    assert out[0].missing == {"prior": "prior worker silent for 2.0 s"}
    assert len(m) == 0


def test_max_pending_evicts_the_oldest():
    m = KeyframeMatcher(max_wait_s=100.0, max_pending=2)
    m.add("keyframe", 1, "K1", 0.0)
    m.add("keyframe", 2, "K2", 0.0)
    out = m.add("keyframe", 3, "K3", 0.0)
    assert [e.keyframe_id for e in out] == [1] and len(m) == 2
    m.add("masks", 2, "M", 0.0)
    m.add("masks", 2, "M'", 0.0)
    assert m.counters["duplicates"] == 1
    with pytest.raises(ConfigError):
        m.add("depth", 2, "x", 0.0)


def test_params_validation():
    with pytest.raises(ConfigError):
        MetrizerNodeParams(mode="fast")
    with pytest.raises(ConfigError):
        MetrizerNodeParams(max_pending=0)


def _keyframe(H=24, W=32, n=30, grey=False):
    rng = np.random.default_rng(0)
    uv = np.c_[rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n)].astype(np.float32)
    z = rng.uniform(2, 20, n).astype(np.float32)
    img = rng.integers(0, 255, (H, W) if grey else (H, W, 3)).astype(np.uint8)
    K = np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]])
    xyz = np.c_[(uv[:, 0] - W / 2) / 30 * z, (uv[:, 1] - H / 2) / 30 * z, z].astype(np.float32)
    return msgs.Keyframe(
        stamp_ns=5,
        frame_id="cam",
        keyframe_id=9,
        image=img,
        K=K,
        T_world_cam=np.eye(4),
        feature_ids=np.arange(n, dtype=np.int64),
        feature_uv_px=uv,
        feature_xyz_cam_m=xyz,
        feature_weight=np.ones(n, np.float32),
    )


def test_inputs_from_messages_with_resizing_and_missing_parts():
    kf = _keyframe(grey=True)
    masks = msgs.Masks(
        stamp_ns=5,
        frame_id="cam",
        keyframe_id=9,
        labels=np.repeat(np.arange(4, dtype=np.int32), 4).reshape(2, 8),
        backend="t",
    )
    prior = msgs.DepthMap(
        stamp_ns=5,
        frame_id="cam",
        keyframe_id=9,
        kind="relative_inverse_depth",
        depth=np.full((12, 16), 0.2, np.float32),
        confidence=np.ones((12, 16), np.float32),
        source="t",
    )
    kw = metrizer_inputs(MatchedKeyframe(9, kf, masks, prior))
    assert kw["labels"].shape == (24, 32) and kw["prior"].shape == (24, 32)
    assert kw["image_rgb"].shape == (24, 32, 3)
    assert kw["prior_kind"] == "relative_inverse_depth"
    assert np.allclose(kw["feature_depth_m"], kf.feature_xyz_cam_m[:, 2])
    assert np.array_equal(kw["T_world_cam"], kf.T_world_cam)  # the road plane's "up"
    out = metrize_depth(**kw)
    assert out.depth_m.shape == (24, 32) and np.all(out.depth_m > 0)
    # nothing but the keyframe: no masks, no prior -> still a valid (fill-based) depth map
    kw = metrizer_inputs(MatchedKeyframe(9, kf))
    assert np.all(kw["prior_confidence"] == 0) and np.all(kw["labels"] == -1)
    out = metrize_depth(**kw)
    assert np.all(np.isfinite(out.depth_m)) and np.all(
        (out.confidence >= 0) & (out.confidence <= 1)
    )
    msgs.DepthMap(
        stamp_ns=5,
        frame_id="cam",
        keyframe_id=9,
        kind="metric",
        depth=out.depth_m,
        confidence=out.confidence,
        source="metrizer:full",
        object_labels=out.object_labels,
        object_model=out.object_model,
    )


# ------------------------------------------------------------------------------ node on a bus


def test_node_matches_and_publishes_metric_depth(inproc_bus, wired_node):
    from mogs_node.metrizer.node import MetrizerNode

    bus, ctx = inproc_bus
    node = MetrizerNode(
        "metrizer",
        {"max_wait_s": 0.3, "metrizer": {"d_max_m": 60.0}},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    w = wired_node(node, ("/frontend/keyframe", "/seg/masks", "/prior/depth"), "/metrizer/depth")
    pub = w.pub
    kf = _keyframe()
    H, W = kf.image.shape[:2]
    labels = np.zeros((H, W), np.int32)
    prior = msgs.DepthMap(
        stamp_ns=5,
        frame_id="cam",
        keyframe_id=9,
        kind="relative_inverse_depth",
        depth=np.full((H, W), 0.1, np.float32),
        confidence=np.ones((H, W), np.float32),
        source="t",
    )
    # keyframe 9 complete (prior first), keyframe 10 without masks and prior: released on timeout
    pub.publish("/prior/depth", prior)
    pub.publish(
        "/seg/masks",
        msgs.Masks(stamp_ns=5, frame_id="cam", keyframe_id=9, labels=labels, backend="t"),
    )
    pub.publish("/frontend/keyframe", kf)
    kf10 = _keyframe()
    kf10.keyframe_id = 10
    pub.publish("/frontend/keyframe", kf10)
    got = w.collect(2, timeout_s=20)
    assert [m.keyframe_id for m in got] == [9, 10]
    for m in got:
        assert m.kind == "metric" and m.source == "metrizer:full"
        assert m.depth.shape == (H, W) and np.all(m.depth <= 60.0)
        assert m.object_labels.shape == (H, W) and m.object_model.dtype == np.int8
    assert np.all(got[0].depth > 0)
    assert node.matcher.counters["complete"] == 1 and node.matcher.counters["partial"] == 1
