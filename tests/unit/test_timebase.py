"""Tests of zplatform.runtime.timebase: the node clock on injected fake clocks, and the virtual
clock."""

from __future__ import annotations

import pytest

from zplatform import NodeClock, TimebaseError, VirtualClock
from zplatform.runtime.timebase import I64_MAX, SKEW_ENV, YEAR_NS, check_overflow

T0 = 1_700_000_000_000_000_000  # 2023-11-14, in ns since the epoch


class FakeClocks:
    """A realtime and a monotonic clock the test moves by hand."""

    def __init__(self, realtime: int = T0, monotonic: int = 5_000) -> None:
        self.real = realtime
        self.mono = monotonic

    def realtime(self) -> int:
        return self.real

    def monotonic(self) -> int:
        return self.mono

    def advance(self, ns: int) -> None:
        self.real += ns
        self.mono += ns

    def clock(self, **kw: int | None) -> NodeClock:
        return NodeClock(realtime=self.realtime, monotonic=self.monotonic, **kw)


@pytest.fixture(autouse=True)
def _no_skew_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(SKEW_ENV, raising=False)


def test_starts_at_realtime() -> None:
    fc = FakeClocks()
    c = fc.clock()
    assert c.now_ns() == T0
    assert (c.skew_ns, c.offset_ns, c.locked) == (0, 0, False)


def test_advances_with_monotonic_linearly() -> None:
    fc = FakeClocks()
    c = fc.clock()
    readings = []
    for step in (1, 10, 1_000_000, 7):
        fc.advance(step)
        readings.append(c.now_ns())
    assert readings == [T0 + 1, T0 + 11, T0 + 1_000_011, T0 + 1_000_018]


def test_realtime_step_after_start_does_not_move_it() -> None:
    fc = FakeClocks()
    c = fc.clock()
    fc.real -= 3_600 * 10**9  # an NTP step / `date -s` an hour back
    assert c.now_ns() == T0
    fc.real += 7_200 * 10**9  # and two hours forward
    fc.mono += 5
    assert c.now_ns() == T0 + 5


def test_monotonic_never_goes_back() -> None:
    fc = FakeClocks()
    c = fc.clock()
    last = c.now_ns()
    for i in range(100):
        fc.mono += i % 3  # sometimes no progress at all
        fc.real -= 1_000_000  # realtime drifting backwards
        now = c.now_ns()
        assert now >= last
        last = now


def test_real_clocks_monotonic() -> None:
    c = NodeClock()
    readings = [c.now_ns() for _ in range(1000)]
    assert readings == sorted(readings)
    assert readings[0] > T0


def test_skew_from_constructor() -> None:
    fc = FakeClocks()
    c = fc.clock(skew_ns=50_000_000)
    assert c.skew_ns == 50_000_000
    assert c.now_ns() == T0 + 50_000_000
    assert fc.clock(skew_ns=-7).now_ns() == T0 - 7


def test_skew_from_env(monkeypatch: pytest.MonkeyPatch) -> None:
    fc = FakeClocks()
    monkeypatch.setenv(SKEW_ENV, "-2500")
    assert SKEW_ENV == "ZPLATFORM_CLOCK_SKEW_NS"
    c = fc.clock()
    assert (c.skew_ns, c.now_ns()) == (-2500, T0 - 2500)
    # An explicit skew wins over the environment.
    assert fc.clock(skew_ns=0).now_ns() == T0


def test_skew_env_empty_means_zero(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(SKEW_ENV, "")
    assert FakeClocks().clock().skew_ns == 0


@pytest.mark.parametrize("text", ["abc", "1.5", "1e6"])
def test_skew_env_not_an_integer(monkeypatch: pytest.MonkeyPatch, text: str) -> None:
    monkeypatch.setenv(SKEW_ENV, text)
    with pytest.raises(TimebaseError, match=f"{SKEW_ENV}={text!r} is not an integer"):
        FakeClocks().clock()


def test_apply_offset_before_lock() -> None:
    fc = FakeClocks()
    c = fc.clock()
    c.apply_offset(1_000)
    c.apply_offset(-250)
    assert c.offset_ns == 750
    assert c.now_ns() == T0 + 750
    fc.advance(10)
    assert c.now_ns() == T0 + 760


def test_apply_offset_after_lock_raises() -> None:
    fc = FakeClocks()
    c = fc.clock()
    c.apply_offset(100)
    c.lock()
    assert c.locked
    with pytest.raises(TimebaseError, match="locked"):
        c.apply_offset(1)
    assert (c.offset_ns, c.now_ns()) == (100, T0 + 100)  # unchanged


def test_apply_offset_that_would_overflow_raises() -> None:
    fc = FakeClocks()
    c = fc.clock()
    with pytest.raises(TimebaseError, match="overflow"):
        c.apply_offset(I64_MAX - YEAR_NS - T0 + 1)
    with pytest.raises(TimebaseError, match="before the epoch"):
        c.apply_offset(-T0 - 1)
    assert (c.offset_ns, c.now_ns()) == (0, T0)  # unchanged


def test_overflow_guard_at_start() -> None:
    limit = I64_MAX - YEAR_NS
    assert YEAR_NS >= 365 * 24 * 3600 * 10**9
    FakeClocks(realtime=limit).clock()  # exactly a year of headroom: fine
    half_year_left = I64_MAX - YEAR_NS // 2
    with pytest.raises(TimebaseError, match="overflow within a year"):
        FakeClocks(realtime=half_year_left).clock()
    with pytest.raises(TimebaseError, match="overflow within a year"):
        FakeClocks(realtime=limit + 1).clock()
    with pytest.raises(TimebaseError, match="overflow"):
        FakeClocks(realtime=limit).clock(skew_ns=1)  # the skewed anchor counts


def test_negative_time_refused() -> None:
    with pytest.raises(TimebaseError, match="before the epoch"):
        FakeClocks(realtime=-1).clock()
    with pytest.raises(TimebaseError, match="before the epoch"):
        FakeClocks(realtime=10).clock(skew_ns=-11)


def test_check_overflow() -> None:
    check_overflow(0)
    check_overflow(I64_MAX - YEAR_NS)
    for bad in (-1, I64_MAX - YEAR_NS + 1, I64_MAX, I64_MAX + 1):
        with pytest.raises(TimebaseError):
            check_overflow(bad)


# -- virtual clock ---------------------------------------------------------------


def test_virtual_clock_moves_only_when_told() -> None:
    vc = VirtualClock(T0)
    assert vc.now_ns() == vc.now_ns() == T0
    assert vc.advance(10) == T0 + 10
    assert vc.advance(0) == T0 + 10
    vc.set(T0 + 100)
    assert vc.now_ns() == T0 + 100
    vc.set(T0 + 100)  # setting the same time is fine
    assert VirtualClock().now_ns() == T0  # the default start


def test_virtual_clock_never_goes_back() -> None:
    vc = VirtualClock(T0)
    with pytest.raises(TimebaseError, match="backwards"):
        vc.advance(-1)
    with pytest.raises(TimebaseError, match="backwards"):
        vc.set(T0 - 1)
    assert vc.now_ns() == T0


def test_virtual_clock_overflow_guard() -> None:
    with pytest.raises(TimebaseError):
        VirtualClock(-1)
    with pytest.raises(TimebaseError):
        VirtualClock(I64_MAX)
    vc = VirtualClock(I64_MAX - YEAR_NS - 5)
    vc.advance(5)
    with pytest.raises(TimebaseError, match="overflow"):
        vc.advance(1)
    assert vc.now_ns() == I64_MAX - YEAR_NS  # a refused advance does not move it
    with pytest.raises(TimebaseError, match="overflow"):
        VirtualClock(T0).set(I64_MAX)


def test_the_anchor_is_read_between_two_monotonic_reads_close_together() -> None:
    """A process preempted between reading its two clocks (a loaded host) does
    not anchor its clock that far off: the realtime reading is bracketed by
    monotonic ones and the tightest bracket of a few tries is kept."""
    fc = FakeClocks()
    stolen = [100_000_000, 100_000_000]  # 100 ms, after each of the first two realtime reads
    after_realtime = False

    def realtime() -> int:
        nonlocal after_realtime
        after_realtime = True
        fc.advance(1_000)
        return fc.real

    def monotonic() -> int:
        nonlocal after_realtime
        if after_realtime and stolen:
            fc.advance(stolen.pop())  # the scheduler ran something else here
        after_realtime = False
        fc.advance(1_000)
        return fc.mono

    c = NodeClock(realtime=realtime, monotonic=monotonic)
    # Both fake clocks advance together: the node clock must read the
    # realtime clock, to a microsecond (the tight bracket's half-width).
    assert abs(c.now_ns() - fc.real) <= 1_000, c.now_ns() - fc.real
