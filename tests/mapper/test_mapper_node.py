"""Mapper node in one process: keyframe + depth in (any order), stats/render/updates out, PLY."""

from __future__ import annotations

import time

import numpy as np
import pytest

from mogs_node import msgs
from mogs_node.bus import Publisher, Subscriber
from mogs_node.errors import ConfigError
from mogs_node.geometry import make_T
from mogs_node.mapper.node import MapperNode
from mogs_node.mapper.ply import read_gaussian_ply

W, H = 48, 24
K = np.array([[30.0, 0, 23.5], [0, 30.0, 11.5], [0, 0, 1]])


def messages(kid: int, x_m: float) -> tuple[msgs.Keyframe, msgs.DepthMap]:
    rng = np.random.default_rng(kid)
    img = rng.integers(0, 255, size=(H, W, 3), dtype=np.uint8)
    T = make_T(np.eye(3), np.array([x_m, 0.0, 0.0]))
    kf = msgs.Keyframe(
        stamp_ns=kid * 10**8,
        frame_id="cam",
        keyframe_id=kid,
        image=img,
        K=K,
        T_world_cam=T,
        feature_ids=np.zeros(0, np.int64),
        feature_uv_px=np.zeros((0, 2), np.float32),
        feature_xyz_cam_m=np.zeros((0, 3), np.float32),
        feature_weight=np.zeros(0, np.float32),
    )
    depth = msgs.DepthMap(
        stamp_ns=kid * 10**8,
        frame_id="cam",
        keyframe_id=kid,
        kind="metric",
        depth=np.full((H, W), 6.0, np.float32),
        confidence=np.ones((H, W), np.float32),
        source="test",
    )
    return kf, depth


def test_mapper_node_publishes_stats_render_and_incremental_updates(inproc_bus, tmp_path) -> None:
    bus, ctx = inproc_bus
    ply = tmp_path / "map.ply"
    node = MapperNode(
        "mapper",
        {"iters_per_keyframe": 3, "ply_path": str(ply), "threads": 1},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    watcher = Subscriber(bus, context=ctx)
    for topic in ("/mapper/stats", "/mapper/render", "/mapper/gaussians"):
        watcher.subscribe(topic)
    pub = Publisher(bus, context=ctx)
    assert pub.wait_for_subscriber("/frontend/keyframe", 5)
    assert pub.wait_for_subscriber("/metrizer/depth", 5)
    assert node._pub.wait_for_subscriber("/mapper/gaussians", 5)
    kf0, d0 = messages(0, 0.0)
    kf1, d1 = messages(1, 0.5)
    pub.publish("/metrizer/depth", d0)  # depth before its keyframe
    pub.publish("/frontend/keyframe", kf0)
    pub.publish("/frontend/keyframe", kf1)
    pub.publish("/metrizer/depth", d1)
    got: dict[str, list] = {"/mapper/stats": [], "/mapper/render": [], "/mapper/gaussians": []}
    deadline = time.monotonic() + 60
    while len(got["/mapper/gaussians"]) < 2 and time.monotonic() < deadline:
        node.spin_once(50)
        env = watcher.receive(timeout_ms=20)
        while env is not None:
            got[env.topic].append(env.msg)
            env = watcher.receive(timeout_ms=20)
    s0, s1 = got["/mapper/stats"]
    assert (s0.keyframe_id, s1.keyframe_id) == (0, 1)
    assert s1.n_keyframes == 2 and s1.iterations == 6 and s1.n_gaussians > 0
    r0 = got["/mapper/render"][0]
    assert r0.image.shape == (H, W, 3) and r0.depth is not None
    assert np.abs(r0.depth[r0.depth > 0] - 6.0).max() < 1.0  # rendered depth near the wall
    u0, u1 = got["/mapper/gaussians"]
    # the first update carries every Gaussian of keyframe 0; the second only what changed since
    ids_after_kf0 = set(u0.ids.tolist())
    assert len(ids_after_kf0) == s0.n_gaussians
    live = (ids_after_kf0 | set(u1.ids.tolist())) - set(u1.removed_ids.tolist())
    assert len(live) == s1.n_gaussians
    node.teardown()
    node.close()
    assert len(read_gaussian_ply(ply)["means"]) == s1.n_gaussians


def test_the_render_snapshot_can_come_at_the_training_resolution(inproc_bus) -> None:
    """``render_at_train_size``: /mapper/render at 1/train_downsample of the keyframe size, the
    same view (depth at the wall), a quarter of the pixels on the drive's critical path."""
    bus, ctx = inproc_bus
    params = {"iters_per_keyframe": 2, "train_downsample": 2, "render_at_train_size": True}
    node = MapperNode("mapper", {**params, "threads": 1}, bus, context=ctx, diagnostics_period_s=0)
    watcher = Subscriber(bus, context=ctx)
    watcher.subscribe("/mapper/render")
    pub = Publisher(bus, context=ctx)
    assert pub.wait_for_subscriber("/metrizer/depth", 5)
    assert node._pub.wait_for_subscriber("/mapper/render", 5)
    for m in messages(0, 0.0):
        pub.publish("/frontend/keyframe" if isinstance(m, msgs.Keyframe) else "/metrizer/depth", m)
    got = None
    deadline = time.monotonic() + 60
    while got is None and time.monotonic() < deadline:
        node.spin_once(50)
        env = watcher.receive(timeout_ms=20)
        got = env.msg if env is not None else None
    assert got is not None and got.image.shape == (H // 2, W // 2, 3)
    assert np.abs(got.depth[got.depth > 0] - 6.0).max() < 1.0
    node.teardown()
    node.close()


def test_mapper_node_params_are_validated(inproc_bus) -> None:
    bus, ctx = inproc_bus
    with pytest.raises(ConfigError):
        MapperNode("mapper", {"iters_per_keyframe": -1}, bus, context=ctx, diagnostics_period_s=0)
    with pytest.raises(ConfigError):
        MapperNode("mapper", {"no_such_param": 1}, bus, context=ctx, diagnostics_period_s=0)


def test_keyframe_with_another_camera_is_rejected_and_counted(inproc_bus) -> None:
    bus, ctx = inproc_bus
    node = MapperNode(
        "mapper", {"iters_per_keyframe": 1, "threads": 1}, bus, context=ctx, diagnostics_period_s=0
    )
    node.process(*messages(0, 0.0))
    kf1, d1 = messages(1, 0.5)
    kf1.K[0, 0] = 45.0  # another focal length: not the map's camera
    node.process(kf1, d1)
    assert node.counters["keyframes_rejected"] == 1 and node.counters["keyframes_mapped"] == 1
    assert node.mapper is not None and len(node.mapper.keyframes) == 1
    node.close()


def test_behind_the_input_every_keyframe_is_mapped_with_fewer_iterations_then_caught_up(
    inproc_bus, wired_node
) -> None:
    """A live source does not wait: with ``iters_when_behind`` a keyframe that has more input
    queued behind it gets fewer iterations, and the ones saved are run once the queue is empty."""
    bus, ctx = inproc_bus
    params = {"iters_per_keyframe": 4, "iters_when_behind": 1, "idle_iters_per_tick": 2}
    node = MapperNode("mapper", {**params, "threads": 1}, bus, context=ctx, diagnostics_period_s=0)
    w = wired_node(node, ("/frontend/keyframe", "/metrizer/depth"), "/mapper/stats")
    for kid in range(3):  # three keyframes arrive while the mapper is busy
        kf, d = messages(kid, 0.3 * kid)
        w.pub.publish("/frontend/keyframe", kf)
        w.pub.publish("/metrizer/depth", d)
    time.sleep(0.3)
    stats = w.collect(3, timeout_s=60)
    # cumulative iterations: 1 and 1 while two and one keyframes waited, then the full 4
    assert [s.iterations for s in stats] == [1, 2, 6]
    assert node.counters["keyframes_behind"] == 2 and node.counters["keyframes_mapped"] == 3
    while node.counters["owed_iters"] > 0:  # the idle timer's work, run here without waiting
        node._idle_optimize()
    assert node.mapper is not None and node.mapper.iterations == 3 * 4  # same total as in step
    node._idle_optimize()  # nothing owed: nothing runs
    assert node.mapper.iterations == 12


def test_by_default_the_mapper_never_cuts_iterations(inproc_bus) -> None:
    bus, ctx = inproc_bus
    node = MapperNode("mapper", {"iters_per_keyframe": 3}, bus, context=ctx, diagnostics_period_s=0)
    node._queue.append(None)  # as if input waited behind this keyframe
    assert node.iterations_for_next_keyframe() == 3
    node._queue.clear()
    with pytest.raises(ConfigError, match="iters_when_behind"):
        MapperNode("m2", {"iters_when_behind": -2}, bus, context=ctx, diagnostics_period_s=0)
    node.close()


def test_after_the_drive_the_map_is_refined_once_and_marked_final(inproc_bus, wired_node) -> None:
    """With ``final_refine_iters`` the mapper refines the whole map once the source stopped and
    every keyframe it saw is mapped, a chunk per timer tick, then publishes the update and a
    ``/mapper/stats`` marked final (the run report waits for it)."""
    bus, ctx = inproc_bus
    params = {"iters_per_keyframe": 2, "final_refine_iters": 7, "final_refine_chunk": 3}
    node = MapperNode("mapper", {**params, "threads": 1}, bus, context=ctx, diagnostics_period_s=0)
    w = wired_node(node, ("/frontend/keyframe", "/metrizer/depth"), "/mapper/stats")
    for kid in range(2):
        kf, d = messages(kid, 0.3 * kid)
        w.pub.publish("/frontend/keyframe", kf)
        w.pub.publish("/metrizer/depth", d)
    stats = w.collect(2, timeout_s=60)
    assert [s.iterations for s in stats] == [2, 4]
    assert not any(s.extra.get("final") for s in stats)
    node._final_refine()  # the source has not stopped: nothing happens
    assert node.mapper is not None and node.mapper.iterations == 4
    other = msgs.Diagnostics(
        stamp_ns=0, frame_id="", node="frontend", pid=1, uptime_s=1.0, status="stopped",
        counters={}, topics={},
    )  # fmt: skip
    node.on_diagnostics(other)
    node._final_refine()
    assert node.mapper.iterations == 4  # only the source's stop counts
    node.on_diagnostics(msgs.Diagnostics(**{**other.__dict__, "node": "player"}))
    (final,) = w.collect(1, timeout_s=60)
    assert final.extra.get("final") == 1.0 and final.iterations == 4 + 7
    assert final.keyframe_id == 1
    assert node.counters["refine_left"] == 0  # on the heartbeat: the run report sees it advance
    node._final_refine()  # once only
    assert node.mapper.iterations == 11


def test_without_a_refinement_the_map_is_still_marked_final(inproc_bus, wired_node) -> None:
    """``final_refine_iters: 0`` (the fast preset): once the source stopped, the map as it is goes
    out marked final, so that a report waiting for the final map does not wait for its timeout."""
    bus, ctx = inproc_bus
    params = {"iters_per_keyframe": 2, "final_refine_iters": 0, "threads": 1}
    node = MapperNode("mapper", params, bus, context=ctx, diagnostics_period_s=0)
    w = wired_node(node, ("/frontend/keyframe", "/metrizer/depth"), "/mapper/stats")
    kf, d = messages(0, 0.0)
    w.pub.publish("/frontend/keyframe", kf)
    w.pub.publish("/metrizer/depth", d)
    (first,) = w.collect(1, timeout_s=60)
    assert not first.extra.get("final")
    node.on_diagnostics(
        msgs.Diagnostics(
            stamp_ns=0, frame_id="", node="player", pid=1, uptime_s=1.0, status="stopped",
            counters={}, topics={},
        )
    )  # fmt: skip
    (final,) = w.collect(1, timeout_s=60)
    assert final.extra.get("final") == 1.0 and final.iterations == 2  # no iteration added
    node.close()
