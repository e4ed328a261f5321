"""Waiting in tests, never sleeping on a guess.

A test waits for a *condition* (a peer's declaration, a file a child
writes, a thread's state), never for a time it hopes is long enough:

* :func:`wait_matching`: a zenoh publisher or querier has a match, told by
  zenoh's matching listener (no polling);
* :func:`wait_until`: a condition holds, polled with a deadline (an
  AssertionError naming what was awaited when it passes); the condition
  may itself raise (a child process that exited) to fail at once;
* :func:`poll_until`: the same, saying False at the deadline.

The one ``time.sleep`` left in tests that is not a stimulus (a test's own
pacing, a hold, a slow fake) is this module's poll period. Blocks the
calling thread; never touches zenoh's threads.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

import zenoh

T = TypeVar("T")

POLL_S = 0.01
"""How often :func:`wait_until` looks at its condition (seconds)."""


def poll_until(pred: Callable[[], object], timeout_s: float, *, poll_s: float = POLL_S) -> bool:
    """Whether ``pred()`` became truthy within ``timeout_s`` (looked at every
    ``poll_s``; at least once)."""
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(poll_s)  # the poll period of the one polling helper, not a wait on a guess
    return True


def wait_until(
    pred: Callable[[], T | None], timeout_s: float, what: str, *, poll_s: float = POLL_S
) -> T:
    """Block until ``pred()`` returns a truthy value, and return it.

    Raises AssertionError ``timed out after N s waiting for {what}`` at
    ``timeout_s``; whatever ``pred`` raises passes through."""
    got: list[T] = []

    def holds() -> bool:
        v = pred()
        if v:
            got.append(v)
            return True
        return False

    if not poll_until(holds, timeout_s, poll_s=poll_s):
        raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
    return got[0]


def wait_matching(entity: zenoh.Publisher | zenoh.Querier, timeout_s: float, what: str) -> None:
    """Block until ``entity`` matches a subscriber / queryable (zenoh's
    matching listener says so; already matching returns at once).
    AssertionError naming ``what`` at ``timeout_s``."""
    matched = threading.Event()

    def on_status(status: Any) -> None:  # zenoh's thread: hand off only
        if getattr(status, "matching", status):
            matched.set()

    listener = entity.declare_matching_listener(zenoh.handlers.Callback(on_status, indirect=False))
    try:
        status: Any = entity.matching_status  # a MatchingStatus at run time (a bool in the stub)
        if not (getattr(status, "matching", status) or matched.wait(timeout_s)):
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
    finally:
        listener.undeclare()
