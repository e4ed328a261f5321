"""The live flood suite generated from the key space (``keyfloods.py``).

* the plan (in process, no network): every (row, frame kind) of the
  shipped flight and recovery_igniter missions has a flood or a reason,
  and the floods are what the rows say (victim, counter, size);
* ``-m slow``: every flood of each mission, 2 s at 6,000 frames/s each, in
  one flight per mission, the nodes as configured (SCHED_FIFO where the
  user may) and without real-time priority; a flight whose every failed
  check is a defect this suite found and reports (``KNOWN_DEFECTS``) is an
  xfail naming it;
* one flood per class (query key, sample key, reply path) of
  recovery_igniter, 1 s each, with its nodes on the pad: with the soaks too,
  until the DN safing it showed (below) is explained.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.faults.keyfloods import (
    CLASSES,
    KNOWN_DEFECTS,
    MISSIONS,
    NOT_FLOODED,
    case_keyfloods,
    flood_plan,
    known_failures,
    representatives,
)
from zplatform.mission.load import load_mission
from zplatform.security.keyspace import KEYSPACE, KeyFrames, KeyRow, expand_keys

pytestmark = [pytest.mark.faults]
_LOADED = {n: load_mission(p) for n, p in MISSIONS.items()}


@pytest.mark.parametrize("mission", list(MISSIONS))
def test_every_reachable_row_has_a_flood_or_a_reason(mission: str) -> None:
    m = _LOADED[mission]
    floods, skipped = flood_plan(m)
    covered = {(f.row, f.kind) for f in floods}
    for k in expand_keys(m):
        for f in k.row.frames:
            tag = f"{k.id}/{f.kind}"
            assert (k.row.name, f.kind) in covered or tag in skipped, tag
    # A flood for each class, and none of a reason's rows flooded.
    assert {f.cls for f in floods} == set(CLASSES)
    assert not covered & set(NOT_FLOODED)
    # Every reason names a row of the table (a renamed row drops its reason).
    rows = {(r.name, f.kind) for r in KEYSPACE for f in r.frames}
    assert set(NOT_FLOODED) <= rows, set(NOT_FLOODED) - rows


def test_the_plan_follows_the_rows() -> None:
    """Per device node, its keys; each key attacked once; the counters and
    victims of the rows that have them."""
    floods, skipped = flood_plan(_LOADED["flight"])
    by_id = {f.id: f for f in floods}
    assert len(by_id) == len(floods)
    for dn in ("dn0", "dn1"):
        q = by_id[f"dn_to_cn[{dn}]"]
        assert (q.victim, q.counter, q.count) == (dn, f"{dn}_bad_frames", "exact")
        assert q.capture == f"rocket/cn/to_{dn}"
        rep = by_id[f"dn_to_cn[{dn}]/reply"]
        assert (rep.victim, rep.counter, rep.count, rep.cls) == (
            "cn",
            "cn_bad_frames",
            "at_most",
            "reply",
        )
        assert by_id[f"probe[{dn}]"].counter == f"{dn}_bad_frames"
    gn = by_id["gn_to_cn"]
    assert (gn.counter, gn.count) == ("cn_cmd_rejects+cn_bad_frames", "at_least")
    assert by_id["gn_to_cn"].capture == "wiretap"
    assert by_id["mirror"].victim == "cn_b"
    assert by_id["telemetry"].victim == "gn"
    # One clock key for every asker: flooded once.
    assert [f.id for f in floods if f.row == "clock"] == ["clock[dn0]"]
    assert "same key" in skipped["clock[dn1]/query"]
    assert all(f.size > 0 for f in floods)
    # recovery_igniter has no standby: no mirror, no probe.
    rows = {f.row for f in flood_plan(_LOADED["recovery_igniter"])[0]}
    assert not rows & {"mirror", "probe"}


def _row(name: str, kind: str, channel: str, intake: str) -> KeyRow:
    return KeyRow(
        name,
        "{vehicle}/" + name,
        puts=("gn",),
        declares=("commander",),
        queries=(),
        frames=(KeyFrames(kind, channel, "uplink", intake, "-", "-"),),
        when="always",
        what="a channel added later",
    )


def test_a_row_added_later_gets_its_flood_or_fails_the_plan() -> None:
    m = _LOADED["recovery_igniter"]
    # A tagged sample row: flooded (junk of its in-process recipe's size);
    # without a recipe there, the plan fails naming RECIPES.
    with pytest.raises(AssertionError, match="RECIPES"):
        flood_plan(m, (*KEYSPACE, _row("novel", "sample", "gn_to_cn", "x.Y commander")))
    # A frame no attack class takes (a token with an intake): a reason is due.
    with pytest.raises(KeyError, match="novel"):
        flood_plan(m, (*KEYSPACE, _row("novel", "token", "", "x.Y commander")))


# With the soaks (-m slow) until the DN safing it showed is explained: in 2
# of 4 whole-suite runs here (once on a quiet box) both device nodes of this
# pad flight safed during a flood ("no valid trigger for 133 ms"), the
# telemetry flood at the ground once and dn0's trigger key once: a real
# finding of issue 25's flood suite, open, not a rate to tune.
@pytest.mark.slow
@pytest.mark.timeout(120)
def test_one_flood_per_class_on_the_pad(tmp_path: Path) -> None:
    """The representative run: a query key, a sample key and the reply path
    of recovery_igniter, 1 s each at 6,000 frames/s."""
    reps = representatives(_LOADED["recovery_igniter"])
    assert [f.cls for f in reps] == list(CLASSES)
    only = tuple(f.id for f in reps)
    r = case_keyfloods(tmp_path, True, "recovery_igniter", only=only, launch=False, flood_s=1.0)
    print(r.figures)
    assert r.ok, f"{r.failures()} figures={r.figures}"


@pytest.mark.slow
@pytest.mark.timeout(600)
@pytest.mark.parametrize("realtime", [True, False], ids=["rt", "no_rt"])
@pytest.mark.parametrize("mission", list(MISSIONS))
def test_every_flood_in_one_flight(mission: str, realtime: bool, tmp_path: Path) -> None:
    r = case_keyfloods(tmp_path, True, mission, realtime=realtime)
    print(r.case, json.dumps(r.figures, default=str))
    unknown, known = known_failures(r)
    assert not unknown, f"{r.case}: {unknown} figures={r.figures}"
    if known:  # found by this suite and reported (KNOWN_DEFECTS), not fixed yet
        pytest.xfail("; ".join(f"{k}: {KNOWN_DEFECTS[k][1]}" for k in known))


def test_known_defects_explain_only_their_checks() -> None:
    from tests.faults.live import CaseResult

    r = CaseResult("x")
    r.check("dn_to_cn[dn0]_cn_memory_flat", True)
    assert known_failures(r) == ([], [])
    r.check("flight_no_takeover", False)  # no service flood failed: unexplained
    assert known_failures(r)[0] == ["flight_no_takeover: "]
    r.check("clock[dn0]_no_takeover", False)
    assert known_failures(r) == ([], ["commander_service_flood"])
    # The ground's memory is a check again (no shared memory for the ground
    # node: tests/integration/test_ground_shared_memory.py).
    r.check("events[cn]_gn_memory_flat", False, 19.3)
    assert known_failures(r)[0] == ["events[cn]_gn_memory_flat: 19.3"]
    r.check("dn_to_cn[dn0]_every_frame_counted_exactly", False)
    assert len(known_failures(r)[0]) == 2
