"""The player node as a real process: sim and KITTI streams, and flow control against slow consumers.

The slow consumer nodes below are started as processes (``mogs node tests.bridges.test_bridges_player:...``).
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zmq

from mogs_node import msgs
from mogs_node.bus import BusConfig, Subscriber
from mogs_node.demo_nodes import make_keyframe
from mogs_node.node import Node

# node processes import this module (its test node classes) without tests/ on their path
sys.path.insert(0, str(Path(__file__).parents[1]))  # tests/: the helpers
from _reliability_harness import cli_process, receive_for, start_node, stop_process  # noqa: E402

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------ helper processes


def collect(
    sub: Subscriber, proc: subprocess.Popen, timeout_s: float, arrivals: list[float] | None = None
) -> list[msgs.Envelope]:
    """Everything ``sub`` receives until ``proc`` exits and the socket has been quiet a moment
    (with the monotonic arrival time of each message appended to ``arrivals``)."""
    out: list[msgs.Envelope] = []
    deadline = time.monotonic() + timeout_s
    quiet_since = None
    while time.monotonic() < deadline:
        env = sub.receive(timeout_ms=100)
        if env is not None:
            out.append(env)
            if arrivals is not None:
                arrivals.append(time.monotonic())
            quiet_since = None
        elif proc.poll() is not None:
            quiet_since = quiet_since or time.monotonic()
            if time.monotonic() - quiet_since > 0.5:
                break
    return out


def play_to_end(
    bus: BusConfig,
    sub: Subscriber,
    timeout_s: float,
    *args: str,
    arrivals: list[float] | None = None,
) -> tuple[list[msgs.Envelope], str]:
    """Runs ``mogs play ARGS`` to its successful end: what ``sub`` received (see :func:`collect`)
    and the player's output."""
    proc = cli_process(bus, "play", *args)
    got = collect(sub, proc, timeout_s, arrivals)
    out = proc.communicate(timeout=30)[0].decode()
    assert proc.returncode == 0, out
    return got, out


# ------------------------------------------------------------------------ slow consumer nodes


@dataclass(frozen=True)
class SlowFrontendParams:
    delay_ms: float = 50.0  # work per image
    after_ack_ms: float = 0.0  # work per image after its acknowledgement (the real frontend
    # publishes the odometry, then the keyframe)
    keyframe_every: int = 3  # every n-th image becomes a keyframe
    summary_path: str = ""  # JSON summary on shutdown


class SlowFrontend(Node):
    """Like the frontend's interface: latest-wins images in, one Odometry per handled image (its
    stamp acknowledges the image), a Keyframe every ``keyframe_every`` images."""

    Params = SlowFrontendParams

    def setup(self) -> None:
        self.stamps: list[int] = []
        self.subscribe("/camera/image", self.on_image, reliable=False, msg_type=msgs.Image)

    def on_image(self, msg: msgs.Message) -> None:
        time.sleep(self.params.delay_ms / 1000)
        self.stamps.append(msg.stamp_ns)
        n = len(self.stamps)
        self.publish(
            "/frontend/odometry",
            msgs.Odometry(
                stamp_ns=msg.stamp_ns,
                frame_id="camera",
                frame_index=n - 1,
                T_world_cam=np.eye(4),
                velocity_world_m_s=(0.0, 0.0, 0.0),
                status="tracking",
            ),
        )
        if (n - 1) % self.params.keyframe_every == 0:
            kf = make_keyframe(n - 1, 32, 24, 4)
            kf.stamp_ns = msg.stamp_ns
            self.publish("/frontend/keyframe", kf)
        time.sleep(self.params.after_ack_ms / 1000)

    def teardown(self) -> None:
        if self.params.summary_path:
            Path(self.params.summary_path).write_text(
                json.dumps({"stamps": self.stamps, "topics": self.topic_stats()})
            )


@dataclass(frozen=True)
class SlowMetrizerParams:
    delay_ms: float = 150.0  # work per keyframe
    summary_path: str = ""  # JSON summary on shutdown


class SlowMetrizer(Node):
    """Keyframes in (reliable), one metric DepthMap per keyframe after ``delay_ms``."""

    Params = SlowMetrizerParams

    def setup(self) -> None:
        self.ids: list[int] = []
        self.max_backlog = 0
        self.subscribe("/frontend/keyframe", self.on_keyframe, msg_type=msgs.Keyframe)

    def on_keyframe(self, msg: msgs.Message) -> None:
        self.max_backlog = max(self.max_backlog, self.queue_depth)
        time.sleep(self.params.delay_ms / 1000)
        self.ids.append(msg.keyframe_id)
        d = np.ones((4, 4), np.float32)
        self.publish(
            "/metrizer/depth",
            msgs.DepthMap(
                stamp_ns=msg.stamp_ns,
                frame_id="camera",
                keyframe_id=msg.keyframe_id,
                kind="metric",
                depth=d,
                confidence=d,
                source="test",
            ),
        )

    def teardown(self) -> None:
        if self.params.summary_path:
            Path(self.params.summary_path).write_text(
                json.dumps(
                    {"ids": self.ids, "max_backlog": self.max_backlog, "topics": self.topic_stats()}
                )
            )


# ------------------------------------------------------------------------ tests


def test_sim_sequence_streams_every_message_in_time_order(broker_bus, bus_subscriber) -> None:
    from mogs_node.sim import SimConfig, make_sequence

    sub = bus_subscriber
    for t in ("/camera/image", "/imu", "/groundtruth/pose", "/groundtruth/depth", "/camera/info"):
        sub.subscribe(t)
    got, out = play_to_end(
        broker_bus,
        sub,
        120,
        "sim",
        "--gt-depth",
        "--frames",
        "6",
        "--size",
        "96x32",
        "--seed",
        "2",
        "--rate",
        "0",
        "--start",
        "0.1",
        "--end",
        "0.4",
    )
    seq = make_sequence(SimConfig(seed=2, n_frames=6, width=96, height=32))
    # the calibration first (and again every 2 s): the sim rig's camera and T_imu_cam
    assert got[0].topic == "/camera/info"
    infos = [e.msg for e in got if e.topic == "/camera/info"]
    got = [e for e in got if e.topic != "/camera/info"]
    assert all(i == infos[0] for i in infos)
    np.testing.assert_array_equal(infos[0].K, seq.camera.K)
    np.testing.assert_allclose(infos[0].T_imu_cam, seq.T_imu_cam, atol=1e-12)
    assert (infos[0].width, infos[0].height, infos[0].distortion_model) == (96, 32, "none")
    # frames 1..4 (0.1 s .. 0.4 s after frame 0), IMU from 1.2 s (the default imu_lead_s, where
    # the drive has it) before frame 1 up to frame 4
    t1, t4 = int(seq.stamps_ns[1]), int(seq.stamps_ns[4])
    imu_idx = [k for k, t in enumerate(seq.imu_stamps_ns) if t1 - 1_200_000_000 <= t <= t4]
    expected = sorted(
        [(int(seq.imu_stamps_ns[k]), 0, "/imu", k) for k in imu_idx]
        + [(int(seq.stamps_ns[i]), 1, "/camera/image", i) for i in range(1, 5)]
        + [(int(seq.stamps_ns[i]), 2, "/groundtruth/pose", i) for i in range(1, 5)]
        + [(int(seq.stamps_ns[i]), 3, "/groundtruth/depth", i) for i in range(1, 5)]
    )
    assert [(e.msg.stamp_ns, e.topic) for e in got] == [(t, topic) for t, _, topic, _ in expected]
    for env, (_, _, topic, k) in zip(got, expected):
        if topic == "/imu":
            assert env.msg.gyro_rad_s == tuple(seq.imu_gyro_rad_s[k].tolist())
            assert env.msg.accel_m_s2 == tuple(seq.imu_accel_m_s2[k].tolist())
        elif topic == "/camera/image":
            assert env.msg.encoding == "rgb8"
            np.testing.assert_array_equal(env.msg.data, seq.render(k).rgb)
        elif topic == "/groundtruth/pose":
            np.testing.assert_array_equal(env.msg.T_world_cam, seq.T_world_cam[k])
        else:
            d = seq.render(k).depth_m
            d = np.where(np.isfinite(d), d, 0.0).astype(np.float32)
            assert (env.msg.kind, env.msg.keyframe_id) == ("metric", k)
            np.testing.assert_array_equal(env.msg.depth, d)
            np.testing.assert_array_equal(env.msg.confidence, (d > 0).astype(np.float32))
    assert all(st.lost == 0 for st in sub.stats.values())
    assert "[####################] 4/4 frames (100.0%)" in out


@pytest.mark.shared_data
def test_kitti_excerpt_streams_all_78_frames_at_10_hz(
    broker_bus, bus_subscriber, tmp_path: Path
) -> None:
    from conftest import shared_data

    data = shared_data("kitti_raw_2011_09_26_78")
    summary = tmp_path / "recorder.json"
    recorder = start_node(
        "mogs_node.demo_nodes:Recorder",
        "recorder",
        {"topics": ["/camera/image"], "expect": 78, "summary_path": str(summary)},
        broker_bus,
    )
    sub = bus_subscriber
    sub.subscribe("/diagnostics")
    arrivals: list[float] = []
    try:
        # the recorder's first heartbeat: its subscription is in place before the player starts
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            env = sub.receive(timeout_ms=200)
            if env is not None and env.msg.node == "recorder":
                break
        sub.subscribe("/camera/image")
        sub.socket.setsockopt(zmq.UNSUBSCRIBE, b"/diagnostics")
        got, out = play_to_end(
            broker_bus, sub, 120, "kitti", str(data), "--progress", "1", arrivals=arrivals
        )
        recorder.wait(20)
        arrivals = [t for t, e in zip(arrivals, got) if e.topic == "/camera/image"]
        got = [e for e in got if e.topic == "/camera/image"]
    finally:
        stop_process(recorder)
    assert recorder.returncode == 0
    counted = json.loads(summary.read_text())
    assert counted["count"] == {"/camera/image": 78}
    assert counted["topics"]["/camera/image"]["lost"] == 0
    # no timestamps.txt in the excerpt: the reader stamps at 10 Hz from 0, the player keeps them
    assert [e.msg.stamp_ns for e in got] == [i * 100_000_000 for i in range(78)]
    assert all(e.msg.data.shape == (375, 1242, 3) and e.msg.encoding == "rgb8" for e in got)
    span = arrivals[-1] - arrivals[0]
    log.info("kitti78: 78 frames over %.2f s at the subscriber = %.2f Hz", span, 77 / span)
    assert "78/78 frames (100.0%)" in out


def _flow_run(
    bus: BusConfig,
    tmp_path: Path,
    play_args: list[str],
    frontend_delay_ms: float = 40.0,
    after_ack_ms: float = 0.0,
    metrizer_delay_ms: float = 120.0,
) -> tuple[dict, dict, str]:
    fe_sum, mz_sum = tmp_path / "fe.json", tmp_path / "mz.json"
    fe = start_node(
        "tests.bridges.test_bridges_player:SlowFrontend",
        "slow_frontend",
        {
            "delay_ms": frontend_delay_ms,
            "after_ack_ms": after_ack_ms,
            "keyframe_every": 3,
            "summary_path": str(fe_sum),
        },
        bus,
    )
    mz = start_node(
        "tests.bridges.test_bridges_player:SlowMetrizer",
        "slow_metrizer",
        {"delay_ms": metrizer_delay_ms, "summary_path": str(mz_sum)},
        bus,
    )
    try:
        time.sleep(0.5)  # both consumers subscribed before the player starts
        proc = cli_process(
            bus, "play", "sim", "--frames", "18", "--size", "64x24", "--wait", "10", *play_args
        )
        out = proc.communicate(timeout=120)[0].decode()
        time.sleep(0.5)  # the metrizer finishes its last keyframe
    finally:
        stop_process(fe)
        stop_process(mz)
    assert proc.returncode == 0, out
    return json.loads(fe_sum.read_text()), json.loads(mz_sum.read_text()), out


def test_fast_mode_loses_no_frame_and_bounds_the_keyframe_backlog(
    broker_bus, tmp_path: Path
) -> None:
    from mogs_node.sim import SimConfig, make_sequence

    # the default window (1 image in flight) with a frontend that keeps working after its
    # acknowledgement: the next image waits in its latest-wins queue and is not superseded
    fe, mz, out = _flow_run(
        broker_bus, tmp_path, ["--fast", "--max-keyframes-in-flight", "1"], 20.0, after_ack_ms=20.0
    )
    stamps = make_sequence(SimConfig(n_frames=18, width=64, height=24)).stamps_ns.tolist()
    assert fe["stamps"] == stamps  # every image handled, in order
    assert fe["topics"]["/camera/image"]["dropped"] == 0
    assert mz["ids"] == list(range(0, 18, 3))  # every keyframe metrized, in order
    assert mz["max_backlog"] == 0  # never more than one keyframe waiting
    assert "18/18 frames (100.0%)" in out


@pytest.mark.slow
def test_two_images_in_flight_lose_frames_to_a_latest_wins_frontend(
    broker_bus, tmp_path: Path
) -> None:
    """Why the default window is 1: with 2, the image sent on an acknowledgement arrives while
    the previous one still waits in the frontend's one-deep queue and supersedes it."""
    fe, _, out = _flow_run(
        broker_bus, tmp_path, ["--fast", "--max-in-flight", "2"], 20.0, after_ack_ms=60.0
    )
    st = fe["topics"]["/camera/image"]
    assert "18/18 frames (100.0%)" in out  # all published (dropped ones acknowledged by later)
    assert st["dropped"] > 0 and len(fe["stamps"]) == 18 - st["dropped"]


@pytest.mark.slow
def test_without_flow_control_a_slow_consumer_drops_frames(broker_bus, tmp_path: Path) -> None:
    """The control experiment: the same consumers, everything published at once (rate 0)."""
    fe, _, _ = _flow_run(broker_bus, tmp_path, ["--rate", "0"], frontend_delay_ms=300.0)
    st = fe["topics"]["/camera/image"]
    assert len(fe["stamps"]) < 18
    assert st["dropped"] + st["lost"] == 18 - len(fe["stamps"])  # every missing image is counted


@pytest.mark.parametrize(
    ("fmt", "compressed"),
    [
        pytest.param("mcap", True, marks=pytest.mark.slow),
        pytest.param("rosbag1", False, marks=pytest.mark.slow),
    ],
)
def test_standard_bag_replays_images_imu_and_ground_truth(
    broker_bus, bus_subscriber, tmp_path: Path, fmt: str, compressed: bool
) -> None:
    from mogs_node.datasets import BagTopics, write_sim_bag
    from mogs_node.sim import SimConfig, make_sequence

    seq = make_sequence(SimConfig(seed=1, n_frames=3, width=64, height=24))
    bag = tmp_path / ("sim.bag" if fmt == "rosbag1" else "sim_mcap")
    topics = BagTopics(image="/cam/image", imu="/imu0")
    write_sim_bag(seq, bag, fmt=fmt, topics=topics, compressed=compressed, with_depth=False)
    sub = bus_subscriber
    for t in ("/camera/image", "/imu", "/groundtruth/pose"):
        sub.subscribe(t)
    got, _ = play_to_end(
        broker_bus,
        sub,
        60,
        "bag",
        str(bag),
        "--image-topic",
        "/cam/image",
        "--imu-topic",
        "/imu0",
        "--rate",
        "0",
        "--encoding",
        "bgr8",
    )
    images = [e.msg for e in got if e.topic == "/camera/image"]
    assert [m.stamp_ns for m in images] == seq.stamps_ns.tolist()
    for i, m in enumerate(images):
        assert m.encoding == "bgr8"
        np.testing.assert_array_equal(m.data, seq.render(i).rgb[..., ::-1])  # PNG is lossless
    imu = [e.msg for e in got if e.topic == "/imu"]
    inside = (seq.imu_stamps_ns >= seq.stamps_ns[0] - 100_000_000) & (
        seq.imu_stamps_ns <= seq.stamps_ns[-1]
    )
    assert [m.stamp_ns for m in imu] == seq.imu_stamps_ns[inside].tolist()
    np.testing.assert_array_equal([m.gyro_rad_s for m in imu], seq.imu_gyro_rad_s[inside])
    poses = [e.msg for e in got if e.topic == "/groundtruth/pose"]
    np.testing.assert_allclose([p.T_world_cam for p in poses], seq.T_world_cam, atol=1e-9)


@pytest.mark.slow
def test_sigusr1_pauses_and_sigusr2_resumes(broker_bus, bus_subscriber) -> None:
    import signal

    sub = bus_subscriber
    sub.subscribe("/camera/image")
    got: list[msgs.Envelope] = []
    proc = cli_process(
        broker_bus, "play", "sim", "--frames", "12", "--size", "32x16", "--rate", "2"
    )
    while not got:
        env = sub.receive(timeout_ms=30_000)
        assert env is not None, "player published nothing"
        got.append(env)
    proc.send_signal(signal.SIGUSR1)
    time.sleep(0.1)  # the pause applies at the next tick; a frame may be on its way
    n_paused = len(got) + len(receive_for(sub, 0.1))
    during = receive_for(sub, 0.6)  # 0.6 s paused: at 2 x 10 Hz about 12 frames would come
    proc.send_signal(signal.SIGUSR2)
    rest = collect(sub, proc, 60)
    out = proc.communicate(timeout=30)[0].decode()
    assert proc.returncode == 0, out
    assert during == []
    assert n_paused < 12
    assert n_paused + len(rest) == 12
    assert "paused at frame" in out and "resumed" in out


def test_a_replay_at_its_rate_waits_for_the_keyframes_of_a_slow_pipeline(
    broker_bus, tmp_path: Path
) -> None:
    """Issue 23: at rate 1 (frames every 0.1 s, a keyframe every 0.3 s) a metrizer taking 1.2 s
    per keyframe would fall ever further behind; with ``--max-keyframes-in-flight 1`` the replay's
    clock holds instead, so no keyframe ever waits in its queue, and every one is metrized."""
    fe, mz, out = _flow_run(
        broker_bus,
        tmp_path,
        ["--rate", "1.0", "--max-keyframes-in-flight", "1"],
        frontend_delay_ms=5.0,
        metrizer_delay_ms=1200.0,
    )
    # in order, each after the previous one was done (the last one may still be in the works when
    # the harness stops the metrizer, 0.5 s after the player's end)
    assert mz["ids"] in (list(range(0, 18, 3)), list(range(0, 15, 3)))
    assert mz["max_backlog"] == 0  # the replay waited: never a keyframe queued behind another
    assert "18/18 frames (100.0%)" in out


def test_a_fast_player_blocked_on_acknowledgements_sleeps_instead_of_ticking(inproc_bus) -> None:
    """While no acknowledgement comes, the player's loop sleeps in its poll (the tick timer is
    snoozed until an acknowledgement or the ack timeout) instead of ticking every ``tick_s``:
    on 2 cores a 2 ms tick took CPU from the mapper it waits for."""
    from bridges.player import PlayerNode

    bus, ctx = inproc_bus
    params = {
        "source": "sim",
        "sim": {"n_frames": 6, "width": 32, "height": 16},
        "fast": True,
        "wait_for_subscriber_s": 0.0,
        "ack_timeout_s": 0.0,  # never give up: blocked for good after the first image
        "tick_s": 0.002,
        "progress_period_s": 0.0,
    }
    node = PlayerNode("player", params, bus, context=ctx, diagnostics_period_s=0)  # set up
    ticks: list[int] = []
    timer = node._timers[node._tick_timer]
    tick = timer[2]
    timer[2] = lambda: (ticks.append(node.frames_published), tick())[1]
    t_end = time.monotonic() + 1.0
    while time.monotonic() < t_end:
        node.spin_once(100)
    assert node.frames_published == 1  # the first image went out, then no acknowledgement
    # a 2 ms tick would run ~500 times in that second; snoozed 0.25 s at a time: ~5
    assert 1 <= len(ticks) <= 20, len(ticks)
    node.teardown()
    node.close()


def test_the_sim_source_casts_each_frame_once_for_its_image_and_depth(monkeypatch) -> None:
    """The player loads a frame's image and then its ground-truth depth: one render serves both,
    with the pixels of a render of its own."""
    from bridges.sources import open_sequence
    from mogs_node.sim import SimConfig, SimSequence, make_sequence

    cfg = {"seed": 0, "n_frames": 5, "width": 96, "height": 48}
    own = make_sequence(SimConfig(**cfg)).render(2)
    calls: list[int] = []
    render = SimSequence.render

    def counted(self: SimSequence, i: int):
        calls.append(i)
        return render(self, i)

    monkeypatch.setattr(SimSequence, "render", counted)
    seq = open_sequence("sim", sim=cfg)
    for f in seq.frames[:3]:
        image, depth = f.image, f.load_depth()
    assert calls == [0, 1, 2]
    assert np.array_equal(image, own.rgb)
    assert np.array_equal(depth, np.where(np.isfinite(own.depth_m), own.depth_m, 0.0))


def test_a_player_has_its_prefetch_loaded_before_the_first_image(inproc_bus, monkeypatch) -> None:
    """Loading starts while the pipeline comes up (setup), and the ``prefetch`` frames loaded
    ahead (the sim renders each, ~0.16 s of CPU at 621x188) are ready before the first image
    goes out: the sim's rendering does not pace the drive that the pipeline is timed on."""
    from bridges.player import PlayerNode
    from mogs_node.sim import SimSequence

    calls: list[int] = []
    render = SimSequence.render
    monkeypatch.setattr(
        SimSequence, "render", lambda self, i: (calls.append(i), render(self, i))[1]
    )
    bus, ctx = inproc_bus
    params = {
        "source": "sim",
        "sim": {"n_frames": 8, "width": 32, "height": 16},
        "fast": True,
        "prefetch": 4,
        "wait_for_subscriber_s": 0.0,
        "ack_timeout_s": 0.0,
        "progress_period_s": 0.0,
    }
    node = PlayerNode("player", params, bus, context=ctx, diagnostics_period_s=0)
    rendered_at_first_image: list[list[int]] = []
    publish = node.publish

    def spy(topic: str, msg: object, *a: object, **kw: object) -> None:
        if topic == node.params.image_topic and not rendered_at_first_image:
            rendered_at_first_image.append(sorted(set(calls)))
        publish(topic, msg, *a, **kw)

    node.publish = spy  # type: ignore[method-assign]
    t_end = time.monotonic() + 10.0
    while not rendered_at_first_image and time.monotonic() < t_end:
        node.spin_once(100)
    assert rendered_at_first_image == [[0, 1, 2, 3, 4]]  # the first image and 4 ahead
    node.teardown()
    node.close()
