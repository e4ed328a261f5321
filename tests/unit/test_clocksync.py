"""zplatform.clocksync without a network: the estimator a mission picks, its
fallback, and both estimators against a simulated CN whose clocks are known.

:class:`SimSession` stands in for the DN's zenoh session: each ``get`` runs
one exchange with the CN's :class:`~zplatform.clocksync.ClockServer` on a
simulated true time, stamping the node clocks and (when instrumented) zenoh's
four time points the way the real ones are taken: ``t1`` before zenoh's send
stamp, ``t2`` after its receive stamp, ``t3`` before the reply's send stamp,
``t4`` (in the reply callback) after the reply's receive stamp.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass, field
from typing import Any, get_args, get_type_hints

import pytest

from zplatform.clocksync import (
    ESTIMATORS,
    ClockEstimate,
    ClockEstimator,
    ZenohTimestampsError,
    estimate_offset,
    estimate_offset_zenoh,
    estimator_for,
)
from zplatform.config import ClockConfig
from zplatform.errors import ClockSyncError
from zplatform.transport import KeySpace

KEYS = KeySpace("rocket")
_REQ = struct.Struct("<q")
_REP = struct.Struct("<qqq")
US = 1_000


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


@dataclass
class SimSession:
    """Clocks as offsets from a simulated true time ``t`` (ns).

    ``stamps``: whether the CN's zenoh stamps instrumented queries.
    ``step_dn_zenoh_after``: after that many exchanges the DN's zenoh clock
    (the host's real-time clock) steps by ``step_ns``.
    ``answer``: whether the CN answers at all.
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

    def now_ns(self) -> int:
        """The DN's node clock."""
        return self.t + self.dn_node

    def get(self, key: Any, handler: Any, *, payload: bytes, **kw: Any) -> None:
        self.gets += 1
        ti = kw.get("timestamp_instrumentation")
        self.instrumented.append(ti is not None)
        if self.step_dn_zenoh_after is not None and self.gets == self.step_dn_zenoh_after + 1:
            self.dn_zenoh += self.step_ns
        if not self.answer:
            return
        (t1,) = _REQ.unpack(payload)
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
        stack = None
        if ti is not None:
            stack = _Stack([_Record(x) for x in (t1z, t2z, t3z, t4z)] if self.stamps else [])
        handler.callback(_Reply(_Sample(_Payload(_REP.pack(t1, t2, t3)), stack)))


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
    est = fn(s, KEYS, s.now_ns, exchanges=20)
    assert est.exchanges == 20
    # CN - DN node clocks: exact on this symmetric path (to rounding).
    assert abs(est.offset_ns - (s.cn_node - s.dn_node)) <= 1, est


def test_estimators_label_their_estimates() -> None:
    s = _sim()
    assert estimate_offset(s, KEYS, s.now_ns, exchanges=8).estimator == "node_clock"
    assert estimate_offset_zenoh(s, KEYS, s.now_ns, exchanges=8).estimator == "zenoh_ts"


def test_zenoh_ts_without_stamps_is_a_zenoh_timestamps_error() -> None:
    s = _sim(stamps=False)
    with pytest.raises(ZenohTimestampsError, match="answered 20 of 20 exchanges, but only 0"):
        estimate_offset_zenoh(s, KEYS, s.now_ns, exchanges=20)


def test_zenoh_ts_with_a_stepped_host_clock_is_a_zenoh_timestamps_error() -> None:
    s = _sim(step_dn_zenoh_after=10)
    with pytest.raises(ZenohTimestampsError, match=r"the DN's zenoh clock and node clock disagree"):
        estimate_offset_zenoh(s, KEYS, s.now_ns, exchanges=20)


def test_zenoh_ts_unreachable_cn_is_a_plain_clock_sync_error() -> None:
    s = _sim(answer=False)
    with pytest.raises(ClockSyncError) as info:
        estimate_offset_zenoh(s, KEYS, s.now_ns, exchanges=8, timeout_s=0.001)
    assert not isinstance(info.value, ZenohTimestampsError)


# -- the fallback ----------------------------------------------------------------


def test_zenoh_ts_falls_back_to_node_clock_with_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    s = _sim(stamps=False)
    est = estimator_for(ClockConfig())
    with caplog.at_level(logging.INFO, logger="zplatform.clocksync"):
        first = est(s, KEYS, s.now_ns, exchanges=20)
        second = est(s, KEYS, s.now_ns, exchanges=20)
    assert first.estimator == second.estimator == "node_clock"
    assert abs(first.offset_ns - (s.cn_node - s.dn_node)) <= 1
    assert est.fallbacks == 2
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1  # once, when calls start falling back
    assert "falling back to the node-clock estimator" in warned[0].getMessage()
    # zenoh_ts again once the CN's zenoh stamps (the fallback is per call).
    s.stamps = True
    with caplog.at_level(logging.INFO, logger="zplatform.clocksync"):
        assert est(s, KEYS, s.now_ns, exchanges=20).estimator == "zenoh_ts"
    assert "works again" in caplog.records[-1].getMessage()


def test_unreachable_cn_does_not_fall_back() -> None:
    s = _sim(answer=False)
    est = estimator_for(ClockConfig())
    with pytest.raises(ClockSyncError, match="instrumented replies"):
        est(s, KEYS, s.now_ns, exchanges=8, timeout_s=0.001)
    assert est.fallbacks == 0
    assert s.gets == 8  # one series: no second attempt


def test_node_clock_never_asks_zenoh_for_timestamps() -> None:
    s = _sim()
    est = estimator_for(ClockConfig(estimator="node_clock"))
    assert est(s, KEYS, s.now_ns, exchanges=8).estimator == "node_clock"
    assert s.instrumented == [False] * 8


def test_failed_fallback_names_both() -> None:
    def no_stamps(*a: Any, **kw: Any) -> ClockEstimate:
        raise ZenohTimestampsError("no stamps")

    def unreachable(*a: Any, **kw: Any) -> ClockEstimate:
        raise ClockSyncError("clock sync got 0 of 8 replies")

    est = ClockEstimator("zenoh_ts", no_stamps, fallback=unreachable)
    with pytest.raises(ClockSyncError, match=r"0 of 8 replies \(after the zenoh_ts estimator: no"):
        est(_sim(), KEYS, _sim().now_ns, exchanges=8)
