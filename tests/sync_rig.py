"""One control node's sync with one device node's over real zenoh sessions,
a loop at a time on a clock of the test's own (the lost-route tests of
tests/unit/test_queries.py).

The logic is in process (:class:`~zplatform.control.loop.ControlLogic`,
:class:`~zplatform.control.loop.DeviceLogic`, with the simulation's keys);
only the queries and replies cross zenoh. Each loop's stamp is
``T0 + loop * period``, and dn0's clock (its sync's and its intake's) reads
that stamp: the DN's watchdog sees the loops' time, not the host's."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import zenoh

from zplatform.config import Mission
from zplatform.control.intake import ReplyCheck, TriggerIntake
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.core.auth import channel
from zplatform.runtime.queries import set_fault
from zplatform.runtime.sync import ControlSync, DeviceSync
from zplatform.runtime.transport import KeySpace
from zplatform.sim.lockstep import sim_keys

T0 = 10**9


class SyncRig:
    """dn0 serving on ``dn_session`` (its liveliness token declared when
    ``alive``), the CN asking from ``cn_session`` with reply deadline
    ``deadline_ns``; ``ready`` is called once dn0 has declared, to wait
    until the CN's session knows it. ``fault`` (a
    :func:`~zplatform.runtime.queries.set_fault` fault) is installed before
    the CN's sync declares its querier, and removed by :meth:`close`.
    ``ControlSync`` takes ``sync_kw`` too (``unanswered=...``)."""

    def __init__(
        self,
        m: Mission,
        dn_session: zenoh.Session,
        cn_session: zenoh.Session,
        deadline_ns: int,
        *,
        ready: Callable[[], None],
        alive: bool = True,
        fault: Any = None,
        **sync_kw: Any,
    ) -> None:
        self.m = m
        sim = sim_keys(m)
        self.cn = ControlLogic(m, keys=sim)
        self.dn = DeviceLogic(m, "dn0", keys=sim)
        self.ks = ks = KeySpace(m.vehicle)
        self.loop_n = 0
        self.clock = T0
        self.ds = DeviceSync(
            dn_session,
            ks,
            "dn0",
            lambda: self.clock,
            intake=TriggerIntake(m, "dn0", channel(sim, "cn_to_dn0"), now_ns=lambda: self.clock),
        )
        self.cs: ControlSync | None = None
        self.token = dn_session.liveliness().declare_token(ks.alive("dn0")) if alive else None
        try:
            ready()
            if fault is not None:
                set_fault(fault)
            self.fault = fault
            self.cs = ControlSync(
                cn_session,
                ks,
                ["dn0"],
                deadline_ns,
                5.0,
                checks=[ReplyCheck(m, "dn0", channel(sim, "dn0_to_cn"))],
                **sync_kw,
            )
        except BaseException:
            self.close()
            raise

    @property
    def sync(self) -> ControlSync:
        assert self.cs is not None
        return self.cs

    def loop(self, serve: bool = True, dn_wait_s: float = 10.0) -> None:
        """One CN loop: its trigger sent and the replies waited for (the
        sync's deadline); dn0 serves it on a thread (waiting up to
        ``dn_wait_s`` for it) when ``serve``, else nobody does."""
        self.loop_n += 1
        self.clock = T0 + self.loop_n * self.m.period_ns
        served = threading.Thread(target=self.ds.wait, args=(self.dn, dn_wait_s)) if serve else None
        if served is not None:
            served.start()
        self.sync.sync(self.cn.begin(self.loop_n, self.clock), self.cn)
        if served is not None:
            served.join()

    def close(self) -> None:
        if getattr(self, "fault", None) is not None:
            set_fault(None)
        if self.cs is not None:
            self.cs.close()
        self.ds.close()
        if self.token is not None:
            self.token.undeclare()

    def __enter__(self) -> SyncRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
