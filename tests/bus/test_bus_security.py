"""CURVE on tcp: authorised peers talk; an unauthenticated publisher or subscriber gets nothing."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
import zmq
from _reliability_harness import broker_thread, free_tcp_port, receive_for

from mogs_node import msgs
from mogs_node.bus import BusConfig, CurveConfig, Publisher, Subscriber, generate_keys, run_broker
from mogs_node.errors import BusError


def _imu(k: int) -> msgs.Imu:
    return msgs.Imu(
        stamp_ns=k, frame_id="i", gyro_rad_s=(0.0, 0.0, 0.0), accel_m_s2=(0.0, 0.0, 9.8)
    )


@pytest.fixture
def curve_bus(tmp_path: Path):
    keys = tmp_path / "keys"
    generate_keys(keys, ["broker", "good"])
    generate_keys(tmp_path / "rogue", ["rogue"])  # a valid key pair that the broker does not know
    base = dict(
        pub_endpoint=f"tcp://127.0.0.1:{free_tcp_port()}",
        sub_endpoint=f"tcp://127.0.0.1:{free_tcp_port()}",
    )
    broker_cfg = BusConfig(
        **base,
        curve=CurveConfig(
            server_public_key=str(keys / "broker.key"),
            server_secret_key=str(keys / "broker.key_secret"),
            authorized_keys_dir=str(keys / "authorized"),
        ),
    )
    good = BusConfig(
        **base,
        curve=CurveConfig(
            server_public_key=str(keys / "broker.key"),
            client_secret_key=str(keys / "good.key_secret"),
        ),
    )
    rogue = BusConfig(
        **base,
        curve=CurveConfig(
            server_public_key=str(keys / "broker.key"),
            client_secret_key=str(tmp_path / "rogue" / "rogue.key_secret"),
        ),
    )
    plain = BusConfig(**base)
    with broker_thread(broker_cfg):
        yield {"good": good, "rogue": rogue, "plain": plain}


@pytest.fixture
def imu_peer(curve_bus):
    """``imu_peer(who)``: a subscriber to /imu and a publisher with ``who``'s keys (``good``,
    ``rogue`` or ``plain``); every peer is closed after the test."""
    ctx = zmq.Context()
    pubs: list[Publisher] = []
    subs: list[Subscriber] = []

    def connect(who: str) -> tuple[Publisher, Subscriber]:
        subs.append(Subscriber(curve_bus[who], context=ctx))
        subs[-1].subscribe("/imu")
        pubs.append(Publisher(curve_bus[who], context=ctx))
        return pubs[-1], subs[-1]

    yield connect
    for pub in pubs:
        pub.close(0)
    for sub in subs:
        sub.close()
    ctx.term()


def test_authorised_peers_communicate(imu_peer) -> None:
    pub, sub = imu_peer("good")
    assert pub.wait_for_subscriber("/imu", 5)
    for k in range(10):
        pub.publish("/imu", _imu(k))
    got = receive_for(sub, 1.0)
    assert [e.msg.stamp_ns for e in got] == list(range(10))


@pytest.mark.parametrize("intruder", ["rogue", "plain"])
def test_unauthenticated_peers_get_nothing_in_or_out(imu_peer, intruder: str) -> None:
    good_pub, good_sub = imu_peer("good")
    assert good_pub.wait_for_subscriber("/imu", 5)
    bad_pub, bad_sub = imu_peer(intruder)
    # the intruder's subscription never reaches a publisher...
    assert not bad_pub.wait_for_subscriber("/imu", 1.0)
    time.sleep(0.5)
    for k in range(5):
        good_pub.publish("/imu", _imu(k))  # ...so it must not read this
        bad_pub.publish("/imu", _imu(1000 + k))  # and this must not reach the good subscriber
    got_good = receive_for(good_sub, 1.0)
    got_bad = receive_for(bad_sub, 0.5)
    assert [e.msg.stamp_ns for e in got_good] == list(range(5))
    assert got_bad == []


def test_broker_refuses_public_addresses_unless_allowed() -> None:
    cfg = BusConfig(f"tcp://0.0.0.0:{free_tcp_port()}", f"tcp://127.0.0.1:{free_tcp_port()}")
    with pytest.raises(BusError, match="non-loopback"):
        run_broker(cfg, threading.Event())


def test_missing_key_file_is_a_clear_error(tmp_path: Path) -> None:
    cfg = BusConfig(
        "tcp://127.0.0.1:1",
        "tcp://127.0.0.1:2",
        curve=CurveConfig(
            server_public_key=str(tmp_path / "nope.key"),
            client_secret_key=str(tmp_path / "nope.key_secret"),
        ),
    )
    with pytest.raises(BusError, match="nope.key_secret"):
        Publisher(cfg)


@pytest.mark.parametrize("intruder", ["rogue", "plain"])
def test_unauthenticated_traffic_count_is_zero_both_ways(imu_peer, intruder: str) -> None:
    """The figure in docs/reliability.md ("CURVE"): 1,000 messages each way, none gets through.

    The intruder publishes 1,000 IMU samples on /imu while an authorised publisher sends 1,000
    too: the authorised subscriber receives exactly the authorised 1,000 (none of the intruder's),
    the intruder's subscriber receives 0 of them and its publisher never sees a subscription.
    """
    n = 1000
    good_pub, good_sub = imu_peer("good")
    assert good_pub.wait_for_subscriber("/imu", 5)
    bad_pub, bad_sub = imu_peer(intruder)
    assert not bad_pub.wait_for_subscriber("/imu", 1.0)
    for k in range(n):
        bad_pub.publish("/imu", _imu(10_000 + k))
        good_pub.publish("/imu", _imu(k))
    got_good = receive_for(good_sub, 2.0)
    got_bad = receive_for(bad_sub, 0.5)
    stamps = [e.msg.stamp_ns for e in got_good]
    assert stamps == list(range(n))  # all authorised traffic, in order, and nothing else
    assert sum(s >= 10_000 for s in stamps) == 0
    assert len(got_bad) == 0
    assert good_sub.stats["/imu"].malformed == 0 and good_sub.malformed == 0
