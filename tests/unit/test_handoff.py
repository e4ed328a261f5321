"""zplatform.control.handoff: waits that always end, hand-offs that lose nothing.

The first tests reproduce the trap the module doc names: on CPython 3.11 a
``queue.SimpleQueue.get(timeout=...)`` interrupted by a signal whose handler
outlasts the deadline never returns (a device node hung so at ``up``'s stop,
its SIGTERM handled, its loop never woken). Every wait here must return.
"""

from __future__ import annotations

import os
import queue
import signal
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from zplatform.control.handoff import Handoff, Mailbox, Waker

pytestmark = pytest.mark.timeout(30)


@pytest.fixture
def slow_signal() -> Iterator[Callable[[], None]]:
    """Arm a SIGUSR1 to this process 2 ms from now whose handler (run on
    the main thread, inside whatever wait it interrupts) takes 30 ms."""
    old = signal.signal(signal.SIGUSR1, lambda s, f: time.sleep(0.03))  # stimulus: 30 ms
    timers: list[threading.Timer] = []

    def arm() -> None:
        t = threading.Timer(0.002, os.kill, (os.getpid(), signal.SIGUSR1))
        timers.append(t)
        t.start()

    yield arm
    for t in timers:
        t.join()
    signal.signal(signal.SIGUSR1, old)


def test_a_mailbox_wait_ends_when_a_slow_signal_handler_outlasts_its_deadline(
    slow_signal: Callable[[], None],
) -> None:
    box: Mailbox[int] = Mailbox(4)
    for _ in range(5):  # a fresh wait each time: the token's every state
        slow_signal()
        assert box.get(0.01) is None


def test_a_handoff_get_ends_when_a_slow_signal_handler_outlasts_its_deadline(
    slow_signal: Callable[[], None],
) -> None:
    h: Handoff[int] = Handoff()
    for _ in range(5):
        slow_signal()
        with pytest.raises(queue.Empty):
            h.get(timeout=0.01)


def test_an_item_put_during_the_wait_wakes_the_consumer() -> None:
    box: Mailbox[str] = Mailbox(2)
    started = threading.Event()

    def produce() -> None:
        started.wait()
        box.put("x")

    t = threading.Thread(target=produce)
    t.start()
    started.set()
    assert box.get(20.0) == "x"
    t.join()


def test_many_producers_lose_nothing_and_never_release_an_unheld_token() -> None:
    """4 producers x 5000 items against a consumer that waits 0-1 ms at a
    time: every item arrives once, in each producer's order, and no
    notify ever raises (a release of an unheld lock would, in zenoh's
    thread)."""
    h: Handoff[tuple[int, int]] = Handoff()
    errors: list[BaseException] = []
    n, per = 4, 5000

    def produce(k: int) -> None:
        try:
            for i in range(per):
                h.put((k, i))
        except BaseException as e:
            errors.append(e)

    threads = [threading.Thread(target=produce, args=(k,)) for k in range(n)]
    for t in threads:
        t.start()
    seen = [0] * n
    got = 0
    while got < n * per:
        try:
            k, i = h.get(timeout=0.001 * (got % 2))
        except queue.Empty:
            continue
        assert i == seen[k], (k, i, seen[k])
        seen[k] += 1
        got += 1
    for t in threads:
        t.join()
    assert errors == []
    assert seen == [per] * n
    assert h.empty()


def test_a_shared_waker_wakes_for_either_mailbox() -> None:
    w = Waker()
    a: Mailbox[int] = Mailbox(1, w)
    b: Mailbox[int] = Mailbox(1, w)
    threading.Timer(0.001, b.put, (7,)).start()
    assert w.wait(lambda: len(a) or len(b), 20.0)
    assert a.pop() is None and b.pop() == 7


def test_a_handoff_carries_none_and_says_empty() -> None:
    h: Handoff[int | None] = Handoff()
    with pytest.raises(queue.Empty):
        h.get_nowait()
    with pytest.raises(queue.Empty):
        h.get(timeout=0)
    h.put(None)
    h.put(1)
    assert len(h) == 2
    assert h.get(timeout=1.0) is None
    threading.Timer(0.001, h.put, (2,)).start()
    assert h.get_nowait() == 1
    assert h.get() == 2  # no timeout: waits


def test_a_full_mailbox_lets_the_oldest_go_and_counts_it() -> None:
    box: Mailbox[int] = Mailbox(3)
    for i in range(10):
        box.put(i)
    assert len(box) == 3 and box.dropped == 7
    out: list[int] = []
    box.drain(out)
    assert out == [7, 8, 9] and len(box) == 0
    assert box.pop() is None and box.get(0) is None
    with pytest.raises(ValueError):
        Mailbox(0)


def test_get_waits_for_an_item_and_times_out_without_one() -> None:
    box: Mailbox[str] = Mailbox(2)
    t0 = time.monotonic()
    assert box.get(0.05) is None
    assert time.monotonic() - t0 >= 0.04  # a lower bound only: it did wait
    threading.Timer(0.05, box.put, args=("x",)).start()
    assert box.get(5.0) == "x"


def test_a_waker_never_holds_more_than_one_wake_up() -> None:
    """Producers that put while nobody waits leave no wake-up behind: the
    hand-off stays bounded however fast they are."""
    w = Waker()
    a: Mailbox[int] = Mailbox(4, w)
    b: Mailbox[int] = Mailbox(4, w)
    for i in range(10_000):
        (a if i % 2 else b).put(i)
    assert w._token.locked()  # nobody was waiting: no wake-up outstanding
    assert a.get(0.0) is not None
    threading.Timer(0.05, b.put, args=(-1,)).start()
    b.drain([])
    assert b.get(5.0) == -1
