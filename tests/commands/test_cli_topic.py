"""``mogs topic echo`` on a misspelt topic says after 2 s that no publisher is seen and lists the
live topics (issue 18); small arrays such as a pose print in full."""

from __future__ import annotations

import subprocess

import numpy as np
from _reliability_harness import REPO, cli_argv, start_node, stop_process

from mogs_node import msgs
from mogs_node.commands.topic import format_message, silent_topic_hint


def _diag(node: str, topics: dict) -> msgs.Diagnostics:
    return msgs.Diagnostics(
        stamp_ns=1,
        frame_id="",
        node=node,
        pid=1,
        uptime_s=1.0,
        status="ok",
        counters={},
        topics=topics,
    )


def test_silent_topic_hint_names_the_publishers_or_the_live_topics() -> None:
    diags = {
        "player": _diag("player", {"/camera/image": {"published": 5}, "/imu": {"published": 0}}),
        "frontend": _diag(
            "frontend",
            {"/camera/image": {"received": 5}, "/frontend/odometry": {"published": 5}},
        ),
    }
    assert silent_topic_hint("/frontend/odometri", diags, 2.0) == (
        "no publisher of /frontend/odometri seen after 2 s; the live topics are: "
        "/camera/image (player), /frontend/odometry (frontend)"
    )
    assert silent_topic_hint("/camera/image", diags, 2.0) == (
        "nothing on /camera/image after 2 s; it is published by ['player']: "
        "waiting for the next message"
    )
    assert "no node heard on this bus" in silent_topic_hint("/x", {}, 2.0)


def test_a_pose_prints_in_full_and_a_large_array_is_summarised() -> None:
    T = np.eye(4)
    T[0, 3] = 5.357
    odo = msgs.Odometry(
        stamp_ns=1,
        frame_id="c",
        frame_index=0,
        T_world_cam=T,
        velocity_world_m_s=(0.0, 0.0, 0.0),
        status="tracking",
    )
    env = msgs.decode(msgs.encode("/frontend/odometry", odo, seq=0))
    text = format_message(env)
    assert "T_world_cam: <float64 [4, 4]>" in text and "5.357" in text
    img = msgs.Image(stamp_ns=1, frame_id="c", encoding="mono8", data=np.zeros((8, 8), np.uint8))
    env = msgs.decode(msgs.encode("/camera/image", img, seq=0))
    assert "data: <uint8 [8, 8] min 0 max 0>" in format_message(env)
    full = format_message(env, full=True)
    assert full.count("[0 0 0 0 0 0 0 0]") == 8


def test_echo_of_a_misspelt_topic_lists_the_live_topics(broker_bus) -> None:
    src = start_node(
        "mogs_node.demo_nodes:SyntheticSource",
        "source",
        {"n_frames": 0, "rate_hz": 5.0, "width": 8, "height": 8, "wait_for_subscriber_s": 0.0},
        broker_bus,
    )
    try:
        echo = subprocess.Popen(
            cli_argv(
                "topic",
                "echo",
                "/camera/imag",
                "--duration",
                "4",
                "--pub",
                broker_bus.pub_endpoint,
                "--sub",
                broker_bus.sub_endpoint,
            ),
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        out = echo.communicate(timeout=60)[0].decode()
    finally:
        stop_process(src)
    assert echo.returncode == 0, out
    assert "no publisher of /camera/imag seen after 2 s; the live topics are: " in out
    assert "/camera/image (source)" in out
    assert out.count("no publisher") == 1
