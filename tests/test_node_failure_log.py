"""A failure repeating on every call is logged in full once, then as counts on the 2nd, 4th, 8th, ...
occurrence (issue 18: one unreadable image once wrote the same traceback 56,179 times)."""

from __future__ import annotations

import logging
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mogs_node.errors import DatasetError
from mogs_node.failure_log import MAX_KINDS, FailureLog, failure_kind
from mogs_node.node import Node, parse_params


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def _logger(name: str) -> tuple[logging.Logger, _Records]:
    log = logging.getLogger(f"test.failure_log.{name}")
    log.propagate = False
    for h in list(log.handlers):
        log.removeHandler(h)
    rec = _Records()
    log.addHandler(rec)
    log.setLevel(logging.DEBUG)
    return log, rec


def _raise_at_a(msg: str) -> None:
    raise DatasetError(msg)


def _raise_at_b(msg: str) -> None:
    raise DatasetError(msg)


def _caught(fn, msg: str) -> BaseException:
    try:
        fn(msg)
    except DatasetError as err:
        return err
    raise AssertionError("did not raise")


def test_the_same_failure_logs_one_traceback_then_counts() -> None:
    log, rec = _logger("same")
    fl = FailureLog(log)
    for i in range(1, 21):  # messages differ (e.g. file names): still the same kind
        assert fl.failed("timer tick", _caught(_raise_at_a, f"f{i}.png: unreadable"), "failed") == i
    assert [r.exc_info is not None for r in rec.records] == [True, False, False, False, False]
    counts = [r.getMessage() for r in rec.records[1:]]
    assert [c.split("again (")[1].split(" ")[0] for c in counts] == ["2", "4", "8", "16"]
    assert counts[-1].endswith("DatasetError: f16.png: unreadable")
    assert rec.records[0].getMessage() == "timer tick: failed"


def test_kinds_and_sources_are_counted_apart() -> None:
    log, rec = _logger("kinds")
    fl = FailureLog(log)
    a, b = _caught(_raise_at_a, "x"), _caught(_raise_at_b, "x")
    assert failure_kind(a) != failure_kind(b)  # same type and message, other lines
    assert fl.failed("s", a, "w") == 1
    assert fl.failed("s", b, "w") == 1
    assert fl.failed("t", a, "w") == 1
    assert fl.failed("s", a, "w") == 2
    assert len([r for r in rec.records if r.exc_info]) == 3


def test_without_traceback_the_first_is_one_warning_line() -> None:
    log, rec = _logger("warn")
    fl = FailureLog(log)
    fl.failed(
        "/imu", _caught(_raise_at_a, "bad field"), "rejected message seq 3", with_traceback=False
    )
    (r,) = rec.records
    assert r.levelno == logging.WARNING and r.exc_info is None
    assert r.getMessage() == "/imu: rejected message seq 3: bad field"


@settings(max_examples=30, deadline=None)
@given(n=st.integers(min_value=1, max_value=5000))
def test_n_repeats_cost_one_plus_log2_n_lines(n: int) -> None:
    log, rec = _logger("prop")
    fl = FailureLog(log)
    err = _caught(_raise_at_a, "same")
    for _ in range(n):
        fl.failed("src", err, "failed")
    assert len(rec.records) == 1 + (n.bit_length() - 1)


def test_the_kinds_remembered_per_source_are_bounded() -> None:
    log, _ = _logger("bound")
    fl = FailureLog(log)
    for i in range(3 * MAX_KINDS):  # each from another line: compile distinct raisers
        code = compile("\n" * i + "raise DatasetError('x')", f"<gen{i}>", "exec")
        try:
            exec(code, {"DatasetError": DatasetError})
        except DatasetError as err:
            fl.failed("src", err, "w")
    assert len(fl._counts["src"]) == MAX_KINDS


class _Failing(Node):
    """A node whose timer fails the same way on every tick (as the player on a bad frame did)."""

    def setup(self) -> None:
        self.every(0.001, self.tick)

    def tick(self) -> None:
        raise DatasetError("frame.png: missing or not a readable image")


def test_a_timer_failing_every_tick_does_not_flood_the_log(inproc_bus) -> None:
    bus, ctx = inproc_bus
    node = _Failing("failing", parse_params(_Failing.Params, {}), bus, context=ctx)
    log, rec = _logger("node")
    node.failures = FailureLog(log)
    deadline = time.monotonic() + 60  # a bound, not a timing: 200 ticks take ~0.2 s
    while node.counters["handler_errors"] < 200 and time.monotonic() < deadline:
        node.spin_once(2)
    n = int(node.counters["handler_errors"])
    node.close()
    assert n >= 200
    assert len([r for r in rec.records if r.exc_info]) == 1
    assert len(rec.records) == 1 + (n.bit_length() - 1)


@pytest.mark.parametrize("n", [1, 2, 3, 1024, 1025])
def test_count_lines_are_at_powers_of_two(n: int) -> None:
    log, rec = _logger(f"p{n}")
    fl = FailureLog(log)
    err = _caught(_raise_at_b, "z")
    for _ in range(n):
        fl.failed("s", err, "w")
    expected = [1] + [2**k for k in range(1, n.bit_length()) if 2**k <= n]
    got = [1] + [int(r.getMessage().split("again (")[1].split(" ")[0]) for r in rec.records[1:]]
    assert got == expected
