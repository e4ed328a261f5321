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
from zplatform.security.deploy import ROUTER, access_control

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


def mission(extra: str = ROUTERS) -> Any:
    return decode_mission(BASE + extra)


def _get(cfg: Any, key: str) -> Any:
    return json.loads(cfg.get_json(key))


def test_a_router_runs_routers_mode_with_the_missions_tls_and_scouting_off(
    tmp_path: Path,
) -> None:
    m = mission()
    dep = make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn", ROUTER])
    r = find_router(m, "room")
    cfg = router_config(m, r.listen, r.connect, deployment=dep)
    assert _get(cfg, "mode") == "router"
    # tcp/ runs as tls/ in a mission with mutual TLS, as the nodes' endpoints.
    assert _get(cfg, "listen/endpoints") == ["tls/0.0.0.0:7600"]
    assert _get(cfg, "connect/endpoints") == ["tls/10.0.0.9:7500"]
    assert _get(cfg, "scouting/multicast/enabled") is False
    assert _get(cfg, "scouting/gossip/enabled") is False
    assert _get(cfg, "transport/link/tls/listen_certificate").endswith("router.pem")
    assert _get(cfg, "access_control/enabled") is True
    assert link_endpoints(
        decode_mission(BASE.replace("mtls", "plain").replace("tls/", "tcp/")), ["tcp/a:1"]
    ) == ["tcp/a:1"]


def test_a_station_with_a_router_is_a_client_of_it_alone(tmp_path: Path) -> None:
    m = mission()
    dep = make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn", ROUTER])
    cfg = zenoh_config(m, None, deployment=dep, via=list(m.ground.stations[1].connect))
    assert _get(cfg, "mode") == "client"
    assert _get(cfg, "connect/endpoints") == ["tls/10.1.0.2:7600"]
    assert _get(cfg, "listen/endpoints") == []


def test_the_router_policy_forwards_the_stations_keys_only_both_ways(tmp_path: Path) -> None:
    m = mission()
    dep = make_test_pki(tmp_path / "pki", ["cn", "dn0", "gn", ROUTER])
    acl = access_control(m, dep)
    rules = {r["id"]: r for r in acl["rules"]}
    (policy,) = [p for p in acl["policies"] if p["subjects"] == [f"s-{ROUTER}"]]
    assert {"id": f"s-{ROUTER}", "cert_common_names": [ROUTER]} in acl["subjects"]
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
    assert all(s["id"] != f"s-{ROUTER}" for s in plain["subjects"])


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
