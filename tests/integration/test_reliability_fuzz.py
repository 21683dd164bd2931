"""Fuzzed messages on every topic a node subscribes to (issue 9, "Fuzz").

One real process per subscribing node type (frontend, segmentation, depth prior, metrizer, mapper,
run report) on a private bus; a fuzz publisher sends ``N`` malformed messages on each of their
topics, drawn from a seeded RNG: random header bytes, truncated multipart messages (buffers
missing or cut short), valid msgpack headers with bad arrays (dtype not allowed, shape not matching
the buffer or the other arrays, NaN / inf where finiteness is required, too many dimensions),
wrong or unknown type names, a valid message of another type, bad header fields (version, keys,
scalar types) and oversize messages. Every generated message is first checked here to be rejected
by the codec (or to be of another type than the topic's), so the expected count is exact.

Asserted from each node's ``/diagnostics``: ``malformed == N`` on every one of its topics, the
node never crashed, and afterwards it still handles a valid message: one keyframe rendered from
the sim world goes through segmentation, depth prior, metrizer and mapper (one ``/seg/masks``,
``/prior/depth``, ``/metrizer/depth``, ``/mapper/stats``), a valid IMU sample reaches the
frontend and the report node handles the keyframe, all with no handler error.

Reliable accounting: the fuzz goes out in chunks well below the high-water marks and the test
waits for every node to have counted a chunk before sending the next, so ZeroMQ drops nothing.
"""

from __future__ import annotations

import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq
from _reliability_harness import Monitor, Procs, private_bus

from mogs_node import msgs
from mogs_node.bus import Publisher
from mogs_node.errors import MessageError

MAX_BYTES = 2 << 20  # the fuzz bus's message size limit (oversize messages exceed it)
CHUNK = 5_000  # messages per topic between two waits for the counters: the report node
# subscribes to 8 topics, 8 x 5,000 stays below the 100,000-message high-water marks

TOPIC_TYPES: dict[str, type[msgs.Message]] = {
    "/imu": msgs.Imu,
    "/camera/image": msgs.Image,
    "/frontend/keyframe": msgs.Keyframe,
    "/seg/masks": msgs.Masks,
    "/prior/depth": msgs.DepthMap,
    "/metrizer/depth": msgs.DepthMap,
    "/frontend/odometry": msgs.Odometry,
    "/mapper/stats": msgs.MapStats,
    "/mapper/render": msgs.Render,
    "/mapper/gaussians": msgs.GaussianUpdate,
    "/groundtruth/pose": msgs.PoseStamped,
    "/groundtruth/depth": msgs.DepthMap,
    "/diagnostics": msgs.Diagnostics,
    "/camera/info": msgs.CameraInfo,
}

# node name -> (class, params, topics it subscribes to)
NODES: dict[str, tuple[str, dict, tuple[str, ...]]] = {
    "frontend": (
        "mogs_node.frontend.node:FrontendNode",
        {},
        ("/imu", "/camera/image", "/camera/info"),
    ),
    "segmentation": (
        "mogs_node.segmentation.node:SegmentationNode",
        {"backend": "graph"},
        ("/frontend/keyframe",),
    ),
    "prior": (
        "mogs_node.depth_prior.node:DepthPriorNode",
        {"backend": "flow"},
        ("/frontend/keyframe",),
    ),
    "metrizer": (
        "mogs_node.metrizer.node:MetrizerNode",
        {"mode": "full"},
        ("/frontend/keyframe", "/seg/masks", "/prior/depth"),
    ),
    "mapper": (
        "mogs_node.mapper.node:MapperNode",
        {"iters_per_keyframe": 2, "ply_path": ""},
        ("/frontend/keyframe", "/metrizer/depth"),
    ),
    "report": (
        "mogs_node.report.node:RunReportNode",
        {"source_node": "nobody"},
        (
            "/frontend/odometry",
            "/frontend/keyframe",
            "/metrizer/depth",
            "/mapper/stats",
            "/mapper/render",
            "/mapper/gaussians",
            "/camera/image",
            "/groundtruth/pose",
            "/groundtruth/depth",
            "/diagnostics",
        ),
    ),
}


# ---------------------------------------------------------------------------------------- fuzz


def _sample(cls: type[msgs.Message], rng: np.random.Generator) -> msgs.Message:
    """A small valid message of ``cls``."""
    h, w, n = int(rng.integers(2, 9)), int(rng.integers(2, 9)), int(rng.integers(1, 6))
    f32 = lambda *s: rng.random(s, dtype=np.float32)  # noqa: E731
    base = {"stamp_ns": int(rng.integers(0, 1 << 40)), "frame_id": "f"}
    if cls is msgs.Imu:
        return msgs.Imu(**base, gyro_rad_s=(0.0, 0.1, 0.2), accel_m_s2=(0.0, 0.0, 9.8))
    if cls is msgs.Image:
        return msgs.Image(**base, encoding="rgb8", data=rng.integers(0, 255, (h, w, 3), np.uint8))
    if cls is msgs.Keyframe:
        return msgs.Keyframe(
            **base,
            keyframe_id=1,
            image=rng.integers(0, 255, (h, w, 3), np.uint8),
            K=np.eye(3),
            T_world_cam=np.eye(4),
            feature_ids=np.arange(n, dtype=np.int64),
            feature_uv_px=f32(n, 2),
            feature_xyz_cam_m=f32(n, 3),
            feature_weight=f32(n),
        )
    if cls is msgs.Masks:
        return msgs.Masks(**base, keyframe_id=1, labels=np.zeros((h, w), np.int32), backend="g")
    if cls is msgs.DepthMap:
        return msgs.DepthMap(
            **base, keyframe_id=1, kind="metric", depth=f32(h, w), confidence=f32(h, w), source="s"
        )
    if cls is msgs.Odometry:
        return msgs.Odometry(
            **base,
            frame_index=1,
            T_world_cam=np.eye(4),
            velocity_world_m_s=(0.0, 0.0, 0.0),
            status="ok",
        )
    if cls is msgs.MapStats:
        return msgs.MapStats(
            **base,
            keyframe_id=1,
            n_gaussians=1,
            n_keyframes=1,
            iterations=1,
            loss=0.1,
            psnr_db=20.0,
        )
    if cls is msgs.Render:
        return msgs.Render(**base, keyframe_id=1, image=rng.integers(0, 255, (h, w, 3), np.uint8))
    if cls is msgs.PoseStamped:
        return msgs.PoseStamped(**base, T_world_cam=np.eye(4))
    if cls is msgs.Diagnostics:
        return msgs.Diagnostics(**base, node="n", pid=1, uptime_s=1.0, status="ok")
    if cls is msgs.GaussianUpdate:
        z = np.zeros((2, 3), np.float32)  # two Gaussians: arrays for the bad_array fuzz
        return msgs.GaussianUpdate(
            **base,
            keyframe_id=1,
            ids=np.arange(2, dtype=np.int64),
            means=z,
            log_scales=z,
            quats_wxyz=np.tile(np.array([1, 0, 0, 0], np.float32), (2, 1)),
            opacity_logit=np.zeros(2, np.float32),
            colors_rgb=z,
            removed_ids=np.zeros(0, np.int64),
        )
    if cls is msgs.CameraInfo:
        return msgs.CameraInfo(
            **base,
            width=64,
            height=48,
            K=np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]),
            distortion_model="radtan",
            distortion_coeffs=np.array([0.1, -0.01, 0.0, 0.0]),
            T_imu_cam=np.eye(4),
            camera_height_m=1.65,
            imu_noise={"gyro_noise_rad_s_rthz": 1e-3},
            source="test",
        )
    raise AssertionError(cls)  # pragma: no cover


def _header(frames: list) -> dict:
    return msgpack.unpackb(frames[1], raw=False)


def _pack(topic: bytes, header: dict, buffers: list) -> list:
    return [topic, msgpack.packb(header, use_bin_type=True), *buffers]


KINDS = ("random_bytes", "truncated", "bad_array", "wrong_type", "bad_header", "oversize")


def fuzz_message(topic: str, rng: np.random.Generator, kind: str, seq: int) -> list:
    """One malformed multipart message for ``topic`` of the given ``kind``."""
    cls = TOPIC_TYPES[topic]
    t = topic.encode()
    if kind == "random_bytes":
        n_extra = int(rng.integers(0, 3))
        return [
            t,
            rng.bytes(int(rng.integers(0, 200))),
            *[rng.bytes(int(rng.integers(0, 64))) for _ in range(n_extra)],
        ]
    good = [bytes(f) for f in msgs.encode(topic, _sample(cls, rng), seq=seq, src=7)]
    if kind == "truncated":
        if len(good) > 2 and rng.random() < 0.5:  # the last buffer cut short
            cut = int(rng.integers(0, max(1, len(good[-1]))))
            if len(good[-1]) == 0:
                return good[:-1]
            return [*good[:-1], good[-1][:cut]]
        keep = int(rng.integers(1, len(good)))  # whole frames missing from the end
        if keep == 2 and len(good) == 2:
            keep = 1
        out = good[:keep]
        if len(out) >= 2 and len(good) == 2:  # no arrays: cut the header instead
            out = [t, good[1][: int(rng.integers(0, len(good[1])))]]
        return out
    header = _header(good)
    buffers = good[2:]
    if kind == "bad_array":
        if not header["a"]:  # a type without arrays: an array it does not have, or NaN scalars
            if cls in (msgs.Imu, msgs.Odometry):
                header["f"][next(k for k, v in cls.SCALARS.items() if v == "vec3")] = [
                    float("nan"),
                    0.0,
                    0.0,
                ]
                return _pack(t, header, buffers)
            header["a"] = [["data", "|u1", [4]]]
            return _pack(t, header, [b"\0" * 4])
        i = int(rng.integers(0, len(header["a"])))
        name, dtype, shape = header["a"][i]
        choice = int(rng.integers(0, 6))
        if choice == 0:  # a dtype that may not travel, or the wrong one for this field
            header["a"][i][1] = str(rng.choice(["<c8", "|O", ">f4", "<f2", "<U4", "|V8", "<u8"]))
        elif choice == 1:  # shape that does not fit the buffer
            header["a"][i][2] = [s + 1 for s in shape] or [1]
        elif choice == 2:  # negative or huge dimension
            header["a"][i][2] = [-1, *shape[1:]] if shape else [-1]
        elif choice == 3:  # too many dimensions
            header["a"][i][2] = [1, 1, 1, 1, 1, *shape]
        elif choice == 4 and any(d[1] in ("<f4", "<f8") for d in header["a"]):
            # NaN / inf in a float array (all of them require finite values)
            j = next(
                k for k, d in enumerate(header["a"]) if d[1] in ("<f4", "<f8") and np.prod(d[2]) > 0
            )
            arr = np.frombuffer(buffers[j], dtype=header["a"][j][1]).copy()
            arr.reshape(-1)[int(rng.integers(0, arr.size))] = rng.choice([np.nan, np.inf, -np.inf])
            buffers[j] = arr.tobytes()
        else:  # the same array given twice / a name the type does not have
            header["a"].append([f"not_{name}", dtype, shape])
            buffers.append(buffers[i])
        return _pack(t, header, buffers)
    if kind == "wrong_type":
        if rng.random() < 0.5:  # unknown or misspelt type name
            header["t"] = str(rng.choice(["Bogus", cls.TYPE.lower(), "", "Imu2", "Image "]))
            return _pack(t, header, buffers)
        other = [c for c in msgs.MESSAGE_TYPES.values() if c is not cls]
        o = other[int(rng.integers(0, len(other)))]  # a valid message of another type
        # its own publisher session with consecutive numbers: no gap is counted as a loss
        return [bytes(f) for f in msgs.encode(topic, _sample(o, rng), seq=seq, src=11)]
    if kind == "bad_header":
        choice = int(rng.integers(0, 5))
        if choice == 0:
            header["v"] = int(rng.integers(2, 100))
        elif choice == 1:
            del header[str(rng.choice(["t", "v", "seq", "src", "f", "a"]))]
        elif choice == 2:
            header["extra"] = 1
        elif choice == 3:
            k = str(rng.choice(list(cls.SCALARS)))
            header["f"][k] = {
                "int": "x",
                "str": 5,
                "float": "x",
                "float_or_nan": "x",
                "vec3": [1.0],
                "dict_num": [1],
                "dict_any": 3,
                "bool": 1,
            }[cls.SCALARS[k]]
        else:
            header["seq"] = "zero"
        return _pack(t, header, buffers)
    if kind == "oversize":
        return [t, good[1], *buffers, b"\0" * (MAX_BYTES + 1)]
    raise AssertionError(kind)  # pragma: no cover


def is_rejected(topic: str, frames: list) -> bool:
    """What a node does with ``frames``: True when it must count them as malformed."""
    try:
        env = msgs.decode(frames, max_bytes=MAX_BYTES)
    except MessageError:
        return True
    return not isinstance(env.msg, TOPIC_TYPES[topic])


def fuzz_batch(
    topic: str, rng: np.random.Generator, n: int, first: int, seqs: dict[str, int]
) -> list[list]:
    """``n`` malformed messages for ``topic``; one in 1000 is oversize (they are 2 MB each).

    ``seqs`` holds the next sequence number per topic of the well-formed messages of another
    type (the only fuzz a subscriber decodes far enough to read a sequence number).
    """
    out = []
    for i in range(n):
        kind = "oversize" if (first + i) % 1000 == 999 else KINDS[int(rng.integers(0, 5))]
        frames = fuzz_message(topic, rng, kind, seq=seqs.get(topic, 0))
        try:
            env = msgs.decode(frames, max_bytes=MAX_BYTES)
        except MessageError:
            env = None
        if env is not None:  # well-formed, of another type: it used up a sequence number
            seqs[topic] = env.seq + 1
        assert is_rejected(topic, frames), (topic, kind, frames[:2])
        out.append(frames)
    return out


def test_every_fuzz_kind_is_rejected_by_the_codec() -> None:
    """The oracle: each kind, on each topic, gives messages the decoder rejects."""
    rng = np.random.default_rng(1)
    for topic in TOPIC_TYPES:
        for kind in KINDS:
            for i in range(40):
                assert is_rejected(topic, fuzz_message(topic, rng, kind, i)), (topic, kind)


# ---------------------------------------------------------------------------------------- run


def _valid_keyframe() -> msgs.Keyframe:
    """A keyframe of the sim world with 300 features at their true depth."""
    from mogs_node.sim import SimConfig, make_sequence

    seq = make_sequence(SimConfig(seed=0, n_frames=2, width=621, height=188))
    f = seq.render(0)
    rng = np.random.default_rng(0)
    ok = np.argwhere(np.isfinite(f.depth_m) & (f.depth_m > 0) & (f.depth_m < 60))
    vu = ok[rng.choice(len(ok), 300, replace=False)]
    z = f.depth_m[vu[:, 0], vu[:, 1]]
    K = seq.camera.K
    uv = vu[:, ::-1].astype(np.float64) + 0.5
    xyz = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], 1)
    return msgs.Keyframe(
        stamp_ns=int(seq.stamps_ns[0]),
        frame_id="world",
        keyframe_id=0,
        image=np.ascontiguousarray(f.rgb),
        K=np.asarray(K, np.float64),
        T_world_cam=np.asarray(f.T_world_cam, np.float64),
        feature_ids=np.arange(300, dtype=np.int64),
        feature_uv_px=uv.astype(np.float32),
        feature_xyz_cam_m=xyz.astype(np.float32),
        feature_weight=np.ones(300, np.float32),
    )


def _received(mon: Monitor, node: str, topic: str) -> int:
    d = mon.diag.get(node)
    return -1 if d is None else int(d.topics.get(topic, {}).get("received", 0))


def _malformed(mon: Monitor, node: str, topic: str) -> int:
    d = mon.diag.get(node)
    return -1 if d is None else int(d.topics.get(topic, {}).get("malformed", 0))


CHAIN = {  # output topic -> the nodes that make it from one valid keyframe
    "/seg/masks": ("segmentation",),
    "/prior/depth": ("prior",),
    "/metrizer/depth": ("segmentation", "prior", "metrizer"),
    "/mapper/stats": ("segmentation", "prior", "metrizer", "mapper"),
}


def run_fuzz(
    tmp_path: Path, n_per_topic: int, nodes: tuple[str, ...] = tuple(NODES), seed: int = 0
) -> dict:
    bus = private_bus(max_message_bytes=MAX_BYTES, reliable_hwm=100_000)
    procs = Procs(bus)
    procs.start_broker(tmp_path)
    for name in nodes:
        cls, params, _ = NODES[name]
        if name == "mapper":
            params = {**params, "ply_path": str(tmp_path / "map.ply")}
        if name == "report":
            params = {**params, "out_dir": str(tmp_path / "report")}
        procs.start_node(name, cls, params, tmp_path)
    chain = tuple(t for t, need in CHAIN.items() if set(need) <= set(nodes))
    mon = Monitor(bus, chain, TOPIC_TYPES)
    ctx = zmq.Context()
    pub = Publisher(bus, context=ctx)
    rng = np.random.default_rng(seed)
    sent: dict[str, int] = {}
    seqs: dict[str, int] = {}
    t_fuzz = 0.0
    try:
        assert mon.wait_for_nodes(list(nodes), 120), {n: procs.tail(n) for n in nodes}
        subscribers = {t: [n for n in nodes if t in NODES[n][2]] for t in TOPIC_TYPES}
        subscribers = {t: ns for t, ns in subscribers.items() if ns}
        for topic in subscribers:
            assert pub.wait_for_subscriber(topic, 10), topic
            sent[topic] = 0
        t0 = time.monotonic()
        while any(k < n_per_topic for k in sent.values()):
            for topic in subscribers:  # one chunk on every topic, then wait until all counted
                n = min(CHUNK, n_per_topic - sent[topic])
                for frames in fuzz_batch(topic, rng, n, sent[topic], seqs):
                    pub.publish_frames(frames)
                sent[topic] += n
            counted = mon.wait_for(
                lambda m: all(
                    _malformed(m, x, t) >= sent[t] for t, ns in subscribers.items() for x in ns
                ),
                300,
            )
            assert counted, {
                t: {x: _malformed(mon, x, t) for x in ns} for t, ns in subscribers.items()
            }
        t_fuzz = time.monotonic() - t0
        alive = procs.alive()
        # (well-formed fuzz of another type counts as received, and as malformed)
        before = {
            (n, t): _received(mon, n, t)
            for n, t in (("report", "/frontend/keyframe"), ("frontend", "/imu"))
            if n in nodes
        }
        # still working: one valid keyframe through the whole chain, one IMU sample
        kf = _valid_keyframe()
        pub.publish("/frontend/keyframe", kf)
        pub.publish(
            "/imu",
            msgs.Imu(
                stamp_ns=1, frame_id="imu", gyro_rad_s=(0.0, 0.0, 0.0), accel_m_s2=(0.0, 0.0, 9.81)
            ),
        )
        chain_ok = mon.wait_for(lambda m: all(m.counts[t] >= 1 for t in chain), 120)
        handled_ok = mon.wait_for(
            lambda m: all(_received(m, n, t) == before[(n, t)] + 1 for n, t in before),
            30,
        )
        time.sleep(1.5)  # one more heartbeat after the valid messages
        diag = {n: mon.latest(n) for n in nodes}
        return {
            "n_per_topic": n_per_topic,
            "sent": sent,
            "fuzz_s": t_fuzz,
            "alive_after_fuzz": alive,
            "alive_at_end": procs.alive(),
            "chain_ok": chain_ok,
            "chain_counts": {t: mon.counts[t] for t in chain},
            "handled_ok": handled_ok,
            "malformed": {n: {t: _malformed(mon, n, t) for t in NODES[n][2]} for n in nodes},
            "counters": {n: dict(d.counters) for n, d in diag.items()},
            "topics": {n: d.topics for n, d in diag.items()},
            "logs": {n: procs.tail(n, 2000) for n in nodes},
        }
    finally:
        pub.close(0)
        mon.close()
        procs.stop()
        ctx.term()


def check_fuzz(fig: dict) -> None:
    n = fig["n_per_topic"]
    assert all(fig["alive_after_fuzz"].values()), (fig["alive_after_fuzz"], fig["logs"])
    assert all(fig["alive_at_end"].values()), fig["alive_at_end"]
    for node, per_topic in fig["malformed"].items():
        assert per_topic == {t: n for t in NODES[node][2]}, (node, per_topic)
        c = fig["counters"][node]
        # node-wide malformed: exactly the fuzz (nothing unattributed), no handler error from it;
        # topics a node reads beside its fuzzed inputs (the metrizer's /diagnostics) count theirs
        extra = sum(
            int(st.get("malformed", 0))
            for t, st in fig["topics"][node].items()
            if t not in NODES[node][2]
        )
        assert c["malformed"] - extra == n * len(NODES[node][2]), (node, c)
        assert c["handler_errors"] == 0, (node, c, fig["logs"][node])
    assert fig["chain_ok"], (fig["chain_counts"], fig["logs"])
    assert fig["handled_ok"]
    assert fig["chain_counts"] == {t: 1 for t in fig["chain_counts"]}


def test_fuzz_every_topic_small(tmp_path: Path) -> None:
    """2,000 per topic on all 12 topics through three node types (frontend, metrizer and the
    report node, which subscribes to 8 topics); the full size and every node type is the slow
    test below."""
    fig = run_fuzz(tmp_path, n_per_topic=2_000, nodes=("frontend", "metrizer", "report"))
    check_fuzz(fig)
    topics = {t for n in fig["malformed"].values() for t in n}
    assert topics == set(TOPIC_TYPES)


@pytest.mark.slow
def test_fuzz_every_topic_of_every_node_100k(tmp_path: Path) -> None:
    fig = run_fuzz(tmp_path, n_per_topic=100_000)
    check_fuzz(fig)
