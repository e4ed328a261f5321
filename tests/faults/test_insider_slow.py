"""A slow answerer (issue 25): a device node's insider, holding that node's
key and answering the CN's sync queries on its own key, answers late or
never. In process, on one zenoh session (tests/zsession.py), with the CN's
real sync (zplatform.runtime.sync.ControlSync) and ControlLogic, the honest
dn0 a DeviceLogic behind its queryable:

* ``never``: dn1's queryable keeps every query and answers none. Each sync
  returns while dn1 still holds that loop's query (the loop never waits on
  an insider); the CN counts a miss of dn1 every loop, and dn0 is taken
  every loop.
* ``late``: dn1 answers each loop's query, with its genuine reply, only when
  the next loop's query comes. The CN's reply check refuses each as stale
  (not the loop asked), counted once, and counts dn1 missed every loop.
"""

from __future__ import annotations

import os
import threading
from typing import Any

import pytest

from tests.faults.insider import ROOT
from tests.zsession import lone_session
from zplatform.control.intake import CnRefusals, ReplyCheck
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.core.auth import KEY_ENV, KeySet, channel
from zplatform.mission.load import load_mission
from zplatform.runtime.sync import ControlSync
from zplatform.runtime.transport import KeySpace

M = load_mission(ROOT / "configs" / "recovery_igniter.yaml")
KEYS = KeySet.from_master(M, bytes.fromhex(os.environ[KEY_ENV]))
T0 = 1_700_000_000_000_000_000
LOOPS = 8


class _Dn:
    """A DN's queryable on its own sync key: honest (answers at once) or an
    insider (keeps the query; ``late``: answers it when the next one comes)."""

    def __init__(self, session: Any, dn: str, mode: str) -> None:
        self.logic = DeviceLogic(M, dn, keys=KEYS.for_node(dn))
        self.mode, self.lock = mode, threading.Lock()
        self.held: list[Any] = []
        self.t = T0
        self.q = session.declare_queryable(KeySpace(M.vehicle).dn_to_cn(dn), self._on)

    def _answer(self, query: Any) -> None:
        reply = self.logic.trigger(query.payload.to_bytes(), self.t)
        assert reply is not None, self.logic.reject_reason
        query.reply(query.key_expr, bytes(reply))

    def _on(self, query: Any) -> None:
        with self.lock:
            if self.mode == "honest":
                self._answer(query)
                return
            if self.mode == "late" and self.held:
                old = self.held.pop()
                self._answer(old)
                old.drop()
            self.held.append(query)

    def holding(self) -> int:
        with self.lock:
            return len(self.held)

    def close(self) -> None:
        with self.lock:
            for q in self.held:
                q.drop()
            self.held.clear()
        self.q.undeclare()


@pytest.mark.parametrize("mode", ["never", "late"])
def test_a_slow_insider_costs_a_counted_miss_and_never_holds_the_loop(mode: str) -> None:
    session = lone_session()
    dns = [_Dn(session, "dn0", "honest"), _Dn(session, "dn1", mode)]
    cn = ControlLogic(M, keys=KEYS.for_node("cn"), epoch=T0)
    checks = [ReplyCheck(M, dn, channel(KEYS, f"{dn}_to_cn")) for dn in M.device_nodes]
    cs = ControlSync(
        session,
        KeySpace(M.vehicle),
        M.device_nodes,
        # The sync's deadline: 200 ms, not the mission's period, so that on a
        # box busy enough to delay dn0's answer or the query's delivery to
        # dn1 by 10 ms the counts still tell what the sync did, not how fast
        # the box was (beside a CPU hog dn0 was missed once in 8 loops).
        200_000_000,
        5.0,  # far beyond the test: dn1's queries stay open while it holds them
        checks=checks,
    )
    stale = bad = 0
    try:
        for n in range(1, LOOPS + 1):
            t = T0 + n * M.period_ns
            for d in dns:
                d.t = t
            cs.sync(cn.begin(n, t), cn)
            # The sync returned while the insider still holds this loop's
            # query (and, never answering, every one before).
            assert dns[1].holding() == (1 if mode == "late" else n)
            r = CnRefusals()
            cs.take_refusals(r)
            stale += r.reply_stale
            bad += r.reply_bad + r.reply_size
            cn.finish((), refused=r)
    finally:
        cs.close()
        for d in dns:
            d.close()
        session.close()
    dv = cn.dv
    assert dv.get("cn_rx_dn0") == LOOPS and dv.get("cn_missed_dn0") == 0
    assert dv.get("cn_rx_dn1") == 0 and dv.get("cn_missed_dn1") == LOOPS
    # Each late reply (every loop's but the last) refused as stale, once.
    assert (stale, bad) == ((LOOPS - 1, 0) if mode == "late" else (0, 0))
