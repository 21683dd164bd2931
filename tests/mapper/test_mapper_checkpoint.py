"""Mapper checkpoints: exact round trip, identical continuation, rejected bad files, node resume."""

from __future__ import annotations

import argparse
import io
import json
import os
import time
from dataclasses import replace

import numpy as np
import pytest
import torch

from mogs_node.bus import Publisher
from mogs_node.errors import ModelError, MogsError
from mogs_node.geometry import make_T
from mogs_node.mapper.checkpoint import (
    CHECKPOINT_NAME,
    CheckpointError,
    _digest,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from mogs_node.mapper.gaussians import PARAM_NAMES
from mogs_node.mapper.mapper import GaussianMapper, MapperParams
from mogs_node.mapper.node import MapperNode

W, H = 48, 24
K = np.array([[30.0, 0, 23.5], [0, 30.0, 11.5], [0, 0, 1]])


@pytest.fixture(autouse=True)
def one_thread():
    """Bit-exact comparisons need one thread: the multi-threaded backward sums per-thread
    buffers in a varying order, so even two uninterrupted runs differ in the last bits."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def view(kid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Image, pose, depth and confidence of keyframe ``kid`` looking at a textured wall."""
    rng = np.random.default_rng(kid)
    coarse = rng.uniform(0, 255, size=(H // 6 + 1, W // 6 + 1, 3))
    img = np.kron(coarse, np.ones((6, 6, 1)))[:H, :W].astype(np.uint8)
    T = make_T(np.eye(3), np.array([0.3 * kid, 0.05 * kid, 0.0]))
    depth = np.full((H, W), 6.0, np.float32) + rng.uniform(-0.2, 0.2, (H, W)).astype(np.float32)
    conf = rng.uniform(0.3, 1.0, (H, W)).astype(np.float32)
    return img, T, depth, conf


def build(n_kf: int = 4, iters: int = 3, **kw) -> GaussianMapper:
    """A mapper with several keyframes, random past views, exposure, pose refinement, densify."""
    p = MapperParams(
        window_size=2, n_random_past=1, refine_poses=True, densify=True, densify_grad_px=1e-6, **kw
    )
    m = GaussianMapper(p, K, W, H)
    for k in range(n_kf):
        img, T, d, c = view(k)
        m.add_keyframe(100 + k, img, T, d, c)
        m.optimize(iters)
    return m


def assert_same_state(a: GaussianMapper, b: GaussianMapper) -> None:
    assert torch.equal(a.map.ids, b.map.ids)
    for k in PARAM_NAMES:
        assert torch.equal(a.map.params[k], b.map.params[k]), k
        assert torch.equal(a.map.adam_m[k], b.map.adam_m[k]), k
        assert torch.equal(a.map.adam_v[k], b.map.adam_v[k]), k
    assert torch.equal(a.map.steps, b.map.steps)
    assert a.window == b.window and a.iterations == b.iterations
    for ka, kb in zip(a.keyframes, b.keyframes, strict=True):
        assert torch.equal(ka.T_cam_world, kb.T_cam_world)
        assert torch.equal(ka.exposure_ab, kb.exposure_ab)


def test_round_trip_renders_identically_and_continues_like_an_uninterrupted_run(tmp_path) -> None:
    a = build()
    assert a.n_densified > 0 and len(a.window) == 2  # densify + window state is exercised
    assert any(bool(k.exposure_ab.abs().sum() > 0) for k in a.keyframes)
    path = save_checkpoint(a, tmp_path / "m.ckpt")
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]  # temp file renamed
    b = load_checkpoint(path)
    assert b.params == a.params and (b.width, b.height, b.K) == (a.width, a.height, a.K)
    assert_same_state(a, b)
    for kf in a.keyframes:
        ra, rb = a.render_view(kf.T_world_cam), b.render_view(kf.T_world_cam)
        assert torch.equal(ra.color, rb.color) and torch.equal(ra.depth, rb.depth)
        assert torch.equal(ra.alpha, rb.alpha)
    assert b.stats() == pytest.approx(a.stats(), nan_ok=True)
    # the pending change log survives: the restored mapper sends the same increment
    ca, cb = a.drain_changes(), b.drain_changes()
    np.testing.assert_array_equal(ca.ids, cb.ids)
    np.testing.assert_array_equal(ca.removed_ids, cb.removed_ids)
    # continuing: optimisation (random past views from the saved RNG state), a new keyframe
    # (insertion, window update, pruning) -> bit-identical to the uninterrupted mapper
    for m in (a, b):
        m.optimize(2)
        img, T, d, c = view(4)
        m.add_keyframe(104, img, T, d, c)
        m.optimize(2)
    assert_same_state(a, b)
    np.testing.assert_array_equal(a.drain_changes().ids, b.drain_changes().ids)


def test_keyframe_images_are_kept_as_uint8_and_version_1_files_still_load(tmp_path) -> None:
    a = build(n_kf=2, iters=1)
    img0 = view(0)[0]
    assert a.keyframes[0].image.dtype == torch.uint8  # a quarter of f32's memory
    np.testing.assert_array_equal(a.keyframes[0].image.numpy(), img0)
    assert torch.equal(a.keyframes[0].image_f32, torch.as_tensor(img0.astype(np.float32) / 255.0))
    # a version-1 file (images as u8 / 255 in f32) reads back to the same uint8 images
    raw = save_checkpoint(a, tmp_path / "v2.ckpt").read_bytes()
    state = torch.load(io.BytesIO(raw), weights_only=True)
    meta = json.loads(state["meta"])
    assert meta["version"] == 2
    meta["version"] = 1
    for i in range(len(a.keyframes)):
        key = f"kf{i}.image"
        state["tensors"][key] = state["tensors"][key].to(torch.float32) / 255.0
    state["meta"] = json.dumps(meta)
    state["sha256"] = _digest(state["meta"], state["tensors"])
    torch.save(state, tmp_path / "v1.ckpt")
    b = load_checkpoint(tmp_path / "v1.ckpt")
    assert_same_state(a, b)
    for ka, kb in zip(a.keyframes, b.keyframes, strict=True):
        assert kb.image.dtype == torch.uint8 and torch.equal(ka.image, kb.image)
    # a version-2 file with a float image is malformed
    meta["version"] = 2
    state["meta"] = json.dumps(meta)
    state["sha256"] = _digest(state["meta"], state["tensors"])
    torch.save(state, tmp_path / "bad.ckpt")
    with pytest.raises(CheckpointError, match="kf0.image.*expected uint8"):
        load_checkpoint(tmp_path / "bad.ckpt")


def test_rng_state_is_saved(tmp_path) -> None:
    a = build(n_kf=4, iters=1)
    b = load_checkpoint(save_checkpoint(a, tmp_path / "m.ckpt"))
    assert a._rng.integers(0, 2**62) == b._rng.integers(0, 2**62)


def test_params_can_be_overridden_on_load(tmp_path) -> None:
    a = build(n_kf=2, iters=1)
    p = replace(a.params, n_random_past=0)
    b = load_checkpoint(save_checkpoint(a, tmp_path / "m.ckpt"), params=p)
    assert b.params.n_random_past == 0 and len(b.map) == len(a.map)


def test_missing_truncated_corrupt_and_wrong_version_files_are_rejected(tmp_path) -> None:
    a = build(n_kf=2, iters=1)
    good = save_checkpoint(a, tmp_path / "good.ckpt")
    raw = good.read_bytes()
    with pytest.raises(CheckpointError, match="no such file") as e:
        load_checkpoint(tmp_path / "absent.ckpt")
    assert isinstance(e.value, ModelError) and isinstance(e.value, MogsError)
    assert "absent.ckpt" in str(e.value)
    bad = tmp_path / "bad.ckpt"
    for cut in (0, 10, len(raw) // 2, len(raw) - 30):
        bad.write_bytes(raw[:cut])
        with pytest.raises(CheckpointError, match="bad.ckpt"):
            load_checkpoint(bad)
    # flipped bytes inside the tensor data: the SHA-256 digest catches them
    flipped = bytearray(raw)
    mid = len(raw) // 2
    flipped[mid : mid + 16] = bytes(b ^ 0xFF for b in flipped[mid : mid + 16])
    bad.write_bytes(bytes(flipped))
    with pytest.raises(CheckpointError, match="corrupt|malformed|shape"):
        load_checkpoint(bad)
    bad.write_bytes(os.urandom(4096))
    with pytest.raises(CheckpointError, match="unreadable or corrupt"):
        load_checkpoint(bad)

    def rewrite(edit, redigest: bool = True) -> None:
        state = torch.load(io.BytesIO(raw), weights_only=True)
        meta = json.loads(state["meta"])
        edit(state, meta)
        state["meta"] = json.dumps(meta)
        if redigest:  # a self-consistent file with wrong contents
            state["sha256"] = _digest(state["meta"], state["tensors"])
        torch.save(state, bad)

    rewrite(lambda s, m: m.update(version=99))
    with pytest.raises(CheckpointError, match="version 99"):
        load_checkpoint(bad)
    rewrite(lambda s, m: m.update(format="something-else"))
    with pytest.raises(CheckpointError, match="not a mapper checkpoint"):
        load_checkpoint(bad)
    rewrite(lambda s, m: s["tensors"].pop("map.params.colors"))
    with pytest.raises(CheckpointError, match="map.params.colors"):
        load_checkpoint(bad)
    rewrite(lambda s, m: s["tensors"].update({"map.ids": s["tensors"]["map.ids"][:-1]}))
    with pytest.raises(CheckpointError, match="map.ids"):
        load_checkpoint(bad)
    rewrite(lambda s, m: m.update(iterations=7), redigest=False)
    with pytest.raises(CheckpointError, match="digest mismatch"):
        load_checkpoint(bad)
    rewrite(lambda s, m: m.pop("window"))
    with pytest.raises(CheckpointError, match="malformed"):
        load_checkpoint(bad)
    # arbitrary pickled objects are refused (weights_only), never executed
    torch.save({"meta": "{}", "evil": argparse.Namespace(x=1)}, bad)
    with pytest.raises(CheckpointError, match="unreadable or corrupt"):
        load_checkpoint(bad)


def test_failed_write_keeps_the_previous_checkpoint(tmp_path, monkeypatch) -> None:
    a = build(n_kf=2, iters=1)
    path = save_checkpoint(a, tmp_path / "m.ckpt")
    before = path.read_bytes()

    def boom(*_a, **_k) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", boom)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(a, path)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["m.ckpt"]


def _feed(node: MapperNode, pub: Publisher, kids: list[int], expect: int | None = None) -> None:
    from test_mapper_node import messages

    for kid in kids:
        kf, d = messages(kid, 0.4 * kid)
        pub.publish("/frontend/keyframe", kf)
        pub.publish("/metrizer/depth", d)
    want = node.counters["keyframes_mapped"] + (len(kids) if expect is None else expect)
    deadline = time.monotonic() + 60
    while node.counters["keyframes_mapped"] < want and time.monotonic() < deadline:
        node.spin_once(50)
    assert node.counters["keyframes_mapped"] == want


def _wait_until_receiving(node: MapperNode, pub: Publisher) -> None:
    """The publisher's view of the subscriptions keeps the closed node's (it only adds), so
    ``wait_for_subscriber`` can pass before the new node's subscription reached the broker: send
    an already integrated keyframe's depth (ignored by the mapper) until the node receives it."""
    from test_mapper_node import messages

    def received() -> int:
        return sum(s.received for s in node._sub.stats.values()) if node._sub else 0

    _, d = messages(0, 0.0)
    before = received()
    deadline = time.monotonic() + 30
    while received() == before and time.monotonic() < deadline:
        pub.publish("/metrizer/depth", d)
        node.spin_once(50)
    assert received() > before


def test_node_saves_on_shutdown_and_resumes(inproc_bus, tmp_path) -> None:
    bus, ctx = inproc_bus
    ckdir = tmp_path / "ck"
    params = {
        "iters_per_keyframe": 2,
        "threads": 1,
        "checkpoint_dir": str(ckdir),
        "checkpoint_every_keyframes": 2,
    }
    node = MapperNode("mapper", params, bus, context=ctx, diagnostics_period_s=0)
    assert node.integrated_keyframe_ids == set()
    pub = Publisher(bus, context=ctx)
    assert pub.wait_for_subscriber("/metrizer/depth", 5)
    _feed(node, pub, [0, 1])
    assert node.integrated_keyframe_ids == {0, 1}
    periodic = latest_checkpoint(ckdir)  # written after the 2nd keyframe
    assert periodic is not None and periodic.name == CHECKPOINT_NAME
    assert load_checkpoint(periodic).iterations == 4
    _feed(node, pub, [2])
    m0 = node.mapper
    assert m0 is not None and load_checkpoint(periodic).iterations == 4  # not yet saved again
    node.close()  # shutdown: teardown saves
    saved = load_checkpoint(latest_checkpoint(ckdir))
    assert saved.iterations == 6
    node2 = MapperNode(
        "mapper", {**params, "resume": True}, bus, context=ctx, diagnostics_period_s=0
    )
    m1 = node2.mapper
    assert m1 is not None and node2.integrated_keyframe_ids == {0, 1, 2}
    assert torch.equal(m1.map.ids, m0.map.ids)
    for k in PARAM_NAMES:
        assert torch.equal(m1.map.params[k], m0.map.params[k])
    # an already integrated keyframe is not mapped twice; a new one continues the map
    _wait_until_receiving(node2, pub)
    _feed(node2, pub, [2, 3], expect=1)
    assert node2.integrated_keyframe_ids == {0, 1, 2, 3} and len(m1.keyframes) == 4
    assert m1.iterations == 8
    node2.close()
    pub.close()
    # resume with an empty directory starts fresh
    node3 = MapperNode(
        "mapper",
        {**params, "resume": True, "checkpoint_dir": str(tmp_path / "empty")},
        bus,
        context=ctx,
        diagnostics_period_s=0,
    )
    assert node3.mapper is None and node3.integrated_keyframe_ids == set()
    node3.close()


def test_node_with_a_corrupt_checkpoint_starts_fresh_instead_of_crash_looping(
    inproc_bus, tmp_path
) -> None:
    bus, ctx = inproc_bus
    ckdir = tmp_path / "ck"
    ckdir.mkdir()
    (ckdir / CHECKPOINT_NAME).write_bytes(b"PK\x03\x04 torn write")
    params = {"iters_per_keyframe": 1, "threads": 1, "checkpoint_dir": str(ckdir), "resume": True}
    node = MapperNode("mapper", params, bus, context=ctx, diagnostics_period_s=0)
    assert node.mapper is None and node.integrated_keyframe_ids == set()
    assert node.counters["checkpoint_errors"] == 1
    assert not (ckdir / CHECKPOINT_NAME).exists()
    assert (ckdir / (CHECKPOINT_NAME + ".corrupt")).read_bytes() == b"PK\x03\x04 torn write"
    node.close()


def test_optimize_stops_between_iterations_when_asked() -> None:
    m = build(n_kf=2, iters=0)
    it0 = m.iterations
    calls = []
    m.optimize(5, should_stop=lambda: len(calls) >= 2 or calls.append(1) is not None)
    assert m.iterations == it0 + 2
