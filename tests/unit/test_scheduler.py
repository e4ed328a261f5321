"""Tests of zplatform.runtime.scheduler: deterministic, on a fake clock (one real-clock behaviour
check)."""

from __future__ import annotations

import gc
import logging
import os
import time
from collections.abc import Callable, Iterable

import numpy as np
import pytest

from zplatform.control.rategroups import RateGroup, RateGroups, rate_due
from zplatform.errors import SchedulerError
from zplatform.runtime import scheduler
from zplatform.runtime.scheduler import (
    GcGuard,
    LoopStats,
    PeriodicLoop,
    RealtimeStatus,
    setup_realtime,
)

MS = 1_000_000


class FakeClock:
    """Integer-ns clock that moves only when slept on, advanced, or (optionally) read."""

    def __init__(self, start: int = 1_000 * MS, tick: int = 0) -> None:
        self.now = start
        self.tick = tick
        self.sleeps: list[int] = []

    def __call__(self) -> int:
        self.now += self.tick
        return self.now

    def sleep(self, seconds: float) -> None:
        ns = round(seconds * 1e9)
        assert ns >= 0
        self.sleeps.append(ns)
        self.now += ns

    def advance(self, ns: int) -> None:
        self.now += ns


def make_loop(clock: FakeClock, period: int = 10 * MS, **kw: object) -> PeriodicLoop:
    kw.setdefault("spin_ns", 0)
    return PeriodicLoop(period, clock=clock, sleep=clock.sleep, **kw)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- periodic loop


def test_absolute_deadlines_do_not_drift_with_varying_step_times() -> None:
    clock = FakeClock()
    start = clock.now
    durations = [1, 7, 3, 9, 0, 5, 2, 8, 4, 6]
    calls: list[tuple[int, int, int]] = []

    def step(k: int, deadline: int) -> None:
        calls.append((k, deadline, clock.now))
        clock.advance(durations[k % len(durations)] * MS)

    stats = make_loop(clock).run(step, max_loops=100)

    assert [c[0] for c in calls] == list(range(100))
    for k, deadline, started in calls:
        assert deadline == start + k * 10 * MS
        assert started == deadline  # fake sleep is exact: zero lateness, no drift
    assert stats.loops == 100
    assert stats.overruns == 0
    assert stats.skipped_periods == 0
    assert stats.max_lateness_ns == 0


def test_spin_phase_sleeps_until_spin_then_busy_waits() -> None:
    clock = FakeClock(tick=1_000)  # each read moves 1 us: the spin terminates
    loop = make_loop(clock, spin_ns=200_000, record=16)
    starts: list[int] = []

    def step(k: int, deadline: int) -> None:
        starts.append(clock.now - deadline)
        clock.advance(2 * MS)

    loop.run(step, max_loops=5)
    # Sleeps stop 200 us early (less the clock ticks); the rest is spun on the clock.
    for ns in clock.sleeps:
        assert 10 * MS - 2 * MS - 200_000 - 10_000 <= ns <= 10 * MS - 2 * MS - 200_000
    assert len(clock.sleeps) == 4  # step 0 runs at once
    assert all(0 <= late <= 2_000 for late in starts)
    assert np.all(loop.lateness_ns() >= 0)


def test_overrun_is_counted_reported_and_missed_periods_skipped() -> None:
    clock = FakeClock()
    start = clock.now
    overruns: list[tuple[int, int]] = []
    ks: list[int] = []
    deadlines: list[int] = []

    def step(k: int, deadline: int) -> None:
        ks.append(k)
        deadlines.append(deadline)
        if k == 2:
            clock.advance(35 * MS)  # ends at start + 55 ms: past deadlines 3, 4 and 5
        else:
            clock.advance(1 * MS)

    loop = make_loop(clock, on_overrun=lambda k, late: overruns.append((k, late)))
    stats = loop.run(step, max_loops=6)

    assert overruns == [(2, 25 * MS)]  # lateness past deadline k+1 = start + 30 ms
    assert ks == [0, 1, 2, 6, 7, 8]  # no burst: 3, 4, 5 are skipped, not run late
    assert deadlines == [start + k * 10 * MS for k in ks]
    assert stats.overruns == 1
    assert stats.skipped_periods == 3
    assert stats.max_overrun_ns == 25 * MS
    assert stats.loops == 6


def test_overrun_ending_exactly_on_a_deadline_runs_that_deadline_on_time() -> None:
    clock = FakeClock()
    ks: list[int] = []
    late: list[int] = []

    def step(k: int, deadline: int) -> None:
        ks.append(k)
        late.append(clock.now - deadline)
        clock.advance(20 * MS if k == 0 else 0)  # ends 10 ms past deadline 1, on deadline 2

    stats = make_loop(clock).run(step, max_loops=3)
    assert ks == [0, 2, 3]  # only period 1 is skipped; deadline 2 has not passed yet
    assert late == [0, 0, 0]
    assert stats.overruns == 1
    assert stats.skipped_periods == 1


def test_step_ending_exactly_on_next_deadline_is_not_an_overrun() -> None:
    clock = FakeClock()
    slack: list[int] = []

    def step(k: int, deadline: int) -> None:
        clock.advance(10 * MS)

    stats = make_loop(clock, slack_hook=slack.append).run(step, max_loops=3)
    assert stats.overruns == 0
    assert slack == [0, 0, 0]


def test_slack_hook_gets_time_left_and_is_skipped_on_overrun() -> None:
    clock = FakeClock()
    slack: list[int] = []

    def step(k: int, deadline: int) -> None:
        clock.advance((3 if k != 1 else 15) * MS)

    make_loop(clock, slack_hook=slack.append).run(step, max_loops=3)
    assert slack == [7 * MS, 7 * MS]


def test_step_returning_false_stops_and_none_or_true_continue() -> None:
    clock = FakeClock()
    results = [None, True, None, False, None]
    ks: list[int] = []

    def step(k: int, deadline: int) -> bool | None:
        ks.append(k)
        return results[k]

    stats = make_loop(clock).run(step)
    assert ks == [0, 1, 2, 3]
    assert stats.loops == 4
    assert not stats.running


def test_max_loops() -> None:
    clock = FakeClock()
    ks: list[int] = []
    loop = make_loop(clock)
    assert loop.run(lambda k, d: ks.append(k), max_loops=7).loops == 7
    assert ks == list(range(7))
    assert loop.run(lambda k, d: None, max_loops=0).loops == 0


def test_stop_from_step_ends_loop_after_current_step() -> None:
    clock = FakeClock()
    ks: list[int] = []
    loop = make_loop(clock)

    def step(k: int, deadline: int) -> None:
        ks.append(k)
        if k == 4:
            loop.stop()

    stats = loop.run(step, max_loops=100)
    assert ks == [0, 1, 2, 3, 4]
    assert stats.loops == 5


def test_stop_during_wait_prevents_next_step() -> None:
    clock = FakeClock()
    ks: list[int] = []

    def sleep_then_stop(seconds: float) -> None:
        clock.sleep(seconds)
        loop.stop()  # as a signal handler or another thread would, mid-wait

    loop = PeriodicLoop(10 * MS, clock=clock, sleep=sleep_then_stop, spin_ns=0)

    def step(k: int, deadline: int) -> None:
        ks.append(k)
        clock.advance(MS)

    loop.run(step, max_loops=10)
    assert ks == [0]


def test_stop_before_run_is_honoured_then_cleared() -> None:
    clock = FakeClock()
    loop = make_loop(clock)
    loop.stop()
    assert loop.run(lambda k, d: None, max_loops=5).loops == 0
    assert loop.run(lambda k, d: None, max_loops=5).loops == 5


def test_stop_from_another_thread() -> None:
    import threading

    clock = FakeClock()
    loop = make_loop(clock)
    started = threading.Event()
    release = threading.Event()

    def step(k: int, deadline: int) -> None:
        if k == 3:
            started.set()
            assert release.wait(5)

    thread = threading.Thread(target=loop.run, args=(step,))
    thread.start()
    assert started.wait(5)
    loop.stop()
    release.set()
    thread.join(5)
    assert not thread.is_alive()
    assert loop.stats().loops == 4


def test_start_ns_in_the_future_and_in_the_past() -> None:
    clock = FakeClock()
    deadlines: list[tuple[int, int]] = []

    loop = make_loop(clock)
    epoch = clock.now + 25 * MS
    loop.run(lambda k, d: deadlines.append((k, d)), max_loops=2, start_ns=epoch)
    assert deadlines == [(0, epoch), (1, epoch + 10 * MS)]

    deadlines.clear()
    epoch = clock.now - 25 * MS  # joins at the first deadline not yet passed: k = 3
    stats = loop.run(lambda k, d: deadlines.append((k, d)), max_loops=2, start_ns=epoch)
    assert deadlines == [(3, epoch + 30 * MS), (4, epoch + 40 * MS)]
    assert stats.skipped_periods == 0


def test_lateness_ring_records_latest_samples_in_order() -> None:
    clock = FakeClock()
    loop = make_loop(clock, record=4)
    assert loop.record_capacity == 4

    def sleep_late(seconds: float) -> None:
        clock.sleep(seconds)
        clock.advance(len(clock.sleeps) * 1_000)  # the n-th sleep wakes n us late

    loop._sleep = sleep_late  # white-box: a sleep that overshoots by a growing amount
    loop.run(lambda k, d: None, max_loops=3)
    assert loop.lateness_ns().tolist() == [0, 1_000, 2_000]
    assert loop.stats().recorded == 3

    clock.sleeps.clear()
    stats = loop.run(lambda k, d: None, max_loops=7)  # counters reset per run
    samples = loop.lateness_ns()
    assert samples.dtype == np.int64
    assert samples.tolist() == [3_000, 4_000, 5_000, 6_000]
    assert stats.recorded == 4
    assert stats.max_lateness_ns == 6_000
    samples[0] = -1  # a copy: the ring is untouched
    assert loop.lateness_ns()[0] == 3_000


def test_recording_off_by_default() -> None:
    clock = FakeClock()
    loop = make_loop(clock)
    loop.run(lambda k, d: None, max_loops=3)
    assert loop.lateness_ns().shape == (0,)
    assert loop.stats().recorded == 0


def test_stats_is_a_frozen_snapshot() -> None:
    clock = FakeClock()
    loop = make_loop(clock)
    before = loop.stats()
    loop.run(lambda k, d: None, max_loops=2)
    assert isinstance(before, LoopStats)
    assert before.loops == 0
    assert loop.stats().loops == 2
    with pytest.raises(AttributeError):
        before.loops = 5  # type: ignore[misc]


def test_exception_in_step_propagates_and_loop_is_reusable() -> None:
    clock = FakeClock()
    loop = make_loop(clock)

    def step(k: int, deadline: int) -> None:
        if k == 2:
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        loop.run(step)
    assert loop.stats().loops == 2
    assert not loop.stats().running
    assert loop.run(lambda k, d: None, max_loops=1).loops == 1


def test_run_is_not_reentrant() -> None:
    clock = FakeClock()
    loop = make_loop(clock)

    def step(k: int, deadline: int) -> None:
        loop.run(lambda k, d: None, max_loops=1)

    with pytest.raises(SchedulerError, match="already in progress"):
        loop.run(step, max_loops=1)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"period_ns": 0}, "period_ns must be >= 1"),
        ({"period_ns": -5}, "period_ns must be >= 1"),
        ({"period_ns": 1.5}, "period_ns must be an int"),
        ({"period_ns": True}, "period_ns must be an int"),
        ({"period_ns": MS, "spin_ns": -1}, "spin_ns must be >= 0"),
        ({"period_ns": MS, "record": -1}, "record must be >= 0"),
        ({"period_ns": MS, "on_overrun": 3}, "on_overrun must be callable"),
        ({"period_ns": MS, "slack_hook": "x"}, "slack_hook must be callable"),
    ],
)
def test_periodic_loop_validation(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(SchedulerError, match=match):
        PeriodicLoop(**kwargs)  # type: ignore[arg-type]


def test_run_validation() -> None:
    loop = make_loop(FakeClock())
    with pytest.raises(SchedulerError, match="max_loops must be >= 0"):
        loop.run(lambda k, d: None, max_loops=-1)
    with pytest.raises(SchedulerError, match="start_ns must be an int"):
        loop.run(lambda k, d: None, start_ns=1.0)  # type: ignore[arg-type]


def test_real_clock_behaviour_50_loops_of_1ms_take_at_least_49ms() -> None:
    # A behaviour check (deadlines are honoured), not a performance check.
    loop = PeriodicLoop(MS, record=64)
    t0 = time.monotonic_ns()
    stats = loop.run(lambda k, d: None, max_loops=50)
    elapsed = time.monotonic_ns() - t0
    assert stats.loops == 50
    assert elapsed >= 49 * MS
    assert len(loop.lateness_ns()) == 50
    assert np.all(loop.lateness_ns() >= 0)


# --------------------------------------------------------------------------- rate groups


def test_rate_due_pattern_with_phases() -> None:
    assert [rate_due(n, 1) for n in range(4)] == [True] * 4
    assert [rate_due(n, 2) for n in range(6)] == [True, False] * 3
    assert [rate_due(n, 2, 1) for n in range(6)] == [False, True] * 3
    assert [n for n in range(20) if rate_due(n, 5, 3)] == [3, 8, 13, 18]


def test_rate_groups_due_for_divisors_1_2_5_with_phases() -> None:
    groups: RateGroups[str] = RateGroups()
    groups.add("fast", 1)
    groups.add("half", 2)
    groups.add("half_odd", 2, phase=1)
    groups.add("fifth", 5)
    groups.add("fifth_p3", 5, phase=3)
    assert groups.hyperperiod == 10
    assert groups.tabled
    assert len(groups) == 5

    expected = {
        0: ("fast", "half", "fifth"),
        1: ("fast", "half_odd"),
        2: ("fast", "half"),
        3: ("fast", "half_odd", "fifth_p3"),
        4: ("fast", "half"),
        5: ("fast", "half_odd", "fifth"),
        8: ("fast", "half", "fifth_p3"),
        10: ("fast", "half", "fifth"),
        13: ("fast", "half_odd", "fifth_p3"),
    }
    for loop, members in expected.items():
        assert groups.due(loop) == members, loop
    for loop in range(100):
        assert groups.due(loop) == tuple(
            g.member for g in groups if rate_due(loop, g.divisor, g.phase)
        )
    # Precomputed: the same tuple object every hyperperiod, nothing built per call.
    assert groups.due(3) is groups.due(13)


def test_rate_groups_from_entries_and_untabled_fallback() -> None:
    entries = [RateGroup("a", 7), RateGroup("b", 11, 2), RateGroup("c", 13, 5)]
    groups = RateGroups(entries, max_table=100)
    assert groups.hyperperiod == 1001
    assert not groups.tabled
    for loop in range(2002):
        assert groups.due(loop) == tuple(e.member for e in entries if e.due(loop))
    assert RateGroups(entries).tabled  # default table limit holds 1001


def test_empty_rate_groups() -> None:
    groups: RateGroups[int] = RateGroups()
    assert groups.due(0) == ()
    assert groups.due(12345) == ()


@pytest.mark.parametrize(
    ("divisor", "phase", "match"),
    [
        (0, 0, "divisor must be >= 1"),
        (-2, 0, "divisor must be >= 1"),
        (2, 2, r"phase must be in \[0, 2\)"),
        (3, -1, "phase must be"),
    ],
)
def test_rate_group_validation(divisor: int, phase: int, match: str) -> None:
    with pytest.raises(SchedulerError, match=match):
        rate_due(0, divisor, phase)
    with pytest.raises(SchedulerError, match=match):
        RateGroups[str]().add("x", divisor, phase)
    with pytest.raises(SchedulerError, match=match):
        RateGroup("x", divisor, phase)


# --------------------------------------------------------------------------- real-time set-up


@pytest.fixture
def no_os_rt(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, object]]:
    """Refuse every real-time call (and never really change this test process)."""
    calls: list[tuple[str, object]] = []

    def setscheduler(pid: int, policy: int, param: object) -> None:
        calls.append(("sched_setscheduler", policy))
        raise PermissionError(1, "Operation not permitted")

    def setaffinity(pid: int, cpus: Iterable[int]) -> None:
        calls.append(("sched_setaffinity", tuple(cpus)))
        raise OSError(22, "Invalid argument")

    def mlockall() -> None:
        calls.append(("mlockall", None))
        raise OSError(12, "Cannot allocate memory")

    monkeypatch.setattr(os, "sched_setscheduler", setscheduler, raising=False)
    monkeypatch.setattr(os, "sched_setaffinity", setaffinity, raising=False)
    monkeypatch.setattr(scheduler, "_mlockall", mlockall)
    return calls


@pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="needs Linux scheduling constants")
def test_setup_realtime_falls_back_without_raising(
    no_os_rt: list[tuple[str, object]], caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="zplatform.scheduler"):
        status = setup_realtime(priority=10, cpu=1, lock_memory=True)
    assert isinstance(status, RealtimeStatus)
    assert [name for name, _ in no_os_rt] == ["sched_setscheduler", "sched_setaffinity", "mlockall"]
    assert no_os_rt[1] == ("sched_setaffinity", (1,))
    assert status.fifo is False
    assert status.priority is None
    assert status.memory_locked is False
    assert len(status.notes) == 3
    assert "SCHED_FIFO priority 10" in status.notes[0]
    assert "PermissionError" in status.notes[0]
    assert "CPU affinity [1]" in status.notes[1]
    assert "mlockall" in status.notes[2]
    warnings = [r for r in caplog.records if r.name == "zplatform.scheduler"]
    assert len(warnings) == 1  # a single warning naming every fallback
    assert warnings[0].levelno == logging.WARNING
    assert "SCHED_FIFO" in warnings[0].getMessage()
    assert "mlockall" in warnings[0].getMessage()


@pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="needs Linux scheduling constants")
def test_setup_realtime_success_path(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    seen: list[object] = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda pid, pol, par: seen.append(par))
    monkeypatch.setattr(os, "sched_setaffinity", lambda pid, cpus: seen.append(tuple(cpus)))
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {1, 0})
    monkeypatch.setattr(scheduler, "_mlockall", lambda: None)
    with caplog.at_level(logging.WARNING, logger="zplatform.scheduler"):
        status = setup_realtime(priority=5, cpu=[0, 1], lock_memory=True)
    assert status == RealtimeStatus(
        fifo=True, priority=5, cpu_affinity=(0, 1), memory_locked=True, notes=()
    )
    assert seen[0] == os.sched_param(5)
    assert seen[1] == (0, 1)
    assert not [r for r in caplog.records if r.name == "zplatform.scheduler"]


def test_setup_realtime_with_nothing_requested_does_nothing(
    no_os_rt: list[tuple[str, object]],
) -> None:
    status = setup_realtime()
    assert no_os_rt == []
    assert status.fifo is False
    assert status.notes == ()


def test_setup_realtime_on_a_platform_without_sched_calls(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delattr(os, "sched_setscheduler", raising=False)
    monkeypatch.delattr(os, "sched_setaffinity", raising=False)
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    status = setup_realtime(priority=5, cpu=0)
    assert status.fifo is False
    assert status.cpu_affinity is None
    assert any("not supported" in note for note in status.notes)


@pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="needs Linux scheduling constants")
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"priority": 0}, "priority must be >= 1"),
        ({"priority": 1000}, "SCHED_FIFO priority must be in"),
        ({"cpu": -1}, "cpu must be >= 0"),
        ({"cpu": []}, "at least one CPU"),
    ],
)
def test_setup_realtime_misuse_raises(
    no_os_rt: list[tuple[str, object]], kwargs: dict[str, object], match: str
) -> None:
    with pytest.raises(SchedulerError, match=match):
        setup_realtime(**kwargs)  # type: ignore[arg-type]
    assert no_os_rt == []


# --------------------------------------------------------------------------- gc guard


def test_gc_guard_freeze_and_restore_leaves_gc_enabled() -> None:
    assert gc.isenabled()
    guard = GcGuard()
    try:
        guard.freeze_after_startup()
        assert not gc.isenabled()
        assert guard.frozen
        assert gc.get_freeze_count() > 0
    finally:
        guard.restore()
    assert gc.isenabled()
    assert not guard.frozen
    assert gc.get_freeze_count() == 0


def test_gc_guard_context_manager_restores_on_error() -> None:
    with pytest.raises(RuntimeError), GcGuard():
        assert not gc.isenabled()
        raise RuntimeError
    assert gc.isenabled()


def test_gc_guard_restores_previous_disabled_state() -> None:
    gc.disable()
    try:
        guard = GcGuard()
        guard.freeze_after_startup()
        guard.restore()
        assert not gc.isenabled()
    finally:
        gc.enable()


def _recording_collect(generations: list[int]) -> Callable[..., int]:
    def collect(generation: int = 2) -> int:
        generations.append(generation)
        return 0

    return collect


def test_collect_in_slack_only_with_enough_slack(monkeypatch: pytest.MonkeyPatch) -> None:
    generations: list[int] = []
    monkeypatch.setattr(gc, "collect", _recording_collect(generations))
    monkeypatch.setattr(gc, "get_count", lambda: (10_000, 0, 0))  # work pending
    guard = GcGuard(threshold_ns=2 * MS)
    assert guard.collect_in_slack(5 * MS, 2 * MS) is True
    assert guard.collect_in_slack(1 * MS, 2 * MS) is False
    guard.on_slack(3 * MS)
    guard.on_slack(MS)
    assert generations == [0, 0]  # generation 0 only
    assert guard.collections == 2


def test_collect_in_slack_skips_an_empty_generation(monkeypatch: pytest.MonkeyPatch) -> None:
    generations: list[int] = []
    monkeypatch.setattr(gc, "collect", _recording_collect(generations))
    monkeypatch.setattr(gc, "get_count", lambda: (3, 0, 0))  # almost nothing new
    guard = GcGuard(threshold_ns=MS)
    assert guard.collect_in_slack(9 * MS, MS) is False
    assert generations == [] and guard.collections == 0


def test_gc_guard_plugs_into_the_loop_as_slack_hook(monkeypatch: pytest.MonkeyPatch) -> None:
    generations: list[int] = []
    monkeypatch.setattr(gc, "collect", _recording_collect(generations))
    monkeypatch.setattr(gc, "get_count", lambda: (10_000, 0, 0))  # work pending
    clock = FakeClock()
    guard = GcGuard(threshold_ns=5 * MS)

    def step(k: int, deadline: int) -> None:
        clock.advance((2 if k % 2 == 0 else 8) * MS)  # slack 8 ms, then 2 ms

    make_loop(clock, slack_hook=guard.on_slack).run(step, max_loops=6)
    assert guard.collections == 3
    assert generations == [0, 0, 0]


def test_gc_guard_validation() -> None:
    with pytest.raises(SchedulerError, match="threshold_ns must be >= 0"):
        GcGuard(threshold_ns=-1)


def test_the_control_nodes_overrun_hook_counts_every_skipped_period() -> None:
    """The defect (seen as a hole of 3 loops with ``cn_loop_overruns`` up by
    1 in a live recorder test): the control node's ``on_overrun`` added 1
    per overrun, but one overrun skips every deadline it passed, so the
    loops no one ran went uncounted. Its count must equal the scheduler's
    ``skipped_periods``, over overruns of 1, 2 (ending on a deadline) and 3
    periods."""
    from types import SimpleNamespace

    from zplatform.node.control import ControlNode

    clock = FakeClock()
    node = SimpleNamespace(mission=SimpleNamespace(period_ns=10 * MS), health=None, _skipped=0)
    stalls = {1: 12 * MS, 4: 29 * MS, 8: 31 * MS}

    def step(k: int, deadline: int) -> None:
        clock.advance(stalls.get(k, 1 * MS))

    loop = make_loop(clock, on_overrun=lambda k, late: ControlNode._on_overrun(node, k, late))  # type: ignore[arg-type]
    stats = loop.run(step, max_loops=12)
    assert stats.overruns == 3
    assert node._skipped == stats.skipped_periods == 1 + 2 + 3
