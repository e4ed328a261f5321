"""The sync's public trace hook (zplatform.runtime.sync.SyncTrace): every hop of an
exchange, at both ends, in order; what bench.sync_trace stamps."""

from __future__ import annotations

import threading
from pathlib import Path

from tests.zsession import lone_session
from zplatform.control.intake import ReplyCheck, TriggerIntake
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.core.auth import channel
from zplatform.mission.load import load_mission
from zplatform.runtime.sync import ControlSync, DeviceSync
from zplatform.runtime.transport import KeySpace
from zplatform.sim.lockstep import sim_keys

MINIMAL = Path(__file__).resolve().parents[2] / "configs" / "minimal.yaml"


def test_both_ends_report_every_hop_in_order() -> None:
    m = load_mission(MINIMAL)
    cn = ControlLogic(m, keys=sim_keys(m))
    dn = DeviceLogic(m, "dn0", keys=sim_keys(m))
    cn_hops: list[tuple[str, int]] = []
    dn_hops: list[tuple[str, int]] = []
    session = lone_session()
    try:
        keys = KeySpace(m.vehicle)
        now = iter(range(10**9, 2 * 10**9, 10**7)).__next__
        sim = sim_keys(m)
        ds = DeviceSync(
            session,
            keys,
            "dn0",
            now,
            intake=TriggerIntake(m, "dn0", channel(sim, "cn_to_dn0")),
            trace=lambda h, n: dn_hops.append((h, n)),
        )
        # A generous deadline: this checks the hooks, not the timing.
        cs = ControlSync(
            session,
            keys,
            ["dn0"],
            2_000_000_000,
            2.0,
            checks=[ReplyCheck(m, "dn0", channel(sim, "dn0_to_cn"))],
            trace=lambda h, n: cn_hops.append((h, n)),
        )
        try:
            for loop in (1, 2):
                served = threading.Thread(target=ds.wait, args=(dn, 10.0))
                served.start()
                cs.sync(cn.begin(loop, 10**9 + loop * 10**7), cn)
                served.join()
                assert cn.pending == 0  # the reply came back and was applied
                cn.finish()
        finally:
            cs.close()
            ds.close()
    finally:
        session.close()
    assert cn_hops == [("issued", 0), ("back", 0), ("taken", 0)] * 2
    assert dn_hops == [
        *(("arrive", 0), ("serve", 0), ("replied", 1)),
        *(("arrive", 0), ("serve", 0), ("replied", 2)),
    ]
