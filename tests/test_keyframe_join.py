"""The one keyframe join (mogs_node.keyframe_join): n inputs by keyframe id, bounded in count and
time, counting what it gives up. Pure: driven with numbers, no process."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import ConfigError
from mogs_node.keyframe_join import KeyframeJoin


def test_pairs_match_by_id_in_any_order_and_bound_pending() -> None:
    """The mapper's use: keyframe + depth, no time bound, incomplete entries dropped on eviction."""
    j = KeyframeJoin(("depth",), max_pending=2, release_partial=False)
    assert j.add("depth", 3, "d3") == []
    assert j.add("keyframe", 1, "k1") == []
    [e] = j.add("keyframe", 3, "k3")
    assert (e.keyframe_id, e.keyframe, e.get("depth"), e.missing) == (3, "k3", "d3", {})
    assert j.add("keyframe", 4, "k4") == []
    assert j.add("keyframe", 5, "k5") == []  # evicts keyframe 1: given up, not released
    assert len(j) == 2
    assert j.add("depth", 1, "d1") == []  # its keyframe is gone: counted, not kept
    c = j.counters
    assert (c["complete"], c["evicted"], c["dropped"], c["partial"]) == (1, 1, 2, 0)
    assert len(j) == 2
    assert j.expire(1e9) == []  # max_wait_s = inf: no time bound


def test_three_inputs_every_arrival_order_gives_one_complete_entry() -> None:
    names = ("a", "b", "c")
    for order in itertools.permutations(("keyframe", *names)):
        j = KeyframeJoin(names, max_wait_s=1.0)
        out = []
        for t, slot in enumerate(order):
            out += j.add(slot, 7, slot.upper(), float(t))
        assert len(out) == 1 and out[0].complete_for(names), order
        assert [out[0].get(s) for s in ("keyframe", *names)] == ["KEYFRAME", "A", "B", "C"]
        assert j.counters["complete"] == 1 and len(j) == 0


def test_a_failure_notice_answers_the_input_at_once() -> None:
    j = KeyframeJoin(("masks", "prior"), max_wait_s=100.0)
    j.add("keyframe", 1, "K", 0.0)
    j.add("masks", 1, "M", 0.0)
    [e] = j.add("prior", 1, None, 0.1, failure="no model")
    assert e.get("prior") is None and e.missing == {"prior": "prior backend failed: no model"}
    c = j.counters
    assert (c["partial"], c["failed_inputs"], c["complete"]) == (1, 1, 0)


def test_time_bound_follows_the_worker_pace_and_heartbeats() -> None:
    j = KeyframeJoin(("prior",), max_wait_s=2.0, stall_factor=1.0)
    for k, t in enumerate((0.0, 1.0, 2.0)):  # the prior worker answers every 1 s
        j.add("keyframe", k, "K", t)
        j.add("prior", k, "P", t)
    assert j.pace["prior"].interval_s == pytest.approx(1.0)
    j.add("keyframe", 10, "K10", 2.5)
    # patience = 2 + 1 * 1 * (0 + 1) = 3 s after the worker's last output (t = 2)
    assert j.expire(4.9) == []
    j.worker_alive("prior", 4.9)  # a heartbeat: it computes, so wait on from now
    assert j.expire(7.8) == []
    [e] = j.expire(7.9)
    assert e.missing == {"prior": "prior worker silent for 3.0 s"}
    assert j.counters["stalled_inputs"] == 1 and j.counters["partial"] == 1


def test_inputs_without_keyframe_are_dropped_after_the_wait() -> None:
    j = KeyframeJoin(("masks",), max_wait_s=2.0, first_wait_s=1.0)
    j.add("masks", 4, "M4", 10.0)
    assert j.expire(12.9) == [] and len(j) == 1
    assert j.expire(13.0) == [] and len(j) == 0
    assert j.counters["dropped"] == 1


def test_duplicates_are_counted_and_the_last_message_kept() -> None:
    j = KeyframeJoin(("masks", "prior"))
    j.add("keyframe", 2, "K", 0.0)
    j.add("masks", 2, "M", 0.0)
    j.add("masks", 2, "M'", 0.0)
    [e] = j.add("prior", 2, "P", 0.0)
    assert e.get("masks") == "M'" and j.counters["duplicates"] == 1


@pytest.mark.parametrize(
    "kwargs",
    [
        {"inputs": ()},
        {"inputs": ("keyframe",)},
        {"inputs": ("a", "a")},
        {"inputs": ("a",), "max_pending": 0},
    ],
)
def test_bad_configuration_is_one_clear_error(kwargs) -> None:
    with pytest.raises(ConfigError, match="KeyframeJoin"):
        KeyframeJoin(**kwargs)


def test_unknown_slot_is_rejected() -> None:
    with pytest.raises(ConfigError, match="unknown slot 'depth'"):
        KeyframeJoin(("masks",)).add("depth", 1, "x")


@settings(max_examples=60, deadline=None)
@given(
    events=st.lists(
        st.tuples(st.sampled_from(("keyframe", "a", "b")), st.integers(0, 12)), max_size=60
    ),
    max_pending=st.integers(1, 5),
    release_partial=st.booleans(),
)
def test_every_keyframe_is_accounted_for(events, max_pending, release_partial) -> None:
    """Whatever the arrival order: never more than ``max_pending`` waiting, each keyframe id
    released at most once, and what came is released, waiting, or counted as given up."""
    j = KeyframeJoin(
        ("a", "b"), max_pending=max_pending, max_wait_s=math.inf, release_partial=release_partial
    )
    released: list[int] = []
    for slot, kid in events:
        released += [e.keyframe_id for e in j.add(slot, kid, f"{slot}{kid}")]
        assert len(j) <= max_pending
    assert len(released) == len(set(released))
    c = j.counters
    assert c["complete"] + c["partial"] == len(released)
    if not release_partial:
        assert c["partial"] == 0
    n_messages = len(events)
    assert n_messages >= c["complete"] * 3 + c["duplicates"]
