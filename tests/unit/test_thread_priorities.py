"""zplatform.runtime.process.split_thread_priorities: what bench/sync_trace.py's
ZP_TRACE_ZENOH_PRIORITY sets (it used to patch the runtime's private
_promote_threads): when a node promotes its threads, the calling (loop) thread
gets the loop's priority, every other thread the split one; by default all
get the loop's, and a node (``others``: :func:`io_priority`) puts them below
every loop."""

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


def test_a_nodes_other_threads_run_below_every_loop(
    calls: dict[int, int], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 25: a flood of a DN's trigger key kept that DN's zenoh thread
    busy (about 0.6 of a CPU) at the loops' SCHED_FIFO priority, which no
    loop thread can preempt: on a 2-core box the commander's loop waited
    and both DNs safed. Now a node's other threads get ``others``
    (io_priority: half the loop's), so none outranks or equals a loop."""
    from zplatform.runtime import scheduler

    status = scheduler.RealtimeStatus  # what setup_realtime returns, with FIFO on
    monkeypatch.setattr(
        runtime,
        "setup_realtime",
        lambda priority, cpu: status(
            fifo=True, priority=priority, cpu_affinity=None, memory_locked=False, notes=()
        ),
    )
    runtime.realtime_setup(20, None, others=runtime.io_priority(20))
    me = threading.get_native_id()
    assert calls.pop(me) == 20
    assert calls and set(calls.values()) == {10}
    assert runtime.io_priority(1) == 1 and runtime.io_priority(99) == 49
    # A benchmark's split still wins.
    calls.clear()
    runtime.split_thread_priorities(30)
    runtime.realtime_setup(20, None, others=10)
    assert calls.pop(me) == 20 and set(calls.values()) == {30}
