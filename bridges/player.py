"""The player node: streams a recorded or simulated sequence onto the bus in time order.

Publishes ``/camera/image`` (:class:`~mogs_node.msgs.Image`) and ``/imu``
(:class:`~mogs_node.msgs.Imu`) with the recorded stamps, the source's calibration on
``/camera/info`` (:class:`~mogs_node.msgs.CameraInfo`: before the first image, then every
``camera_info_period_s``), and ground truth when the dataset has it:
``/groundtruth/pose`` (:class:`~mogs_node.msgs.PoseStamped`, ``T_world_cam``) and, with
``groundtruth_depth``, ``/groundtruth/depth`` (:class:`~mogs_node.msgs.DepthMap`, kind metric,
``keyframe_id`` = frame index). A recording of ``mogs record`` is re-published bit-exactly, frame
for frame, on its recorded topics.

Timing (see :mod:`bridges.replay`):

- ``rate`` 1.0 plays at the recorded rate, N at N times it (``rate`` 0 or ``fast``: no clock);
- ``fast``: as fast as the pipeline accepts: at most ``max_frames_in_flight`` images are published
  and not yet acknowledged on ``ack_topic`` (default ``/frontend/odometry``; any message whose
  ``stamp_ns`` is at or after an image's stamp acknowledges it), and, if
  ``max_keyframes_in_flight`` > 0, at most that many keyframes seen on ``keyframe_topic`` are
  waiting for ``keyframe_done_topic`` (default ``/metrizer/depth``). The default of one image in
  flight is what makes this lossless: the frontend's image subscription is best effort and keeps
  only the latest image, so a second image published while the first still waits in its queue
  supersedes it (measured: 11 of 60 frames lost with 2 in flight). The keyframe workers' backlog
  stays bounded;
- a replay at a ``rate`` waits for the pipeline too (issue 23): with ``max_keyframes_in_flight``
  > 0 its clock holds while that many keyframes wait for ``keyframe_done_topic`` (the schedule
  shifts by the wait, as with a pause); frames the frontend cannot keep up with are still
  superseded (latest wins), keyframes are not. In both modes the ``ack_timeout_s`` runs only while
  no other node's heartbeat says it is busy: a pipeline that works is waited for;
- ``start_s`` / ``end_s``: seconds after the first frame; IMU samples from ``imu_lead_s`` before
  the first played frame are included;
- pause / resume: ``SIGUSR1`` pauses, ``SIGUSR2`` resumes (the schedule shifts by the pause), or
  :meth:`PlayerNode.pause` / :meth:`PlayerNode.resume` in-process;
- a progress line (bar, frames published / total, rate, IMU count, state) every
  ``progress_period_s`` in the log, and the same figures in ``/diagnostics`` counters.

An image (or ground-truth depth map) that cannot be read, e.g. a truncated PNG, is logged once
(later ones at the 2nd, 4th, 8th, ... with the count), skipped with its ground truth, and counted
as ``frames_unreadable`` in ``/diagnostics`` (the run report carries it); the stream goes on.

When everything is published the node lingers ``linger_s`` (flushing, late acknowledgements) and
stops with exit code 0 if ``exit_when_done``.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor, wait

import cv2
import numpy as np

from bridges.player_params import PlayerParams, convert_encoding
from bridges.recording import RecordedMessage, count_recording, read_recording
from bridges.replay import (
    IMAGE,
    FlowWindow,
    RateMeter,
    ReplayClock,
    build_events,
    format_progress,
    select_window,
)
from bridges.sources import camera_info_of, open_sequence
from mogs_node import msgs
from mogs_node.datasets import Sequence
from mogs_node.errors import DatasetError
from mogs_node.heartbeat import other_node_busy
from mogs_node.node import CATCH_UP_ENV, Node

__all__ = ["PlayerNode", "PlayerParams"]

HELD_SNOOZE_S = 0.1  # rate mode, clock held or next message not due: longest sleep [s]


class PlayerNode(Node):
    """Streams a sequence (see the module docstring); one instance plays once."""

    Params = PlayerParams

    # ------------------------------------------------------------------ set-up

    def setup(self) -> None:
        p: PlayerParams = self.params
        self.seq: Sequence | None = None
        self.user_poses: list[np.ndarray | None] = []  # player.poses, per frame
        self.events: list[tuple[int, str, int]] = []
        self._rec_iter: Iterator[RecordedMessage] | None = None
        self._rec_next: RecordedMessage | None = None
        if p.source == "recording":
            counts = count_recording(p.path)
            self.total_frames = counts.get(p.image_topic, 0)
            self.total_messages = sum(counts.values())
            self._rec_iter = read_recording(p.path)
            self._rec_next = next(self._rec_iter, None)
        else:
            self.seq = open_sequence(
                p.source,
                p.path,
                bag_topics=p.bag_topics(),
                intrinsics=p.intrinsics,
                sim=p.sim,
            )
            imu_stamps = self.seq.imu.stamps_ns if self.seq.imu is not None else ()
            self.events = select_window(
                build_events(self.seq.stamps_ns, imu_stamps),
                start_s=p.start_s,
                end_s=p.end_s,
                imu_lead_s=p.imu_lead_s,
            )
            self.total_frames = sum(1 for e in self.events if e[1] == IMAGE)
            self.total_messages = len(self.events)
            self.camera_info: msgs.CameraInfo | None = None
            if len(self.seq):
                first = self.events[0][0] if self.events else int(self.seq.stamps_ns[0])
                self.camera_info = camera_info_of(
                    self.seq,
                    stamp_ns=first,
                    frame_id=p.camera_frame_id,
                    camera_height_m=p.camera_height_m,
                )
                self._log_calibration(self.camera_info)
            if p.poses:
                from mogs_node.datasets.vi_folder import read_user_poses

                self.user_poses = read_user_poses(p.poses, self.seq.stamps_ns)
                self.log.info(
                    "poses of %d of %d frames from %s on %s",
                    sum(T is not None for T in self.user_poses),
                    len(self.seq),
                    p.poses,
                    p.pose_topic,
                )
        self._resume_in_flight: int | None = None
        skipped = self._skip_journaled()
        self.pos = 0
        self.frames_published = skipped
        self.imu_published = 0
        self.messages_published = 0
        self.clock = ReplayClock(0.0 if p.fast else p.rate)
        self.frames = FlowWindow(p.max_frames_in_flight if p.fast else 0)
        self.keyframes = FlowWindow(p.max_keyframes_in_flight)
        self._held = False  # rate mode: clock held while keyframes wait (issue 23)
        if self._resume_in_flight is not None:  # journaled, not yet acknowledged: wait for it
            self.frames.sent(self._resume_in_flight)
        self.meter = RateMeter()
        self.state = "starting"
        self._blocked_since: float | None = None
        self._done_at: float | None = None
        self._started = False
        self._last_progress = time.monotonic()
        self._pause_requested: bool | None = None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="player-load")
        self._loads: dict[int, Future] = {}
        self._image_positions = [i for i, e in enumerate(self.events) if e[1] == IMAGE]
        self._next_image = 0  # index into _image_positions of the next image to publish
        # recordings are re-published frame for frame: they keep their recorded seq and src
        self._replay_raw = p.source == "recording"
        for k in (
            "frames_published",
            "frames_unreadable",
            "imu_published",
            "ack_waits",
            "ack_timeouts",
        ):
            self.counters[k] = 0
        self.counters["frames_total"] = self.total_frames
        if p.fast:
            self.subscribe(p.ack_topic, self._on_ack, reliable=True)
        if p.fast or p.max_keyframes_in_flight > 0:
            # a replay waits for a pipeline that works (issue 23): the ack timeout runs only
            # while no node reports being busy in its heartbeat (mogs_node/heartbeat.py)
            self.subscribe("/diagnostics", self._on_heartbeat, reliable=False, queue_size=64)
        if p.max_keyframes_in_flight > 0:
            self.subscribe(p.keyframe_topic, self._on_keyframe, reliable=True)
            self.subscribe(p.keyframe_done_topic, self._on_keyframe_done, reliable=True)
        self.log.info(
            "playing %s %s: %d frames, %d messages, %s",
            p.source,
            p.path or "",
            self.total_frames,
            self.total_messages,
            f"fast (flow control on {p.ack_topic})" if p.fast else f"rate {p.rate}x",
        )
        self._tick_timer = self.every(p.tick_s, self.tick)
        if self.seq is not None:  # load (the sim: render) ahead while the pipeline comes up
            self._prefetch()
        if self.seq is not None and self.camera_info is not None:
            self.every(p.camera_info_period_s, self._publish_camera_info)

    def _log_calibration(self, info: msgs.CameraInfo) -> None:
        K = info.K
        self.log.info(
            "calibration of %s: %dx%d fx %.3f fy %.3f cx %.3f cy %.3f, distortion %s, "
            "T_imu_cam %s, camera height %s, IMU noise %s",
            info.source,
            info.width,
            info.height,
            K[0, 0],
            K[1, 1],
            K[0, 2],
            K[1, 2],
            info.distortion_model,
            "known" if info.T_imu_cam is not None else "unknown",
            f"{info.camera_height_m:.3f} m"
            if info.camera_height_m == info.camera_height_m
            else "unknown",
            "known" if info.imu_noise else "unknown",
        )

    def _publish_camera_info(self) -> None:
        """The calibration on ``camera_info_topic`` (reliable; again every period: no latching)."""
        if self.camera_info is not None and self._started:
            self.publish(self.params.camera_info_topic, self.camera_info)
            self.counters["camera_info_published"] = (
                self.counters.get("camera_info_published", 0) + 1
            )

    def _skip_journaled(self) -> int:
        """After a restart or on ``--resume``: drop the images and IMU samples the journal already
        holds (the frontend replays those from it); returns how many images were skipped."""
        if os.environ.get(CATCH_UP_ENV) != "1":
            return 0
        if self.seq is None:
            self.log.warning("a recording is replayed from its start after a restart")
            return 0
        from mogs_node.journal.protocol import JournalClient

        p: PlayerParams = self.params
        client = JournalClient(self.bus, context=self.context)
        try:
            keys = client.keys([p.image_topic, p.imu_topic, p.ack_topic])
        finally:
            client.close()
        last_img = max(keys.get(p.image_topic) or [-1])
        if last_img >= 0 and max(keys.get(p.ack_topic) or [-1]) < last_img:
            self._resume_in_flight = last_img  # a new image now could supersede it unhandled
        last_imu = max(keys.get(p.imu_topic) or [-1])
        before = len(self.events)
        self.events = [e for e in self.events if e[0] > (last_img if e[1] == IMAGE else last_imu)]
        skipped = self.total_frames - sum(1 for e in self.events if e[1] == IMAGE)
        self.log.info(
            "resuming after the journal: %d frames and %d IMU samples already played",
            skipped,
            before - len(self.events) - skipped,
        )
        return skipped

    def run(self, *, install_signal_handlers: bool = True, duration_s: float | None = None) -> int:
        """As :meth:`Node.run`, plus SIGUSR1 (pause) / SIGUSR2 (resume) handlers."""
        if install_signal_handlers and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGUSR1, lambda *_: self.pause())
            signal.signal(signal.SIGUSR2, lambda *_: self.resume())
        return super().run(install_signal_handlers=install_signal_handlers, duration_s=duration_s)

    def pause(self) -> None:
        """Pause playback (signal-safe: applied at the next tick)."""
        self._pause_requested = True

    def resume(self) -> None:
        """Resume playback (signal-safe: applied at the next tick)."""
        self._pause_requested = False

    # ------------------------------------------------------------------ flow control

    def _on_ack(self, msg: msgs.Message) -> None:
        self.frames.ack(msg.stamp_ns)
        self.reschedule(self._tick_timer, 0.0)  # a blocked player may go on now

    def _on_keyframe(self, msg: msgs.Message) -> None:
        self.keyframes.sent(msg.stamp_ns)

    def _on_keyframe_done(self, msg: msgs.Message) -> None:
        self.keyframes.ack(msg.stamp_ns)
        self.reschedule(self._tick_timer, 0.0)

    def _on_heartbeat(self, msg: msgs.Message) -> None:
        if self._blocked_since and other_node_busy(msg, self.name):
            self._blocked_since = max(self._blocked_since, time.monotonic())

    def _may_send_image(self, now: float) -> bool:
        if self.frames.can_send() and self.keyframes.can_send():
            self._blocked_since = None
            return True
        if self._blocked_since is None:
            self._blocked_since = now
            self.counters["ack_waits"] += 1
        timeout = self.params.ack_timeout_s
        if timeout > 0 and now - self._blocked_since > timeout:
            self.log.warning(
                "no acknowledgement for %.1f s (frames in flight %d on %s, keyframes %d on %s): "
                "going on",
                timeout,
                self.frames.in_flight,
                self.params.ack_topic,
                self.keyframes.in_flight,
                self.params.keyframe_done_topic,
            )
            self.counters["ack_timeouts"] += 1
            self.frames = FlowWindow(self.frames.max_in_flight)
            self.keyframes = FlowWindow(self.keyframes.max_in_flight)
            self._blocked_since = None
            return True
        return False

    # ------------------------------------------------------------------ loading

    def _load(self, frame_index: int) -> tuple[np.ndarray, str, np.ndarray | None]:
        assert self.seq is not None
        f = self.seq.frames[frame_index]
        image, enc = convert_encoding(f.image, f.encoding, self.params.encoding)
        depth = f.depth_m() if (self.params.groundtruth_depth and f.has_depth) else None
        return image, enc, depth

    def _prefetch(self) -> None:
        ahead = self._image_positions[
            self._next_image : self._next_image + 1 + self.params.prefetch
        ]
        for pos in ahead:
            k = self.events[pos][2]
            if k not in self._loads:
                self._loads[k] = self._pool.submit(self._load, k)

    def _wait_for_loads(self) -> None:
        """Before the first image: the ``prefetch`` frames loaded ahead are ready, so that
        loading the sequence (the sim renders each frame and its depth, ~0.16 s of CPU a frame)
        is not part of the drive that the pipeline is timed on (issue 17); heartbeats go on."""
        pending = set(self._loads.values())
        while pending and not self.stopping:
            _, pending = wait(pending, timeout=1.0)
            if self.diagnostics_period_s > 0:
                self.publish_diagnostics()

    # ------------------------------------------------------------------ publishing

    def _publish_event(self, ev: tuple[int, str, int]) -> None:
        assert self.seq is not None
        p: PlayerParams = self.params
        stamp, kind, k = ev
        if kind != IMAGE:
            imu = self.seq.imu
            assert imu is not None
            g, a = imu.gyro_rad_s[k], imu.accel_m_s2[k]
            self.publish(
                p.imu_topic,
                msgs.Imu(
                    stamp_ns=stamp,
                    frame_id=p.imu_frame_id,
                    gyro_rad_s=(float(g[0]), float(g[1]), float(g[2])),
                    accel_m_s2=(float(a[0]), float(a[1]), float(a[2])),
                ),
            )
            self.imu_published += 1
            self.counters["imu_published"] = self.imu_published
            return
        self._prefetch()
        self._next_image += 1
        try:
            image, enc, depth = self._loads.pop(k).result()
        except (DatasetError, OSError, cv2.error) as err:
            self._unreadable(k, err)
            return
        if self.user_poses and self.user_poses[k] is not None:  # before its image
            self.publish(
                p.pose_topic,
                msgs.PoseStamped(stamp_ns=stamp, frame_id="world", T_world_cam=self.user_poses[k]),
            )
        self.publish(
            p.image_topic,
            msgs.Image(stamp_ns=stamp, frame_id=p.camera_frame_id, encoding=enc, data=image),
        )
        self.frames.sent(stamp)
        frame = self.seq.frames[k]
        if p.groundtruth and frame.T_world_cam is not None:
            self.publish(
                p.gt_pose_topic,
                msgs.PoseStamped(
                    stamp_ns=stamp,
                    frame_id=p.camera_frame_id,
                    T_world_cam=np.asarray(frame.T_world_cam, dtype=np.float64),
                ),
            )
        if depth is not None:
            d = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
            self.publish(
                p.gt_depth_topic,
                msgs.DepthMap(
                    stamp_ns=stamp,
                    frame_id=p.camera_frame_id,
                    keyframe_id=frame.index,
                    kind="metric",
                    depth=d,
                    confidence=(d > 0).astype(np.float32),
                    source="groundtruth",
                ),
            )
        self._frame_done()

    def _unreadable(self, frame_index: int, err: Exception) -> None:
        """Skip frame ``frame_index``, which could not be read: counted, logged once."""
        n = int(self.counters["frames_unreadable"]) + 1
        self.counters["frames_unreadable"] = n
        if n & (n - 1) == 0:  # 1st, 2nd, 4th, ...: a folder of bad files is not a log flood
            self.log.warning(
                "frame %d unreadable, skipped (%d unreadable so far): %s", frame_index, n, err
            )

    def _frame_done(self) -> None:
        self.frames_published += 1
        self.counters["frames_published"] = self.frames_published
        self.meter.tick(time.monotonic())

    def _publish_recorded(self, rec: RecordedMessage) -> None:
        assert self._replay_raw
        self.publish_frames(rec.frames)
        if rec.topic == self.params.image_topic:
            self.frames.sent(msgs.decode(rec.frames).msg.stamp_ns)
            self._frame_done()

    # ------------------------------------------------------------------ the loop

    def _peek(self) -> tuple[int, bool] | None:
        """(stamp of the next message, whether it is an image), or None at the end."""
        if self._rec_iter is not None:
            if self._rec_next is None:
                return None
            return self._rec_next.log_time_ns, self._rec_next.topic == self.params.image_topic
        if self.pos >= len(self.events):
            return None
        ev = self.events[self.pos]
        return ev[0], ev[1] == IMAGE

    def _publish_next(self) -> None:
        if self._rec_iter is not None:
            assert self._rec_next is not None
            self._publish_recorded(self._rec_next)
            self._rec_next = next(self._rec_iter, None)
        else:
            self._publish_event(self.events[self.pos])
        self.pos += 1
        self.messages_published += 1

    def tick(self) -> None:
        p: PlayerParams = self.params
        if not self._started:
            self._started = True
            topic = p.image_topic
            if self._replay_raw and self.total_frames == 0 and self._rec_next is not None:
                topic = self._rec_next.topic
            if (
                p.wait_for_subscriber_s > 0
                and not self.wait_for_subscriber(topic, p.wait_for_subscriber_s)
                and not self.stopping
            ):
                self.log.warning(
                    "no subscriber of %s after %.1f s: playing anyway",
                    topic,
                    p.wait_for_subscriber_s,
                )
            if p.wait_for_nodes:
                self._wait_for_nodes(p.wait_for_nodes, p.wait_for_nodes_s)
            if self.seq is not None:
                self._publish_camera_info()  # before the first image and IMU sample
                self._prefetch()
                self._wait_for_loads()
            self.state = "playing"
        now = time.monotonic()
        if self._pause_requested is not None:
            if self._pause_requested:
                self.clock.pause(now)
                self.state = "paused"
                self.log.info("paused at frame %d/%d", self.frames_published, self.total_frames)
            else:
                self.clock.resume(now)
                self.state = "playing"
                self.log.info("resumed")
            self._pause_requested = None
        if self._held and self.state != "paused" and self._may_send_image(now):
            # rate mode: the keyframes were done (a user's pause stays a pause)
            self._held = False
            self.clock.resume(now)
            self.state = "playing"
        budget_end = now + 0.05
        while self._done_at is None:
            nxt = self._peek()
            if nxt is None:
                self._done_at = now
                self.state = "done"
                self._progress(now, force=True)
                break
            stamp, is_image = nxt
            if self.clock.paused:
                break
            if p.fast:
                if is_image and not self._may_send_image(now):
                    self.state = "waiting for " + (
                        p.ack_topic if not self.frames.can_send() else p.keyframe_done_topic
                    )
                    # nothing to do until an acknowledgement arrives (its handler wakes the
                    # tick) or the ack timeout runs out: sleep in the poll instead of ticking
                    snooze = 0.25
                    if p.ack_timeout_s > 0 and self._blocked_since is not None:
                        snooze = min(snooze, self._blocked_since + p.ack_timeout_s - now)
                    self.reschedule(self._tick_timer, snooze)
                    break
                self.state = "playing"
            elif is_image and self.keyframes.max_in_flight and not self._may_send_image(now):
                self._held = True  # the clock waits for the pipeline's keyframes
                self.clock.pause(now)
                self.state = "waiting for " + p.keyframe_done_topic
                # the keyframe-done handler wakes the tick; meanwhile sleep in the poll (at a
                # 2 ms tick a held replay took a sixth of a core from the chain it waits for)
                self.reschedule(self._tick_timer, HELD_SNOOZE_S)
                break
            elif not self.clock.is_due(stamp, now):  # sleep in the poll until it is due
                due = self.clock.due_s(stamp, now) - now
                self.reschedule(self._tick_timer, min(max(due, p.tick_s), HELD_SNOOZE_S))
                break
            self._publish_next()
            if time.monotonic() > budget_end:
                break
        if self._done_at is not None and p.exit_when_done and now - self._done_at >= p.linger_s:
            self.request_stop()
        self._progress(now)

    def _progress(self, now: float, force: bool = False) -> None:
        period = self.params.progress_period_s
        if not force and (period <= 0 or now - self._last_progress < period):
            return
        self._last_progress = now
        self.log.info(
            "%s",
            format_progress(
                self.frames_published,
                self.total_frames,
                self.meter.rate_hz(now),
                imu=self.imu_published,
                state=self.state,
            ),
        )

    def _wait_for_nodes(self, names: tuple[str, ...], timeout_s: float) -> None:
        """Block until every named node has sent a heartbeat on /diagnostics.

        A node sends its first heartbeat after ``setup()``, so its subscriptions exist: messages
        published from then on reach it. Without this a slow-starting consumer (e.g. the mapper,
        which loads torch) misses the first keyframes, before its first sequence number.
        """
        from mogs_node.bus import Subscriber

        waiting = set(names)
        sub = Subscriber(self.bus, context=self.context)
        sub.subscribe("/diagnostics")
        deadline = time.monotonic() + timeout_s
        beat = time.monotonic()
        try:
            while waiting and time.monotonic() < deadline and not self.stopping:
                if self.diagnostics_period_s > 0 and time.monotonic() - beat >= 1.0:
                    # our own heartbeat meanwhile: the launcher must not think us hung
                    beat = time.monotonic()
                    self.publish_diagnostics()
                env = sub.receive(timeout_ms=200)
                if env is not None and isinstance(env.msg, msgs.Diagnostics):
                    waiting.discard(env.msg.node)
        finally:
            sub.close()
        if waiting and not self.stopping:
            self.log.warning(
                "no heartbeat from %s after %.0f s: playing anyway", sorted(waiting), timeout_s
            )
        else:
            self.log.info("all %d pipeline nodes are up", len(names))

    def teardown(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        self.log.info(
            "played %d/%d frames (%d unreadable, skipped), %d IMU samples, %d messages",
            self.frames_published,
            self.total_frames,
            self.counters["frames_unreadable"],
            self.imu_published,
            self.messages_published,
        )
