"""Logging a failure that repeats without flooding the log (issue 18).

A handler or timer that fails the same way on every call (a file that cannot be read, a bad
message re-sent in a loop) must not write the same traceback thousands of times: one truncated
image once produced a 126 MB log in two minutes. :class:`FailureLog` keeps, per source (a topic,
a timer), a count per kind of failure: the same exception type raised from the same lines. A kind
is logged in full (with its traceback) the first time only; later occurrences as one line with
the count and the latest message, on the 2nd, 4th, 8th, ... occurrence. n failures of one kind
cost about ``log2(n)`` lines, whatever their messages.
"""

from __future__ import annotations

import logging
import traceback
from collections import OrderedDict

__all__ = ["FailureLog", "failure_kind"]

Kind = tuple[str, tuple[tuple[str, int], ...]]

#: kinds remembered per source (least recently seen forgotten first)
MAX_KINDS = 64


def failure_kind(err: BaseException) -> Kind:
    """What makes two failures the same: exception type and the lines it was raised through."""
    frames = tuple(
        (frame.f_code.co_filename, lineno) for frame, lineno in traceback.walk_tb(err.__traceback__)
    )
    return type(err).__name__, frames


class FailureLog:
    """Rate-limited logging of failures, per source; see the module docstring."""

    def __init__(self, log: logging.Logger) -> None:
        self.log = log
        self._counts: dict[str, OrderedDict[Kind, int]] = {}

    def failed(
        self, source: str, err: BaseException, what: str, *, with_traceback: bool = True
    ) -> int:
        """Log ``err`` raised in ``source`` (``what`` says what failed, e.g. "handler failed on
        seq 12") unless rate-limited; returns how often this kind of failure has occurred."""
        kinds = self._counts.setdefault(source, OrderedDict())
        kind = failure_kind(err)
        n = kinds.pop(kind, 0) + 1
        kinds[kind] = n  # most recent last
        if len(kinds) > MAX_KINDS:
            kinds.popitem(last=False)
        if n == 1:
            if with_traceback:
                self.log.error("%s: %s", source, what, exc_info=err)
            else:
                self.log.warning("%s: %s: %s", source, what, err)
        elif n & (n - 1) == 0:  # 2nd, 4th, 8th, ...
            self.log.warning(
                "%s: %s again (%d times so far; logged on the 2nd, 4th, 8th, ...): %s: %s",
                source,
                what,
                n,
                kind[0],
                err,
            )
        return n
