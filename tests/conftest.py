"""Shared test fixtures: paths to the real data excerpts, private bus endpoints."""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MOGS_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


def shared_data(sub: str) -> Path:
    """Path of a real-data excerpt; skips the test with a reason when it is absent."""
    p = SHARED_DATA / sub
    if not p.exists():
        pytest.skip(f"real data excerpt {p} is absent (a user checkout has no ../shared)")
    return p


@pytest.fixture
def ipc_endpoints(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    d = Path("/tmp") / f"mogs-test-{uuid.uuid4().hex[:8]}"
    d.mkdir()
    return f"ipc://{d}/pub.ipc", f"ipc://{d}/sub.ipc"


@pytest.fixture(autouse=True)
def _no_leftover_processes():
    """Kill whatever a test left running (a failed test must not leave nodes burning CPU)."""
    import psutil

    yield
    kids = psutil.Process().children(recursive=True)
    for k in kids:
        with contextlib.suppress(psutil.NoSuchProcess):
            k.kill()
    psutil.wait_procs(kids, timeout=5)


@pytest.fixture
def inproc_bus():
    """A broker in a thread with inproc endpoints; yields ``(BusConfig, zmq.Context)``.

    For in-process node tests: nodes and publishers must use the yielded context.
    """
    import threading

    import zmq

    from mogs_node.bus import BusConfig, run_broker

    ctx = zmq.Context()
    name = uuid.uuid4().hex[:8]
    bus = BusConfig(f"inproc://{name}-pub", f"inproc://{name}-sub", reliable_hwm=10_000)
    stop, ready = threading.Event(), threading.Event()
    t = threading.Thread(
        target=run_broker, args=(bus, stop), kwargs={"ready": ready, "context": ctx}
    )
    t.start()
    assert ready.wait(5)
    yield bus, ctx
    stop.set()
    t.join(5)
    ctx.destroy(linger=0)  # a failed test may leave sockets open: term() would wait for them
