"""ZeroMQ transport: broker, publisher, subscriber, security.

Process graph: every publisher connects a socket to the broker's XSUB endpoint, every subscriber
connects a SUB socket to the broker's XPUB endpoint; the broker forwards with ``zmq.proxy`` (C code,
no per-message Python). Publishers use XPUB sockets so that they can see subscriptions arrive
(``Publisher.wait_for_subscriber``) and avoid the PUB/SUB slow-joiner loss at start-up.

Topic policies (DESIGN.md section 5):

- ``reliable`` (keyframes, masks, depth, IMU): large high-water marks; per-topic sequence numbers
  from every publisher session; the subscriber detects gaps and counts every lost message, so
  nothing is lost silently.
- ``best_effort`` (camera images, renders, diagnostics): small high-water marks; the node keeps the
  latest message per topic and counts what it drops.

Security: on tcp endpoints the broker can run as a CURVE server that accepts only client public keys
found in an authorised-keys folder (ZAP via ``zmq.auth``); unauthenticated peers get nothing in or
out. ``generate_keys`` writes key pairs in the ``zmq.auth`` certificate format.
"""

from mogs_node.bus.broker import run_broker
from mogs_node.bus.config import (
    BusConfig,
    CurveConfig,
    default_bus_config,
    generate_keys,
    tune_malloc_for_large_messages,
    with_endpoints,
)
from mogs_node.bus.pubsub import Publisher, Subscriber, TopicStats, queued

__all__ = [
    "BusConfig",
    "CurveConfig",
    "Publisher",
    "Subscriber",
    "TopicStats",
    "default_bus_config",
    "generate_keys",
    "queued",
    "run_broker",
    "tune_malloc_for_large_messages",
    "with_endpoints",
]
