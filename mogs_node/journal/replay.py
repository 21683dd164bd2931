"""A restarted node's replay of its inputs from the journal (the client side of catch-up).

Pure of the node shell: it asks the journal which outputs already exist and hands back decoded
input envelopes batch by batch; :meth:`mogs_node.node.Node.catch_up` dispatches them.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import zmq

from mogs_node import msgs
from mogs_node.bus.config import BusConfig
from mogs_node.errors import MogsError
from mogs_node.journal.protocol import JournalClient

__all__ = ["JournalReplay"]


@dataclass
class JournalReplay:
    """Where a replay stands: the journal client, its input topics and the next record."""

    client: JournalClient
    topics: tuple[str, ...]
    published: dict[str, set[int]] = field(default_factory=dict)  # outputs the journal holds
    start: int = 0
    replayed: int = 0
    t0: float = field(default_factory=time.monotonic)

    @classmethod
    def open(
        cls,
        bus: BusConfig,
        context: zmq.Context,
        inputs: Sequence[str],
        outputs: Sequence[str],
        *,
        endpoint: str | None,
        timeout_s: float,
        settle_s: float,
    ) -> JournalReplay:
        """Connect and fetch the keys of ``outputs``; raises :class:`MogsError` (client closed)
        when no journal answers. ``settle_s`` lets the caller's subscriptions reach the broker
        first, so that nothing falls between the journal and the live stream."""
        client = JournalClient(bus, endpoint=endpoint, context=context, timeout_s=timeout_s)
        if settle_s > 0:
            time.sleep(settle_s)
        try:
            keys = client.keys(list(outputs)) if outputs else {}
        except MogsError:
            client.close()
            raise
        published = {t: set(keys.get(t, ())) for t in outputs}
        return cls(client, tuple(inputs), published)

    def next_batch(
        self, max_records: int, max_bytes: int
    ) -> tuple[list[msgs.Envelope], list[str]] | None:
        """The next stored input messages, decoded, and the reasons of records rejected; None
        (and the client closed) when the journal holds nothing newer or stopped answering."""
        try:
            records, nxt = self.client.read(self.topics, self.start, max_records=max_records)
        except MogsError:
            self.close()
            raise
        if not records:
            self.close()
            return None
        self.start = nxt
        envelopes, rejected = [], []
        for frames in records:
            try:
                envelopes.append(msgs.decode(frames, max_bytes=max_bytes))
            except MogsError as err:
                rejected.append(str(err))
        return envelopes, rejected

    def close(self) -> None:
        self.client.close()
