"""zplatform.trace: the named trace points benchmarks time (bench/frame_trace.py
and the others use nothing else). A Ring keeps the last records in order and
never grows; with no tracer installed nothing is recorded; a live exchange
reaches every point of both ends, in the order the module doc lists them."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.zsession import lone_session
from zplatform import trace
from zplatform.control.intake import ReplyCheck, TriggerIntake
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.core.auth import channel
from zplatform.mission.load import load_mission
from zplatform.runtime.sync import ControlSync, DeviceSync
from zplatform.runtime.transport import KeySpace
from zplatform.sim.lockstep import sim_keys

MINIMAL = Path(__file__).resolve().parents[2] / "configs" / "minimal.yaml"


@pytest.fixture(autouse=True)
def _no_tracer() -> Iterator[None]:
    trace.uninstall()
    yield
    trace.uninstall()


def test_ring_keeps_marks_in_order_with_their_index_value_and_time() -> None:
    ticks = iter(range(100, 200)).__next__
    r = trace.Ring(8, clock=ticks)
    r.mark("sync.issued", 1, 40)
    r.mark("sync.sent", 1)
    r.mark("sync.taken", 0)
    assert r.count == 3
    assert r.records() == [
        ("sync.issued", 1, 40, 100),
        ("sync.sent", 1, 0, 101),
        ("sync.taken", 0, 0, 102),
    ]


def test_ring_is_bounded_and_keeps_the_newest() -> None:
    ticks = iter(range(1000)).__next__
    r = trace.Ring(4, clock=ticks)
    names, n_before, v_before = r._names, r._n, r._v  # the same arrays after
    for k in range(10):
        r.mark("dn.serve", k)
    assert r.count == 10
    assert [rec[1] for rec in r.records()] == [6, 7, 8, 9]
    assert len(r._names) == len(r._n) == len(r._v) == len(r._t) == 4
    assert r._names is names and r._n is n_before and r._v is v_before


def test_ring_refuses_no_capacity() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        trace.Ring(0)


def test_nothing_is_recorded_when_no_tracer_is_installed() -> None:
    m = load_mission(MINIMAL)
    cn = ControlLogic(m, keys=sim_keys(m))
    dn = DeviceLogic(m, "dn0", keys=sim_keys(m))
    r = trace.Ring(64)
    trace.install(r)
    trace.uninstall()
    assert trace.tracer is None
    frames = cn.begin(1, 10**9)
    reply = dn.trigger(frames[0], 10**9)
    assert reply is not None
    dn.run(10**9)
    assert cn.reply(0, reply)
    assert list(cn.replied) == [True]  # public: what bench/reliability.py reads per loop
    cn.telemetry()
    assert r.count == 0
    cn.begin(2, 10**9 + 10**7)
    assert list(cn.replied) == [False]


CN_LOOP = (
    "cn.encode",
    "cn.encoded",
    "cn.sealed",
    "sync.issued",
    "sync.sent",
    "sync.taken",
    "cn.opened",
    "cn.decoded",
    "cn.applied",
    "tm.encode",
    "tm.encoded",
    "tm.sealed",
)
CN_ZENOH = ("sync.back", "sync.queued")
DN = (
    "dn.arrive",
    "dn.admitted",
    "dn.serve",
    "dn.opened",
    "dn.decoded",
    "dn.encoded",
    "dn.sealed",
    "dn.replied",
    "dn.apply",
    "dn.applied",
)


def test_an_exchange_reaches_every_point_in_order() -> None:
    m = load_mission(MINIMAL)
    sim = sim_keys(m)
    cn = ControlLogic(m, keys=sim)
    dn = DeviceLogic(m, "dn0", keys=sim)
    r = trace.Ring(1024)
    session = lone_session()
    try:
        keys = KeySpace(m.vehicle)
        now = iter(range(10**9, 2 * 10**9, 10**7)).__next__
        ds = DeviceSync(
            session,
            keys,
            "dn0",
            now,
            intake=TriggerIntake(m, "dn0", channel(sim, "cn_to_dn0")),
        )
        # A generous deadline: this checks the points, not the timing.
        cs = ControlSync(
            session,
            keys,
            ["dn0"],
            2_000_000_000,
            2.0,
            checks=[ReplyCheck(m, "dn0", channel(sim, "dn0_to_cn"))],
        )
        trace.install(r)
        try:
            for loop in (1, 2):
                served = threading.Thread(target=ds.wait, args=(dn, 10.0))
                served.start()
                frames = cn.begin(loop, 10**9 + loop * 10**7)
                cs.sync(frames, cn)
                served.join()
                dn.run(10**9 + loop * 10**7)
                assert cn.pending == 0  # the reply came back and was applied
                assert cn.finish() is not None  # telemetry every loop
        finally:
            trace.uninstall()
            cs.close()
            ds.close()
    finally:
        session.close()
    recs = [rec for rec in r.records() if rec[0] != "sync.shm"]
    names = [rec[0] for rec in recs]
    assert set(names) | {"sync.shm"} == set(trace.POINTS) - {"tm.put", "tm.sent"}
    # Each thread's points in the documented order, once per loop.
    assert [x for x in names if x in CN_LOOP] == [*CN_LOOP] * 2
    assert [x for x in names if x in CN_ZENOH] == [*CN_ZENOH] * 2
    assert [x for x in names if x in DN] == [*DN] * 2
    # Across threads, causes before effects, per loop.
    for half in (names[: len(names) // 2], names[len(names) // 2 :]):
        at = half.index
        assert at("sync.issued") < at("dn.arrive")
        assert at("dn.sealed") < at("sync.back") < at("sync.taken")
        assert at("sync.back") < at("sync.queued")
    by = {(rec[0], k // (len(recs) // 2)): rec for k, rec in enumerate(recs)}
    assert by[("dn.replied", 0)][1] == 1 and by[("dn.replied", 1)][1] == 2  # the loop served
    assert by[("tm.encode", 1)][1] == 2  # telemetry: n is the loop
    assert by[("sync.issued", 0)][2] == len(frames[0])  # v: the query's length
    assert by[("sync.back", 0)][2] > 0  # v: the reply's length
    times = [rec[3] for rec in recs]
    assert times[0] > 0
