"""zplatform.runtime.clocksync without a network: the estimator a mission picks, its
fallback, and both estimators against a simulated CN whose clocks are known.

:class:`SimSession` stands in for the DN's zenoh session: each ``get`` runs
one exchange with the CN's :class:`~zplatform.runtime.clocksync.ClockServer` on a
simulated true time, stamping the node clocks and (when instrumented) zenoh's
four time points the way the real ones are taken: ``t1`` before zenoh's send
stamp, ``t2`` after its receive stamp, ``t3`` before the reply's send stamp,
``t4`` (in the reply callback) after the reply's receive stamp.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_args, get_type_hints

import pytest
import zenoh

from zplatform.config import ClockConfig
from zplatform.core.auth import NO_RUN, Channel, KeySet, Run
from zplatform.errors import ClockSyncError
from zplatform.mission.load import load_mission
from zplatform.runtime.clocksync import (
    ADAPT_AFTER,
    ADAPT_FACTOR,
    ADAPT_FLOOR_S,
    ESTIMATORS,
    ClockEstimate,
    ClockEstimator,
    ClockLink,
    ClockResponder,
    ExchangeTimeout,
    ZenohTimestampsError,
    estimate_offset,
    estimate_offset_zenoh,
    estimator_for,
)
from zplatform.runtime.transport import KeySpace

ROOT = Path(__file__).resolve().parents[2]
IGNITER = load_mission(ROOT / "configs" / "recovery_igniter.yaml")
MASTER = bytes.fromhex("3f8a1c9e27d45b60f1e83a97c2d0456b8e19f7a3c5d2e0b4a6918f3c7e25d0b1")
ALL_KEYS = KeySet.from_master(IGNITER, MASTER)
KEYS = KeySpace("rocket")
US = 1_000
MS = 1_000_000


def _link(dn: str = "dn0") -> ClockLink:
    return ClockLink(IGNITER, dn, ALL_KEYS.for_node(dn))


def _responder() -> ClockResponder:
    return ClockResponder(IGNITER, ALL_KEYS.for_node("cn"))


@dataclass
class _Ntp:
    ns: int

    def as_nanos(self) -> int:
        return self.ns


@dataclass
class _Ts:
    ns: int

    def get_time_as_ntp64(self) -> _Ntp:
        return _Ntp(self.ns)


@dataclass
class _Record:
    ns: int

    def timestamp(self) -> _Ts:
        return _Ts(self.ns)


@dataclass
class _Payload:
    raw: bytes

    def __len__(self) -> int:
        return len(self.raw)

    def to_bytes(self) -> bytes:
        return self.raw


@dataclass
class _Stack:
    records: list[_Record]


@dataclass
class _Sample:
    payload: _Payload
    timestamp_stack: _Stack | None


@dataclass
class _Reply:
    ok: _Sample | None
    replier_id: str = "cn"  # zenoh's id of the answering queryable


class _Blocked(Exception):
    """What the simulated zenoh does where the real one would block the thread."""


Rogue = Callable[[bytes, int], bytes | None]
"""A peer answering the clock key too: (the DN's query, the true time) -> its reply."""


@dataclass
class SimSession:
    """Clocks as offsets from a simulated true time ``t`` (ns); the CN
    answers through the real :class:`ClockResponder`.

    ``stamps``: whether the CN's zenoh stamps instrumented queries.
    ``step_dn_zenoh_after``: after that many exchanges the DN's zenoh clock
    (the host's real-time clock) steps by ``step_ns``.
    ``answer``: whether the CN answers at all. ``rogues``: other peers on
    the clock key, answering before the CN (``rogues_first``, each
    ``flood`` times) or after it. ``congested``: the link stopped draining
    (no query gets through; a BLOCKing get raises :class:`_Blocked`).
    ``lost``: the gets (counted from 1) whose reply never arrives.
    ``kwargs``: each get's options.
    """

    cn_node: int = 0
    cn_zenoh: int = 0
    dn_node: int = 0
    dn_zenoh: int = 0
    stamps: bool = True
    answer: bool = True
    step_dn_zenoh_after: int | None = None
    step_ns: int = 1_000_000_000
    t: int = 1_000_000_000_000
    gets: int = 0
    instrumented: list[bool] = field(default_factory=list)
    targets: list[Any] = field(default_factory=list)
    rogues: list[Rogue] = field(default_factory=list)
    rogues_first: bool = True
    flood: int = 1
    congested: bool = False
    lost: set[int] = field(default_factory=set)
    kwargs: list[dict[str, Any]] = field(default_factory=list)
    responder: ClockResponder = field(default_factory=_responder)

    def now_ns(self) -> int:
        """The DN's node clock."""
        return self.t + self.dn_node

    def get(self, key: Any, handler: Any, *, payload: bytes, **kw: Any) -> None:
        self.gets += 1
        self.kwargs.append(kw)
        if self.congested:
            # A link that stopped draining: zenoh blocks a BLOCKing get for
            # seconds (a stalled thread); a DROPped one is lost, and zenoh
            # ends it at its timeout (here: later than the asker waits).
            if kw.get("congestion_control") != zenoh.CongestionControl.DROP:
                raise _Blocked("a BLOCKing get on a congested link stalls the asking thread")
            return
        if self.gets in self.lost:  # its reply DROPped on the way: zenoh ends it at its timeout
            return
        ti = kw.get("timestamp_instrumentation")
        self.instrumented.append(ti is not None)
        self.targets.append(kw.get("target"))
        if self.step_dn_zenoh_after is not None and self.gets == self.step_dn_zenoh_after + 1:
            self.dn_zenoh += self.step_ns
        rogue = [
            (f"rogue{k}", r)
            for k, r in enumerate(f(payload, self.t) for f in self.rogues)
            if r is not None
        ]
        if self.rogues_first:
            for who, raw in rogue:
                for _ in range(self.flood):
                    handler.callback(_Reply(_Sample(_Payload(raw), None), who))
        if self.answer:
            self._cn(handler, payload, ti)
        if not self.rogues_first:
            for who, raw in rogue:
                handler.callback(_Reply(_Sample(_Payload(raw), None), who))
        handler.drop()

    def _cn(self, handler: Any, payload: bytes, ti: Any) -> None:
        self.t += 2 * US
        t1z = self.t + self.dn_zenoh  # send stamp, after t1
        self.t += 50 * US  # network
        t2z = self.t + self.cn_zenoh  # receive stamp
        self.t += 3 * US
        t2 = self.t + self.cn_node  # ClockServer callback
        self.t += 20 * US  # server thread hand-off
        t3 = self.t + self.cn_node
        self.t += 2 * US
        t3z = self.t + self.cn_zenoh  # reply's send stamp, after t3
        self.t += 50 * US  # network
        t4z = self.t + self.dn_zenoh  # reply's receive stamp
        self.t += 3 * US  # then the callback reads t4
        reply = self.responder.answer(payload, t2, t3)
        if reply is None:
            handler.callback(_Reply(None))  # the server's error reply
            return
        stack = None
        if ti is not None:
            stack = _Stack([_Record(x) for x in (t1z, t2z, t3z, t4z)] if self.stamps else [])
        handler.callback(_Reply(_Sample(_Payload(reply), stack)))


def _sim(**kw: Any) -> SimSession:
    return SimSession(cn_node=7_000_000, cn_zenoh=-3_000_000, dn_node=-42_000_000, **kw)


# -- estimator_for ---------------------------------------------------------------


def test_estimator_for_picks_zenoh_ts_by_default() -> None:
    est = estimator_for(ClockConfig())
    assert est.name == "zenoh_ts"
    assert est.primary is estimate_offset_zenoh
    assert est.fallback is estimate_offset


def test_estimator_for_picks_node_clock() -> None:
    est = estimator_for(ClockConfig(estimator="node_clock"))
    assert est.name == "node_clock"
    assert est.primary is estimate_offset
    assert est.fallback is None


def test_every_config_name_has_an_estimator() -> None:
    names = get_args(get_type_hints(ClockConfig)["estimator"])
    assert set(names) == set(ESTIMATORS)
    for name in names:
        assert estimator_for(ClockConfig(estimator=name)).primary is ESTIMATORS[name]


# -- both estimators on the simulated CN -----------------------------------------


@pytest.mark.parametrize("fn", [estimate_offset, estimate_offset_zenoh])
def test_estimators_measure_the_node_clock_offset(fn: Any) -> None:
    s = _sim()
    est = fn(s, KEYS, s.now_ns, _link(), exchanges=20)
    assert est.exchanges == 20
    # CN - DN node clocks: exact on this symmetric path (to rounding).
    assert abs(est.offset_ns - (s.cn_node - s.dn_node)) <= 1, est


def test_estimators_label_their_estimates() -> None:
    s = _sim()
    assert estimate_offset(s, KEYS, s.now_ns, _link(), exchanges=8).estimator == "node_clock"
    assert estimate_offset_zenoh(s, KEYS, s.now_ns, _link(), exchanges=8).estimator == "zenoh_ts"


def test_zenoh_ts_without_stamps_is_a_zenoh_timestamps_error() -> None:
    s = _sim(stamps=False)
    with pytest.raises(ZenohTimestampsError, match="answered 20 of 20 exchanges, but only 0"):
        estimate_offset_zenoh(s, KEYS, s.now_ns, _link(), exchanges=20)


def test_zenoh_ts_with_a_stepped_host_clock_is_a_zenoh_timestamps_error() -> None:
    s = _sim(step_dn_zenoh_after=10)
    with pytest.raises(
        ZenohTimestampsError,
        match=r"the DN's zenoh clock and node clock disagree by [\d.]+ us over the exchanges' "
        r"[\d.]+ s \(a host clock stepped, or slewed",
    ):
        estimate_offset_zenoh(s, KEYS, s.now_ns, _link(), exchanges=20)


def test_zenoh_ts_unreachable_cn_is_a_plain_clock_sync_error() -> None:
    s = _sim(answer=False)
    with pytest.raises(ClockSyncError) as info:
        estimate_offset_zenoh(s, KEYS, s.now_ns, _link(), exchanges=8, timeout_s=0.001)
    assert not isinstance(info.value, ZenohTimestampsError)


# -- the fallback ----------------------------------------------------------------


def test_zenoh_ts_falls_back_to_node_clock_with_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    s = _sim(stamps=False)
    est = estimator_for(ClockConfig())
    with caplog.at_level(logging.INFO, logger="zplatform.clocksync"):
        first = est(s, KEYS, s.now_ns, _link(), exchanges=20)
        second = est(s, KEYS, s.now_ns, _link(), exchanges=20)
    assert first.estimator == second.estimator == "node_clock"
    assert abs(first.offset_ns - (s.cn_node - s.dn_node)) <= 1
    assert est.fallbacks == 2
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1  # once, when calls start falling back
    assert "falling back to the node-clock estimator" in warned[0].getMessage()
    # zenoh_ts again once the CN's zenoh stamps (the fallback is per call).
    s.stamps = True
    with caplog.at_level(logging.INFO, logger="zplatform.clocksync"):
        assert est(s, KEYS, s.now_ns, _link(), exchanges=20).estimator == "zenoh_ts"
    assert "works again" in caplog.records[-1].getMessage()


@pytest.mark.parametrize(
    "fault", [{"stamps": False}, {"step_dn_zenoh_after": 10}], ids=["no-stamps", "stepped"]
)
def test_the_fallback_takes_the_same_exchanges_by_the_node_clock(fault: dict[str, Any]) -> None:
    """zenoh_ts failing (no stamps, or zenoh's clock stepped) falls back to
    the node-clock estimate of the exchanges it made, asking no second
    series: a start-up that fell back used to ask twice as many, which
    spent the clock server's rate bound for the asker (seen under a CPU
    hog: a device node restarted soon after could not start)."""
    s = _sim(**fault)
    est = estimator_for(ClockConfig())
    got = est(s, KEYS, s.now_ns, _link(), exchanges=20)
    assert (got.estimator, got.exchanges, s.gets, est.fallbacks) == ("node_clock", 20, 20, 1)
    assert abs(got.offset_ns - (s.cn_node - s.dn_node)) <= 1, got


def test_unreachable_cn_does_not_fall_back() -> None:
    s = _sim(answer=False)
    est = estimator_for(ClockConfig())
    with pytest.raises(ClockSyncError, match="instrumented replies"):
        est(s, KEYS, s.now_ns, _link(), exchanges=8, timeout_s=0.001)
    assert est.fallbacks == 0
    # One series, no second attempt; it stops once half cannot answer.
    assert s.gets == 5


def test_node_clock_never_asks_zenoh_for_timestamps() -> None:
    s = _sim()
    est = estimator_for(ClockConfig(estimator="node_clock"))
    assert est(s, KEYS, s.now_ns, _link(), exchanges=8).estimator == "node_clock"
    assert s.instrumented == [False] * 8


def test_failed_fallback_names_both() -> None:
    def no_stamps(*a: Any, **kw: Any) -> ClockEstimate:
        raise ZenohTimestampsError("no stamps")

    def unreachable(*a: Any, **kw: Any) -> ClockEstimate:
        raise ClockSyncError("clock sync got 0 of 8 replies")

    est = ClockEstimator("zenoh_ts", no_stamps, fallback=unreachable)
    with pytest.raises(ClockSyncError, match=r"0 of 8 replies \(after the zenoh_ts estimator: no"):
        est(_sim(), KEYS, _sim().now_ns, _link(), exchanges=8)


# -- authenticated exchanges (codecs/FORMAT.md §6.3) ------------------------------------

_Q = struct.Struct("<2sBB16sq")
_R = struct.Struct("<2sBB16sqqq")


def _rogue(shift_ns: int) -> Rogue:
    """A peer without the key: answers every query with the CN's time
    ``+ shift_ns``, echoing the query's nonce, under a made-up tag (the best
    it can do)."""

    def answer(query: bytes, true_t: int) -> bytes:
        _, _, index, nonce, t1 = _Q.unpack_from(query)
        cn_t = true_t + 7_000_000 + shift_ns
        return _R.pack(b"ZR", 1, index, nonce, t1, cn_t, cn_t + 20 * US) + bytes(16)

    return answer


@pytest.mark.parametrize("fn", [estimate_offset, estimate_offset_zenoh])
@pytest.mark.parametrize("shift_ns", [30 * MS, 5_000 * MS])
def test_a_rogue_clock_without_the_key_is_refused_and_counted(fn: Any, shift_ns: int) -> None:
    s = _sim(rogues=[_rogue(shift_ns)])
    link = _link()
    est = fn(s, KEYS, s.now_ns, link, exchanges=20)
    assert abs(est.offset_ns - (s.cn_node - s.dn_node)) <= 1, est  # the CN's, not the rogue's
    assert (link.refused_bad, link.refused_other) == (20, 0)
    # Every queryable on the clock key is asked: a rogue cannot take the CN's place.
    assert s.targets and all(t == zenoh.QueryTarget.ALL for t in s.targets)


def test_only_rogues_answering_is_a_clock_sync_error_that_says_so() -> None:
    s = _sim(answer=False, rogues=[_rogue(30 * MS)])
    with pytest.raises(ClockSyncError, match=r"0 of 8 valid replies .*5 replies refused for a bad"):
        estimate_offset(s, KEYS, s.now_ns, _link(), exchanges=8, timeout_s=0.001)


def test_a_replayed_real_reply_is_refused_and_counted() -> None:
    """A captured authentic reply of an earlier exchange, replayed into every
    later one: its nonce is another exchange's."""
    captured: list[bytes] = []
    real = _responder()

    def replay(query: bytes, true_t: int) -> bytes | None:
        if not captured:  # capture the CN's answer to the first query
            captured.append(bytes(real.answer(query, true_t, true_t + 5 * MS) or b""))
            return None
        return captured[0]

    s = _sim(rogues=[replay])
    link = _link()
    est = estimate_offset(s, KEYS, s.now_ns, link, exchanges=10)
    assert abs(est.offset_ns - (s.cn_node - s.dn_node)) <= 1
    assert (link.refused_bad, link.refused_other) == (0, 9)


def test_a_late_rogue_is_never_read() -> None:
    """A rogue answering after the CN: the exchange ends at the CN's answer;
    the rogue's reply is refused in zenoh's callback (its header tag,
    counted), never read by the exchange."""
    s = _sim(rogues=[_rogue(30 * MS)], rogues_first=False)
    link = _link()
    est = estimate_offset(s, KEYS, s.now_ns, link, exchanges=10)
    assert abs(est.offset_ns - (s.cn_node - s.dn_node)) <= 1
    assert link.refused == link.screened == 10


def test_the_cn_answers_only_its_dns_queries() -> None:
    cn = _responder()
    dn0, dn1 = _link("dn0"), _link("dn1")
    q, nonce = dn0.query(123)
    reply = cn.answer(q, 1000, 2000)
    assert reply is not None and dn0.check(reply, nonce) == (123, 1000, 2000)
    assert dn1.check(reply, nonce) is None and dn1.refused_bad == 1  # dn0's, not dn1's
    assert dn0.check(reply, b"\0" * 16) is None and dn0.refused_other == 1  # another exchange
    # A query claiming to be dn1's under dn0's tag; a made-up tag; junk.
    claim = bytearray(q)
    claim[3] = 1
    for bad in (bytes(claim), q[:-16] + bytes(16), b"", b"\x00" * 44, q[:-1]):
        assert cn.answer(bad, 1, 2) is None
    assert cn.refused == 5 and cn.reason
    # A peer holding only the ground's keys cannot even make a query.
    with pytest.raises(Exception, match="no key for link cn-dn0"):
        ClockLink(IGNITER, "dn0", ALL_KEYS.for_node("gn"))


def test_peers_with_another_mac_do_not_sync() -> None:
    hm = load_mission(ROOT / "configs" / "recovery_igniter.yaml")  # a copy of its own
    hm.security.mac = "hmac-sha256"
    link = ClockLink(hm, "dn0", KeySet.from_master(hm, MASTER).for_node("dn0"))
    q, _ = link.query(1)
    assert _responder().answer(q, 2, 3) is None  # the CN's MAC is blake3


# -- a slow, silent or flooding clock peer never holds the asking thread -----------------


@pytest.mark.parametrize("fn", [estimate_offset, estimate_offset_zenoh])
def test_a_congested_link_drops_clock_queries_and_counts_timeouts(fn: Any) -> None:
    """A peer that stops reading its link: every clock query is DROPped, never
    blocked on (zenoh's default for a get is BLOCK), and each exchange ends
    at its own timeout as a counted timeout, even though zenoh finalises
    none of them; the series stops once half can no longer answer."""
    s = _sim(congested=True)
    link = _link()
    with pytest.raises(ClockSyncError, match="0 of 8"):
        fn(s, KEYS, s.now_ns, link, exchanges=8, timeout_s=0.001)
    assert s.gets == 5 and link.timeouts == 5 and link.refused == 0
    for kw in s.kwargs:  # zplatform.runtime.queries.ask: the one way a query is sent
        assert kw["congestion_control"] == zenoh.CongestionControl.DROP
        assert kw["target"] == zenoh.QueryTarget.ALL
        assert kw["consolidation"] == zenoh.ConsolidationMode.NONE
        assert 0 < kw["timeout"] == 0.001


def test_an_exchange_timeout_follows_the_answered_round_trips() -> None:
    """The caller's timeout for the first ADAPT_AFTER exchanges, then twenty
    median round trips, at least the floor, never above the caller's; a
    miss counts as a trip of the time it waited."""
    t = ExchangeTimeout(1.0)
    for _ in range(ADAPT_AFTER - 1):
        t.answered(0, 130 * US)
        assert t.next_s() == 1.0
    t.answered(0, 130 * US)
    assert t.next_s() == ADAPT_FLOOR_S  # 20 x 130 us is below the floor
    slow = ExchangeTimeout(1.0)
    for rtt_ms in (9, 10, 10, 11, 10, 10, 400, 10, 10):  # one outlier: the median holds
        slow.answered(5_000, 5_000 + rtt_ms * 1_000_000)
    assert slow.next_s() == pytest.approx(ADAPT_FACTOR * 0.010)
    turned = ExchangeTimeout(1.0)  # fast answers, then a host too slow to answer in time
    for _ in range(ADAPT_AFTER):
        turned.answered(0, 130 * US)
    for _ in range(ADAPT_AFTER - 1):
        turned.missed(turned.next_s())
        assert turned.next_s() == ADAPT_FLOOR_S  # the median is still an answer
    turned.missed(turned.next_s())
    assert turned.next_s() == 1.0  # as many misses as answers: back to the caller's
    capped = ExchangeTimeout(0.15)
    for _ in range(ADAPT_AFTER):
        capped.answered(0, 10_000_000)  # 20 x 10 ms = 0.2 s, above the caller's 0.15 s
    assert capped.next_s() == 0.15


@pytest.mark.parametrize("fn", [estimate_offset, estimate_offset_zenoh])
def test_a_lost_clock_reply_costs_the_adapted_timeout_not_the_whole_one(fn: Any) -> None:
    """A reply DROPped on a busy link (zenoh ends its query only at its
    timeout): once ADAPT_AFTER exchanges were answered, each exchange waits
    the adapted timeout, so the lost one costs that, not the caller's 1 s;
    it is counted, and the estimate is of the rest."""
    s = _sim(lost={12})
    link = _link()
    est = fn(s, KEYS, s.now_ns, link, exchanges=20, timeout_s=1.0)
    timeouts = [kw["timeout"] for kw in s.kwargs]
    assert timeouts[:ADAPT_AFTER] == [1.0] * ADAPT_AFTER
    assert timeouts[ADAPT_AFTER:] == [ADAPT_FLOOR_S] * (20 - ADAPT_AFTER)  # sim round trip 130 us
    assert link.timeouts == 1 and est.exchanges == 19
    assert est.offset_ns == 49_000_000  # CN node clock minus the DN's (the sim's offsets)


@pytest.mark.parametrize("fn", [estimate_offset, estimate_offset_zenoh])
def test_a_flooding_rogue_gets_no_reply_read(fn: Any) -> None:
    """A peer without the key answers every query 2000 times before the CN:
    each of its replies is refused in zenoh's callback by its header tag
    (ClockLink.screen, counted), none reaches the exchange, and the CN's
    answer is the one taken."""
    s = _sim(rogues=[_rogue(30 * MS)], flood=2000)
    link = _link()
    est = fn(s, KEYS, s.now_ns, link, exchanges=20)
    assert abs(est.offset_ns - (s.cn_node - s.dn_node)) <= 1, est
    assert (link.refused_bad, link.refused_other, link.timeouts) == (20 * 2000, 0, 0)
    assert link.screened == 20 * 2000


def test_junk_replies_from_many_peers_never_crowd_out_the_cns() -> None:
    """Issue 25: an exchange's replies waited unchecked in a mailbox of
    CLOCK_REPLIERS_MAX + 1 (one per replier, the oldest let go), so keyless
    peers answering from more sessions right after the CN, before the
    exchange read it, pushed the CN's answer out and every exchange timed
    out (the node never synchronised). Now zenoh's callback screens each
    reply (length, header tag, the query's nonce) first: the junk is refused
    there, counted, and the CN's answer is taken."""
    from zplatform.runtime.clocksync import CLOCK_REPLIERS_MAX

    rogues = [_rogue(k * MS) for k in range(2 * CLOCK_REPLIERS_MAX)]
    s = _sim(rogues=rogues, rogues_first=False)
    link = _link()
    est = estimate_offset(s, KEYS, s.now_ns, link, exchanges=10)
    assert abs(est.offset_ns - (s.cn_node - s.dn_node)) <= 1, est
    assert link.timeouts == 0 and link.screened == 10 * 2 * CLOCK_REPLIERS_MAX


def test_a_dns_clock_timeouts_are_counted_and_evented_at_most_once_a_second() -> None:
    """The DN's loop thread puts the clock link's timeouts into
    ``dnX_clock_timeouts`` at every account, and says so in a
    ``clock_timeout`` event at most once a second."""
    from zplatform.control.loop import DeviceLogic
    from zplatform.core.events import EventLog
    from zplatform.node.device import ClockTally

    logic = DeviceLogic(IGNITER, "dn0")
    link = ClockLink(IGNITER, "dn0", None)
    events = EventLog("dn0")
    tally = ClockTally(logic.dv, "dn0", link, events)
    t0 = 5_000 * MS
    tally.count(t0)
    assert int(logic.dv.get("dn0_clock_timeouts")) == 0 and not events.drain()
    link.timeouts = 3
    tally.count(t0)
    assert int(logic.dv.get("dn0_clock_timeouts")) == 3
    [ev] = events.drain()
    assert ev.id == "clock_timeout" and "3 more time(s), 3 in all" in ev.text
    link.timeouts = 7
    tally.count(t0 + 600 * MS)  # within the second: counted, not told
    assert int(logic.dv.get("dn0_clock_timeouts")) == 7 and not events.drain()
    tally.count(t0 + 1_000 * MS)  # the second is over: told, with what was held
    [ev] = events.drain()
    assert "4 more time(s), 7 in all" in ev.text
    tally.count(t0 + 5_000 * MS)  # nothing new: nothing said
    assert not events.drain() and int(logic.dv.get("dn0_clock_timeouts")) == 7


# -- freshness of the exchange: replays and absurd times -----------------------------

T0 = 1_700_000_000_000_000_000
DAY = 86_400 * 10**9
I64_MAX = (1 << 63) - 1


def test_the_clock_server_refuses_a_replayed_or_absurdly_stamped_query_unanswered() -> None:
    """An authentic query is answered once: its replay (the same nonce), one
    stamped at i64 max, or more than a day from the CN's clock, is refused
    unanswered and counted; a query a few hours off (an unsynchronised
    asker's clock) is still answered."""
    link, cn = _link(), _responder()
    q, _ = link.query(T0)
    assert cn.answer(q, T0 + MS, T0 + 2 * MS) is not None
    assert cn.answer(q, T0 + 3 * MS, T0 + 4 * MS) is None  # a replay
    assert "replay" in cn.reason
    assert cn.answer(link.query(I64_MAX)[0], T0, T0 + 1) is None
    assert cn.answer(link.query(T0 - DAY - 1)[0], T0, T0 + 1) is None
    # An asker's first query a few hours off (its clock not yet corrected):
    # answered (after a genuine one in bounds it would look like a replay).
    first = _responder().answer(link.query(T0 - 5 * 3600 * 10**9)[0], T0, T0 + 1)
    assert first is not None
    assert cn.refused == 3
    peer = ClockLink(IGNITER, "dn1", ALL_KEYS.for_node("dn1"))
    assert cn.answer(peer.query(T0)[0], T0, T0 + 1) is not None  # its nonces are its own


def test_a_clock_reply_with_absurd_times_is_refused_and_counted() -> None:
    """An authentic reply echoing this exchange's nonce, but whose t1 is not
    the query's, whose t2 is after t3, or whose times are a day away, is
    refused (refused_other); the genuine reply is taken."""
    link = _link()
    seal = ALL_KEYS.for_node("cn").channel("clock_cn_to_dn0")
    reply = struct.Struct("<2sBB16sqqq")

    def forged(nonce: bytes, t1: int, t2: int, t3: int) -> bytes:
        return bytes(seal.seal(reply.pack(b"ZR", 1, link.index, nonce, t1, t2, t3)))

    _, nonce = link.query(T0)
    for t1, t2, t3 in (
        (I64_MAX, I64_MAX, I64_MAX),  # a t1 not the query's
        (T0, T0 + 2 * MS, T0 + MS),  # answered before asked
        (T0, T0 + DAY + 1, T0 + DAY + 2),  # a day away
    ):
        assert link.check(forged(nonce, t1, t2, t3), nonce) is None
    assert (link.refused_bad, link.refused_other) == (0, 3)
    assert link.check(forged(nonce, T0, T0 + MS, T0 + 2 * MS), nonce) == (T0, T0 + MS, T0 + 2 * MS)


def test_the_clock_exchange_tells_the_run_and_refuses_another_runs_query() -> None:
    """Keys bound to the run (zplatform.core.auth.Run, FORMAT.md §6.3): a device
    node's first query names no run (a hello) and is answered; the answer,
    tagged in the CN's run and echoing the node's fresh nonce, tells it the
    run; its next query names the run. A query of an earlier run (the same
    node's, recorded then, never answered in this run) is refused unanswered
    before its MAC; after an unanswered exchange the node says hello again
    and learns a new run."""
    run = Run(7_000)
    cn = ClockResponder(IGNITER, ALL_KEYS.for_node("cn"), run)
    learned = Run()
    link = ClockLink(IGNITER, "dn0", ALL_KEYS.for_node("dn0"), run=learned)
    hello, n = link.query(T0)
    assert Channel.run_of(hello) == NO_RUN and not learned.known
    reply = cn.answer(hello, T0, T0 + 1)
    assert reply is not None and Channel.run_of(reply) == 7_000
    assert link.check(reply, n) is not None and learned.epoch == 7_000
    q, n = link.query(T0 + 1)
    assert Channel.run_of(q) == 7_000
    reply = cn.answer(q, T0 + 1, T0 + 2)
    assert reply is not None and link.check(reply, n) is not None
    # An earlier run's query, genuine then: refused, not answered.
    old = ClockLink(IGNITER, "dn0", ALL_KEYS.for_node("dn0"), run=Run())
    old_cn = ClockResponder(IGNITER, ALL_KEYS.for_node("cn"), Run(6_000))
    h, n = old.query(T0 - 10)
    r = old_cn.answer(h, T0 - 10, T0 - 9)
    assert r is not None and old.check(r, n) is not None
    replayed = old.query(T0 - 5)[0]
    assert Channel.run_of(replayed) == 6_000
    assert cn.answer(replayed, T0 + 3, T0 + 4) is None
    assert "not of this run (7000)" in cn.reason and cn.refused == 1
    # The CN starts a new run: the node's query of the old one goes
    # unanswered, so its next is a hello, whose answer tells the new run.
    run.set(8_000)
    q, n = link.query(T0 + 5)
    assert cn.answer(q, T0 + 5, T0 + 6) is None
    q, n = link.query(T0 + 7)
    assert Channel.run_of(q) == NO_RUN
    reply = cn.answer(q, T0 + 7, T0 + 8)
    assert reply is not None and link.check(reply, n) is not None and learned.epoch == 8_000
    # A reply of another run that is not the answer to the latest query teaches nothing.
    assert link.check(r, n) is None and learned.epoch == 8_000


def test_a_replay_of_an_old_query_is_refused_after_many_newer_ones() -> None:
    """Issue 25: the clock server remembered the last 256 nonces of each
    asker, so once a DN had sent 256 newer queries a replayed old one was
    answered again (and handed to the server's thread). Now a query looks
    its age (its stamp against the CN's clock, beside the asker's newest
    answered): 300 genuine queries 100 ms apart are all answered; a replay
    of the first is refused, counted once as stale, and so is a replay of
    the newest (its nonce)."""
    link, cn = _link(), _responder()
    first, _ = link.query(T0)
    assert cn.answer(first, T0 + MS, T0 + 2 * MS) is not None
    t = T0
    for _ in range(300):
        t += 100 * MS
        newest, _ = link.query(t)
        assert cn.answer(newest, t + MS, t + 2 * MS) is not None
    refused = cn.refused
    assert cn.answer(first, t + 3 * MS, t + 4 * MS) is None
    assert "replay" in cn.reason
    assert cn.answer(newest, t + 5 * MS, t + 6 * MS) is None
    assert cn.refused - refused == 2 and getattr(cn, "stale", 2) == 2


def test_a_clock_asker_is_bounded_after_its_tag() -> None:
    """An asker's genuine queries at once: two start-ups (a node restarted
    at once), each its offset's and its residual's series, and an
    in-flight one (and a few hellos) are answered, then one every
    ``every_ns``; the excess is refused unanswered and counted exactly; a
    fresh query after the wait is answered again."""
    from zplatform.runtime.clocksync import ask_bound, drift_exchanges

    link, cn = _link(), _responder()
    burst, every = ask_bound(IGNITER.clock)
    start = IGNITER.clock.exchanges + drift_exchanges(IGNITER.clock)  # a device node's start-up
    assert burst == 2 * start + 58  # a restart's series too (CI saw one refused without)
    answered = sum(cn.answer(link.query(T0)[0], T0, T0 + 1) is not None for _ in range(burst + 40))
    assert answered == burst
    assert cn.ask_excess == 40 == cn.refused and cn.stale == 0
    assert cn.answer(link.query(T0 + every)[0], T0 + every, T0 + every + 1) is not None


# -- the run hello: junk and replays never spend its rate bound (issue 25) --------


def _hello_responder(now: list[int]) -> ClockResponder:
    return ClockResponder(IGNITER, ALL_KEYS.for_node("cn"), mono_ns=lambda: now[0])


def test_keyless_run_hellos_never_spend_the_bound_a_grounds_hello_needs() -> None:
    """Issue 25: the run hello's rate bound was checked before its tag, so
    a keyless flood of hello-shaped junk (magic right, tag wrong) spent it
    and a ground's genuine hello, at the same instant, went unanswered. Now
    the header tag comes first: every junk hello is refused (counted), the
    bound untouched, and the ground's hello is answered."""
    from zplatform.runtime.clocksync import HELLO_BURST, RunAsker

    now = [5 * 10**9]
    cn = _hello_responder(now)
    asker = RunAsker(ALL_KEYS.for_node("gn"))
    genuine = asker.hello()
    for i in range(10 * HELLO_BURST):
        junk = bytearray(genuine)
        junk[3:19] = i.to_bytes(16, "little")  # another nonce, the tag not redone
        assert cn.answer(bytes(junk), 0, 0) is None
    assert cn.refused == 10 * HELLO_BURST and cn.hello_excess == 0 and cn.hellos == 0
    answer = cn.answer(genuine, 0, 0)
    assert answer is not None and asker.check(answer) and asker.run.epoch == cn.run.epoch


def test_a_replayed_run_hello_is_answered_once_and_spends_no_more_of_the_bound() -> None:
    """Issue 25: a captured hello, replayed, was answered again and again
    (up to the bound), so its replayer kept a ground from learning the run.
    Now its nonce is remembered (:data:`HELLO_KEPT` of them): replays are
    refused, counted stale, before the MAC and the bound, and a ground's
    hello meanwhile is answered."""
    from zplatform.runtime.clocksync import RunAsker

    now = [5 * 10**9]
    cn = _hello_responder(now)
    captured = RunAsker(ALL_KEYS.for_node("gn")).hello()
    answered = sum(cn.answer(captured, 0, 0) is not None for _ in range(100))
    assert answered == 1 and cn.hellos == 1
    assert cn.refused == 99 == cn.stale and cn.hello_excess == 0
    assert "replay" in cn.reason
    ground = RunAsker(ALL_KEYS.for_node("gn"))
    answer = cn.answer(ground.hello(), 0, 0)
    assert answer is not None and ground.check(answer)


def test_a_replayer_of_many_hellos_spends_the_bound_for_one_pass_at_most(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The remaining cost (ClockResponder._answer_hello): a replayer holding
    :data:`HELLO_KEPT` captured hellos has each answered (or refused by the
    bound) once; a second pass is refused whole as replays, without the
    bound, so a ground's hello after the first pass is answered as soon as
    the bound refills (one HELLO_EVERY_NS). A hello pushed out of the ring
    by HELLO_KEPT newer ones is taken again (the ring's limit), shown on a
    ring of 256 that a test fills twice quickly."""
    from zplatform.runtime import clocksync
    from zplatform.runtime.clocksync import HELLO_BURST, HELLO_EVERY_NS, RunAsker

    monkeypatch.setattr(clocksync, "HELLO_KEPT", 256)
    kept = clocksync.HELLO_KEPT

    now = [5 * 10**9]
    cn = _hello_responder(now)
    captured = [RunAsker(ALL_KEYS.for_node("gn")).hello() for _ in range(kept)]
    first = sum(cn.answer(h, 0, 0) is not None for h in captured)
    assert first == HELLO_BURST and cn.hello_excess == kept - HELLO_BURST
    stale = cn.stale
    assert all(cn.answer(h, 0, 0) is None for h in captured)
    assert cn.stale - stale == kept and cn.hello_excess == kept - HELLO_BURST
    now[0] += HELLO_EVERY_NS
    ground = RunAsker(ALL_KEYS.for_node("gn"))
    answer = cn.answer(ground.hello(), 0, 0)
    assert answer is not None and ground.check(answer)
    # The ground's hello pushed the oldest captured one out: it is new again.
    now[0] += HELLO_EVERY_NS
    assert cn.answer(captured[0], 0, 0) is not None
    assert cn.answer(captured[1], 0, 0) is None  # still kept: a replay


def test_more_captured_hellos_than_the_old_ring_held_are_answered_one_pass_only() -> None:
    """Issue 25, left last stop: the ring kept 256 nonces, so a replayer
    holding more captured hellos pushed its own out and cycled them, each
    pass spending the bound a ground's hello needs, for as long as it
    replayed. It keeps 65,536 now: 1,000 captured hellos are answered (or
    refused by the bound) once, and every later pass is refused whole as
    replays, the bound untouched."""
    from zplatform.runtime.clocksync import HELLO_BURST, HELLO_EVERY_NS, HELLO_KEPT, RunAsker

    assert HELLO_KEPT == 65_536
    now = [5 * 10**9]
    cn = _hello_responder(now)
    captured = [RunAsker(ALL_KEYS.for_node("gn")).hello() for _ in range(1000)]
    first = sum(cn.answer(h, 0, 0) is not None for h in captured)
    assert first == HELLO_BURST and cn.hello_excess == 1000 - HELLO_BURST
    for _ in range(3):
        stale = cn.stale
        now[0] += HELLO_EVERY_NS  # time passes: the bound would let one through
        assert all(cn.answer(h, 0, 0) is None for h in captured)
        assert cn.stale - stale == 1000 and cn.hello_excess == 1000 - HELLO_BURST
    ground = RunAsker(ALL_KEYS.for_node("gn"))
    answer = cn.answer(ground.hello(), 0, 0)
    assert answer is not None and ground.check(answer)
