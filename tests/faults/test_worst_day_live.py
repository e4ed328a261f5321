"""The worst day on real node processes (tests/faults/live.py has the cases
and what each proves). Loopback, dn0 behind a frame-tapping fault relay
where the case needs the link; every case is bounded in time and cleans up
its processes (``Live.close``) and relays."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.faults import live
from tests.faults.live import CASES

pytestmark = [pytest.mark.faults, pytest.mark.timeout(150)]


# The cable cuts found a product bug, fixed: the CN's sync get() used
# zenoh's default congestion control (BLOCK), so a DN link whose TCP stopped
# draining blocked the CN's loop thread inside Session.get for seconds. It
# now uses DROP (a dropped query is a counted miss), and so do the DN's
# replies and every node's events.
# Not root-caused (reported): with the GN's cable cut, the CN sometimes
# misses every dn0 sync for ~4 s (DN_LOST) although its loop runs on
# (2 runs of 5 here; 3 of 4 on 2026-11-23, 433 loops each); dn0 and the CN
# share a host, gossip connects both to gn. A relative: with zenoh's receive
# pool at one thread (ZENOH_RUNTIME rx 1) a dn0 cable cut froze the CN's
# whole loop for 4.38 s, every time. Bounding zenoh's blocked sends
# (congestion_control block/wait_before_close 250 ms, drop/wait_before_drop
# 100 us instead of 5 s and 1 ms) changed neither, so that is not it.
_GN_CUT = pytest.mark.xfail(
    reason="a GN cable cut sometimes costs dn0's syncs for ~4 s (DN_LOST); reported",
    strict=False,
)
# The default suite keeps one case of each kind (a node killed, the ground
# killed, a CN restart, a short cable cut, loss, junk and forged input);
# the long cuts, SIGSTOPs, heavier loss, delay and clock skews run with the
# soaks (-m slow), as does the GN cable cut, known to fail now and then.
SOAK = {
    "loss_10pct",
    "delay_1ms",
    "partition_5s",
    "cable_cut_dn0_5s_netns",
    "dn0_sigstop",
    "gn_sigstop",
    "cn_sigstop",
    "clock_skew_50ms",
    "clock_skew_500ms",
}


def _param(c: str) -> Any:
    if c.startswith("cable_cut_gn"):
        return pytest.param(c, marks=[_GN_CUT, pytest.mark.slow])
    return pytest.param(c, marks=pytest.mark.slow) if c in SOAK else c


PARAMS = [_param(c) for c in CASES]


@pytest.mark.parametrize("case", PARAMS)
def test_worst_day(case: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Rates are the bench's targets (bench.faults): a test asserts checks only.
    monkeypatch.setattr(live, "MEASURE_RATES", False)
    r = CASES[case](tmp_path, True)
    if "skipped" in r.figures:
        pytest.skip(r.figures["skipped"])
    print(case, r.figures)
    assert r.ok, f"{case}: {r.failures()} figures={r.figures}"


def test_a_device_node_without_resyncs_follows_a_restarted_control_nodes_new_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """cn_kill9_restart with ``clock.resync_s: 0`` (no periodic re-sync): the
    restarted control node's new run still reaches dn0, whose intake cues a
    hello on its first trigger (zplatform.node.device.ClockResync): dn0
    follows it, as with re-syncs, instead of refusing every trigger of the
    new run until DN_LOST."""
    mission = tmp_path / "minimal.yaml"
    mission.write_text(live.MISSION.read_text() + "clock:\n  resync_s: 0\n")
    monkeypatch.setattr(live, "MEASURE_RATES", False)
    (tmp_path / "run").mkdir()
    r = live.case_cn_restart(tmp_path / "run", True, mission=mission)
    print(r.figures)
    assert r.ok, f"{r.failures()} figures={r.figures}"
