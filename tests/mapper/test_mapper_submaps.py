"""Submaps of a long drive: exact offload / reload, resume after an offload, streamed PLY."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node import msgs
from mogs_node.errors import ConfigError
from mogs_node.geometry import make_T
from mogs_node.mapper.checkpoint import load_checkpoint_with_extra, save_checkpoint
from mogs_node.mapper.gaussians import PARAM_NAMES, GaussianMap
from mogs_node.mapper.mapper import GaussianMapper, MapperParams
from mogs_node.mapper.ply import read_gaussian_ply
from mogs_node.mapper.submaps import (
    SubmapError,
    SubmapParams,
    SubmapStore,
    put_rows,
    take_rows,
    write_map_ply,
)

W, H = 40, 24
K = np.array([[30.0, 0, 19.5], [0, 30.0, 11.5], [0, 0, 1]])
STEP_M = 10.0  # keyframes 10 m apart along x: submaps of 15 m hold one or two of them


@pytest.fixture(autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # bit-exact comparisons
    yield
    torch.set_num_threads(n)


def drive(n_kf: int, store: SubmapStore | None = None, iters: int = 2) -> GaussianMapper:
    """A mapper along a straight drive, keyframe k at x = 10 k m, looking at a wall 6 m ahead."""
    m = GaussianMapper(MapperParams(window_size=2, n_random_past=1), K, W, H)
    for k in range(n_kf):
        rng = np.random.default_rng(k)
        img = np.kron(rng.uniform(0, 255, (H // 4, W // 4, 3)), np.ones((4, 4, 1))).astype(np.uint8)
        T = make_T(np.eye(3), np.array([STEP_M * k, 0.0, 0.0]))
        depth = np.full((H, W), 6.0, np.float32)
        conf = np.full((H, W), 0.8, np.float32)
        m.add_keyframe(k, img, T, depth, conf)
        if store is not None:
            store.add_keyframe(m.keyframes[-1].index, T)
        m.optimize(iters)
        m.drain_changes()
    return m


def snapshot(m: GaussianMapper) -> dict[str, torch.Tensor]:
    gm = m.map
    out = {"ids": gm.ids.clone(), "steps": gm.steps.clone(), "birth": gm.birth_kf.clone()}
    out["n_obs"], out["dirty"] = gm.n_obs.clone(), gm._dirty.clone()
    for d in ("params", "adam_m", "adam_v"):
        for k in PARAM_NAMES:
            out[f"{d}.{k}"] = getattr(gm, d)[k].clone()
    for kf in m.keyframes:
        for name in ("image", "depth_m", "confidence"):
            out[f"kf{kf.index}.{name}"] = getattr(kf, name).clone()
        out[f"kf{kf.index}.ids"] = torch.as_tensor(kf.visible_ids.copy())
        out[f"kf{kf.index}.w"] = torch.as_tensor(kf.visible_weights.copy())
    return out


def assert_same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


PARAMS = SubmapParams(length_m=15.0, offload_distance_m=25.0, reload_distance_m=12.0)


def test_offloaded_submap_leaves_ram_and_comes_back_identical(tmp_path) -> None:
    store = SubmapStore(PARAMS, tmp_path)
    m = drive(6, store)
    before = snapshot(m)
    n_before = len(m.map)
    here = np.array([STEP_M * 5, 0.0, 0.0])
    gone = store.offload_far(m, here)
    # keyframes 0 (0 m) and 1 (10 m) form submap 0, 2 (20 m) submap 1: both farther than 25 m
    # from x = 50 m; submap 2 (30, 40 m) holds the window's keyframe 4, submap 3 is the current
    assert gone == [0, 1]
    assert m.offloaded_kfs == {0, 1, 2}
    born = before["birth"]
    moved = int(torch.isin(born, torch.tensor([0, 1, 2])).sum())
    assert moved > 0 and len(m.map) == n_before - moved == n_before - store.gaussians_on_disk
    assert not bool(torch.isin(m.map.birth_kf, torch.tensor([0, 1, 2])).any())
    assert m.keyframes[0].image.numel() == 0 and len(m.keyframes[1].visible_ids) == 0
    assert m.map.drain_changes().removed_ids.size == 0  # offloading is not removal
    assert len(list(tmp_path.glob("submap_*.pt"))) == 2
    # the vehicle comes back to the start: submap 0 returns, submap 1 (20 m away) stays out
    assert store.reload_near(m, np.array([-1.0, 0.0, 0.0])) == [0]
    assert m.offloaded_kfs == {2}
    store.reload_all(m)
    assert not m.offloaded_kfs and not store.offloaded
    assert_same(snapshot(m), before)
    assert not list(tmp_path.glob("submap_*.pt"))  # no checkpoint refers to them: deleted


def test_resume_after_offload_gives_the_same_map(tmp_path) -> None:
    store = SubmapStore(PARAMS, tmp_path / "submaps")
    m = drive(6, store)
    store.offload_far(m, np.array([STEP_M * 5, 0.0, 0.0]))
    save_checkpoint(m, tmp_path / "mapper.ckpt", extra={"submaps": store.state()})
    store.pin()
    # the run goes on: the region comes back and is offloaded again (a newer file generation)
    store.reload_all(m)
    expected = snapshot(m)
    store.offload_far(m, np.array([STEP_M * 5, 0.0, 0.0]))
    assert len(list((tmp_path / "submaps").glob("submap_*.pt"))) == 4  # pinned + new
    store.reload_all(m)
    m.optimize(3)
    expected_next = snapshot(m)
    # ... and dies: a new process resumes from the checkpoint and its submap files
    r, extra = load_checkpoint_with_extra(tmp_path / "mapper.ckpt")
    store2 = SubmapStore(PARAMS, tmp_path / "submaps")
    store2.restore(extra["submaps"], r)
    assert r.offloaded_kfs == {0, 1, 2}
    assert len(list((tmp_path / "submaps").glob("submap_*.pt"))) == 2  # unreferenced: gone
    store2.reload_all(r)
    assert_same(snapshot(r), expected)
    r.optimize(3)  # and it maps on as the original did
    assert_same(snapshot(r), expected_next)


def test_missing_submap_file_is_named(tmp_path) -> None:
    store = SubmapStore(PARAMS, tmp_path)
    m = drive(6, store, iters=1)
    store.offload_far(m, np.array([STEP_M * 5, 0.0, 0.0]))
    state = store.state()
    for f in tmp_path.glob("submap_*.pt"):
        f.unlink()
    with pytest.raises(SubmapError, match="submap file .* is missing"):
        SubmapStore(PARAMS, tmp_path).restore(state, m)


def test_streamed_ply_holds_the_whole_drive(tmp_path) -> None:
    store = SubmapStore(PARAMS, tmp_path / "submaps")
    m = drive(6, store, iters=1)
    whole = {k: v.clone() for k, v in m.map.params.items()}
    birth = m.map.birth_kf.clone()
    store.offload_far(m, np.array([STEP_M * 5, 0.0, 0.0]))
    n = write_map_ply(m, store, tmp_path / "map.ply")
    assert n == len(whole["means"]) > len(m.map)
    ply = read_gaussian_ply(tmp_path / "map.ply")
    # streamed in submap order, then the rows in RAM (each in id order)
    order = torch.cat(
        [
            torch.nonzero(torch.isin(birth, torch.tensor([0, 1]))).flatten(),
            torch.nonzero(birth == 2).flatten(),
            torch.nonzero(birth > 2).flatten(),
        ]
    )
    np.testing.assert_array_equal(ply["means"], whole["means"][order].numpy())
    np.testing.assert_array_equal(ply["opacity_logit"], whole["opacity_logit"][order].numpy())
    np.testing.assert_allclose(ply["colors_rgb"], whole["colors"][order].numpy(), atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 30),
    seed=st.integers(0, 2**16),
    data=st.data(),
)
def test_take_then_put_rows_is_the_identity(n: int, seed: int, data) -> None:
    gm = GaussianMap()
    g = torch.Generator().manual_seed(seed)
    vals = {
        "means": torch.randn(n, 3, generator=g),
        "quats_wxyz": torch.randn(n, 4, generator=g),
        "log_scales": torch.randn(n, 3, generator=g),
        "opacity_logit": torch.randn(n, generator=g),
        "colors": torch.rand(n, 3, generator=g),
    }
    gm.add(vals, birth_kf=0)
    gm.remove(torch.rand(n, generator=g) < 0.3)  # ids with gaps, as after pruning
    for k in PARAM_NAMES:
        gm.adam_m[k] = torch.randn_like(gm.params[k])
    mask = torch.tensor(data.draw(st.lists(st.booleans(), min_size=len(gm), max_size=len(gm))))
    before = {k: (v.clone() if isinstance(v, torch.Tensor) else None) for k, v in vars(gm).items()}
    params = {k: v.clone() for k, v in gm.params.items()}
    rows = take_rows(gm, mask.to(torch.bool).reshape(len(gm)))
    assert len(gm) == len(before["ids"]) - int(mask.sum())
    assert put_rows(gm, rows) == int(mask.sum())
    assert torch.equal(gm.ids, before["ids"])
    assert torch.equal(gm.steps, before["steps"]) and torch.equal(gm._dirty, before["_dirty"])
    for k in PARAM_NAMES:
        assert torch.equal(gm.params[k], params[k])
    if len(rows["ids"]):  # the same rows twice: refused
        with pytest.raises(SubmapError, match="already in the map"):
            put_rows(gm, rows)


def test_submap_params_are_checked() -> None:
    with pytest.raises(ConfigError, match="hysteresis"):
        SubmapParams(offload_distance_m=50.0, reload_distance_m=60.0)
    with pytest.raises(ConfigError, match="length_m"):
        SubmapParams(length_m=0.0)
    assert not SubmapParams(offload_distance_m=0.0).enabled


def test_mapper_node_offloads_streams_its_ply_and_resumes(inproc_bus, tmp_path) -> None:
    """The node shell: regions behind go to disk, the incremental updates and the PLY still hold
    the whole drive, and a resumed node restores the same map from its checkpoint and files."""
    from test_mapper_node import messages

    from mogs_node.bus import Publisher, Subscriber
    from mogs_node.mapper.node import MapperNode

    bus, ctx = inproc_bus
    params = {
        "iters_per_keyframe": 2,
        "threads": 1,
        "ply_path": str(tmp_path / "map.ply"),
        "checkpoint_dir": str(tmp_path / "ck"),
        "checkpoint_every_keyframes": 1,
        "submap_length_m": 15.0,
        "offload_distance_m": 25.0,
        "reload_distance_m": 12.0,
        "publish_render": False,
    }
    node = MapperNode("mapper", params, bus, context=ctx, diagnostics_period_s=0)
    watcher = Subscriber(bus, context=ctx)
    for topic in ("/mapper/stats", "/mapper/gaussians"):
        watcher.subscribe(topic)
    pub = Publisher(bus, context=ctx)
    assert pub.wait_for_subscriber("/metrizer/depth", 5)
    assert node._pub.wait_for_subscriber("/mapper/gaussians", 5)
    for k in range(6):
        for m in messages(k, STEP_M * k):
            topic = "/metrizer/depth" if isinstance(m, msgs.DepthMap) else "/frontend/keyframe"
            pub.publish(topic, m)
    stats, live = [], set()
    deadline = time.monotonic() + 120
    while len(stats) < 6 and time.monotonic() < deadline:
        node.spin_once(50)
        env = watcher.receive(timeout_ms=20)
        while env is not None:
            if env.topic == "/mapper/stats":
                stats.append(env.msg)
            else:
                live = (live | set(env.msg.ids.tolist())) - set(env.msg.removed_ids.tolist())
            env = watcher.receive(timeout_ms=20)
    last = stats[-1]
    assert last.extra["gaussians_on_disk"] > 0 and node.counters["submap_offloads"] >= 1
    assert last.n_gaussians == last.extra["gaussians_in_ram"] + last.extra["gaussians_on_disk"]
    assert len(live) == last.n_gaussians  # offloading removed nothing from the replica
    node.close()  # checkpoint + PLY streamed from the submaps
    first_ply = (tmp_path / "map.ply").read_bytes()
    assert len(read_gaussian_ply(tmp_path / "map.ply")["means"]) == last.n_gaussians
    resumed = MapperNode("m2", {**params, "resume": True}, bus, context=ctx, diagnostics_period_s=0)
    assert resumed.mapper is not None and resumed.mapper.offloaded_kfs == node.mapper.offloaded_kfs
    resumed.close()
    assert (tmp_path / "map.ply").read_bytes() == first_ply


@pytest.mark.parametrize(("cap_below", "gone"), [(1, [0]), (None, [0, 1])])
def test_a_bound_on_gaussians_in_ram_offloads_the_farthest_regions_first(
    tmp_path, cap_below, gone
) -> None:
    """Nothing is far enough to leave by distance (100 m); over the bound, the farthest closed
    submap leaves first, then the next, never one within reload_distance_m or in the window."""
    m = drive(6)
    n = len(m.map)
    cap = 1 if cap_below is None else n - cap_below
    params = SubmapParams(
        length_m=15.0, offload_distance_m=100.0, reload_distance_m=12.0, max_gaussians_in_ram=cap
    )
    store = SubmapStore(params, tmp_path)
    for kf in m.keyframes:
        store.add_keyframe(kf.index, make_T(np.eye(3), np.array([STEP_M * kf.index, 0.0, 0.0])))
    # x = 50 m: submap 0 (0, 10 m) is 40 m away, submap 1 (20 m) 30 m, submap 2 (30, 40 m)
    # holds the window's keyframe 4, submap 3 is the current one
    assert store.offload_far(m, np.array([STEP_M * 5, 0.0, 0.0])) == gone
    assert store.counters["offloads_for_count"] == len(gone)
    assert len(m.map) + store.gaussians_on_disk == n
    assert (len(m.map) <= cap) == (cap_below is not None)  # the window's and the current stay


def test_the_bound_on_gaussians_in_ram_must_not_be_negative() -> None:
    with pytest.raises(ConfigError, match="max_gaussians_in_ram"):
        SubmapParams(max_gaussians_in_ram=-1)


def test_final_refinement_skips_the_offloaded_keyframes(tmp_path) -> None:
    """The end-of-run refinement over a map with offloaded regions trains the keyframes in RAM
    only (an offloaded keyframe's image is an empty placeholder: it failed on it before)."""
    store = SubmapStore(PARAMS, tmp_path)
    m = drive(6, store)
    store.offload_far(m, np.array([STEP_M * 5, 0.0, 0.0]))
    assert m.offloaded_kfs == {0, 1, 2}
    before = {k.index: k.iterations for k in m.keyframes}
    m.refine(6)
    gained = {k.index: k.iterations - before[k.index] for k in m.keyframes}
    assert gained == {0: 0, 1: 0, 2: 0, 3: 2, 4: 2, 5: 2}
