"""Two zenoh peers in two network namespaces exchange queries; a link set
down partitions them and set up heals them. The namespaces go away after."""

from __future__ import annotations

import select
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

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
