"""zplatform.runtime.process.split_thread_priorities: what bench/sync_trace.py's
ZP_TRACE_ZENOH_PRIORITY sets (it used to patch the runtime's private
_promote_threads): when a node promotes its threads, the calling (loop) thread
gets the loop's priority, every other thread the split one; by default all
get the loop's."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator

import pytest

from zplatform.runtime import process as runtime


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[int, int]]:
    got: dict[int, int] = {}

    def fake(tid: int, policy: int, param: os.sched_param) -> None:
        assert policy == os.SCHED_FIFO
        got[tid] = param.sched_priority

    monkeypatch.setattr(os, "sched_setscheduler", fake)
    # A second thread, alive while the threads are promoted.
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        yield got
    finally:
        stop.set()
        t.join()
        runtime.split_thread_priorities(None)


def test_every_thread_gets_the_loops_priority_by_default(calls: dict[int, int]) -> None:
    n = runtime._promote_threads(20)
    assert n == len(calls) >= 2
    assert set(calls.values()) == {20}


def test_split_gives_the_other_threads_their_own(calls: dict[int, int]) -> None:
    runtime.split_thread_priorities(10)
    runtime._promote_threads(20)
    me = threading.get_native_id()
    assert calls.pop(me) == 20
    assert calls and set(calls.values()) == {10}
