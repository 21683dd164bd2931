"""Multi-process transport: broker + publisher + subscriber as separate OS processes."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mogs_node.bus import BusConfig

PY = [sys.executable, "-m", "mogs_node.cli"]


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_broker(bus: BusConfig) -> subprocess.Popen:
    proc = subprocess.Popen([*PY, "broker", "--bus-json", json.dumps(bus.to_dict())])
    deadline = time.monotonic() + 10
    ep = bus.sub_endpoint
    while time.monotonic() < deadline:
        if ep.startswith("ipc://") and Path(ep[6:]).exists():
            return proc
        if ep.startswith("tcp://"):
            host, port = ep[6:].rsplit(":", 1)
            with socket.socket() as s:
                if s.connect_ex((host, int(port))) == 0:
                    return proc
        time.sleep(0.05)
    proc.kill()
    raise RuntimeError("broker did not come up")


def run_node(cls: str, name: str, params: dict, bus: BusConfig) -> subprocess.Popen:
    return subprocess.Popen(
        [
            *PY,
            "node",
            cls,
            "--name",
            name,
            "--params-json",
            json.dumps(params),
            "--bus-json",
            json.dumps(bus.to_dict()),
        ]
    )


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(2)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("transport", ["tcp", "ipc"])
def test_500_large_keyframes_arrive_complete_and_in_order(
    transport: str, tmp_path: Path, ipc_endpoints
) -> None:
    if transport == "tcp":
        bus = BusConfig(f"tcp://127.0.0.1:{free_tcp_port()}", f"tcp://127.0.0.1:{free_tcp_port()}")
    else:
        bus = BusConfig(*ipc_endpoints)
    broker = start_broker(bus)
    summary = tmp_path / "sub.json"
    n = 500
    try:
        sub = run_node(
            "mogs_node.demo_nodes:Recorder",
            "sub",
            {"topics": ["/frontend/keyframe"], "expect": n, "summary_path": str(summary)},
            bus,
        )
        # 800x640 RGB + 500 features = 1.55 MB per keyframe
        pub = run_node(
            "mogs_node.demo_nodes:SyntheticSource",
            "pub",
            {"n_frames": n, "rate_hz": 1000.0, "keyframes": True, "width": 800, "height": 640},
            bus,
        )
        assert pub.wait(120) == 0
        assert sub.wait(120) == 0
    finally:
        for p in (locals().get("pub"), locals().get("sub"), broker):
            if p is not None:
                stop(p)
    data = json.loads(summary.read_text())
    assert data["ids"] == list(range(n))
    st = data["topics"]["/frontend/keyframe"]
    assert st["received"] == n and st["lost"] == 0 and st["malformed"] == 0
    assert st["received_bytes"] > n * 1_500_000


def test_overwhelmed_reliable_subscriber_reports_exact_gap_count(
    tmp_path: Path, ipc_endpoints
) -> None:
    # tiny high-water marks everywhere so that a slow subscriber must lose messages
    bus = BusConfig(*ipc_endpoints, reliable_hwm=4)
    broker = start_broker(bus)
    summary = tmp_path / "slow.json"
    n = 300
    try:
        sub = run_node(
            "mogs_node.demo_nodes:Recorder",
            "slow",
            {"topics": ["/frontend/keyframe"], "summary_path": str(summary), "delay_ms": 20.0},
            bus,
        )
        pub = run_node(
            "mogs_node.demo_nodes:SyntheticSource",
            "fast",
            {
                "n_frames": n,
                "rate_hz": 2000.0,
                "keyframes": True,
                "width": 320,
                "height": 240,
                "final_after_s": 3.0,
            },
            bus,
        )
        assert pub.wait(60) == 0
        time.sleep(1.0)  # the final frame reaches the idle subscriber
        stop(sub)
        assert sub.returncode == 0
    finally:
        for p in (locals().get("pub"), locals().get("sub"), broker):
            if p is not None:
                stop(p)
    data = json.loads(summary.read_text())
    ids = data["ids"]
    st = data["topics"]["/frontend/keyframe"]
    published = n + 1  # n frames and the final one
    assert ids[-1] == n, "the final frame must arrive so that trailing loss is visible"
    assert ids == sorted(ids)
    missing = published - len(ids)
    assert missing > 0, "the subscriber was meant to be overwhelmed"
    # the reported count equals exactly what is missing, and gap events match holes in the ids
    assert st["lost"] == missing
    holes = sum(1 for a, b in zip(ids, ids[1:]) if b != a + 1) + (ids[0] != 0)
    assert st["gaps"] == holes
