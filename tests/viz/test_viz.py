"""The rerun sink: pure helpers (trajectory, Gaussian cloud, sparse points) always; logging to an
``.rrd`` file and reading it back, directly and through a running node, when rerun-sdk (the
``viz`` extra) is installed."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node import msgs
from mogs_node.bus import Publisher
from mogs_node.geometry import se3_inverse
from mogs_node.viz import ENTITY_PATHS
from mogs_node.viz.rerun_log import GaussianCloud, Trajectory, sparse_points_world


def _pose(yaw: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = t
    return T


def _update(ids: list[int], removed: list[int], k: int = 0) -> msgs.GaussianUpdate:
    n = len(ids)
    means = (
        np.stack([np.full(3, i + 0.5 * k, np.float32) for i in ids])
        if n
        else np.zeros((0, 3), np.float32)
    )
    return msgs.GaussianUpdate(
        stamp_ns=k,
        frame_id="world",
        keyframe_id=k,
        ids=np.asarray(ids, np.int64),
        means=means,
        log_scales=np.zeros((n, 3), np.float32),
        quats_wxyz=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
        opacity_logit=np.zeros(n, np.float32),
        colors_rgb=np.full((n, 3), 0.5, np.float32),
        removed_ids=np.asarray(removed, np.int64),
    )


# ---------------------------------------------------------------------------------------- pure


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.lists(st.integers(0, 30), unique=True, max_size=12),
            st.lists(st.integers(0, 30), unique=True, max_size=6),
        ),
        max_size=8,
    )
)
def test_gaussian_cloud_follows_updates_like_a_dict(steps) -> None:
    """Removals then additions/replacements by id, against a dict as the reference."""
    cloud, ref = GaussianCloud(), {}
    for k, (ids, removed) in enumerate(steps):
        cloud.apply(_update(ids, removed, k))
        for i in removed:
            ref.pop(i, None)
        for i in ids:
            ref[i] = i + 0.5 * k
    assert sorted(cloud.ids.tolist()) == sorted(ref)
    assert len(set(cloud.ids.tolist())) == len(cloud.ids)
    for i, m in zip(cloud.ids.tolist(), cloud.means):
        np.testing.assert_allclose(m, np.full(3, ref[i], np.float32))
    assert cloud.means.shape == (len(ref), 3) and cloud.colors.shape == (len(ref), 3)


def test_sparse_points_go_to_the_world_frame() -> None:
    T = _pose(0.3, (1.0, -2.0, 5.0))
    xyz_world = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [-4.0, 0.5, 10.0]])
    xyz_cam = (se3_inverse(T) @ np.c_[xyz_world, np.ones(3)].T).T[:, :3]
    kf = _keyframe(T, xyz_cam.astype(np.float32))
    np.testing.assert_allclose(sparse_points_world(kf), xyz_world, atol=1e-5)


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 40), st.integers(2, 12))
def test_trajectory_keeps_the_newest_half_and_stays_bounded(n: int, cap: int) -> None:
    traj = Trajectory(max_points=cap)
    for i in range(n):
        pts = traj.add(_pose(0.0, (float(i), 0.0, 0.0)))
    assert len(pts) <= cap
    assert pts[-1][0] == n - 1  # the latest position is always there
    assert np.all(np.diff(pts[:, 0]) > 0)  # in time order


def _keyframe(T: np.ndarray, xyz_cam: np.ndarray, kf_id: int = 0) -> msgs.Keyframe:
    n = len(xyz_cam)
    return msgs.Keyframe(
        stamp_ns=1_000 + kf_id,
        frame_id="world",
        keyframe_id=kf_id,
        image=np.full((6, 8, 3), 100, np.uint8),
        K=np.array([[5.0, 0, 4], [0, 5.0, 3], [0, 0, 1]]),
        T_world_cam=T,
        feature_ids=np.arange(n, dtype=np.int64),
        feature_uv_px=np.zeros((n, 2), np.float32),
        feature_xyz_cam_m=xyz_cam,
        feature_weight=np.ones(n, np.float32),
    )


# ---------------------------------------------------------------------------------------- rerun


def _read_entities(path: Path) -> dict[str, int]:
    """Entity path -> rows logged, read back from an .rrd with rerun's own reader."""
    import rerun as rr

    out: dict[str, int] = {}
    try:
        from rerun.chunk import RrdReader  # rerun >= 0.32
    except ImportError:  # older: the dataframe API
        rec = rr.dataframe.load_recording(str(path))
        for col in rec.schema().component_columns():
            out[col.entity_path.lstrip("/")] = out.get(col.entity_path.lstrip("/"), 0) + 1
        return out
    for chunk in RrdReader(path).stream():
        if not chunk.is_static:
            e = chunk.entity_path.lstrip("/")
            out[e] = out.get(e, 0) + chunk.num_rows
    return out


def _messages() -> list[tuple[str, msgs.Message]]:
    T0, T1 = _pose(0.0, (0, 0, 0)), _pose(0.1, (0, 0, 1.0))
    img = msgs.Image(
        stamp_ns=10, frame_id="camera", encoding="bgr8", data=np.zeros((6, 8, 3), np.uint8)
    )
    odo = [
        msgs.Odometry(
            stamp_ns=10 + i,
            frame_id="world",
            frame_index=i,
            T_world_cam=T,
            velocity_world_m_s=(0.0, 0.0, 1.0),
            status="tracking",
        )
        for i, T in enumerate((T0, T1))
    ]
    kf = _keyframe(T1, np.array([[0, 0, 5.0], [1, 1, 6.0]], np.float32))
    masks = msgs.Masks(
        stamp_ns=kf.stamp_ns,
        frame_id="world",
        keyframe_id=0,
        labels=np.full((6, 8), -1, np.int32),
        backend="graph",
    )
    depth = msgs.DepthMap(
        stamp_ns=kf.stamp_ns,
        frame_id="world",
        keyframe_id=0,
        kind="metric",
        depth=np.full((6, 8), 4.0, np.float32),
        confidence=np.ones((6, 8), np.float32),
        source="metrizer",
    )
    prior = msgs.DepthMap(
        stamp_ns=kf.stamp_ns,
        frame_id="world",
        keyframe_id=0,
        kind="relative_depth",
        depth=np.ones((6, 8), np.float32),
        confidence=np.ones((6, 8), np.float32),
        source="flow",
    )
    render = msgs.Render(
        stamp_ns=kf.stamp_ns, frame_id="world", keyframe_id=0, image=np.zeros((6, 8, 3), np.uint8)
    )
    stats = msgs.MapStats(
        stamp_ns=kf.stamp_ns,
        frame_id="world",
        keyframe_id=0,
        n_gaussians=3,
        n_keyframes=1,
        iterations=6,
        loss=0.2,
        psnr_db=float("nan"),
    )
    return [
        ("/camera/image", img),
        ("/frontend/odometry", odo[0]),
        ("/frontend/odometry", odo[1]),
        ("/frontend/keyframe", kf),
        ("/seg/masks", masks),
        ("/prior/depth", prior),
        ("/metrizer/depth", depth),
        ("/mapper/gaussians", _update([1, 2, 3], [], 1)),
        ("/mapper/gaussians", _update([4], [2], 2)),
        ("/mapper/render", render),
        ("/mapper/stats", stats),
    ]


EXPECTED = {
    ENTITY_PATHS[k]: n
    for k, n in {
        "camera_image": 1,
        "camera": 2,
        "trajectory": 2,
        "keyframe": 1,
        "keyframe_image": 1,
        "masks": 1,
        "prior_depth": 1,
        "depth": 1,
        "sparse_points": 1,
        "gaussians": 2,
        "render": 1,
    }.items()
}


def test_logging_functions_write_every_entity_to_an_rrd(tmp_path: Path) -> None:
    rr = pytest.importorskip("rerun", reason="rerun-sdk (the viz extra) is not installed")
    from mogs_node.viz import rerun_log as vl

    path = tmp_path / "out.rrd"
    rec = rr.RecordingStream("mogs-test")
    rec.save(str(path))
    traj, cloud = Trajectory(), GaussianCloud()
    for topic, m in _messages():
        if topic == "/camera/image":
            vl.log_image(rr, rec, m)
        elif topic == "/frontend/odometry":
            vl.log_odometry(rr, rec, m, traj)
        elif topic == "/frontend/keyframe":
            vl.log_keyframe(rr, rec, m)
        elif topic == "/seg/masks":
            vl.log_masks(rr, rec, m)
        elif topic == "/prior/depth":
            vl.log_depth(rr, rec, m, prior=True)
        elif topic == "/metrizer/depth":
            vl.log_depth(rr, rec, m)
        elif topic == "/mapper/gaussians":
            vl.log_gaussians(rr, rec, m, cloud)
        elif topic == "/mapper/render":
            vl.log_render(rr, rec, m)
        else:
            vl.log_stats(rr, rec, m)
    rec.flush()
    del rec
    assert sorted(cloud.ids.tolist()) == [1, 3, 4]
    assert path.stat().st_size > 0
    ents = _read_entities(path)
    for e, n in EXPECTED.items():
        assert ents.get(e, 0) >= n, (e, ents)
    # NaN PSNR is not logged; the finite stats are
    assert "mapper/stats/n_gaussians" in ents and "mapper/stats/psnr_db" not in ents


def test_viz_node_saves_what_the_pipeline_publishes(tmp_path: Path, inproc_bus) -> None:
    pytest.importorskip("rerun", reason="rerun-sdk (the viz extra) is not installed")
    from mogs_node.viz.node import VizNode

    bus, ctx = inproc_bus
    path = tmp_path / "run" / "mogs.rrd"
    node = VizNode("viz", {"mode": "save", "rrd_path": str(path)}, bus, context=ctx)
    t = threading.Thread(target=node.run, kwargs={"install_signal_handlers": False})
    t.start()
    pub = Publisher(bus, context=ctx)
    try:
        for topic in {tp for tp, _ in _messages()}:
            assert pub.wait_for_subscriber(topic, 5)
        for topic, m in _messages():
            pub.publish(topic, m)
            time.sleep(0.02)  # best-effort topics keep the latest: one at a time
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and (
            node.counters["viz_logged"] + _dropped(node) < len(_messages())
        ):
            time.sleep(0.05)
    finally:
        node.request_stop()
        t.join(10)
        pub.close(0)
    # every message logged, but for best-effort ones superseded on a loaded machine (counted)
    assert node.counters["viz_logged"] + _dropped(node) == len(_messages())
    assert _dropped(node) <= 1  # only the first of the two odometry messages can be superseded
    assert node.counters["handler_errors"] == 0
    ents = _read_entities(path)
    for e in EXPECTED:
        assert ents.get(e, 0) >= 1, (e, ents)


def _dropped(node) -> int:
    return sum(st.get("dropped", 0) for st in node.topic_stats().values())


def test_viz_params_are_checked() -> None:
    from mogs_node.errors import ConfigError
    from mogs_node.params import parse_params
    from mogs_node.viz.node import VizParams

    with pytest.raises(ConfigError, match="mode"):
        parse_params(VizParams, {"mode": "screen"})
    with pytest.raises(ConfigError, match="image_every"):
        parse_params(VizParams, {"image_every": 0})


def test_demo_viz_launch_file_is_the_demo_plus_a_viz_node() -> None:
    import yaml

    from mogs_node.launch import load_launch_file
    from mogs_node.viz.node import VizNode

    repo = Path(__file__).resolve().parents[2]
    demo = yaml.safe_load((repo / "launch/demo.yaml").read_text())
    viz = yaml.safe_load((repo / "launch/demo_viz.yaml").read_text())
    extra = [n for n in viz["nodes"] if n["name"] == "viz"]
    assert [n for n in viz["nodes"] if n["name"] != "viz"] == demo["nodes"]
    assert len(extra) == 1 and extra[0]["class"] == "mogs_node.viz.node:VizNode"
    assert {k: v for k, v in viz.items() if k not in ("name", "nodes")} == {
        k: v for k, v in demo.items() if k not in ("name", "nodes")
    }
    launch = load_launch_file(repo / "launch/demo_viz.yaml")  # parses, params included
    node = next(n for n in launch.nodes if n.name == "viz")
    from mogs_node.params import parse_params

    parse_params(VizNode.Params, node.params)


def test_viz_node_without_rerun_is_a_clear_error(monkeypatch, inproc_bus) -> None:
    import sys

    from mogs_node.errors import ConfigError
    from mogs_node.viz.node import VizNode

    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun -> ImportError
    bus, ctx = inproc_bus
    with pytest.raises(ConfigError, match="rerun-sdk"):
        VizNode("viz", {}, bus, context=ctx)
