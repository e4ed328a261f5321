"""The device node's watchdog and its own starvation
(zplatform.node.device.StarvedWait): a wait that overslept (this process was
not scheduled, a trigger may still be unread in zenoh's socket) earns one more
idle period before the watchdog blames the control node, once per silence."""

from __future__ import annotations

from zplatform.node.device import StarvedWait

MS = 1_000_000


def test_a_silence_on_time_goes_to_the_watchdog_at_once() -> None:
    s = StarvedWait(20 * MS, 0)
    assert [s.idle(t * 10 * MS) for t in range(1, 12)] == [False] * 11


def test_an_overslept_wait_is_graced_once_per_silence() -> None:
    s = StarvedWait(20 * MS, 0)
    assert not s.idle(10 * MS)
    assert s.idle(160 * MS)  # 150 ms unscheduled: look once more
    assert not s.idle(170 * MS)  # on time: the watchdog judges
    assert not s.idle(400 * MS)  # overslept again, same silence: no second grace
    s.triggered(405 * MS)  # a trigger: the next silence starts afresh
    assert s.idle(600 * MS)
