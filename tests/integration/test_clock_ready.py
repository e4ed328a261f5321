"""A control node's liveliness token tells device nodes its clock is served.

Device nodes wait for a control node's token, then set their clocks by the
commander's clock server (docs/architecture.md, "Start-up"). A redundant
mission's ``cn`` declared its token before it served the clock, for as long
as it looked for device nodes already running (half a second): a device
node that started then found no clock, its exchanges ended unanswered at
once, and the operator saw ``clock_timeout`` (101 in all) on every such
start. The token now comes after the server.
"""

from __future__ import annotations

from pathlib import Path

from tests.integration.harness import CONFIGS, Cluster
from zplatform.core.auth import load_keys
from zplatform.runtime.clocksync import ClockLink, learn_run
from zplatform.runtime.timebase import NodeClock
from zplatform.runtime.transport import wait_for_nodes


def test_a_redundant_commanders_token_comes_after_its_clock(tmp_path: Path) -> None:
    with Cluster(CONFIGS / "flight.yaml", tmp_path) as c:
        assert c.mission.standby is not None  # the redundant case
        rx = c.rx  # the test's session, open before cn starts
        c.spawn("cn")
        wait_for_nodes(rx.ns.session, rx.keys, ["cn"], 60.0)
        # As dn0 does at start: one exchange, right after the token.
        link = ClockLink(c.mission, "dn0", load_keys(c.mission, "dn0"))
        assert learn_run(rx.ns.session, rx.keys, NodeClock().now_ns, link, tries=1, timeout_s=5.0)
        assert link.timeouts == 0
