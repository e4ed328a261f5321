"""Routers in the mission (``ground.routers``), their zenoh config and
access-control rows (zplatform.runtime.router, zplatform.security.deploy),
``zplatform router``'s refusals, and what ``up`` starts for them."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from tests.pki import make_test_pki
from zplatform.cli import supervisor
from zplatform.cli.main import main
from zplatform.errors import ConfigError
from zplatform.mission.load import decode_mission
from zplatform.runtime.router import find_router, link_endpoints, router_config
from zplatform.runtime.transport import zenoh_config
from zplatform.security.deploy import ROUTER, access_control, router_identity

BASE = """
mission: routed
security: {transport: mtls}
nodes:
  cn:  {listen: ['tls/127.0.0.1:7447']}
  dn0: {connect: ['tls/127.0.0.1:7447']}
  gn:  {connect: ['tls/127.0.0.1:7447']}
regions:
  dn0_to_cn:
    - {name: v, type: f64}
ground:
  stations:
    - {name: pad}
    - {name: room, connect: ['tcp/10.1.0.2:7600']}
  operators:
    - {name: fd, roles: [flight_director]}
"""
ROUTERS = """  routers:
    - {name: pad, listen: ['tcp/0.0.0.0:7500'], connect: ['tls/127.0.0.1:7447']}
    - {name: room, listen: ['tcp/0.0.0.0:7600'], connect: ['tcp/10.0.0.9:7500'], start: false}
"""


ROUTER_IDS = ["router-pad", "router-room"]


def mission(extra: str = ROUTERS) -> Any:
    return decode_mission(BASE + extra)


def _get(cfg: Any, key: str) -> Any:
    return json.loads(cfg.get_json(key))


def test_a_router_runs_routers_mode_with_the_missions_tls_and_scouting_off(
    tmp_path: Path,
) -> None:
    m = mission()
    dep = make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn", *ROUTER_IDS])
    r = find_router(m, "room")
    cfg = router_config(m, r.listen, r.connect, deployment=dep, name="room")
    assert _get(cfg, "mode") == "router"
    # tcp/ runs as tls/ in a mission with mutual TLS, as the nodes' endpoints.
    assert _get(cfg, "listen/endpoints") == ["tls/0.0.0.0:7600"]
    assert _get(cfg, "connect/endpoints") == ["tls/10.0.0.9:7500"]
    assert _get(cfg, "scouting/multicast/enabled") is False
    assert _get(cfg, "scouting/gossip/enabled") is False
    assert _get(cfg, "transport/link/tls/listen_certificate").endswith("/router-room.pem")
    assert _get(cfg, "access_control/enabled") is True
    assert link_endpoints(
        decode_mission(BASE.replace("mtls", "plain").replace("tls/", "tcp/")), ["tcp/a:1"]
    ) == ["tcp/a:1"]


def test_a_station_with_a_router_is_a_client_of_it_alone(tmp_path: Path) -> None:
    m = mission()
    dep = make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn", *ROUTER_IDS])
    cfg = zenoh_config(m, None, deployment=dep, via=list(m.ground.stations[1].connect))
    assert _get(cfg, "mode") == "client"
    assert _get(cfg, "connect/endpoints") == ["tls/10.1.0.2:7600"]
    assert _get(cfg, "listen/endpoints") == []


def test_the_router_policy_forwards_the_stations_keys_only_both_ways(tmp_path: Path) -> None:
    m = mission()
    dep = make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn", *ROUTER_IDS])
    acl = access_control(m, dep)
    rules = {r["id"]: r for r in acl["rules"]}
    # One subject per router's own certificate, one forwarding-only policy.
    subjects = [f"s-{router_identity(n)}" for n in ("pad", "room")]
    (policy,) = [p for p in acl["policies"] if p["subjects"] == subjects]
    for n in ("pad", "room"):
        ident = router_identity(n)
        assert {"id": f"s-{ident}", "cert_common_names": [ident]} in acl["subjects"]
    # The shared identity of old is named by no subject: its certificate is denied.
    assert all(ROUTER not in s["cert_common_names"] for s in acl["subjects"])
    assert "egress-all" not in policy["rules"]  # bounded both ways
    keys: dict[tuple[str, str], set[str]] = {}
    for rid in policy["rules"]:
        r = rules[rid]
        for flow in r["flows"]:
            for msg in r["messages"]:
                keys.setdefault((flow, msg), set()).update(r["key_exprs"])
    v = "rocket"
    carried = {
        f"{v}/cn/telemetry",
        f"{v}/*/events",
        f"{v}/cn/downlink",
        f"{v}/cn/to_dn0",
        f"{v}/dn0/to_cn",
        f"{v}/gn/to_cn",
    }
    for flow in ("ingress", "egress"):
        assert keys[(flow, "put")] == carried
        assert keys[(flow, "declare_subscriber")] == carried
        assert keys[(flow, "declare_queryable")] == {f"{v}/cn/clock", f"{v}/archive/query"}
        assert keys[(flow, "query")] == {f"{v}/cn/clock", f"{v}/archive/query"}
        assert keys[(flow, "liveliness_token")] == {f"{v}/*/alive", f"{v}/*/standby"}
    assert ("ingress", "delete") not in keys
    # A mission without routers has no router subject at all.
    plain = access_control(mission(""), dep)
    assert all(not s["id"].startswith(f"s-{ROUTER}") for s in plain["subjects"])
    # One router removed: its subject goes, the other's stays as it was.
    only_pad = access_control(
        mission(ROUTERS.splitlines(keepends=True)[0] + ROUTERS.splitlines(keepends=True)[1]), dep
    )
    assert [s for s in only_pad["subjects"] if s["id"].startswith(f"s-{ROUTER}")] == [
        {"id": "s-router-pad", "cert_common_names": ["router-pad"]}
    ]


@pytest.mark.parametrize(
    ("extra", "path", "text"),
    [
        (
            "  routers:\n    - {name: gn, listen: ['tcp/0.0.0.0:1']}\n",
            "$.ground.routers[0].name",
            "duplicate router or node name 'gn'",
        ),
        ("  routers:\n    - {name: pad}\n", "$.ground.routers[0]", "neither listens nor connects"),
        (
            "  routers:\n    - {name: pad, listen: ['tcp/nowhere']}\n",
            "$.ground.routers[0].listen[0]",
            "needs host:port",
        ),
    ],
)
def test_bad_routers_are_config_errors_at_their_path(extra: str, path: str, text: str) -> None:
    with pytest.raises(ConfigError) as exc:
        mission(extra)
    assert exc.value.path == path and text in str(exc.value)


def test_zplatform_router_refuses_an_unknown_name_and_no_endpoints(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(BASE + ROUTERS)
    assert main(["router", str(path), "--name", "rom"]) == 2
    assert "lists no router 'rom' (routers: pad, room)" in capsys.readouterr().err
    assert main(["router", str(path)]) == 2
    assert "give --name NAME" in capsys.readouterr().err


def test_up_starts_the_routers_marked_start_and_the_ground_as_its_operator(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(BASE + ROUTERS)
    m = decode_mission(path.read_text())
    seen: dict[str, Any] = {}

    def fake_supervise(mission: Any, spawn: Any, tmp: Any, reg: Any, **kw: Any) -> int:
        seen.update(spawn=spawn, routers=kw["routers"])
        return 0

    reg = SimpleNamespace(
        name="routed", mission_file=str(path), update=lambda **kw: None, remove=lambda: None
    )
    monkeypatch.setattr(supervisor, "_supervise", fake_supervise)
    monkeypatch.setattr("zplatform.cli.registry.register", lambda *a: reg)
    assert supervisor.run_up(m, str(path), quiet=True, operator=("fd", "room")) == 0
    assert seen["routers"] == {"router:pad": ["router", str(path.resolve()), "--name", "pad"]}
    assert seen["spawn"]["gn"][-4:] == ["--operator", "fd", "--station", "room"]


def test_keygen_writes_a_certificate_per_router_and_removing_one_keeps_the_others(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each router its own certificate (CN and SAN its identity), private
    key 0600; a router removed from the mission needs nothing new: keygen
    makes no certificate, the others' files are byte for byte the same."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    from zplatform.core.auth import KEY_ENV, KEY_FILE_ENV
    from zplatform.security.pki import ensure_mission_pki

    monkeypatch.delenv(KEY_ENV, raising=False)
    monkeypatch.delenv(KEY_FILE_ENV, raising=False)
    path, out = tmp_path / "m.yaml", tmp_path / "keys"
    path.write_text(BASE + ROUTERS)
    assert main(["keygen", str(path), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    for name in ("pad", "room"):
        ident = router_identity(name)
        cert = x509.load_pem_x509_certificate((out / f"{ident}.pem").read_bytes())
        assert [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)] == [
            ident
        ]
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert san.get_values_for_type(x509.DNSName) == [ident]
        assert (out / f"{ident}.tls.key").stat().st_mode & 0o777 == 0o600
        assert f"{ident}.pem {ident}.tls.key" in said and f"router {name}'s host" in said
    assert not (out / "router.pem").exists()  # no shared certificate any more
    before = {p.name: p.read_bytes() for p in out.glob("router-pad*")}
    only_pad = decode_mission(BASE + ROUTERS.splitlines(keepends=True)[0] + ROUTERS.splitlines()[1])
    assert ensure_mission_pki(only_pad, out).made == []
    assert {p.name: p.read_bytes() for p in out.glob("router-pad*")} == before


def _swap_cert(tmp_path: Path, identity: str, to: str) -> Any:
    """The test PKI with ``identity``'s entry naming ``to``'s files (a
    certificate copied or named in its place)."""
    import yaml

    make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn", *ROUTER_IDS])
    dep_file = tmp_path / "pki" / "deployment.yaml"
    raw = yaml.safe_load(dep_file.read_text())
    raw["nodes"][identity] = {"cert": f"{to}.pem", "key": f"{to}.tls.key"}
    dep_file.write_text(yaml.safe_dump(raw))
    from zplatform.security.deploy import load_deployment

    return load_deployment(dep_file)


@pytest.mark.parametrize(
    ("name", "to", "whose"),
    [("room", "router-pad", "router-pad"), ("pad", "dn0", "dn0")],
    ids=["router A's as router B's", "a node's as a router's"],
)
def test_a_router_refuses_a_certificate_not_its_own(
    tmp_path: Path, name: str, to: str, whose: str
) -> None:
    m = mission()
    dep = _swap_cert(tmp_path, router_identity(name), to)
    r = find_router(m, name)
    with pytest.raises(ConfigError) as exc:
        router_config(m, r.listen, r.connect, deployment=dep, name=name)
    assert exc.value.path == f"$.nodes.{router_identity(name)}.cert"
    assert f"is {whose}'s, not {router_identity(name)}'s" in str(exc.value)


def test_a_router_without_its_own_certificate_or_name_does_not_start(tmp_path: Path) -> None:
    m = mission()
    dep = make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn", "router-pad"])
    r = find_router(m, "room")
    with pytest.raises(ConfigError) as exc:
        router_config(m, r.listen, r.connect, deployment=dep, name="room")
    assert "no cert and key for router 'room'" in str(exc.value) and "keygen" in str(exc.value)
    with pytest.raises(ConfigError) as exc:
        router_config(m, r.listen, r.connect, deployment=dep)
    assert "presents its own certificate: name it" in str(exc.value)
