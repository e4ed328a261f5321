"""What a test on real node processes may assert about deadline misses.

A miss is not a failure of the platform: it is the platform doing its job.
The CN waited its 2 ms for a DN's reply, did not get it, counted the miss
and flew on; the late reply, if it came, was counted and never applied.
Whether a reply makes the deadline depends on whether the box ran the DN,
the CN and zenoh's threads within those 2 ms, and that is the machine's
business, not the code's: this project's tests run on a shared 2-core VM
beside other work (CI starts while the lead's box is still busy; several
suites may run at once), and must pass beside a CPU hog on both cores
(``python3 scripts/cpu_hog.py -- ./scripts/test.sh``). Measured there with
the live tests beside the hog: when the nodes may not use SCHED_FIFO (not
root), up to 17 % of a DN's syncs missed over a whole led_test flight, and
62 % over a 21-loop window with the box at a load of 10 (other suites and
a second hog beside ours); when they may (root: every thread of a CN or DN
process runs SCHED_FIFO 20 and preempts the hog) a handful in a thousand,
more where the path runs through the test's own process (a fault relay, a
rogue queryable), which never has SCHED_FIFO.

So a live test asserts what the platform guarantees whatever the load:

* every loop is accounted for, exactly: for each DN, replies taken plus
  misses equal the CN's loops (``rx + missed == loops``), a late reply is
  the answer to a loop already missed (``late <= missed``), telemetry
  snapshots received plus gaps span the run (``received + gaps == last -
  first + 1``); zero errors; bad frames counted exactly;
* the behaviour: states reached, verdicts given, LEDs lit, DNs that rejoin,
  events that name what happened;
* misses only against a ceiling that catches a dead or wedged link, never a
  slow box: over a whole run each DN answered at least :data:`LINK_ALIVE` of
  the loops, and in a window of tens of loops at least once. A dead link
  answers none of them.

Miss *rates*, the thesis' 99.999 % reliability, loop rates and latencies are
measurements, and live in ``bench/`` (``python -m bench.reliability``,
``bench.jitter``, ``bench.faults``), reported as figures on a quiet box. The
opt-in soak (``-m slow``, ``tests/system/test_soak.py``) holds a long run
to :data:`THESIS_RELIABILITY`; it is a measurement too and wants a quiet box.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

#: The fraction of a whole run's loops each DN must have answered for its
#: link to count as alive: one in ten. Well below what the hog alone costs
#: (17 % missed at worst without SCHED_FIFO), well above a dead link (0 %).
LINK_ALIVE = 0.1

#: The thesis' network reliability requirement, held by the opt-in soak.
THESIS_RELIABILITY = 0.99999


def _cn(summary: Mapping[str, Any]) -> Mapping[str, Any]:
    """The CN's own summary: ``up``'s has it under ``nodes.cn``."""
    nodes = summary.get("nodes")
    if isinstance(nodes, Mapping) and isinstance(nodes.get("cn"), Mapping):
        return nodes["cn"]  # type: ignore[no-any-return]
    return summary


def assert_every_loop_counted(summary: Mapping[str, Any]) -> None:
    """Each DN's loops are exactly its replies plus its misses, late replies
    answer missed loops only, and every link was alive (:data:`LINK_ALIVE`).

    ``summary``: the CN's ``--summary`` or ``up``'s (with ``nodes.cn``).
    """
    cn = _cn(summary)
    loops = int(cn["loops"])
    rx, missed, late = cn["rx"], cn["missed"], cn["late"]
    assert set(rx) == set(missed) == set(late), cn
    for dn in rx:
        assert rx[dn] + missed[dn] == loops, f"{dn}: {rx[dn]} rx + {missed[dn]} missed != {loops}"
        assert late[dn] <= missed[dn], f"{dn}: {late[dn]} late replies but {missed[dn]} misses"
        assert rx[dn] >= LINK_ALIVE * loops, (
            f"{dn} answered {rx[dn]} of {loops} loops: its link looks dead"
        )


def assert_telemetry_counted(summary: Mapping[str, Any]) -> None:
    """The ground's snapshots plus its counted gaps span the run exactly,
    and most snapshots arrived (:data:`LINK_ALIVE`).

    Telemetry is published with DROP congestion control (the CN's loop never
    blocks on a slow ground), so on a loaded box a snapshot may be lost, and
    a period the CN's loop skipped has no snapshot: both are gaps.
    ``summary``: ``up``'s (with ``nodes.gn``) or the GN's own.
    """
    nodes = summary.get("nodes")
    gn = nodes["gn"] if isinstance(nodes, Mapping) and "gn" in nodes else summary
    received, gaps = int(gn["telemetry_received"]), int(gn["telemetry_gaps"])
    span = int(gn["last_seq"]) - int(gn["first_seq"]) + 1
    assert received + gaps == span, (received, gaps, gn["first_seq"], gn["last_seq"])
    assert received >= LINK_ALIVE * span, f"{received} of {span} snapshots: telemetry looks dead"


def sync_counts(dv: Any, dns: list[str] | tuple[str, ...]) -> dict[str, int]:
    """``cn_loop`` and each DN's ``cn_rx_*``/``cn_missed_*`` from a CN-layout
    Data Vector (the latest telemetry a test read), as plain ints."""
    out = {"cn_loop": int(dv.get("cn_loop"))}
    for dn in dns:
        out[f"rx_{dn}"] = int(dv.get(f"cn_rx_{dn}"))
        out[f"missed_{dn}"] = int(dv.get(f"cn_missed_{dn}"))
    return out


def assert_kept_syncing(
    before: Mapping[str, int], after: Mapping[str, int], dns: list[str] | tuple[str, ...]
) -> None:
    """Between two :func:`sync_counts`, every DN in ``dns`` was synced: each
    loop the CN ran is a reply or a miss for each of them, the same number
    of loops for all (periods the CN skipped have neither), and each DN
    answered in the window. A window (tens of loops) is too short for a
    fraction: one scheduling storm on a loaded box can take most of it."""
    passed = after["cn_loop"] - before["cn_loop"]
    assert passed > 0, (before, after)
    ran = set()
    for dn in dns:
        rx = after[f"rx_{dn}"] - before[f"rx_{dn}"]
        missed = after[f"missed_{dn}"] - before[f"missed_{dn}"]
        ran.add(rx + missed)
        assert rx > 0, f"{dn} never answered in {passed} loops: link dead? {before} {after}"
    assert len(ran) == 1 and ran.pop() <= passed, (before, after)


def later_than_now(margin_s: float = 0.05) -> Callable[[Any], bool]:
    """A telemetry predicate: the snapshot's loop started after this call
    (plus ``margin_s``). A test reads telemetry from a queue, possibly well
    behind the CN on a busy box; this tells a snapshot made after, say, a
    kill from one still queued from before it. Nodes on one host share its
    epoch clock (``cn_time_ns`` is the CN's, anchored on ``time.time_ns()``)."""
    t = time.time_ns() + int(margin_s * 1e9)
    return lambda dv: int(dv.get("cn_time_ns")) > t
