"""mTLS and access control across network namespaces (zplatform.security.deploy).

First, the default: the recovery igniter (hazardous commands, so
``security.transport: auto`` runs mutual TLS) with the PKI made where ``up``
and ``keygen`` make it; every node finds it there, with no setting of its
own. A probe with the mission's ``tool`` cert sees the flight; a probe
without a cert, in a namespace of its own, gets no session, sees no key and
reaches no node.

Then the rules, on the minimal mission with ``security.transport: mtls``
(its ``tcp/`` endpoints run as ``tls/``) and a test PKI named by
``ZPLATFORM_DEPLOYMENT``: cn, dn0 and gn as ``zplatform node`` processes in
three namespaces. Probes (tests/faults/tls_probe.py) in a fourth namespace
then show:

* a peer with the mission's ``tool`` cert connects and receives telemetry
  (the set-up works, and telemetry is how the test observes the CN);
* a peer without a cert, and one with a cert from another CA, get no zenoh
  session at all: no peers, no telemetry, no reply;
* a peer with a *valid* cert the ACL does not allow is denied, and the
  same request from an identity the ACL allows shows the path works:

  - ``gn``'s cert queries ``rocket/dn0/to_cn`` with a garbage payload:
    ``dn0_bad_frames`` stays 0; the same query with ``cn``'s cert makes it
    rise (dn0's intake refuses every bad query it gets unread, with no
    reply, and counts it: so the gn probe's query never reached it);
  - the ``tool`` cert (not allowed to command) puts garbage on
    ``rocket/gn/to_cn``: the CN's ``cn_cmd_rejects`` and ``cn_bad_frames``
    stay 0; the same put with ``gn``'s cert makes them rise;
  - ``gn``'s cert puts garbage on ``rocket/cn/telemetry``: the GN node, which
    is connected to the probe and subscribes to telemetry, counts no bad
    telemetry frame (its summary's ``telemetry_bad``).

Every wait is bounded; processes and namespaces go with the fixture.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.faults.missions import netns_mission
from tests.faults.netns import NetnsHost
from tests.faults.test_netns import readline
from tests.pki import make_test_pki
from zplatform.mission.load import load_mission
from zplatform.security.deploy import DEPLOYMENT_ENV
from zplatform.security.pki import ensure_mission_pki

ROOT = Path(__file__).resolve().parents[2]
PY = sys.executable


class Probe:
    """A tls_probe process in ``host``; ``wait=False``: call :meth:`ready`
    later (probes start side by side)."""

    def __init__(
        self, host: NetnsHost, mission: Path, env: dict[str, str], *ident: str, wait: bool = True
    ) -> None:
        self.p = host.popen(
            [PY, "-m", "tests.faults.tls_probe", str(mission), *ident],
            pipe_stdio=True,
            env=env,
            cwd=ROOT,
        )
        if wait:
            self.ready()

    def ready(self) -> Probe:
        assert readline(self.p, 30) == "ready"
        return self

    def send(self, **req: Any) -> None:
        """Send one request; :meth:`reply` reads its answer (so several
        probes can be asked at once)."""
        assert self.p.stdin is not None
        self.p.stdin.write(json.dumps(req) + "\n")
        self.p.stdin.flush()

    def reply(self, timeout_s: float = 10) -> dict[str, Any]:
        out: dict[str, Any] = json.loads(readline(self.p, timeout_s + 10))
        return out

    def ask(self, timeout_s: float = 10, **req: Any) -> dict[str, Any]:
        self.send(**req)
        return self.reply(timeout_s)

    def telemetry(self, timeout: float, count: int = 1) -> dict[str, Any]:
        return self.ask(timeout, op="telemetry", timeout=timeout, count=count)

    def get(self, key: str, timeout: float = 1.0) -> dict[str, Any]:
        """``{"ok": n, "err": n, "why": [...]}`` replies to a garbage get."""
        return self.ask(timeout, op="get", key=key, timeout=timeout)

    def put(self, key: str) -> None:
        assert self.ask(op="put", key=key) == {"done": True}

    def peers(self) -> int:
        return int(self.ask(op="peers")["peers"])


def _ident(pki: Path, name: str) -> list[str]:
    return [
        "--ca",
        str(pki / "ca.pem"),
        "--cert",
        str(pki / f"{name}.pem"),
        "--key",
        str(pki / f"{name}.tls.key"),
    ]


# The same refusal as tests/integration/test_secure_transport.py's, across
# namespaces: with the soaks (-m slow).
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_the_default_transport_gives_an_unknown_peer_no_session(
    netns_hosts: Callable[..., list[NetnsHost]], tmp_path: Path
) -> None:
    h_cn, h_dn, h_gn, h_x = netns_hosts(4)
    # The world serves both DNs' boards on loopback: they share a host.
    path = netns_mission(
        ROOT / "configs" / "recovery_igniter.yaml",
        tmp_path / "m.yaml",
        {"cn": h_cn, "dn0": h_dn, "dn1": h_dn, "gn": h_gn},
    )
    mission = load_mission(path)
    assert mission.security.transport == "auto" and mission.mtls
    # What `zplatform keygen` and the first `up` make, in the session's config
    # directory (tests/conftest.py), where every node below looks by itself.
    pki = Path(ensure_mission_pki(mission).directory)
    bare = {k: v for k, v in os.environ.items() if k != DEPLOYMENT_ENV}
    node = [PY, "-m", "zplatform", "node", str(path)]
    world = h_dn.popen(
        [PY, "-m", "zplatform", "world", str(path), "--no-realtime"],
        pipe_stdio=True,
        env=bare,
        cwd=ROOT,
    )
    assert readline(world, 60) == "READY"
    for dn in ("dn0", "dn1"):
        h_dn.popen([*node, dn], log=tmp_path / f"{dn}.log", env=bare, cwd=ROOT)
    h_gn.popen([*node, "gn", "--duration", "200"], log=tmp_path / "gn.log", env=bare, cwd=ROOT)
    cn = h_cn.popen(
        [*node, "cn", "--duration", "200", "--ground-wait", "30"],
        log=tmp_path / "cn.log",
        env=bare,
        cwd=ROOT,
    )

    def logs() -> str:
        return "\n".join(
            f"--- {n}\n" + (tmp_path / f"{n}.log").read_text()[-2000:]
            for n in ("cn", "dn0", "dn1", "gn")
        )

    legit = Probe(h_x, path, bare, *_ident(pki, "tool"))
    t = legit.telemetry(90, count=20)
    assert t["new"] == 20, logs()
    x = Probe(h_x, path, bare)  # no certificate
    assert x.telemetry(3)["received"] == 0
    assert x.peers() == 0
    assert x.get("rocket/dn0/to_cn") == {"ok": 0, "err": 0, "why": []}
    x.put("rocket/gn/to_cn")
    t = legit.telemetry(10, count=50)
    assert t["new"] == 50 and t["cn_bad_frames"] == 0 and t["cn_cmd_rejects"] == 0, t
    assert cn.poll() is None, logs()


@pytest.mark.timeout(240)
def test_unknown_peers_cannot_connect_and_the_acl_denies_what_a_cert_may_not_do(
    netns_hosts: Callable[..., list[NetnsHost]], tmp_path: Path
) -> None:
    h_cn, h_dn, h_gn, h_x = netns_hosts(4)
    path = netns_mission(
        ROOT / "configs" / "minimal.yaml",
        tmp_path / "m.yaml",
        {"cn": h_cn, "dn0": h_dn, "gn": h_gn},
    )
    raw = yaml.safe_load(path.read_text())
    raw["security"] = {"transport": "mtls"}  # the endpoints stay tcp/: they run as tls/
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    pki = tmp_path / "pki"
    make_test_pki(pki, ["cn", "dn0", "gn"])
    foreign = tmp_path / "foreign"
    make_test_pki(foreign, ["gn"], tool=False, ca_name="intruder CA")
    env = {DEPLOYMENT_ENV: str(pki / "deployment.yaml")}

    # `zplatform check` says which deployment a session would use (none on a
    # host without one: checking a mission needs no certificate).
    check = [PY, "-m", "zplatform", "check", str(path)]
    bare = {k: v for k, v in os.environ.items() if k != DEPLOYMENT_ENV}
    bare["XDG_CONFIG_HOME"] = str(tmp_path / "empty")
    r = subprocess.run(check, capture_output=True, text=True, env=bare, cwd=ROOT, timeout=60)
    assert r.returncode == 0 and "no deployment on this host" in r.stdout, r
    r = subprocess.run(
        check, capture_output=True, text=True, env={**bare, **env}, cwd=ROOT, timeout=60
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"mutual TLS with access control (security.transport is mtls); deployment {pki}" in (
        r.stdout
    )

    node = [PY, "-m", "zplatform", "node", str(path)]
    h_dn.popen([*node, "dn0"], log=tmp_path / "dn0.log", env=env, cwd=ROOT)
    gn = h_gn.popen(
        [*node, "gn", "--duration", "200", "--summary", str(tmp_path / "gn.json")],
        log=tmp_path / "gn.log",
        env=env,
        cwd=ROOT,
    )
    cn = h_cn.popen(
        [*node, "cn", "--duration", "200", "--ground-wait", "30"],
        log=tmp_path / "cn.log",
        env=env,
        cwd=ROOT,
    )

    def logs() -> str:
        return "\n".join(
            f"--- {n}\n" + (tmp_path / f"{n}.log").read_text()[-2000:] for n in ("cn", "dn0", "gn")
        )

    # Every probe starts now, side by side (each is a process): a legitimate
    # peer (the mission's tool cert); two unknown ones, without a cert and
    # with a cert from another CA; and two valid certs for the ACL's rules.
    legit = Probe(h_x, path, env, *_ident(pki, "tool"), wait=False)
    unknown = [Probe(h_x, path, env, *ident, wait=False) for ident in ([], _ident(foreign, "gn"))]
    as_gn = Probe(h_x, path, env, *_ident(pki, "gn"), wait=False)
    as_cn = Probe(h_x, path, env, *_ident(pki, "cn"), wait=False)
    for probe in (legit, *unknown, as_gn, as_cn):
        probe.ready()

    # The legitimate peer sees the mission run.
    t = legit.telemetry(90, count=20)
    assert t["new"] == 20, logs()
    assert t["cn_bad_frames"] == 0 and t["cn_cmd_rejects"] == 0, t
    assert legit.peers() >= 1

    # Unknown peers: no cert at all, or a cert from another CA. Both watch
    # for telemetry over the same 3 s.
    for x in unknown:
        x.send(op="telemetry", timeout=3, count=1)
    for x in unknown:
        assert x.reply(3)["received"] == 0
    for x in unknown:
        assert x.peers() == 0
        assert x.get("rocket/dn0/to_cn") == {"ok": 0, "err": 0, "why": []}
        x.put("rocket/gn/to_cn")
        x.put("rocket/cn/telemetry")

    # A valid cert the ACL does not allow to query a DN: the query never
    # reaches dn0; with the CN's cert the same query does.
    assert as_gn.telemetry(30)["new"] == 1  # connected and receiving: a legit peer
    assert as_gn.get("rocket/dn0/to_cn") == {"ok": 0, "err": 0, "why": []}
    as_gn.put("rocket/cn/telemetry")  # only cn may put its telemetry
    t = legit.telemetry(10, count=50)  # half a second of loops
    assert t["cn_bad_frames"] == 0 and t["dn0_bad_frames"] == 0, t
    for _ in range(50):  # until the probe's session has learnt dn0's queryable
        # dn0's intake refuses the garbage unread (no reply) and counts it.
        assert as_cn.get("rocket/dn0/to_cn", 0.5) == {"ok": 0, "err": 0, "why": []}
        t = legit.telemetry(10, count=10)
        if t["dn0_bad_frames"]:
            break
    # dn0 counts every bad query it gets: the gn probe's, uncounted, never got there.
    assert t["dn0_bad_frames"] >= 1 and t["cn_bad_frames"] == 0, t

    # Commands: the tool cert may not put them (may_command false); gn may.
    # The CN counts a garbage request it takes in cn_cmd_rejects.
    legit.put("rocket/gn/to_cn")
    t = legit.telemetry(10, count=50)
    assert t["cn_cmd_rejects"] == 0 and t["cn_bad_frames"] == 0, (t, logs())
    for _ in range(50):
        as_gn.put("rocket/gn/to_cn")
        t = legit.telemetry(10, count=10)
        if t["cn_cmd_rejects"]:
            break
    assert t["cn_cmd_rejects"] >= 1 and t["cn_bad_frames"] >= 1, (t, logs())

    # The GN node got telemetry all along and no forged snapshot.
    assert cn.poll() is None, logs()
    gn.send_signal(signal.SIGTERM)
    assert gn.wait(timeout=30) == 0, logs()
    s = json.loads((tmp_path / "gn.json").read_text())
    assert s["telemetry_received"] > 0 and s["telemetry_bad"] == 0, s
