"""Two zenoh peers in two network namespaces exchange queries; a link set
down partitions them and set up heals them. The namespaces go away after."""

from __future__ import annotations

import json
import select
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.budget import assert_every_loop_counted
from tests.faults.missions import netns_mission
from tests.faults.netns import NetnsHost, NetnsLab, netns_unavailable

ROOT = Path(__file__).resolve().parents[2]
PORT = 7447  # inside the test's own namespaces: never clashes


def readline(p: subprocess.Popen[Any], timeout_s: float) -> str:
    assert p.stdout is not None
    ready, _, _ = select.select([p.stdout], [], [], timeout_s)
    if not ready:
        raise AssertionError(f"no output from {p.args} within {timeout_s} s")
    line = str(p.stdout.readline())
    if not line:
        raise AssertionError(f"{p.args} exited ({p.wait()})")
    return line.strip()


def ask(probe: subprocess.Popen[Any], timeout_s: float = 0.2) -> bool:
    """One get from the probe; whether it was answered."""
    assert probe.stdin is not None
    probe.stdin.write(f"{timeout_s}\n")
    probe.stdin.flush()
    return readline(probe, timeout_s + 5).startswith("ok")


def until(probe: subprocess.Popen[Any], answered: bool, within_s: float) -> float:
    """Ask until the answer is ``answered``; the time it took."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < within_s:
        if ask(probe) is answered:
            return time.monotonic() - t0
    raise AssertionError(f"gets never {'answered' if answered else 'lost'} in {within_s} s")


def start_pair(server: NetnsHost, client: NetnsHost, server_addr: str) -> subprocess.Popen[Any]:
    peers = [sys.executable, "-m", "tests.faults.peers"]
    srv = server.popen(
        [*peers, "serve", "--listen", f"tcp/{server_addr}:{PORT}"], pipe_stdio=True, cwd=ROOT
    )
    assert readline(srv, 20) == "ready"
    return client.popen(
        [*peers, "probe", "--connect", f"tcp/{server_addr}:{PORT}"], pipe_stdio=True, cwd=ROOT
    )


@pytest.mark.timeout(90)
@pytest.mark.parametrize(("topology", "down_s"), [("bridge", 0.0), ("mesh", 0.0), ("bridge", 2.0)])
def test_peers_in_namespaces_partition_on_link_down_heal_on_up(
    netns_hosts: Callable[..., list[NetnsHost]], topology: str, down_s: float
) -> None:
    """``down_s``: keep the link down at least this long (2 s: past the 1 s
    lease, so zenoh closes the session and must reconnect)."""
    h0, h1 = netns_hosts(2, topology)
    addr = h0.lab.addr_of(0, seen_from=1)
    probe = start_pair(h0, h1, addr)
    until(probe, True, 20)  # readiness: a reply
    h1.link_down()
    t0 = time.monotonic()
    until(probe, False, 5)
    assert not ask(probe)  # stays cut off
    while time.monotonic() - t0 < down_s:
        assert not ask(probe)  # every get in the window is lost
    h1.link_up()
    healed = until(probe, True, 15)
    print(f"{topology} down {down_s} s: healed in {healed:.3f} s")


@pytest.mark.timeout(30)
def test_lab_removes_its_namespaces_and_processes() -> None:
    why = netns_unavailable()
    if why is not None:
        pytest.skip(why)
    with NetnsLab(2) as lab:
        names = list(lab.namespaces)
        p = lab.hosts[0].popen(["sleep", "60"])
        r = lab.hosts[1].run(["ip", "-4", "-o", "addr", "show", "eth0"])
        assert "10.77.0.2/24" in r.stdout
    assert p.poll() is not None
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert not any(n in listed for n in names)


@pytest.mark.timeout(120)
def test_mission_nodes_sync_across_namespaces(
    netns_hosts: Callable[..., list[NetnsHost]], tmp_path: Path
) -> None:
    """`zplatform node` processes in two namespaces: the CN syncs with dn0
    over the bridge at its rate (DN first, then a 2 s CN run). The mission
    says ``transport.intra_host: auto`` and both share this kernel and its
    /dev/shm, but not a network namespace: their sync stays on zenoh (the
    link's name holds the namespace, docs/architecture.md#intra-host)."""
    h0, h1 = netns_hosts(2)
    path = netns_mission(
        ROOT / "configs" / "minimal.yaml", tmp_path / "m.yaml", {"cn": h0, "dn0": h1, "gn": h0}
    )
    node = [sys.executable, "-m", "zplatform", "node", str(path)]
    dn = h1.popen([*node, "dn0"], log=tmp_path / "dn0.log", cwd=ROOT)
    cn = h0.popen(
        [
            *node,
            "cn",
            "--duration",
            "2",
            "--ground-wait",
            "0",
            "--summary",
            str(tmp_path / "cn.json"),
        ],
        log=tmp_path / "cn.log",
        cwd=ROOT,
    )
    assert cn.wait(timeout=90) == 0, (tmp_path / "cn.log").read_text()[-3000:]
    assert dn.poll() is None, (tmp_path / "dn0.log").read_text()[-3000:]
    s = json.loads((tmp_path / "cn.json").read_text())
    assert s["loops"] == 200
    # Connectivity, not timing: every loop a reply or a counted miss, and
    # the link alive (tests/budget.py).
    assert_every_loop_counted(s)
    log = (tmp_path / "cn.log").read_text()
    assert "sync_on_shm" not in log and "sync_fallback" not in log, log[-3000:]
