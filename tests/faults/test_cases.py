"""Fault cases on real node processes: the minimal mission with dn0 behind a
fault relay. The CN keeps its rate; dn0's misses climb while its link drops
or is partitioned, and sync resumes when the fault ends."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from tests.budget import later_than_now, sync_counts
from tests.faults.missions import relay_links
from tests.faults.relay import FaultRelay
from tests.integration.harness import CONFIGS, Cluster
from zplatform.mission.load import load_mission

pytestmark = pytest.mark.timeout(120)


def relayed_cluster(
    tmp_path: Path, fault_relay: Callable[..., FaultRelay]
) -> tuple[Cluster, FaultRelay]:
    c = Cluster(CONFIGS / "minimal.yaml", tmp_path)
    relay = relay_links(c.path, fault_relay, ["dn0"], seed=2024)["dn0"]
    c.mission = load_mission(c.path)
    return c, relay


def test_dropped_batches_become_cn_misses(
    tmp_path: Path, fault_relay: Callable[..., FaultRelay]
) -> None:
    c, relay = relayed_cluster(tmp_path, fault_relay)
    with c:
        c.spawn("dn0")
        c.spawn("cn")
        c.wait_for(lambda dv: int(dv.get("cn_rx_dn0")) >= 20, 120, "dn0 in sync")
        missed0 = int(c.tm.get("cn_missed_dn0"))
        relay.arm(drop=0.1)
        c.advance(150, timeout_s=120)
        relay.disarm()
        counts = relay.counts()
        for d, st in counts.items():
            assert st.decisions() == relay.plan.expected(st.seen, d).decisions(), d
        dropped = counts["up"].dropped + counts["down"].dropped
        missed = int(c.tm.get("cn_missed_dn0")) - missed0
        assert dropped > 0
        # Every dropped batch that carried a query or a reply costs that loop's
        # sync (tests/faults/live.py case_loss proves it frame by frame);
        # keepalives cost nothing. A busy box (the relay runs in this test's
        # process) adds misses of its own, so no upper bound here.
        print(f"dropped {dropped} batches, CN missed {missed} syncs: {counts}")
        assert missed >= 1, (missed, counts)
        # Sync resumes, on the same session. (Through the relay, which runs
        # in this test's process, how many loops it takes is the box's.)
        rx = int(c.tm.get("cn_rx_dn0"))
        c.wait_for(lambda dv: int(dv.get("cn_rx_dn0")) >= rx + 50, 120, "dn0 back in sync")
        assert relay.connections == 1  # the session lived through it


def test_partition_misses_every_loop_then_heals(
    tmp_path: Path, fault_relay: Callable[..., FaultRelay]
) -> None:
    c, relay = relayed_cluster(tmp_path, fault_relay)
    with c:
        c.spawn("dn0")
        c.spawn("cn")
        c.wait_for(lambda dv: int(dv.get("cn_rx_dn0")) >= 20, 120, "dn0 in sync")
        relay.partition()
        # The first loop that started after the partition: nothing gets
        # through from there on, every loop is a miss.
        c.wait_for(later_than_now(), 60, "a loop after the partition")
        before = sync_counts(c.tm, ("dn0",))
        c.advance(30)  # well under the 1 s lease on an idle box
        after = sync_counts(c.tm, ("dn0",))
        assert after["rx_dn0"] == before["rx_dn0"], (before, after)
        assert after["missed_dn0"] > before["missed_dn0"], (before, after)
        relay.heal()
        rx = int(c.tm.get("cn_rx_dn0"))
        c.wait_for(lambda dv: int(dv.get("cn_rx_dn0")) >= rx + 50, 120, "dn0 back in sync")
