"""The archive served over zenoh, in process (issue 25 leftover 6, issue 28):
the ask bound to the server's session (a recorded ask of an earlier session,
one tagged in run 0, a replay, a forgery: refused and counted), and the
bounds per asker (queries in hand, bytes per second: refused with the reason).

The server's thread is stopped; each test hands frames to its zenoh callback
and serves what it admitted here, in order: no network, no timing."""

from __future__ import annotations

import itertools
import struct
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pyarrow as pa
import pytest

from tests.payload import FakeQuery, FakeSession, deliver
from tests.unit.test_archive import T0, feed
from tests.zsession import lone_session
from zplatform.archive import Archive, ArchiveWriter, Query, RunInfo
from zplatform.archive.server import (
    ASK,
    ASK_MAGIC,
    ERROR,
    REPLY,
    RUNS,
    RUNS_SCHEMA,
    ArchiveAsk,
    ArchiveServer,
    EventsAsk,
    RunsAsk,
    ask_payload,
    runs_from_table,
)
from zplatform.core.auth import TAG_LEN, KeySet, Run
from zplatform.core.datavector import DataVector, Layout
from zplatform.errors import ArchiveError
from zplatform.mission.load import load_mission
from zplatform.telemetry.records import EventRecord

ROOT = Path(__file__).resolve().parents[2]
MISSION = load_mission(ROOT / "configs" / "flight.yaml", code=False)
KEYS = KeySet.from_master(MISSION, bytes.fromhex("8f" + "3a5c91e0b7d24f68" * 3 + "c1d2e3f4a5b6c7"))
S = 10**9
NONCES = itertools.count(1000)


class Clock:
    def __init__(self) -> None:
        self.t = 5 * S

    def __call__(self) -> int:
        return self.t


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("archive")
    w = ArchiveWriter(MISSION, Layout.for_node(MISSION, "cn"), d)
    feed(w, DataVector(Layout.for_node(MISSION, "cn")), range(1, 301))
    w.event(EventRecord(T0, "gn", 1, T0, "COMMAND", "cmd_sent", "command ARM sent"))
    w.event(EventRecord(T0 + 1, "cn", 2, T0, "WARNING_LO", "bad_frame", "a frame refused"))
    w.close()
    return d


def server(root: Path, clock: Clock, session_word: int = 11, **kw: Any) -> ArchiveServer:
    s = ArchiveServer(
        FakeSession(),  # type: ignore[arg-type]
        "rocket/archive/query",
        lambda: Archive(MISSION, root, recover=False),
        KEYS.channel("telemetry"),
        now_ns=clock,
        max_age_ns=kw.pop("max_age_ns", 60 * S),
        serve_bps=10**9,
        max_bytes=kw.pop("max_bytes", 1 << 20),
        session_word=session_word,
        **kw,
    )
    s.close()  # its thread: each test serves what is admitted, in order
    return s


class Station:
    """An asker: its own channel (the tool's key), its word."""

    def __init__(self, asker: int, keys: KeySet | None = None) -> None:
        self.keys = keys or KEYS.for_node("tool")
        self.asker = asker

    def new(self) -> ArchiveAsk:
        return ArchiveAsk(self.keys.channel("telemetry"), next(NONCES), asker=self.asker)

    def learn(self, srv: ArchiveServer) -> ArchiveAsk:
        """A new ask that learned ``srv``'s session (one hello)."""
        a = self.new()
        (q,) = deliver(srv, a.hello())
        assert len(q.replies) == 1 and a.on_reply(q.replies[0])
        assert a.session == srv.session.epoch
        return a


def answer(a: ArchiveAsk, q: FakeQuery) -> pa.Table:
    for r in q.replies:
        assert a.on_reply(r)
    return a.table()


Q = Query("cn_state,apogee_target_m", run=7, start="loop:10", end="loop:19")


def test_a_genuine_ask_is_answered_in_its_session(root: Path) -> None:
    clock = Clock()
    srv = server(root, clock)
    a = Station(1).learn(srv)
    (q,) = deliver(srv, a.ask(Q))
    t = answer(a, q)
    with Archive(MISSION, root) as local:
        assert t.equals(local.query(Q)) and t.num_rows == 10
    assert (srv.served, srv.hellos, srv.refused, srv.stale) == (1, 1, 0, 0)


def test_a_recorded_ask_of_an_earlier_session_is_refused_and_counted(root: Path) -> None:
    """The defect: the ground restarted (a new session); an ask recorded in
    the last one, replayed at once (its stamp or cookie still young), was
    answered. Now refused unanswered, counted stale once."""
    clock = Clock()
    old = server(root, clock, session_word=11)
    a = Station(1).learn(old)
    recorded = a.ask(Q)
    (q,) = deliver(old, recorded)
    assert answer(a, q).num_rows == 10
    new = server(root, clock, session_word=12)  # the ground node started again
    (q,) = deliver(new, recorded)
    assert q.replies == []
    assert (new.stale, new.refused, new.served) == (1, 1, 0)
    b = Station(1).learn(new)  # the asker asks again: answered
    (q,) = deliver(new, b.ask(Q))
    assert answer(b, q).num_rows == 10
    assert (new.stale, new.served) == (1, 1)


def test_an_ask_tagged_in_run_0_is_refused_and_counted(root: Path) -> None:
    """The defect itself: an ask tagged in no run (run 0) was taken. Now the
    session is the run word every ask must carry."""
    clock = Clock()
    srv = server(root, clock)
    ch = KEYS.for_node("tool").channel("telemetry")  # bound to no run: tags in run 0
    (q,) = deliver(srv, ask_payload(ch, Q, clock.t, 99, asker=1))
    assert q.replies == [] and (srv.stale, srv.refused, srv.served) == (1, 1, 0)
    ch.run = Run(12)  # another session's word: likewise
    (q,) = deliver(srv, ask_payload(ch, Q, clock.t, 98, asker=1))
    assert q.replies == [] and (srv.stale, srv.refused, srv.served) == (2, 2, 0)


def test_a_replayed_ask_in_its_session_is_refused_now_and_later(root: Path) -> None:
    clock = Clock()
    srv = server(root, clock, max_age_ns=60 * S)
    a = Station(1).learn(srv)
    p = a.ask(Q)
    q1, q2 = deliver(srv, p, p)
    assert answer(a, q1).num_rows == 10 and q2.replies == []
    assert (srv.stale, srv.served) == (1, 1)
    for _ in range(5000):  # more than it keeps: none is forgotten early
        srv._served[(clock.t, 7, len(srv._served) + 10**6)] = None
        if len(srv._served) >= 4096:
            break
    clock.t += 61 * S  # past its cookie: refused by its age, whatever is kept
    (q,) = deliver(srv, p)
    assert q.replies == [] and (srv.stale, srv.served) == (2, 1)


def test_a_forged_ask_is_refused_and_counted_as_bad(root: Path) -> None:
    clock = Clock()
    srv = server(root, clock)
    a = Station(1).learn(srv)
    good = a.ask(Q)
    flipped = good[:-1] + bytes([good[-1] ^ 1])
    stranger = Station(2, KeySet.generate(MISSION)).new()  # another mission's key
    stranger.session, stranger.cookie = srv.session.epoch, clock.t
    assert stranger._channel is not None
    stranger._channel.run = srv.session  # it even guessed the session
    qs = deliver(srv, flipped, stranger.ask(Q), stranger.hello())
    assert all(q.replies == [] for q in qs)
    # The stranger's two by their header tag on zenoh's thread (never in the
    # inbox), the spliced MAC by the serving thread.
    assert (srv.refused, srv.stale, srv._refused_early, srv._refused_checked) == (3, 0, 2, 1)
    assert (srv.served, srv.hellos) == (0, 1)


def test_an_answer_of_another_session_is_refused_by_the_asker(root: Path) -> None:
    clock = Clock()
    old, new = server(root, clock, session_word=11), server(root, clock, session_word=12)
    st = Station(1)
    a = st.learn(old)
    (q_old,) = deliver(old, a.ask(Q))
    b = st.learn(new)
    b.nonce = a.nonce  # the same nonce: only the session tells them apart
    assert not b.on_reply(q_old.replies[0]) and b.refused == 1
    (q,) = deliver(new, b.ask(Q))
    assert answer(b, q).num_rows == 10


def test_two_askers_each_bounded_in_queries_in_hand(root: Path) -> None:
    """per_asker 1: asker A's second ask in hand is answered with the reason;
    asker B's, in hand at the same time, is answered with rows."""
    clock = Clock()
    srv = server(root, clock, per_asker=1)
    a1, a2 = Station(1).learn(srv), Station(1).learn(srv)
    b = Station(2).learn(srv)
    qa1, qa2, qb = deliver(srv, a1.ask(Q), a2.ask(Q), b.ask(Q))
    assert answer(a1, qa1).num_rows == 10 and answer(b, qb).num_rows == 10
    with pytest.raises(Exception, match="1 queries in hand already"):
        answer(a2, qa2)
    assert (srv.over_bound, srv.served, srv.refused) == (1, 3, 0)
    a3 = Station(1).learn(srv)  # A's first is done: A may ask again
    (q,) = deliver(srv, a3.ask(Q))
    assert answer(a3, q).num_rows == 10 and srv.over_bound == 1 and srv._in_hand == {}


def test_two_askers_each_bounded_in_bytes_per_second(root: Path) -> None:
    """asker_bps: A's answers empty its bucket, A's next is refused with when
    to ask again; B is answered meanwhile; A is answered once it refilled."""
    clock = Clock()
    srv = server(root, clock, asker_bps=10_000, max_bytes=40_000)
    big = Query("*", run=7, start="loop:1", end="loop:3")  # one answer: most of the bucket
    a = Station(1)
    first = a.learn(srv)
    (q,) = deliver(srv, first.ask(big))
    n = sum(len(r) - REPLY.size - TAG_LEN for r in q.replies)
    assert answer(first, q).num_rows == 3 and 20_000 < n <= 40_000
    second = a.learn(srv)
    (q,) = deliver(srv, second.ask(big))
    with pytest.raises(Exception, match=r"10000 bytes/s per asker.*ask again in [0-9.]+ s"):
        answer(second, q)
    b = Station(2).learn(srv)
    (q,) = deliver(srv, b.ask(big))
    assert answer(b, q).num_rows == 3
    clock.t += 4 * S  # 40,000 bytes refilled: the bucket is full again
    third = a.learn(srv)
    (q,) = deliver(srv, third.ask(big))
    assert answer(third, q).num_rows == 3
    assert (srv.over_bound, srv.served, srv.refused) == (1, 4, 0)


def test_an_error_reply_is_one_tagged_frame_echoing_the_nonce(root: Path) -> None:
    clock = Clock()
    srv = server(root, clock)
    a = Station(1).learn(srv)
    (q,) = deliver(srv, a.ask(Query("cn_stat")))
    (r,) = q.replies
    body = bytes(KEYS.for_node("tool").channel("telemetry").open(r))
    kind, nonce, i, n = REPLY.unpack_from(body, 0)
    assert (kind, nonce, i, n) == (ERROR, a.nonce, 0, 1)
    assert b"did you mean" in body
    assert ASK.unpack_from(a.ask(Q), 0)[:2] == (ASK_MAGIC, 1)


# -- the run list and events (issue 28) -------------------------------------------------


def test_the_run_list_is_answered_as_exact_rows(root: Path) -> None:
    """The defect: the server answered queries only (the console's remote
    run picker said "not served"). Now a RUNS ask is answered with
    Archive.runs() as rows, read back into the same run records."""
    clock = Clock()
    srv = server(root, clock)
    a = Station(1).learn(srv)
    (q,) = deliver(srv, a.ask(RunsAsk()))
    t = answer(a, q)
    assert t.schema.equals(RUNS_SCHEMA)
    # Every field of the run record is a column (a field added to RunInfo
    # and not here would be lost on the way): keep RUNS_SCHEMA in step.
    assert RUNS_SCHEMA.names == list(RunInfo.__struct_fields__)
    with Archive(MISSION, root) as local:
        want = local.runs()
    assert runs_from_table(t) == want and [r.run for r in want] == [7]
    assert (srv.served, srv.refused, srv.stale) == (1, 0, 0)


def test_events_are_answered_as_exact_rows_and_filtered_by_severity(root: Path) -> None:
    clock = Clock()
    srv = server(root, clock)
    st = Station(1)
    with Archive(MISSION, root) as local:
        every, infos = local.events(7), local.events(7, severity=["COMMAND"])
    assert every.num_rows > infos.num_rows > 0
    a = st.learn(srv)
    (q,) = deliver(srv, a.ask(EventsAsk(run=7)))
    assert answer(a, q).equals(every)
    b = st.learn(srv)
    (q,) = deliver(srv, b.ask(EventsAsk(severity=["command"])))  # the last run
    assert answer(b, q).equals(infos)
    c = st.learn(srv)
    (q,) = deliver(srv, c.ask(EventsAsk(severity=["WARN"])))
    with pytest.raises(ArchiveError, match="no severity 'WARN'"):
        answer(c, q)
    assert (srv.served, srv.refused) == (3, 0)


def test_a_replayed_runs_or_events_ask_is_refused(root: Path) -> None:
    clock = Clock()
    srv = server(root, clock)
    st = Station(1)
    for ask in (RunsAsk(), EventsAsk(run=7)):
        a = st.learn(srv)
        p = a.ask(ask)
        q1, q2 = deliver(srv, p, p)
        assert answer(a, q1).num_rows > 0 and q2.replies == []
    assert (srv.stale, srv.refused, srv.served) == (2, 2, 2)
    new = server(root, clock, session_word=12)  # another session: refused as well
    (q,) = deliver(new, p)
    assert q.replies == [] and (new.stale, new.served) == (1, 0)


def test_an_ask_of_an_unknown_kind_is_refused_with_its_reason(root: Path) -> None:
    clock = Clock()
    srv = server(root, clock)
    a = Station(1).learn(srv)
    assert a._channel is not None
    (q,) = deliver(srv, ask_payload(a._channel, RunsAsk(), a.cookie, a.nonce, asker=1, kind=9))
    with pytest.raises(
        ArchiveError, match=r"an ask of kind 9, which this station does not serve \(1 query"
    ):
        answer(a, q)
    b = Station(1).learn(srv)  # a runs ask whose body is a query's: refused, said why
    assert b._channel is not None
    (q,) = deliver(srv, ask_payload(b._channel, Q, b.cookie, b.nonce, asker=1, kind=RUNS))
    with pytest.raises(ArchiveError, match="unknown field"):
        answer(b, q)
    assert (srv.served, srv.refused, srv.stale) == (2, 0, 0)


def test_a_run_list_or_events_over_the_answer_bound_are_refused_with_what_to_do(
    root: Path,
) -> None:
    clock = Clock()
    srv = server(root, clock, max_bytes=500)
    st = Station(1)
    a, b = st.learn(srv), st.learn(srv)
    qa, qb = deliver(srv, a.ask(RunsAsk()), b.ask(EventsAsk()))
    with pytest.raises(ArchiveError, match=r"more than this station serves \(500\): the run list"):
        answer(a, qa)
    with pytest.raises(ArchiveError, match=r"serves \(500\): ask fewer severities"):
        answer(b, qb)
    assert (srv.served, srv.refused) == (2, 0)


def test_the_bounds_apply_to_runs_and_events(root: Path) -> None:
    """per_asker and asker_bps hold for every kind: A's second ask in hand
    (events) is refused with the reason; an asker whose events emptied its
    bucket is refused them again with when to ask again."""
    clock = Clock()
    srv = server(root, clock, per_asker=1)
    a1, a2, b = Station(1).learn(srv), Station(1).learn(srv), Station(2).learn(srv)
    qa1, qa2, qb = deliver(srv, a1.ask(RunsAsk()), a2.ask(EventsAsk()), b.ask(EventsAsk()))
    assert answer(a1, qa1).num_rows == 1 and answer(b, qb).num_rows > 0
    with pytest.raises(ArchiveError, match="1 queries in hand already"):
        answer(a2, qa2)
    assert srv.over_bound == 1
    n = sum(len(r) - REPLY.size - TAG_LEN for r in qb.replies)  # the events' answer
    tight = server(root, clock, asker_bps=1, max_bytes=n)  # a bucket of one answer
    st = Station(3)
    first = st.learn(tight)
    (q,) = deliver(tight, first.ask(EventsAsk()))
    assert answer(first, q).num_rows == 2
    second = st.learn(tight)
    (q,) = deliver(tight, second.ask(EventsAsk(run=7)))
    with pytest.raises(ArchiveError, match=r"1 bytes/s per asker.*ask again in"):
        answer(second, q)
    assert (tight.over_bound, tight.served) == (1, 2)


def test_the_cli_prints_runs_and_events_asked_remotely_as_it_prints_them_locally(
    root: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``zplatform archive MISSION runs|events --remote``: a tool's link (its
    keys) asks the server; what it prints equals the local action's output."""
    import zplatform.archive.server as server_mod
    import zplatform.ground.link as link_mod
    from zplatform.cli.main import main

    clock = Clock()
    srv = server(root, clock)
    closed: list[bool] = []

    class Link:  # GroundLink as ask_remote uses it: a tool's keys, no network
        def __init__(self, mission: Any, **kw: Any) -> None:
            self.ns = SimpleNamespace(session=None)
            self.keys = SimpleNamespace(archive="rocket/archive/query")
            self.link_keys = KEYS.for_node("tool")

        def close(self) -> None:
            closed.append(True)

    def remote_query(session: Any, key: str, ch: Any, ask: Any, **kw: Any) -> pa.Table:
        a = ArchiveAsk(ch, kw["nonce"], asker=5)
        (q,) = deliver(srv, a.hello())
        assert a.on_reply(q.replies[0])
        (q,) = deliver(srv, a.ask(ask))
        return answer(a, q)

    monkeypatch.setattr(link_mod, "GroundLink", Link)
    monkeypatch.setattr(server_mod, "remote_query", remote_query)
    flight = str(ROOT / "configs" / "flight.yaml")
    for action in (
        ["runs", "--json"],
        ["events", "--run", "7"],
        ["events", "--severity", "COMMAND"],
    ):
        assert main(["archive", flight, "--dir", str(root), *action]) == 0
        local = capsys.readouterr().out
        assert main(["archive", flight, *action, "--remote", "--timeout", "1"]) == 0
        assert capsys.readouterr().out == local and local.count("\n") >= 1
    assert len(closed) == 3 and (srv.served, srv.refused) == (3, 0)
    assert main(["archive", flight, "events", "--severity", "WARN", "--remote"]) == 2
    err = capsys.readouterr().err  # the station's reason, one line
    assert err == "zplatform: error: the station refused the query: no severity 'WARN'\n"


# -- the per-asker bound counts tagged asks only (issue 25) ------------------------------


def test_a_keyless_peer_using_a_stations_asker_word_cannot_spend_its_bound(root: Path) -> None:
    """The defect: the per-asker bound counted asks by their asker word
    before the tag, so a keyless peer that read station A's word put junk
    in hand under it and A's genuine ask, in hand at the same time, was
    refused "N queries in hand already". Now only an ask whose tag checks
    counts: the junk waits in the inbox (the global bound), is refused
    unanswered, and A is answered with rows."""
    clock = Clock()
    srv = server(root, clock, per_asker=1)
    a = Station(1).learn(srv)
    genuine = a.ask(Q)
    # Junk with A's asker word (read off the wire), untagged and forged-tagged.
    forged = ask_payload(None, Q, a.cookie, 4242, asker=1) + bytes(TAG_LEN)
    qj1, qj2, qa = deliver(srv, forged, forged[:-1] + b"\x01", genuine)
    assert qj1.replies == [] and qj2.replies == []
    assert answer(a, qa).num_rows == 10
    assert (srv.over_bound, srv.served, srv.refused) == (0, 1, 2)
    assert srv._in_hand == {} and srv._counted == {}


def test_tagged_asks_still_count_against_their_askers_bound(root: Path) -> None:
    """The bound holds for genuine asks whatever junk came before."""
    clock = Clock()
    srv = server(root, clock, per_asker=1)
    a1, a2 = Station(1).learn(srv), Station(1).learn(srv)
    junk = ask_payload(None, Q, a1.cookie, 77, asker=1) + bytes(TAG_LEN)
    _, q1, q2 = deliver(srv, junk, a1.ask(Q), a2.ask(Q))
    assert answer(a1, q1).num_rows == 10
    with pytest.raises(ArchiveError, match="1 queries in hand already"):
        answer(a2, q2)
    assert (srv.over_bound, srv.refused) == (1, 1)


# -- an ask or hello of another version: one clear error (issue 28) ----------------------


def _old_ask(a: ArchiveAsk, magic: bytes = b"ZAQ2") -> bytes:
    """An ask as a zplatform of another version makes it (ZAQ2: magic, asker,
    nonce, cookie, then the query's JSON; no kind byte), tagged in the session."""
    import msgspec

    assert a._channel is not None
    body = struct.pack("<4sQQq", magic, a.asker, a.nonce, a.cookie) + msgspec.json.encode(Q)
    return bytes(a._channel.seal(body))


def test_an_ask_of_another_version_gets_one_clear_error_reply(root: Path) -> None:
    """The defect: a tool of the previous version (ZAQ2) asking this ground
    got no answer at all (refused unanswered as "not an archive ask"), and
    waited out its timeout. Now one ERROR reply, tagged, echoing its nonce,
    says which versions; the old asker's own checks take it."""
    clock = Clock()
    srv = server(root, clock)
    a = Station(1).learn(srv)
    (q,) = deliver(srv, _old_ask(a))
    (r,) = q.replies
    assert a.on_reply(r)  # a ZAQ2 asker takes it too: the reply format is unchanged
    with pytest.raises(
        ArchiveError, match=r"archive ask version 2 not served; this ground serves ZAQ3"
    ):
        a.table()
    assert (srv.other_version, srv.served, srv.refused) == (1, 1, 0)


def test_version_error_replies_are_rate_bounded_and_need_a_tag(root: Path) -> None:
    clock = Clock()
    srv = server(root, clock)
    st = Station(1)
    a, b, c = st.learn(srv), st.learn(srv), st.learn(srv)
    qa, qb = deliver(srv, _old_ask(a), _old_ask(b, b"ZAQ9"))
    assert len(qa.replies) == 1 and qb.replies == []  # one a second
    assert (srv.other_version, srv.refused) == (2, 1)
    # An untagged one (a keyless peer) is refused before its magic is read.
    untagged = struct.pack("<4sQQq", b"ZAQ2", 1, 5, clock.t) + b"{}"
    clock.t += 2 * S
    (qu,) = deliver(srv, untagged + bytes(TAG_LEN))
    assert qu.replies == [] and srv.other_version == 2
    (qc,) = deliver(srv, _old_ask(c, b"ZAQ4"))  # a second later: answered again
    assert c.on_reply(qc.replies[0])
    with pytest.raises(ArchiveError, match="archive ask version 4 not served"):
        c.table()


def test_a_hello_of_another_version_gets_one_clear_error_and_the_asker_says_so(
    root: Path,
) -> None:
    """A newer ground answers this version's hello with one error reply
    (simulated here by a hello of magic ZAH9 to this one): the asker turns
    it into the station's reason, not a timeout."""
    clock = Clock()
    srv = server(root, clock)
    a = Station(1).new()
    assert a._channel is not None
    hello = bytes(a._channel.seal(struct.pack("<4sQQ", b"ZAH9", a.asker, a.hello_nonce)))
    (q,) = deliver(srv, hello)
    (r,) = q.replies
    assert a.on_reply(r) and a.session is None
    assert a.error is not None and "archive hello version 9 not served" in a.error


def test_the_client_turns_no_answer_into_a_clear_error(root: Path) -> None:
    """remote_query against a station that answers nothing (an older ground
    refuses a newer ask unanswered): an ArchiveError (a ZPlatformError)
    that names the version it asks in, not a bare timeout."""
    from zplatform.archive.server import remote_query
    from zplatform.errors import ZPlatformError

    session = lone_session()  # nobody serves the archive: the get ends unanswered
    try:
        with pytest.raises(ZPlatformError, match=r"does not answer this one's hello \(ZAH2\)"):
            remote_query(
                session,
                "rocket/archive/query",
                KEYS.for_node("tool").channel("telemetry"),
                Q,
                nonce=1,
                timeout_s=5.0,
            )
    finally:
        session.close()


def test_a_junk_or_replayed_ask_is_refused_without_a_mac_over_its_body(
    root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Header first (codecs/FORMAT.md §6.1): an ask's fixed fields (asker,
    nonce, cookie) are within the header tag's bytes, so a replay and junk
    are refused before the MAC over the ask's body (its JSON)."""
    import os

    from zplatform.core import auth

    clock = Clock()
    srv = server(root, clock)
    a = Station(1).learn(srv)
    p = a.ask(Q)
    (q1,) = deliver(srv, p)
    assert answer(a, q1).num_rows == 10
    macs = [0]
    real = auth._RunKey.mac

    def counted(self: Any, frame: bytes | bytearray | memoryview) -> bytes:
        macs[0] += len(frame) == len(p) - TAG_LEN  # an ask's body, not a reply's
        return real(self, frame)

    monkeypatch.setattr(auth._RunKey, "mac", counted)
    junk = p[:4] + os.urandom(len(p) - 4)  # an ask's magic, then junk
    qs = deliver(srv, p, junk, p, junk)
    assert all(q.replies == [] for q in qs)
    assert macs[0] == 0
    assert (srv.stale, srv.served) == (2, 1)


# -- the inbox holds only frames that can be served (issue 25) ---------------------------


def test_a_keyless_flood_never_takes_the_inbox_a_stations_ask_needs(root: Path) -> None:
    """Issue 25: the inbox's bound (MAX_PENDING, anyone's) came before the
    tag, so a keyless flood of ask-sized junk filled it and a station's
    genuine ask, at the same time, was dropped unanswered (``busy``). Now
    zenoh's callback checks the header tag first: the junk is refused and
    counted there, never in hand, and the station is answered."""
    import os

    from zplatform.archive.server import MAX_PENDING

    clock = Clock()
    srv = server(root, clock)
    a = Station(1).learn(srv)
    genuine = a.ask(Q)
    junk = [genuine[:4] + os.urandom(len(genuine) - 4) for _ in range(4 * MAX_PENDING)]
    *qj, qa = deliver(srv, *junk, genuine)
    assert qa.replies and answer(a, qa).num_rows == 10
    assert all(q.dropped and not q.replies for q in qj)
    assert (srv.busy, srv.refused, srv._refused_early, srv.served) == (0, len(junk), len(junk), 1)


def test_replayed_asks_never_take_the_inbox_a_stations_ask_needs(root: Path) -> None:
    """The same for a replayer: asks recorded in an earlier session, an
    ask of this one answered before, and a hello answered before, are
    refused as stale by their header (the run word, cookie, asker and nonce
    are within the header tag's bytes) on zenoh's thread, never in hand,
    and a station's new ask is answered."""
    from zplatform.archive.server import MAX_PENDING

    clock = Clock()
    old = server(root, clock, session_word=11)
    b = Station(2).learn(old)
    recorded = b.ask(Q)
    new = server(root, clock, session_word=12)
    a = Station(1).learn(new)
    first = a.ask(Q)
    (q1,) = deliver(new, first)
    assert answer(a, q1).num_rows == 10
    a = Station(1).learn(new)
    hello = Station(3).new().hello()
    (qh,) = deliver(new, hello)
    assert len(qh.replies) == 1
    replays = [recorded, first, hello] * (2 * MAX_PENDING)
    *qr, qa = deliver(new, *replays, a.ask(Q))
    assert qa.replies and answer(a, qa).num_rows == 10
    assert all(q.dropped and not q.replies for q in qr)
    assert (new.busy, new.stale, new.served, new.hellos) == (0, len(replays), 2, 3)


def _station_link(
    monkeypatch: pytest.MonkeyPatch, srv: ArchiveServer, flood: Any, lost: Any = None
) -> None:
    """zenoh for ``_ask_station``: the get is served by ``srv`` at once and
    ``flood(genuine)`` lists what reaches the reply callback, in order.
    ``lost(payload)``: ``"get"`` loses the get on its way (the station never
    sees it), ``"answer"`` the station's answer (it served it); either way
    nothing comes back and the get does not end (zenoh ends it at its
    timeout); None: neither."""
    import zplatform.runtime.queries as queries

    def ask(_s: Any, _k: str, handler: Any, *, payload: bytes, **_kw: Any) -> None:
        on_reply, on_done = handler
        what = lost(payload) if lost is not None else None
        if what == "get":
            return
        (q,) = deliver(srv, payload)
        if what == "answer":
            return
        for data in flood(q.replies):
            ok = SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda d=data: d))
            on_reply(SimpleNamespace(ok=ok))
        on_done()

    monkeypatch.setattr(queries, "replies", lambda on_reply, on_done: (on_reply, on_done))
    monkeypatch.setattr(queries, "ask", ask)


def test_a_junk_flood_before_and_among_the_answer_never_pushes_it_out(
    root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 25: zenoh's callback screens each reply to an ask (size, header
    tag, the session, the ask's nonce, kind, index) before its mailbox, so
    70,000 junk replies (more than the 65,536 places it has) before and
    among the station's answer push none of it out; each is counted once."""
    from zplatform.archive.server import DATA, _ask_station

    srv = server(root, Clock())
    a = Station(1).learn(srv)
    other_key = KeySet.from_master(MISSION, bytes(32)).channel("telemetry", Run(a.session))
    old_session = KEYS.channel("telemetry", Run(a.session + 1))  # an earlier session's
    genuine_ch = KEYS.channel("telemetry", Run(a.session))
    head = REPLY.pack(DATA, a.nonce, 0, 1)
    junk = [
        b"",
        bytes(200),  # no tag
        bytes(other_key.seal(head + b"forged")),  # a keyless peer's
        bytes(old_session.seal(head + b"replayed")),  # another session's
        bytes(genuine_ch.seal(REPLY.pack(DATA, a.nonce + 1, 0, 1) + b"x")),  # another ask's
    ]
    n_junk = 70_000
    flood = [junk[i % len(junk)] for i in range(n_junk)]
    _station_link(monkeypatch, srv, lambda genuine: [*flood[:1000], *genuine, *flood[1000:]])
    _ask_station(None, "rocket/archive/query", a, a.ask(Q), 1.0, lambda: a.done)  # type: ignore[arg-type]
    with Archive(MISSION, root) as local:
        assert a.table().equals(local.query(Q))
    assert a.refused == n_junk


def test_an_asks_mailbox_is_bounded_by_bytes(root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Replies that pass the screen (the answer's own chunk, replayed) hold
    at most REPLY_BACKLOG_BYTES in the mailbox: the rest are refused in
    zenoh's callback, counted in ``dropped``."""
    import zplatform.archive.server as server_mod

    srv = server(root, Clock())
    a = Station(1).learn(srv)

    def flood(genuine: list[bytes]) -> list[bytes]:
        (chunk,) = genuine
        monkeypatch.setattr(server_mod, "REPLY_BACKLOG_BYTES", 3 * len(chunk))
        return [chunk] * 10

    _station_link(monkeypatch, srv, flood)
    server_mod._ask_station(None, "k", a, a.ask(Q), 1.0, lambda: a.done)  # type: ignore[arg-type]
    assert a.table().num_rows == 10
    # 3 held (the answer, then its index twice again, never read: done), 7 refused
    assert (a.dropped, a.refused) == (7, 0)


@pytest.mark.parametrize("lost", ["hello", "hello answer"])
def test_a_hello_lost_on_the_way_is_sent_again_and_answered(
    root: Path, monkeypatch: pytest.MonkeyPatch, lost: str
) -> None:
    """A hello or its answer zenoh DROPped on a congested link (nothing
    comes back and the get does not end before its timeout) cost the asker
    RESEND_AFTER_S, not the whole timeout, which used to end in "no station
    answered": the hello goes again under a fresh nonce, and the query is
    answered, the station serving one ask and refusing nothing."""
    from zplatform.archive.server import HELLO_MAGIC, remote_query

    srv = server(root, Clock())
    calls: list[str] = []

    def lose(payload: bytes) -> str | None:  # the first hello, or its answer
        kind = "hello" if payload[:4] == HELLO_MAGIC else "ask"
        calls.append(kind)
        if calls.count(kind) > 1 or kind != "hello":
            return None
        return "answer" if lost == "hello answer" else "get"

    _station_link(monkeypatch, srv, lambda genuine: genuine, lose)
    got = remote_query(
        None,  # type: ignore[arg-type]
        "rocket/archive/query",
        KEYS.for_node("tool").channel("telemetry"),
        Q,
        nonce=next(NONCES),
        timeout_s=30.0,
    )
    with Archive(MISSION, root) as local:
        assert got.equals(local.query(Q))
    assert calls == ["hello", "hello", "ask"]
    assert srv.hellos == (2 if lost == "hello answer" else 1)
    assert srv.served == 1 and srv.refused == 0


def test_an_ask_is_sent_once_and_its_loss_is_said(
    root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The ask is never copied (the station would count a genuine asker's
    copy among its replays once it served the first): a lost ask ends in
    the clear "no station answered the ask" at its timeout, one get."""
    from zplatform.archive.server import ASK_MAGIC, remote_query

    srv = server(root, Clock())
    calls: list[bytes] = []

    def lose(payload: bytes) -> str | None:
        calls.append(payload[:4])
        return "get" if payload[:4] == ASK_MAGIC else None

    _station_link(monkeypatch, srv, lambda genuine: genuine, lose)
    with pytest.raises(ArchiveError, match="no station answered the ask on rocket/archive/query"):
        remote_query(
            None,  # type: ignore[arg-type]
            "rocket/archive/query",
            KEYS.for_node("tool").channel("telemetry"),
            Q,
            nonce=next(NONCES),
            timeout_s=1.0,
        )
    assert calls.count(ASK_MAGIC) == 1 and srv.served == 0 and srv.refused == 0
