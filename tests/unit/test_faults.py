"""Tests of zplatform.control.faults: consecutive-loop thresholds, latching, clearing,
controller failures, non-critical errors."""

from __future__ import annotations

import textwrap

import pytest

from zplatform import DataVector, Layout, decode_mission
from zplatform.config import Mission
from zplatform.control.commands import CommandHandler
from zplatform.control.faults import ErrorCode, Fault, FaultMonitor
from zplatform.control.uplink import element_index, fill_request
from zplatform.core.events import EventLog, Severity

PERIOD = 10_000_000

BASE = """
mission: faulttest
nodes: {cn: {}, dn0: {}, dn1: {}, gn: {}}
regions:
  cn:
    - {name: x, type: u8}
"""


def mission(faults: str = "") -> Mission:
    return decode_mission(BASE + textwrap.dedent(faults))


class Rig:
    def __init__(self, m: Mission) -> None:
        self.m = m
        self.dv = DataVector(Layout.for_node(m, "cn"))
        self.events = EventLog("cn")
        self.fm = FaultMonitor(m, self.dv, self.events)
        self.t = 0

    def bump(self, *names: str) -> None:
        for n in names:
            self.dv.set(n, self.dv.get(n) + 1)

    def loop(self, *bumped: str, n: int = 1) -> str:
        """``n`` loops in each of which the ``bumped`` counters grow."""
        for _ in range(n):
            self.bump(*bumped)
            self.fm.step(self.t)
            self.t += PERIOD
        return self.dv.get_name("cn_fault")

    def critical(self) -> list[str]:
        return [e.text for e in self.events.drain() if e.severity == Severity.WARNING_HI]


def test_dn_lost_after_consecutive_missed_syncs() -> None:
    r = Rig(mission("faults: {dn_lost_loops: 5}\n"))
    assert r.loop("cn_missed_dn1", n=4) == "NONE"
    assert r.loop("cn_missed_dn1") == "DN_LOST"
    assert r.fm.fault == "DN_LOST"
    assert r.critical() == ["fault DN_LOST: dn1 missed 5 syncs in a row"]


def test_an_interrupted_run_starts_over() -> None:
    r = Rig(mission("faults: {dn_lost_loops: 3}\n"))
    for _ in range(10):
        assert r.loop("cn_missed_dn0", n=2) == "NONE"
        assert r.loop() == "NONE"  # one good sync resets the run
    assert r.loop("cn_missed_dn0", n=3) == "DN_LOST"


def test_counters_present_at_construction_are_the_baseline() -> None:
    m = mission("faults: {dn_lost_loops: 2}\n")
    dv = DataVector(Layout.for_node(m, "cn"))
    dv.set("cn_missed_dn0", 1000)
    fm = FaultMonitor(m, dv, EventLog("cn"))
    fm.step(0)
    fm.step(1)
    assert dv.get_name("cn_fault") == "NONE"


def test_sync_overruns() -> None:
    r = Rig(mission("faults: {sync_overrun_loops: 3}\n"))
    assert r.loop("cn_sync_overruns", n=2) == "NONE"
    assert r.loop("cn_sync_overruns") == "SYNC_OVERRUNS"


def test_loop_overruns_are_off_by_default_and_on_when_configured() -> None:
    r = Rig(mission())
    assert r.loop("cn_loop_overruns", n=1000) == "NONE"
    r = Rig(mission("faults: {loop_overrun_loops: 4}\n"))
    assert r.loop("cn_loop_overruns", n=3) == "NONE"
    assert r.loop("cn_loop_overruns") == "LOOP_OVERRUNS"


def test_zero_turns_a_check_off() -> None:
    r = Rig(
        mission("faults: {dn_lost_loops: 0, sync_overrun_loops: 0, controller_fail_loops: 0}\n")
    )
    assert r.loop("cn_missed_dn0", "cn_sync_overruns", "dn0_errors", n=500) == "NONE"
    r.fm.report_controller_failure("ctl", 1000, r.t)
    assert r.dv.get_name("cn_fault") == "NONE"


def test_device_node_errors_are_controller_failures() -> None:
    r = Rig(mission("faults: {controller_fail_loops: 3}\n"))
    assert r.loop("dn0_errors", n=2) == "NONE"
    assert r.loop("dn0_errors") == "CONTROLLER_FAILED"
    assert r.critical() == ["fault CONTROLLER_FAILED: dn0 reported errors in 3 loops in a row"]


def test_report_controller_failure() -> None:
    r = Rig(mission("faults: {controller_fail_loops: 3}\n"))
    r.fm.report_controller_failure("guidance", 2, 5)
    assert r.dv.get_name("cn_fault") == "NONE"
    r.fm.report_controller_failure("guidance", 3, 6)
    assert r.dv.get_name("cn_fault") == "CONTROLLER_FAILED"
    (e,) = r.events.drain()
    assert e.severity == Severity.WARNING_HI and e.id == "fault" and e.t_ns == 6
    assert e.text == "fault CONTROLLER_FAILED: controller guidance failed in 3 loops in a row"


def test_only_the_first_fault_latches_and_is_reported_once() -> None:
    r = Rig(mission("faults: {dn_lost_loops: 2, sync_overrun_loops: 2}\n"))
    assert r.loop("cn_sync_overruns", n=2) == "SYNC_OVERRUNS"
    assert r.loop("cn_sync_overruns", "cn_missed_dn0", n=20) == "SYNC_OVERRUNS"
    r.fm.report_controller_failure("c", 99, r.t)
    assert r.dv.get_name("cn_fault") == "SYNC_OVERRUNS"
    assert len(r.critical()) == 1
    assert r.fm.raise_fault(Fault.DN_LOST, "x", r.t) is False


def test_same_loop_order_is_dn_lost_first() -> None:
    r = Rig(mission("faults: {dn_lost_loops: 1, sync_overrun_loops: 1}\n"))
    assert r.loop("cn_sync_overruns", "cn_missed_dn0") == "DN_LOST"


def test_a_write_clears_the_fault_and_a_persisting_symptom_raises_it_again() -> None:
    m = decode_mission(
        BASE
        + "faults: {dn_lost_loops: 2}\n"
        + "commands: {writable: [cn_fault], whitelist: {IDLE: [WRITE]}}\n"
    )
    r = Rig(m)
    ch = CommandHandler(m, r.dv, r.events)
    assert r.loop("cn_missed_dn0", n=2) == "DN_LOST"
    fill_request(r.dv, "WRITE", 1, element_index(m, "cn_fault"), 0.0)
    ch.step(True, r.t)
    assert r.dv.get_name("cn_cmd_status") == "ACCEPTED"
    assert r.dv.get_name("cn_fault") == "NONE"
    assert r.loop() == "NONE"  # the symptom stopped: stays clear
    assert r.loop("cn_missed_dn0") == "NONE"
    assert r.loop("cn_missed_dn0") == "DN_LOST"
    assert len(r.critical()) == 2


def test_non_critical_error_counts_and_reports() -> None:
    r = Rig(mission())
    r.fm.error(ErrorCode.SYNC_TIMEOUT, "dn0 missed the sync deadline", 42)
    r.fm.error(1234, "mission code", 43)
    assert r.dv.get("cn_errors") == 2
    assert r.dv.get("cn_last_error") == 1234
    assert r.dv.get_name("cn_fault") == "NONE"
    evs = r.events.drain()
    assert [(e.severity, e.id, e.text, e.t_ns) for e in evs] == [
        (Severity.WARNING_LO, "error", "dn0 missed the sync deadline", 42),
        (Severity.WARNING_LO, "error", "mission code", 43),
    ]


@pytest.mark.parametrize(("code", "stored"), [(-5, 0), (70000, 0xFFFF)])
def test_error_never_raises_on_odd_codes_and_saturates(code: int, stored: int) -> None:
    r = Rig(mission())
    r.dv.set("cn_errors", 0xFFFF_FFFF)
    r.fm.error(code, "odd", 0)
    assert r.dv.get("cn_errors") == 0xFFFF_FFFF
    assert r.dv.get("cn_last_error") == stored


def test_clock_drift_beyond_the_bound_during_the_run_is_a_fault() -> None:
    """The clock bound holds for the whole run: the DNs' re-sync reports what
    is left after the start-up correction (thesis 4.9)."""
    r = Rig(mission())
    r.dv.set("dn0_clock_drift_ns", 99_000_000)  # within 100 ms
    assert r.loop() == "NONE"
    r.dv.set("dn0_clock_drift_ns", -101_000_000)
    assert r.loop() == "CLOCK_DRIFT"
    assert r.critical() == [
        "fault CLOCK_DRIFT: dn0's clock drifted -101.000 ms from the CN's, beyond the bound "
        "of 100 ms"
    ]
