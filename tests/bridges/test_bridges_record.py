"""`mogs record` to MCAP and `mogs play bag` of the recording: bit-exact, through real processes."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import zmq
from _reliability_harness import cli_process

from bridges import ros2, ros_convert
from bridges.recording import (
    ROS2_PREFIX,
    RecordingWriter,
    count_recording,
    is_recording,
    join_frames,
    read_recording,
    split_frames,
)
from mogs_node import msgs
from mogs_node.bus import Publisher
from mogs_node.demo_nodes import make_keyframe
from mogs_node.errors import DatasetError


def _messages() -> list[tuple[str, msgs.Message]]:
    rng = np.random.default_rng(0)
    out: list[tuple[str, msgs.Message]] = []
    for i in range(3):
        for k in range(4):
            t = 1_000_000_000 + i * 100_000_000 + k * 5_000_000
            out.append(
                (
                    "/imu",
                    msgs.Imu(
                        stamp_ns=t,
                        frame_id="imu",
                        gyro_rad_s=(0.1 * k, 0.0, -0.5),
                        accel_m_s2=(0.0, 9.81, 0.25 * i),
                    ),
                )
            )
        t = 1_000_000_000 + i * 100_000_000 + 20_000_000
        img = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
        out.append(
            ("/camera/image", msgs.Image(stamp_ns=t, frame_id="camera", encoding="rgb8", data=img))
        )
        T = np.eye(4)
        T[:3, 3] = (i, 0.5 * i, 2.0)
        out.append(
            (
                "/frontend/odometry",
                msgs.Odometry(
                    stamp_ns=t,
                    frame_id="camera",
                    frame_index=i,
                    T_world_cam=T,
                    velocity_world_m_s=(1.0, 0.0, 0.0),
                    status="tracking",
                ),
            )
        )
    kf = make_keyframe(7, 16, 12, 5)
    out.append(("/frontend/keyframe", kf))
    d = rng.uniform(0, 30, (12, 16)).astype(np.float32)
    d[0, :4] = 0
    out.append(
        (
            "/metrizer/depth",
            msgs.DepthMap(
                stamp_ns=kf.stamp_ns,
                frame_id="camera",
                keyframe_id=7,
                kind="metric",
                depth=d,
                confidence=(d > 0).astype(np.float32),
                source="test",
            ),
        )
    )
    out.append(
        (
            "/mapper/stats",
            msgs.MapStats(
                stamp_ns=kf.stamp_ns,
                frame_id="world",
                keyframe_id=7,
                n_gaussians=1000,
                n_keyframes=1,
                iterations=30,
                loss=0.25,
                psnr_db=21.5,
                extra={"ms": 4.0},
            ),
        )
    )
    out.append(
        (
            "/diagnostics",
            msgs.Diagnostics(
                stamp_ns=5,
                frame_id="",
                node="x",
                pid=1,
                uptime_s=1.0,
                status="ok",
                counters={"a": 1},
            ),
        )
    )
    return out


def _bytes(frames) -> list[bytes]:
    return [bytes(f.buffer) if hasattr(f, "buffer") else bytes(f) for f in frames]


def test_join_and_split_frames_round_trip_and_reject_bad_sizes() -> None:
    frames = [b"/imu", b"\x81\xa1t\x01", b"", b"\x00" * 7]
    sizes, data = join_frames(frames)
    assert sizes.tolist() == [4, 4, 0, 7] and split_frames(sizes, data) == frames
    with pytest.raises(DatasetError, match="do not add up"):
        split_frames(np.array([4, 4, 1], np.uint32), data)


@pytest.mark.parametrize("name", ["rec.mcap", "rec_folder"])
def test_writer_and_reader_round_trip_with_ros2_types(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    encoded = []
    with RecordingWriter(path) as w:
        for seq, (topic, m) in enumerate(_messages()):
            frames = msgs.encode(topic, m, seq=seq, src=99)
            encoded.append((topic, _bytes(frames)))
            w.write_frames(1000 + seq, frames, m)
    assert path.is_file() == (name == "rec.mcap")
    assert not (tmp_path / "rec.mcap.rosbag2").exists()
    assert is_recording(path)
    back = list(read_recording(path))
    assert [(r.topic, r.frames) for r in back] == encoded
    assert [r.log_time_ns for r in back] == list(range(1000, 1000 + len(encoded)))
    assert count_recording(path)["/imu"] == 12
    # the standard ROS 2 copies decode back to the same messages
    from rosbags.highlevel import AnyReader

    originals = {}
    for topic, m in _messages():
        originals.setdefault(topic, []).append(m)
    with AnyReader([path]) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert ROS2_PREFIX + "/diagnostics" not in conns  # no standard form
        got: dict[str, list] = {}
        for c, _, raw in reader.messages([v for k, v in conns.items() if k.startswith("/ros2/")]):
            got.setdefault(c.topic, []).append(reader.deserialize(raw, c.msgtype))
    assert [ros_convert.imu_from_ros(r) for r in got["/ros2/imu"]] == originals["/imu"]
    assert [ros_convert.image_from_ros(r) for r in got["/ros2/camera/image"]] == originals[
        "/camera/image"
    ]
    assert (
        ros2.depth_from_ros(got["/ros2/metrizer/depth"][0], keyframe_id=7, source="test")
        == (originals["/metrizer/depth"][0])
    )
    assert (
        ros_convert.mapstats_from_ros(got["/ros2/mapper/stats"][0]) == originals["/mapper/stats"][0]
    )
    for r, m in zip(got["/ros2/frontend/odometry"], originals["/frontend/odometry"]):
        o = ros2.odometry_from_ros(r, frame_index=m.frame_index, status="tracking")
        np.testing.assert_allclose(o.T_world_cam, m.T_world_cam, atol=1e-12)
    kf_pose = ros_convert.pose_from_ros(got["/ros2/frontend/keyframe"][0])
    np.testing.assert_allclose(kf_pose.T_world_cam, originals["/frontend/keyframe"][0].T_world_cam)
    with pytest.raises(DatasetError, match="already exists"):
        RecordingWriter(path)


def test_record_from_a_live_bus_and_replay_bit_exactly(broker_bus, tmp_path: Path) -> None:
    bus = broker_bus
    out = tmp_path / "run.mcap"
    ctx = zmq.Context()
    try:
        n = len(_messages())
        rec = cli_process(bus, "record", str(out), "--count", str(n))
        pub = Publisher(bus, context=ctx)
        assert pub.wait_for_subscriber("/imu", 30)
        sent = []
        for topic, m in _messages():
            seq = pub.publish(topic, m)
            sent.append((topic, _bytes(msgs.encode(topic, m, seq=seq, src=pub.src))))
        rec_out = rec.communicate(timeout=60)[0].decode()
        pub.close()
        assert rec.returncode == 0, rec_out
        assert [(r.topic, r.frames) for r in read_recording(out)] == sent
        # replay: a raw subscriber sees the very same frames, in the same order
        sub = ctx.socket(zmq.SUB)
        sub.connect(bus.sub_endpoint)
        sub.setsockopt(zmq.SUBSCRIBE, b"/")
        time.sleep(0.3)
        play = cli_process(
            bus, "play", "bag", str(out), "--rate", "0", "--wait", "10", "--no-groundtruth"
        )
        got = []
        deadline = time.monotonic() + 60
        while len(got) < n and time.monotonic() < deadline:
            if sub.poll(200):
                frames = sub.recv_multipart()
                env = msgs.decode(frames)
                if not (isinstance(env.msg, msgs.Diagnostics) and env.msg.node == "player"):
                    got.append((env.topic, frames))
        play_out = play.communicate(timeout=60)[0].decode()
        sub.close(linger=0)
    finally:
        ctx.term()
    assert play.returncode == 0, play_out
    assert got == sent
    assert "3/3 frames (100.0%)" in play_out
