"""Tests of zplatform.deploy: deployment files, their fit with the mission,
and the zenoh config pieces (mTLS, access control) generated from them.

Behaviour on the wire (a foreign peer cannot connect, the ACL denies) is
tested across network namespaces in tests/faults/test_tls_acl.py."""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from tests.pki import make_test_pki
from zplatform.deploy import (
    DEPLOYMENT_ENV,
    Deployment,
    DeploymentError,
    access_control,
    load_deployment,
    tls_settings,
    zenoh_settings,
)
from zplatform.errors import ConfigError
from zplatform.mission import decode_mission
from zplatform.transport import zenoh_config

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")

TLS_MISSION = """
mission: tlstest
nodes:
  cn:  {listen: ['tls/10.0.0.1:7447']}
  dn0: {listen: ['tls/10.0.0.2:7447'], connect: ['tls/10.0.0.1:7447']}
  gn:  {connect: ['tls/10.0.0.1:7447']}
regions:
  dn0_to_cn:
    - {name: v, type: f64}
"""


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("pki")
    make_test_pki(d, ["cn", "dn0", "gn"])
    return d


@pytest.fixture
def with_deployment(pki: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    monkeypatch.setenv(DEPLOYMENT_ENV, str(pki / "deployment.yaml"))
    yield pki / "deployment.yaml"


def _write(tmp_path: Path, pki: Path, text: str) -> Path:
    p = tmp_path / "deployment.yaml"
    p.write_text(text.replace("PKI", str(pki)))
    return p


GOOD = """
ca: PKI/ca.pem
nodes:
  cn: {cert: PKI/cn.pem, key: PKI/cn.key}
  dn0: {cert: PKI/dn0.pem, key: PKI/dn0.key}
  gn: {cert: PKI/gn.pem, key: PKI/gn.key}
"""


def test_test_pki_writes_a_deployment_with_absolute_paths(pki: Path) -> None:
    dep = load_deployment(pki / "deployment.yaml")
    assert dep.ca == str(pki / "ca.pem")
    assert set(dep.nodes) == {"cn", "dn0", "gn"}
    assert dep.nodes["cn"].key == str(pki / "cn.key")
    assert dep.tool is not None and not dep.tool.may_command and dep.access_control


def test_a_tls_mission_loads_only_with_a_deployment(
    with_deployment: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    decode_mission(TLS_MISSION)
    monkeypatch.delenv(DEPLOYMENT_ENV)
    with pytest.raises(ConfigError) as ei:
        decode_mission(TLS_MISSION)
    assert ei.value.path == "$.nodes.cn.listen[0]" and DEPLOYMENT_ENV in str(ei.value)


def test_a_deployment_without_a_tls_node_is_refused_at_mission_load(
    pki: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    p = _write(tmp_path, pki, GOOD.replace("  gn: {cert: PKI/gn.pem, key: PKI/gn.key}\n", ""))
    monkeypatch.setenv(DEPLOYMENT_ENV, str(p))
    with pytest.raises(DeploymentError) as ei:
        decode_mission(TLS_MISSION)
    assert "'gn' has tls/ endpoints" in str(ei.value) and ei.value.path == "$.nodes"


@pytest.mark.parametrize(
    ("edit", "path", "words"),
    [
        (("cert: PKI/cn.pem", "certs: PKI/cn.pem"), "$.nodes.cn", "unknown field `certs`"),
        (("key: PKI/dn0.key", "key: PKI/nope.key"), "$.nodes.dn0.key", "no such file"),
        (("ca: PKI/ca.pem", "ca: PKI/none.pem"), "$.ca", "no such file"),
        (("ca: PKI/ca.pem", "ca: 7"), "$.ca", "Expected `str`"),
        (("ca: PKI/ca.pem\n", ""), "$", "missing required field `ca`"),
        (("nodes:", "access_control: maybe\nnodes:"), "$.access_control", "Expected `bool`"),
        (("  gn:", "  dn9:"), "$.nodes.dn9", "not in mission"),
    ],
)
def test_deployment_errors_name_the_yaml_path(
    pki: Path, tmp_path: Path, edit: tuple[str, str], path: str, words: str
) -> None:
    p = _write(tmp_path, pki, GOOD.replace(*edit))
    with pytest.raises(DeploymentError) as ei:
        load_deployment(p, decode_mission(TLS_MISSION.replace("tls/", "tcp/")))
    assert ei.value.path == path, str(ei.value)
    assert words in str(ei.value) and str(p) in str(ei.value)


def test_unreadable_and_non_yaml_deployments_are_refused(tmp_path: Path) -> None:
    with pytest.raises(DeploymentError, match="cannot read deployment file"):
        load_deployment(tmp_path / "absent.yaml")
    (tmp_path / "bad.yaml").write_text("ca: [unclosed\n")
    with pytest.raises(DeploymentError, match="not valid YAML"):
        load_deployment(tmp_path / "bad.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(DeploymentError, match="mapping"):
        load_deployment(tmp_path / "list.yaml")


def test_relative_paths_are_relative_to_the_deployment_file(pki: Path, tmp_path: Path) -> None:
    for f in pki.iterdir():
        shutil.copy(f, tmp_path / f.name)
    sub = tmp_path / "etc"
    sub.mkdir()
    (sub / "d.yaml").write_text("ca: ../ca.pem\nnodes: {cn: {cert: ../cn.pem, key: ../cn.key}}\n")
    dep = load_deployment(sub / "d.yaml")
    assert dep.ca == str((tmp_path / "ca.pem").resolve())
    assert dep.nodes["cn"].cert == str((tmp_path / "cn.pem").resolve())


def test_access_control_needs_every_endpoint_on_tls(pki: Path, tmp_path: Path) -> None:
    p = _write(tmp_path, pki, GOOD)
    m = decode_mission(TLS_MISSION.replace("tls/", "tcp/"))  # loads without a deployment
    m.nodes["cn"].listen[0] = "tls/10.0.0.1:7447"  # then mixed, as a loaded mission could be
    with pytest.raises(DeploymentError) as ei:
        load_deployment(p, m)
    assert ei.value.path == "$.access_control" and "gn: tcp/10.0.0.1:7447" in str(ei.value)
    p = _write(tmp_path, pki, GOOD + "access_control: false\n")
    load_deployment(p, m)


def test_tls_settings_are_mutual_tls_with_the_nodes_identity(pki: Path) -> None:
    dep = load_deployment(pki / "deployment.yaml")
    t = tls_settings(dep, "dn0")
    assert t["root_ca_certificate"] == dep.ca and t["enable_mtls"] is True
    assert t["listen_certificate"] == t["connect_certificate"] == dep.nodes["dn0"].cert
    assert t["listen_private_key"] == t["connect_private_key"] == dep.nodes["dn0"].key
    assert t["verify_name_on_connect"] is False
    assert tls_settings(dep, None)["listen_certificate"] == str(pki / "tool.pem")
    no_tool = Deployment(ca=dep.ca, nodes=dep.nodes)
    with pytest.raises(DeploymentError, match="tools") as ei:
        tls_settings(no_tool, None)
    assert ei.value.path == "$.tool"


def _policy(acl: dict[str, Any], who: str) -> list[dict[str, Any]]:
    (pol,) = [p for p in acl["policies"] if p["subjects"] == [f"s-{who}"]]
    by_id = {r["id"]: r for r in acl["rules"]}
    return [by_id[r] for r in pol["rules"]]


def _allowed(acl: dict[str, Any], who: str, message: str, key: str) -> bool:
    """Whether ``who`` may send ``message`` on exactly ``key`` (ingress)."""
    return any(
        r["flows"] == ["ingress"] and message in r["messages"] and key in r["key_exprs"]
        for r in _policy(acl, who)
    )


def test_acl_follows_the_key_space(with_deployment: Path) -> None:
    m = decode_mission(TLS_MISSION)
    dep = load_deployment(with_deployment, m)
    acl = access_control(m, dep)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects == {"s-cn": ["cn"], "s-dn0": ["dn0"], "s-gn": ["gn"], "s-tool": ["tool"]}
    assert _allowed(acl, "cn", "query", "rocket/dn0/to_cn")
    assert not _allowed(acl, "gn", "query", "rocket/dn0/to_cn")
    assert _allowed(acl, "cn", "put", "rocket/cn/**")
    assert not any("rocket/cn/**" in r["key_exprs"] for r in _policy(acl, "gn"))
    assert _allowed(acl, "gn", "put", "rocket/gn/**")
    assert _allowed(acl, "dn0", "reply", "rocket/dn0/**")
    assert _allowed(acl, "dn0", "query", "rocket/cn/clock")
    assert not any(
        _allowed(acl, "tool", msg, k)
        for msg in ("put", "query")
        for k in ["rocket/gn/to_cn", "rocket/**"]
    )
    assert dep.tool is not None
    operator = msgspec.structs.replace(
        dep, tool=msgspec.structs.replace(dep.tool, may_command=True)
    )
    assert _allowed(access_control(m, operator), "tool", "put", "rocket/gn/to_cn")


def test_only_the_ground_and_the_tools_may_ask_the_cn_recorder(with_deployment: Path) -> None:
    key = "rocket/cn/recorder"
    m = decode_mission(TLS_MISSION)  # no flight recorder: nobody may ask
    acl = access_control(m, load_deployment(with_deployment, m))
    assert not any(_allowed(acl, who, "query", key) for who in ("cn", "dn0", "gn", "tool"))
    m = decode_mission(TLS_MISSION + "recorder: {}\n")
    acl = access_control(m, load_deployment(with_deployment, m))
    assert _allowed(acl, "gn", "query", key) and _allowed(acl, "tool", "query", key)
    assert not _allowed(acl, "dn0", "query", key)
    assert _allowed(acl, "cn", "reply", "rocket/cn/**")  # the CN answers on its own key


def test_zenoh_accepts_the_generated_config(with_deployment: Path) -> None:
    m = decode_mission(TLS_MISSION)
    dep = load_deployment(with_deployment, m)
    for node in ["cn", "dn0", "gn", None]:
        cfg = json.loads(str(zenoh_config(m, node, deployment=dep)))
        tls = cfg["transport"]["link"]["tls"]
        assert tls["enable_mtls"] is True and tls["root_ca_certificate"] == dep.ca
        assert cfg["access_control"]["enabled"] is True
        assert len(cfg["access_control"]["policies"]) == 4


def test_a_mission_without_tls_gets_nothing_from_a_deployment(with_deployment: Path) -> None:
    m = decode_mission(TLS_MISSION.replace("tls/", "tcp/"))
    dep = load_deployment(with_deployment, m)
    assert zenoh_settings(m, dep, "cn") == {}
    cfg = json.loads(str(zenoh_config(m, "cn", deployment=dep)))
    assert cfg["access_control"]["enabled"] is False


def test_a_foreign_ca_makes_other_certs(pki: Path, tmp_path: Path) -> None:
    other = make_test_pki(tmp_path, ["gn"], tool=False, ca_name="intruder CA")
    assert other.tool is None and Path(other.ca).read_bytes() != (pki / "ca.pem").read_bytes()
