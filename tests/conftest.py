"""Shared test fixtures: paths to the real data excerpts, private bus endpoints, a broker process,
an in-process broker and worker nodes wired to it."""

from __future__ import annotations

import contextlib
import uuid
from pathlib import Path

import pytest

from mogs_node.shared_data import shared_data_dir

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = shared_data_dir()


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


@pytest.fixture
def broker_bus(ipc_endpoints: tuple[str, str]):
    """A broker process on the private ipc endpoints; yields its ``BusConfig``, stops it after."""
    from _reliability_harness import start_broker, stop_process

    from mogs_node.bus import BusConfig

    bus = BusConfig(*ipc_endpoints)
    broker = start_broker(bus)
    yield bus
    stop_process(broker)


@pytest.fixture
def bus_subscriber(broker_bus):
    """A subscriber (no topics yet) on ``broker_bus``, closed after the test."""
    from mogs_node.bus import Subscriber

    sub = Subscriber(broker_bus)
    yield sub
    sub.close()


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
    from _reliability_harness import broker_thread

    from mogs_node.bus import BusConfig

    name = uuid.uuid4().hex[:8]
    bus = BusConfig(f"inproc://{name}-pub", f"inproc://{name}-sub", reliable_hwm=10_000)
    with broker_thread(bus) as ctx:
        yield bus, ctx


@pytest.fixture
def wired_node(inproc_bus):
    """Wires in-process worker nodes on ``inproc_bus``: ``wired_node(node, inputs, output)`` returns
    a ``WiredNode`` once the node has subscribed to every input topic and the watcher to
    ``output``; every wired node, its publisher and watcher are closed after the test."""
    from _reliability_harness import WiredNode

    from mogs_node.bus import Publisher, Subscriber

    bus, ctx = inproc_bus
    wired: list[WiredNode] = []

    def wire(node, inputs: tuple[str, ...], output: str) -> WiredNode:
        watcher = Subscriber(bus, context=ctx)
        watcher.subscribe(output)
        w = WiredNode(node, Publisher(bus, context=ctx), watcher)
        wired.append(w)
        for topic in inputs:
            assert w.pub.wait_for_subscriber(topic, 5)
        assert node._pub.wait_for_subscriber(output, 5)
        return w

    yield wire
    for w in wired:
        w.close()
