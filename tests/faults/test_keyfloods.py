"""The live flood suite generated from the key space (``keyfloods.py``).

* the plan (in process, no network): every (row, frame kind) of the
  shipped flight and recovery_igniter missions has a flood or a reason,
  and the floods are what the rows say (victim, counter, size);
* ``-m slow``: every flood of each mission, 2 s at 6,000 frames/s each, in
  one flight per mission, the nodes as configured (SCHED_FIFO where the
  user may) and without real-time priority; every check must pass;
* one flood per class (query key, sample key, reply path) of
  recovery_igniter, 1 s each, with its nodes on the pad: in the default
  suite (the DN safing it showed: below).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest

from tests.faults.keyfloods import (
    CLASSES,
    MISSIONS,
    NOT_FLOODED,
    case_keyfloods,
    flood_plan,
    representatives,
)
from tests.payload import FakeQuery
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


# Issue 25: in 3 of 6 runs on a busy box (with the soaks then) both device
# nodes of this pad flight safed during a flood ("no valid trigger from the
# control node for 109 ms"), once during the flood of dn0's trigger key: the
# control node went silent, not the flooded node. What the runs kept show
# (tests/faults/README.md): refusing 5,000 gets/s costs dn0 about 120 us of
# CPU each (cpu_us_per_frame), on its zenoh thread at the loops' SCHED_FIFO
# priority, which no loop thread can preempt; with another SCHED_FIFO 20
# process on the 2-core box, all three nodes once went unscheduled for 2 s
# at once. Zenoh's threads below the loops cured the pad run but starved the
# standby's mirrors in the flight of `flight` (spinning loops above them):
# reverted. Then, beside a CPU hog, the CN's queries to dn1 went unanswered
# for 10 loops as a flood's attacker came and went (zenoh#2517, a route
# lost): the CN declared its querier again only at the 10th, the DNs'
# watchdog's own length, and dn1 had safed ("no valid trigger for 104 ms"),
# the failure's very signature with the CN's sync on zenoh. It now recovers
# after a third of the watchdog (queries.unanswered_loops,
# test_a_lost_route_is_recovered_well_before_the_dns_watchdog). The pad
# run's reply flood also waited for the CN's queries
# on dn0's key, sent only over zenoh: the suite now syncs on zenoh
# (floods._on_zenoh), and the run is back in the default suite. It still
# failed in 5 of 9 hogged full-suite runs (passing 6 of 6 alone beside the
# hog): the live tests' xdist group had not taken effect since pytest 9.2
# (tests/conftest.py), so another live mission's SCHED_FIFO nodes shared the
# two cores with this one's. The group holds again.
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
    assert r.ok, f"{r.case}: {r.failures()} figures={r.figures}"


# -- the commander's own services under a keyless flood (in process) ------------------


def _recorder_server(m: Any, s: Any) -> Any:
    """The CN's flight recorder server on session ``s``, its run never the
    one asked (junk never reaches the files)."""
    from zplatform.core.auth import KeySet, channel
    from zplatform.recorder import server as rs

    keys = KeySet.from_master(m, bytes(range(32)))
    rec = type("R", (), {"run": -1})()
    return rs.RecorderServer(
        s,
        f"{m.vehicle}/cn/recorder",
        rec,
        channel(keys.for_node("cn"), "telemetry"),
        now_ns=time.time_ns,
        max_age_ns=10**9,
        serve_bps=10**9,
    )


def _junk(size: int, n: int) -> list[bytes]:
    """Junk as the flood suite's attacker sends it: half of ``size`` bytes,
    half of random lengths."""
    import random

    rnd = random.Random(25)
    return [rnd.randbytes(size if i % 2 else rnd.randrange(0, 2000)) for i in range(n)]


def test_a_keyless_clock_flood_never_reaches_the_servers_thread() -> None:
    """Issue 25 (the fault suite's "commander service flood", now fixed): a
    keyless query flood on the commander's clock key stalled its loop, each
    query handed to the clock server's thread, checked there and answered
    with an error (a thread that never waits holds the GIL from the loop).
    Now every junk query, and a replay of a genuine one, is refused in
    zenoh's callback: dropped unanswered, no error reply, nothing handed
    to the thread, each counted; the genuine query is still answered."""
    from tests.zsession import lone_session
    from zplatform.core.auth import KeySet
    from zplatform.runtime.clocksync import ClockLink, ClockServer
    from zplatform.runtime.transport import KeySpace

    m = _LOADED["recovery_igniter"]
    keys = KeySet.from_master(m, bytes(range(32)))
    link = ClockLink(m, "dn0", keys.for_node("dn0"))
    genuine, _ = link.query(time.time_ns())
    s = lone_session()
    server = ClockServer(s, KeySpace(m.vehicle), time.time_ns, m, keys.for_node("cn"))
    try:
        first = FakeQuery(genuine)
        server.on_query(first)  # type: ignore[arg-type]
        flood = [FakeQuery(p) for p in _junk(len(genuine), 2000)]
        flood += [FakeQuery(genuine) for _ in range(500)]  # the genuine query, replayed
        for q in flood:
            server.on_query(q)  # type: ignore[arg-type]
    finally:
        server.close()  # joins the thread: what it was handed is served
        s.close()
    assert len(first.replies) == 1 and server.served == 1
    assert all(q.dropped and not q.replies and not q.errors for q in flood)
    assert server.refused == len(flood)
    assert server.dropped == 0  # the backlog never filled: nothing else was handed off


def test_a_keyless_recorder_flood_never_reaches_the_servers_thread() -> None:
    """Issue 25 (the fault suite's "commander service flood", now fixed): gap-fill
    requests of the right size, junk, each cost the recorder server's thread
    a tag check, back to back during a flood. Then a rate bound in zenoh's
    callback dropped the excess unread, and with it the ground's genuine
    requests. Now zenoh's callback checks the header tag first: of a burst
    of 2,000, none reaches the thread nor the rate bound; each is dropped
    unanswered and counted as refused."""
    from tests.zsession import lone_session
    from zplatform.core.auth import TAG_LEN
    from zplatform.recorder.format import REQUEST

    s = lone_session()
    server = _recorder_server(_LOADED["recovery_igniter"], s)
    flood = [FakeQuery(p) for p in _junk(REQUEST.size + TAG_LEN, 2000)]
    for q in flood:
        server.on_query(q)
    server.close()
    s.close()
    assert server.excess == 0 and server.busy == 0 and server.served == 0
    assert server.refused == len(flood)
    assert all(q.dropped and not q.replies and not q.errors for q in flood)


def test_replayed_run_hellos_are_refused_by_their_nonce() -> None:
    """A run hello is answered statelessly, so a captured one could be
    replayed for ever, each costing the clock server a MAC, an answer and
    a share of the rate bound a ground's hello needs. Of 100 replays at one
    instant, one is answered; the rest are refused by their nonce (kept:
    HELLO_KEPT) before their MAC and the bound, counted stale."""
    from zplatform.core.auth import KeySet
    from zplatform.runtime import clocksync as cs

    m = _LOADED["recovery_igniter"]
    keys = KeySet.from_master(m, bytes(range(32)))
    hello = cs.RunAsker(keys.for_node("gn")).hello()
    responder = cs.ClockResponder(m, keys.for_node("cn"), mono_ns=lambda: 5 * 10**9)
    answered = sum(responder.answer(hello, 0, 0) is not None for _ in range(100))
    assert answered == 1
    assert responder.refused == 99 == responder.stale and responder.hello_excess == 0


def test_the_recorder_servers_refusals_are_logged_at_most_once_a_second(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Issue 25: the recorder server counted the requests it refused but
    said nothing. Now a flood of junk is reported in the CN's log: one line
    a second at most (a thread of its own; zenoh's callback only counts),
    the last (at close) naming the whole count."""
    import logging

    from tests.zsession import lone_session
    from zplatform.core.auth import TAG_LEN
    from zplatform.recorder import server as rs
    from zplatform.recorder.format import REQUEST

    s = lone_session()
    server = _recorder_server(_LOADED["recovery_igniter"], s)
    t0 = time.monotonic()
    with caplog.at_level(logging.WARNING, logger="zplatform.recorder"):
        for q in [FakeQuery(p) for p in _junk(REQUEST.size + TAG_LEN, 2000)]:
            server.on_query(q)
        server.close()
        s.close()
    took = time.monotonic() - t0
    lines = [r.getMessage() for r in caplog.records if "recorder requests refused" in r.message]
    assert 1 <= len(lines) <= took / getattr(rs, "LOG_PERIOD_S", 1.0) + 2
    total = getattr(server, "refusals", -1)
    assert total == server.refused == 2000
    assert lines[-1].startswith(f"recorder requests refused: {total} so far")


def test_a_replayed_clock_query_never_reaches_the_servers_thread_again() -> None:
    """Issue 25 (the clock replay hole): the clock server kept the last 256
    nonces of each asker, so a keyless peer that saw a DN's clock queries
    (a queryable on the clock key) could replay an old one once the DN had
    sent 256 newer ones: answered again, through the server's thread. Now,
    after 300 genuine queries 100 ms apart (each answered), the replay of
    the first is dropped unanswered in zenoh's callback, counted once."""
    from tests.waits import wait_until
    from tests.zsession import lone_session
    from zplatform.core.auth import KeySet
    from zplatform.runtime.clocksync import ClockLink, ClockServer
    from zplatform.runtime.transport import KeySpace

    m = _LOADED["recovery_igniter"]
    keys = KeySet.from_master(m, bytes(range(32)))
    link = ClockLink(m, "dn0", keys.for_node("dn0"))
    now = [1_800_000_000 * 10**9]
    s = lone_session()
    server = ClockServer(s, KeySpace(m.vehicle), lambda: now[0], m, keys.for_node("cn"))
    try:
        first = FakeQuery(link.query(now[0])[0])
        genuine = [first]
        server.on_query(first)  # type: ignore[arg-type]
        for _ in range(300):
            now[0] += 100_000_000
            q = FakeQuery(link.query(now[0])[0])
            genuine.append(q)
            server.on_query(q)  # type: ignore[arg-type]
            # Served before the next (the backlog holds 64): the thread's pace.
            wait_until(lambda q=q: q.replies, 10, "the server's thread to answer")
        refused = server.refused
        replay = FakeQuery(first.payload.to_bytes())
        server.on_query(replay)  # type: ignore[arg-type]
    finally:
        server.close()  # joins the thread: what it was handed is served
        s.close()
    assert server.served == len(genuine) == 301
    assert all(len(q.replies) == 1 for q in genuine)
    assert replay.dropped and not replay.replies and not replay.errors
    assert server.refused - refused == 1
