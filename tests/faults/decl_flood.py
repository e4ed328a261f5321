"""A declaration flood during a flight, for the benchmark (``bench/faults.py``,
``python -m bench.faults --case declaration_flood``); asserted by no test
(what it measures is CPU; that the access control drops the declarations
is tests/faults/test_acl_declarations.py).

Two recovery_igniter flights, each ARMED by ``zplatform cmd ... launch
--arm`` (where losing a DN latches DN_LOST and ABORTs the flight), the
world, dn0, dn1, the CN and the ground node as processes:

* ``mtls``: the mission's default transport (mutual TLS with the
  deployment's access control); the attacker presents the mission's
  read-only ``tool`` certificate;
* ``plain``: the same mission on plain TCP (:func:`plain_tcp_mission`); the
  attacker holds no key and no certificate.

In each, after a reference window without attack, an attacker process
(:mod:`tests.faults.attacker`) floods declarations for ``FLOOD_S`` seconds
at :data:`RATE` per second, holding :data:`HOLD` of each kind and then
replacing its oldest: first ``declare-denied`` (subscribers on
``{vehicle}/**``, queryables on ``{vehicle}/dn0/to_cn``: what the access
control denies a tool), then ``declare-allowed`` (subscribers on telemetry
and events, liveliness subscribers: what it allows one).

Figures per flight and attack: the declarations sent and their rate, each
node's CPU (per cent of one core, psutil) in the window against the
reference window, the CN's sync misses and loop overruns against the
reference's, and each node's RSS growth. Checks: the flight goes on (no
fault, no DN safed) and ends DEPLOYED.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import psutil

from tests.faults.floods import (
    _SYNC,
    IGNITER,
    Attacker,
    _intact,
    _lasts,
    _Mark,
    operator,
)
from tests.faults.live import CaseResult, Live, live
from tests.faults.missions import plain_tcp_mission
from tests.integration.harness import ROOT
from zplatform.runtime.transport import free_port
from zplatform.security.deploy import default_deployment_path

RATE = 2000.0
"""Declarations per second of the attacker."""
HOLD = 2000
"""Declarations of each kind the attacker holds at once."""
FLOOD_S = 3.0
BENCH_FLOOD_S = 10.0
NODES = ("cn", "dn0", "dn1", "gn")
TRANSPORTS = ("mtls", "plain")
ATTACKS = (
    "denied",
    "allowed",
    "denied_distinct",
    "allowed_distinct",
    "keyexpr_distinct",
    "denied_distinct_cn_only",
    "denied_distinct_via_gateway",
    "allowed_distinct_via_gateway",
)
"""Each attack: its mode (``declare-MODE``), ``distinct`` for a key per
declaration, ``cn_only`` when the attacker reaches the CN alone (the DNs on
a network it cannot reach), ``via_gateway`` when it reaches only a ground
gateway (:mod:`tests.faults.gateway`, a zenoh router with the ground's
identity and the mission's access control, connected to the CN)."""


@contextmanager
def _flight(tmp: Path, transport: str) -> Iterator[Live]:
    mission = IGNITER if transport == "mtls" else plain_tcp_mission(IGNITER, tmp / "plain.yaml")
    with live(tmp, mission=mission) as c:
        c.watch_events()
        for name in ("world", "dn0", "dn1", "cn"):
            c.spawn(name)
        c.spawn_node("gn")
        c.ready()
        yield c


def _usage(a: _Mark, b: _Mark) -> dict[str, Any]:
    wall = max(b.t - a.t, 1e-9)
    return {
        "seconds": round(wall, 2),
        "loops": b.counts["cn_loop"] - a.counts["cn_loop"],
        "missed": sum(b.counts[k] - a.counts[k] for k in _SYNC),
        "cpu_pct": {n: round(100 * (b.usage[n][1] - a.usage[n][1]) / wall, 1) for n in a.usage},
        "rss_growth_mb": {n: round(b.usage[n][0] - a.usage[n][0], 1) for n in a.usage},
    }


def _gateway(c: Live, transport: str, log: Path) -> tuple[subprocess.Popen[str], str]:
    """A ground gateway (:mod:`tests.faults.gateway`) on a free port, ready."""
    proto = "tls" if transport == "mtls" else "tcp"
    ep = f"{proto}/127.0.0.1:{free_port()}"
    dep = ["--deployment", str(default_deployment_path(c.mission))] if proto == "tls" else []
    with open(log, "w") as err:
        gw = subprocess.Popen(
            [sys.executable, "-m", "tests.faults.gateway", str(c.path), ep, *dep],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
            cwd=ROOT,
        )
    assert gw.stdout is not None
    line = gw.stdout.readline().strip()
    if line != "ready":
        gw.kill()
        raise AssertionError(f"gateway: {line!r}: {log.read_text()[-2000:]}")
    return gw, ep


def _close_gateway(gw: subprocess.Popen[str]) -> None:
    """End a gateway (idempotent): stdin's end closes its session."""
    if gw.poll() is None and gw.stdin is not None and not gw.stdin.closed:
        gw.stdin.close()
        try:
            gw.wait(10)
        except subprocess.TimeoutExpired:
            gw.kill()
            gw.wait()
    if gw.stdout is not None:
        gw.stdout.close()


def _safed(c: Live, t0: float, t1: float) -> int:
    """``dn_safed`` events the test received between ``t0`` and ``t1``."""
    return sum(1 for t, e in c.drain_events() if t0 <= t <= t1 and e["id"] == "dn_safed")


def case_declaration_flood(tmp: Path, quick: bool) -> CaseResult:
    """Both flights, both attacks (module doc)."""
    r = CaseResult("declaration_flood")
    flood_s = FLOOD_S if quick else BENCH_FLOOD_S
    # The mission PKI (made by the harness for the mTLS flight) goes in the
    # case's own directory, never in the user's configuration.
    old_config = os.environ.get("XDG_CONFIG_HOME")
    os.environ["XDG_CONFIG_HOME"] = str(tmp / "config")
    started: list[Attacker] = []
    started_gw: list[subprocess.Popen[str]] = []
    try:
        for transport in TRANSPORTS:
            sub = tmp / transport
            sub.mkdir()
            with _flight(sub, transport) as c:
                extra: tuple[str, ...] = ("--hold", str(HOLD))
                if transport == "mtls":
                    extra += ("--deployment", str(default_deployment_path(c.mission)))
                launch = operator(c.path, "launch", "--arm")
                out, _ = launch.communicate(timeout=120)
                r.check(f"{transport}_launch_accepted", launch.returncode == 0, out)
                c.wait_for(lambda dv: dv.get_name("cn_state") == "ARMED", 30, "ARMED")
                procs = {n: psutil.Process(c.procs[n].pid) for n in NODES}
                m0 = _Mark(c, procs)
                c.pump_for(flood_s)
                ref = _usage(m0, m1 := _Mark(c, procs))
                ref["dn_safed"] = _safed(c, 0.0, m1.t)  # the flight so far, reference included
                fig: dict[str, Any] = {"reference": ref}
                for what in ATTACKS:
                    mode, *opts = what.split("_")
                    more = ["--distinct"] if "distinct" in opts else []
                    if "only" in opts:
                        more += ["--connect", c.mission.nodes["cn"].listen[0]]
                    watched = procs
                    if "gateway" in opts:
                        gw, gw_ep = _gateway(c, transport, sub / f"{what}.gateway.log")
                        started_gw.append(gw)
                        watched = {**procs, "gateway": psutil.Process(gw.pid)}
                        more += ["--connect", gw_ep]
                    a = Attacker(
                        c.path,
                        f"declare-{mode}",
                        sub / f"{what}.log",
                        rate=RATE,
                        duration=flood_s,
                        extra=(*extra, *more),
                    )
                    started.append(a)
                    a.expect("ready")
                    m0 = _Mark(c, watched)
                    a.go()
                    _lasts(c, a)()
                    res = a.finish()
                    c.pump_for(0.5)  # what the attack left in flight is handled
                    w = _usage(m0, _Mark(c, watched))
                    for gw in started_gw:  # one gateway per attack, gone with it
                        _close_gateway(gw)
                    ref_rate = ref["missed"] / max(ref["loops"], 1)
                    w.update(
                        sent=int(res["sent"]),
                        rate_hz=round(res["rate"]),
                        misses_added_per_loop=round(
                            max(0.0, w["missed"] / max(w["loops"], 1) - ref_rate), 5
                        ),
                        cpu_pct_added={
                            n: round(w["cpu_pct"][n] - ref["cpu_pct"][n], 1) for n in NODES
                        },
                    )
                    # DNs safed in this window (by receipt): the reference
                    # window's own are under "reference" (a loaded box).
                    w["dn_safed"] = _safed(c, m0.t, time.monotonic())
                    fig[what] = w
                    _intact(r, c, f"{transport}_{what}")
                c.wait_for(
                    lambda dv: dv.get_name("cn_state") in ("DEPLOYED", "ABORTED", "NO_FIRE"),
                    90,
                    "the flight's end",
                )
                _intact(r, c, f"{transport}_flight")
                fig["final_state"] = f"{c.now('cn_state')}/{c.now('cn_fault')}"
                r.check(f"{transport}_deployed", fig["final_state"] == "DEPLOYED/NONE")
                r.figures[transport] = fig
    finally:
        for a in started:
            a.close()
        for gw in started_gw:
            _close_gateway(gw)
        if old_config is None:
            os.environ.pop("XDG_CONFIG_HOME", None)
        else:
            os.environ["XDG_CONFIG_HOME"] = old_config
    r.figures["final_state"] = "/".join(
        str(r.figures.get(t, {}).get("final_state")) for t in TRANSPORTS
    )
    r.figures["expected_state"] = "DEPLOYED/NONE/DEPLOYED/NONE"
    r.check("final_state_as_configured", r.figures["final_state"] == r.figures["expected_state"])
    r.figures["forged_applied"] = 0 if r.ok else None
    r.figures["params"] = {"rate_hz": RATE, "hold_per_kind": HOLD, "flood_s": flood_s}
    return r


CASES = {"declaration_flood": case_declaration_flood}
