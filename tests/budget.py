"""The deadline-miss budget that tests on real processes hold the platform to.

Processes on this project's machines share 2 cores (and a hypervisor) with
whatever else runs; a rare scheduling stall longer than the 2 ms sync
deadline shows up as a miss no matter what the platform does (measured: 0 to
~3 misses per 6000 device-node loops, the same at an older commit, so the
box and not the code). The default suite therefore allows misses up to
MISS_BUDGET of all device-node loops (never fewer than one host stall's
worth, STALL_LOOPS per DN; it was 0.5 % before bench.reliability measured
the platform against that floor) and reports
them; the opt-in soak holds the thesis' requirement (99.999 %) over a long
run. Functional checks (states, LEDs, commands, zero errors, zero telemetry
gaps) are exact. A late reply is the same event as its miss (the answer that
missed the deadline), so only misses count against the budget.
"""

from __future__ import annotations

from collections.abc import Mapping

#: Three times the sync miss rate `python -m bench.reliability` measured for
#: the full led_test mission over 10 min on this box, twice (180 and 145 of
#: 180 000 DN syncs, 1.0e-3 and 0.8e-3; the raw-zenoh replica of the same
#: traffic missed 147 and 162): room for a short test's run-to-run spread,
#: not for a regression.
MISS_BUDGET = 3e-3
THESIS_RELIABILITY = 0.99999


#: Loops one host stall may cost every DN at once, whatever the run's length:
#: this VM's vCPUs stop for 1-200 ms every few seconds (bench/jitter.py); a
#: 300-loop run under `up` lost 11 syncs of 900 to one such stall.
STALL_LOOPS = 5


def allowed_misses(loops: int, n_dn: int, budget: float = MISS_BUDGET) -> int:
    return max(STALL_LOOPS * n_dn, int(loops * n_dn * budget))


def assert_within_budget(summary: Mapping[str, object], budget: float = MISS_BUDGET) -> None:
    """Misses summed over DNs stay within the budget; late replies never exceed misses."""
    missed = summary["missed"]
    late = summary["late"]
    assert isinstance(missed, dict) and isinstance(late, dict)
    loops = int(summary["loops"])  # type: ignore[call-overload]
    total = sum(missed.values())
    limit = allowed_misses(loops, len(missed), budget)
    assert total <= limit, f"{total} misses in {loops} loops x {len(missed)} DNs > {limit}"
    for dn, n in late.items():
        assert n <= missed[dn], f"{dn}: {n} late replies but only {missed[dn]} misses"
