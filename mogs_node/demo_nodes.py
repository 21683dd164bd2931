"""Small pass-through nodes used by the runtime's own tests and by the demo until the real
pipeline nodes land (issue 8 replaces the demo graph).

- :class:`SyntheticSource` publishes ``/camera/image`` frames (a moving procedural pattern) and
  ``/imu`` samples at fixed rates, or numbered :class:`~mogs_node.msgs.Keyframe` messages of a
  chosen size for transport tests.
- :class:`Relay` republishes every message of one topic on another topic.
- :class:`Recorder` counts what it receives per topic and writes a JSON summary on shutdown.
"""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mogs_node import msgs
from mogs_node.node import Node

__all__ = ["Recorder", "Relay", "SyntheticSource", "make_keyframe"]


def make_keyframe(
    keyframe_id: int, width: int = 640, height: int = 480, n_features: int = 500
) -> msgs.Keyframe:
    """A keyframe with deterministic content of about ``width*height*3`` bytes."""
    rng = np.random.default_rng(keyframe_id)
    image = np.empty((height, width, 3), np.uint8)
    image[...] = (np.arange(width, dtype=np.uint32)[None, :, None] + keyframe_id) % 251
    return msgs.Keyframe(
        stamp_ns=keyframe_id * 100_000_000,
        frame_id="cam",
        keyframe_id=keyframe_id,
        image=image,
        K=np.array([[500.0, 0, width / 2], [0, 500.0, height / 2], [0, 0, 1]]),
        T_world_cam=np.eye(4),
        feature_ids=np.arange(n_features, dtype=np.int64),
        feature_uv_px=rng.uniform(0, min(width, height), (n_features, 2)).astype(np.float32),
        feature_xyz_cam_m=rng.uniform(1, 20, (n_features, 3)).astype(np.float32),
        feature_weight=np.ones(n_features, np.float32),
    )


@dataclass(frozen=True)
class SyntheticSourceParams:
    n_frames: int = 50  # frames to publish, then stop (0 = forever)
    rate_hz: float = 10.0  # camera rate
    imu_per_frame: int = 10  # IMU samples per camera frame
    width: int = 320  # image width [px]
    height: int = 96  # image height [px]
    keyframes: bool = False  # publish /frontend/keyframe instead of images (transport tests)
    wait_for_subscriber_s: float = 10.0  # wait for a subscriber of the first topic before streaming
    final_after_s: float = 0.0  # if > 0: after n_frames, wait this long and send one last frame


class SyntheticSource(Node):
    """Publishes a fixed number of frames at a fixed rate, then exits with code 0."""

    Params = SyntheticSourceParams

    def setup(self) -> None:
        self.frame = 0
        self.topic = "/frontend/keyframe" if self.params.keyframes else "/camera/image"
        self.waited = False
        self.every(1.0 / self.params.rate_hz, self.tick)

    def tick(self) -> None:
        p = self.params
        if not self.waited:
            self.wait_for_subscriber(self.topic, p.wait_for_subscriber_s)
            self.waited = True
        if p.n_frames and self.frame >= p.n_frames:
            if p.final_after_s > 0 and self.frame == p.n_frames:
                time.sleep(p.final_after_s)  # let slow subscribers drain: the last seq is then seen
            else:
                self.request_stop()
                return
        stamp = time.time_ns()
        if p.keyframes:
            self.publish(self.topic, make_keyframe(self.frame, p.width, p.height))
        else:
            for k in range(p.imu_per_frame):
                self.publish(
                    "/imu",
                    msgs.Imu(
                        stamp_ns=stamp - (p.imu_per_frame - k) * 1_000_000,
                        frame_id="imu",
                        gyro_rad_s=(0.0, 0.01, 0.0),
                        accel_m_s2=(0.0, 0.0, 9.81),
                    ),
                )
            u = np.arange(p.width, dtype=np.int32)[None, :]
            v = np.arange(p.height, dtype=np.int32)[:, None]
            img = (((u + 4 * self.frame) // 16 + v // 16) % 2 * 200 + 30).astype(np.uint8)
            self.publish(
                self.topic, msgs.Image(stamp_ns=stamp, frame_id="cam", encoding="mono8", data=img)
            )
        self.frame += 1
        if p.final_after_s > 0 and self.frame > p.n_frames:
            self.request_stop()


@dataclass(frozen=True)
class RelayParams:
    input_topic: str = "/camera/image"  # topic to read
    output_topic: str = "/relay/image"  # topic to republish on
    reliable: bool = True  # input policy


class Relay(Node):
    """Republishes each message of ``input_topic`` on ``output_topic`` unchanged."""

    Params = RelayParams

    def setup(self) -> None:
        self.subscribe(self.params.input_topic, self.on_message, reliable=self.params.reliable)

    def on_message(self, msg: msgs.Message) -> None:
        self.publish(self.params.output_topic, msg)


@dataclass(frozen=True)
class RecorderParams:
    topics: tuple[str, ...] = ("/relay/image",)  # topics to count (reliable)
    expect: int = 0  # stop after this many messages on the first topic (0 = run until stopped)
    summary_path: str = ""  # JSON summary written on shutdown
    delay_ms: float = 0.0  # artificial work per message (to overwhelm a subscriber in tests)
    hang_after: int = 0  # hang (never return) on this message number (supervision tests; 0 = never)
    crash_after: int = 0  # exit with code 3 on this message number (supervision tests; 0 = never)


class Recorder(Node):
    """Counts messages (and checks keyframe ids arrive in order), writes a JSON summary."""

    Params = RecorderParams

    def setup(self) -> None:
        self.count: dict[str, int] = {t: 0 for t in self.params.topics}
        self.ids: list[int] = []
        for t in self.params.topics:
            self.subscribe(t, lambda m, t=t: self.on_message(t, m), reliable=True)

    def on_message(self, topic: str, msg: msgs.Message) -> None:
        self.count[topic] += 1
        if isinstance(msg, msgs.Keyframe):
            self.ids.append(msg.keyframe_id)
        if self.params.delay_ms:
            time.sleep(self.params.delay_ms / 1000)
        if self.params.crash_after and self.count[topic] == self.params.crash_after:
            self.log.warning("crashing on purpose (crash_after=%d)", self.params.crash_after)
            os._exit(3)
        if self.params.hang_after and self.count[topic] == self.params.hang_after:
            self.log.warning("hanging on purpose (hang_after=%d)", self.params.hang_after)
            threading.Event().wait()
        if self.params.expect and self.count[self.params.topics[0]] >= self.params.expect:
            self.request_stop()

    def teardown(self) -> None:
        if self.params.summary_path:
            stats = self.topic_stats()
            Path(self.params.summary_path).write_text(
                json.dumps({"count": self.count, "ids": self.ids, "topics": stats}, indent=1)
            )
