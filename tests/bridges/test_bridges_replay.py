"""Pure timing and flow-control helpers of the players (no bus, no sleeping)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridges.player import convert_encoding
from bridges.replay import (
    IMAGE,
    IMU,
    FlowWindow,
    RateMeter,
    ReplayClock,
    build_events,
    format_progress,
    select_window,
)
from mogs_node.errors import ConfigError

stamps = st.lists(st.integers(0, 10**12), max_size=40)


@given(stamps, stamps)
def test_build_events_is_time_ordered_complete_and_imu_first_at_ties(f: list, m: list) -> None:
    f, m = sorted(f), sorted(m)
    ev = build_events(np.array(f, np.int64), np.array(m, np.int64))
    assert len(ev) == len(f) + len(m)
    assert [e[0] for e in ev] == sorted(f + m)
    assert [e[2] for e in ev if e[1] == IMAGE] == list(range(len(f)))
    assert [e[2] for e in ev if e[1] == IMU] == list(range(len(m)))
    for a, b in zip(ev, ev[1:]):
        if a[0] == b[0]:
            assert not (a[1] == IMAGE and b[1] == IMU)


def test_build_events_rejects_float_stamps() -> None:
    with pytest.raises(ConfigError, match="frame_stamps_ns"):
        build_events(np.array([0.5, 1.0]))


def test_select_window_keeps_frames_in_range_and_imu_lead() -> None:
    frames = np.arange(10, dtype=np.int64) * 100_000_000 + 5_000_000_000
    imu = np.arange(0, 120, dtype=np.int64) * 10_000_000 + 4_900_000_000
    ev = build_events(frames, imu)
    w = select_window(ev, start_s=0.2, end_s=0.5, imu_lead_s=0.05)
    assert [e[2] for e in w if e[1] == IMAGE] == [2, 3, 4, 5]
    imu_kept = [e[0] for e in w if e[1] == IMU]
    assert imu_kept[0] == frames[2] - 50_000_000 and imu_kept[-1] == frames[5]
    assert len(imu_kept) == 36  # 0.35 s of 100 Hz samples, both ends included
    assert select_window(ev) == ev[: ev.index((int(frames[-1]), IMAGE, 9)) + 1]
    assert select_window(ev, start_s=5.0) == []
    with pytest.raises(ConfigError, match="start_s"):
        select_window(ev, start_s=0.5, end_s=0.2)


def test_replay_clock_rates_and_pause() -> None:
    c = ReplayClock(1.0)
    assert c.due_s(1_000_000_000, now_s=50.0) == 50.0  # the first event is due at once
    assert c.due_s(1_100_000_000, now_s=50.0) == pytest.approx(50.1)
    c.pause(50.05)
    assert c.due_s(1_100_000_000, now_s=60.0) == float("inf")
    c.resume(52.05)  # paused 2 s
    assert c.due_s(1_100_000_000, now_s=52.05) == pytest.approx(52.1)
    assert not c.is_due(1_100_000_000, 52.09) and c.is_due(1_100_000_000, 52.1)
    c4 = ReplayClock(4.0)
    c4.due_s(0, now_s=0.0)
    assert c4.due_s(1_000_000_000, now_s=0.0) == pytest.approx(0.25)
    c0 = ReplayClock(0.0)
    c0.due_s(0, now_s=3.0)
    assert c0.due_s(10**12, now_s=3.0) == 3.0
    with pytest.raises(ConfigError, match="rate"):
        ReplayClock(-1.0)


def test_flow_window_cumulative_acks() -> None:
    w = FlowWindow(2)
    assert w.can_send()
    w.sent(10)
    w.sent(20)
    assert not w.can_send() and w.in_flight == 2
    assert w.ack(15) == 1 and w.can_send()
    w.sent(30)
    assert w.ack(30) == 2 and w.in_flight == 0  # a later ack covers a skipped item
    w.sent(25)  # already covered by the ack at 30
    assert w.in_flight == 0 and w.acked == 3
    unbounded = FlowWindow(0)
    for t in range(100):
        unbounded.sent(t)
    assert unbounded.can_send()
    with pytest.raises(ConfigError, match="max_in_flight"):
        FlowWindow(-1)


def test_rate_meter_and_progress_line() -> None:
    m = RateMeter(window_s=5.0)
    for i in range(11):
        m.tick(100.0 + 0.1 * i)
    assert m.rate_hz(101.0) == pytest.approx(10.0)
    assert m.rate_hz(200.0) == 0.0
    assert (
        format_progress(39, 78, 10.0, imu=7, state="paused")
        == "[##########----------] 39/78 frames (50.0%) 10.0 Hz imu 7 paused"
    )
    assert format_progress(0, 0, 0.0).startswith("[--------------------] 0/0 frames (0.0%)")


def test_convert_encoding() -> None:
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = 200
    bgr, enc = convert_encoding(rgb, "rgb8", "bgr8")
    assert enc == "bgr8" and bgr[0, 0].tolist() == [0, 0, 200]
    grey, enc = convert_encoding(bgr, "bgr8", "mono8")
    assert enc == "mono8" and grey.shape == (2, 3) and int(grey[0, 0]) == 60  # 0.299 * 200
    same, enc = convert_encoding(rgb, "rgb8", "")
    assert same is rgb and enc == "rgb8"
    back, enc = convert_encoding(grey, "mono8", "rgb8")
    assert enc == "rgb8" and back[0, 0].tolist() == [60, 60, 60]
