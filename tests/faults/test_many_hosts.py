"""Many hosts: led_test end to end with every node on a host of its own.

Five network namespaces joined by a bridge, each with its own address; the
same mission file (endpoints on those addresses) runs `zplatform node` in
each: cn, dn0, dn1, dn2 and the ground node, which plays the LED script and
logs telemetry. Made and removed by the test; skipped where namespaces
cannot be made (not root, no `ip`).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.budget import assert_every_loop_counted
from tests.faults.missions import netns_mission
from tests.faults.netns import NetnsHost
from zplatform.telemetry.logs import read_csv

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.faults


# Five namespaces, 18 s: with the soaks (-m slow). The default suite syncs
# a mission across namespaces in tests/faults/test_netns.py.
@pytest.mark.slow
@pytest.mark.timeout(180)
def test_led_test_across_five_hosts(
    netns_hosts: Callable[..., list[NetnsHost]], tmp_path: Path
) -> None:
    hosts = netns_hosts(5)
    names = ["cn", "dn0", "dn1", "dn2", "gn"]
    path = netns_mission(
        ROOT / "configs" / "led_test.yaml",
        tmp_path / "led_test.yaml",
        dict(zip(names, hosts, strict=True)),
    )
    node = [sys.executable, "-m", "zplatform", "node", str(path)]
    procs = {}
    for name, h in zip(names[1:4], hosts[1:4], strict=True):
        procs[name] = h.popen([*node, name], log=tmp_path / f"{name}.log", cwd=ROOT)
    csv = tmp_path / "tm.csv"
    procs["gn"] = hosts[4].popen(
        [
            *node,
            "gn",
            "--log",
            str(csv),
            "--commands",
            str(ROOT / "configs" / "led_test.commands"),
            "--summary",
            str(tmp_path / "gn.json"),
        ],
        log=tmp_path / "gn.log",
        cwd=ROOT,
    )
    cn = hosts[0].popen(
        [*node, "cn", "--duration", "16", "--summary", str(tmp_path / "cn.json")],
        log=tmp_path / "cn.log",
        cwd=ROOT,
    )
    assert cn.wait(timeout=150) == 0, (tmp_path / "cn.log").read_text()[-3000:]
    s = json.loads((tmp_path / "cn.json").read_text())
    assert s["loops"] == 1600 and s["final_state"] == "E", s
    assert_every_loop_counted(s)  # over veth and a bridge
    for dn in ("dn0", "dn1", "dn2"):
        assert procs[dn].poll() is None, (tmp_path / f"{dn}.log").read_text()[-2000:]
    # The ground node, on its own host, logged the run and played the script.
    procs["gn"].terminate()
    procs["gn"].wait(timeout=30)
    g = json.loads((tmp_path / "gn.json").read_text())
    assert [c["status"] for c in g["commands"]] == ["ACCEPTED", "ACCEPTED"], g
    states = []
    for row in read_csv(csv):
        if not states or states[-1] != row["cn_state"]:
            states.append(row["cn_state"])
    assert states == ["A", "B", "C", "D", "E"]
