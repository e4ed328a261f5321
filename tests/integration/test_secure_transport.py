"""Secure transport by default (issue 18), on loopback: the recovery igniter
(hazardous commands, ``security.transport`` left at ``auto``) runs its links
over mutual TLS with access control, from the PKI made where ``up`` makes
it, and every verb finds that PKI the same way.

Real node processes (cn, dn0, dn1); the test's own ground link presents the
mission's ``tool`` certificate and sees the flight. Intruders in this
process, connecting to every node's endpoint as a tool would, get no zenoh
session at all while the legitimate link watches a second of loops: a peer
that trusts the mission CA but has no certificate, a peer with a certificate
from another CA, and a peer speaking plain TCP. None sees a key, none finds
a node alive, and what they put never reaches the CN (the same put from the
legitimate link does). The same, across network namespaces:
tests/faults/test_tls_acl.py.
"""

from __future__ import annotations

import json
import os
import queue
import stat
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.pki import make_test_pki
from zplatform.runtime.transport import open_session, zenoh_config
from zplatform.security.deploy import DEPLOYMENT_ENV, default_deployment_path, load_deployment

from .harness import CONFIGS, ROOT, Cluster, zp_side_by_side

pytestmark = pytest.mark.timeout(180)

GARBAGE = b"\x93intruder\x00not-a-frame"


class _Intruder:
    """A zenoh peer connecting to every node's endpoint, subscribed to everything."""

    def __init__(self, cfg: zenoh.Config, vehicle: str) -> None:
        self.session = open_session(cfg)
        self.vehicle = vehicle
        self.samples: queue.SimpleQueue[str] = queue.SimpleQueue()
        self.sub = self.session.declare_subscriber(
            f"{vehicle}/**",
            zenoh.handlers.Callback(lambda s: self.samples.put(str(s.key_expr)), indirect=False),
            allowed_origin=zenoh.Locality.REMOTE,  # not its own puts
        )

    def peers(self) -> int:
        return len(list(self.session.info.peers_zid()))

    def alive(self) -> list[str]:
        replies = self.session.liveliness().get(f"{self.vehicle}/*/alive", timeout=0.5)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None]

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def _zp(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=90,
        env=dict(os.environ, **(env or {})),
    )


def _insert(cfg: zenoh.Config, key: str, value: Any) -> None:
    cfg.insert_json5(key, json.dumps(value))


# With the soaks (-m slow): unknown peers under the default transport stay
# in the default suite across namespaces (tests/faults/test_tls_acl.py).
@pytest.mark.slow
def test_unknown_peers_get_no_session_under_the_default_transport(tmp_path: Path) -> None:
    with Cluster(CONFIGS / "recovery_igniter.yaml", tmp_path) as c:
        m = c.mission
        assert m.security.transport == "auto" and m.mtls
        assert all(ep.startswith("tls/") for n in m.nodes.values() for ep in n.listen)
        dep = load_deployment(default_deployment_path(m), m)
        for n in ("dn0", "dn1", "cn"):
            c.spawn(n)
        c.wait_for(lambda dv: dv.get_name("cn_state") == "SAFE", 60, "state SAFE")

        # Trusts the mission CA (so only its missing certificate stands in the way).
        no_cert = zenoh_config(m, None)
        _insert(no_cert, "transport/link/tls/root_ca_certificate", dep.ca)
        # Certificates with the mission's names, from a CA of its own.
        foreign = make_test_pki(tmp_path / "foreign", list(m.nodes), ca_name="intruder CA")
        other_ca = zenoh_config(m, None, deployment=foreign)
        # Plain TCP to the TLS ports.
        plain = zenoh_config(m, None)
        _insert(
            plain,
            "connect/endpoints",
            [ep.replace("tls/", "tcp/", 1) for n in m.nodes.values() for ep in n.listen],
        )
        intruders = {
            name: _Intruder(cfg, m.vehicle)
            for name, cfg in (("no cert", no_cert), ("foreign CA", other_ca), ("plain", plain))
        }
        try:
            for x in intruders.values():
                x.session.put(f"{m.vehicle}/gn/to_cn", GARBAGE)
            c.advance(100)  # a second of the flight, seen by the legitimate link
            for name, x in intruders.items():
                seen = []
                while not x.samples.empty():
                    seen.append(x.samples.get_nowait())
                assert (x.peers(), seen, x.alive()) == (0, [], []), name
                x.session.put(f"{m.vehicle}/gn/to_cn", GARBAGE)
            c.advance(20)
            assert int(c.tm.get("cn_bad_frames")) == 0, "an intruder's frame reached the CN"
            assert int(c.tm.get("cn_cmd_rejects")) == 0
            # The same put from the mission's tool (which may command) does reach it.
            c.session.put(f"{m.vehicle}/gn/to_cn", GARBAGE)
            c.wait_for(lambda dv: int(dv.get("cn_bad_frames")) >= 1, 30, "cn_bad_frames >= 1")
        finally:
            for x in intruders.values():
                x.close()

        # Every verb finds the deployment the same way: the mission's default
        # one (where `up` and `keygen` put it), or the file ZPLATFORM_DEPLOYMENT
        # names (a foreign one opens no link), or none on a host without any
        # (no session, and the error says how to make one). The four verbs
        # run side by side: each is a process of its own.
        path = str(c.path)
        foreign_file = str(tmp_path / "foreign" / "deployment.yaml")
        tap, cmd, tap_foreign, tap_none = zp_side_by_side(
            ("tap", path, f"{m.vehicle}/cn/telemetry", "--count", "1", "--timeout", "30"),
            ("cmd", path, "noop"),
            ("tap", path, "--timeout", "3"),
            ("tap", path, "--timeout", "3"),
            envs={
                2: {DEPLOYMENT_ENV: foreign_file},
                3: {"XDG_CONFIG_HOME": str(tmp_path / "empty")},
            },
        )
        assert tap.returncode == 0, tap.stdout + tap.stderr
        assert cmd.returncode == 0 and "ACCEPTED" in cmd.stdout, cmd.stdout + cmd.stderr
        assert tap_foreign.returncode == 1, tap_foreign.stdout + tap_foreign.stderr
        r = tap_none
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert "zplatform keygen" in r.stderr and "security.transport" in r.stderr, r.stderr


def test_up_makes_the_pki_on_first_use_and_keeps_it(tmp_path: Path) -> None:
    """A single host needs no set-up: the first `up` of a hazardous mission
    makes its key set and, beside it, its PKI where every session looks
    (0700/0600), says so, and the next `up` uses them as they are."""
    home = tmp_path / "config"
    # A fifth of a second of loops: what is checked is made before the nodes start.
    up = ("up", str(CONFIGS / "recovery_igniter.yaml"), "--free-ports", "--duration", "0.2")
    env = {"XDG_CONFIG_HOME": str(home), "ZPLATFORM_KEY": ""}  # no master key: a key set
    r = _zp(*up, "--quiet", "--no-realtime", env=env)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    d = home / "zplatform" / "keys" / "recovery_igniter"
    made = "made the certificates of 'recovery_igniter' for mutual TLS (ca, cn, dn0, dn1, gn, tool)"
    assert f"zplatform up: {made} in {d}" in r.stdout, r.stdout
    assert stat.S_IMODE(d.stat().st_mode) == 0o700
    for role in ("cn", "dn0", "dn1", "gn", "tool"):  # each role's files side by side
        assert stat.S_IMODE((d / f"{role}.keys").stat().st_mode) == 0o600, role
        assert stat.S_IMODE((d / f"{role}.tls.key").stat().st_mode) == 0o600, role
        assert (d / f"{role}.pem").is_file(), role
    before = (d / "ca.pem").read_bytes()
    r = _zp(*up, "--quiet", "--no-realtime", env=env)
    assert r.returncode == 0 and "made the certificates" not in r.stdout, r.stdout + r.stderr
    assert (d / "ca.pem").read_bytes() == before
