"""Tests of zplatform.security.deploy: deployment files, their fit with the mission,
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
import zenoh

from tests.pki import make_test_pki
from zplatform.core.auth import KEY_FILE_ENV
from zplatform.errors import CommandError, ConfigError
from zplatform.mission.load import decode_mission
from zplatform.runtime.transport import NodeSession, zenoh_config
from zplatform.security.deploy import (
    DEPLOYMENT_ENV,
    Deployment,
    DeploymentError,
    access_control,
    default_deployment_path,
    find_deployment,
    load_deployment,
    require_deployment,
    tls_settings,
    zenoh_settings,
)

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
    assert dep.nodes["cn"].key == str(pki / "cn.tls.key")
    assert dep.tool is not None and not dep.tool.may_command and dep.access_control


def test_a_tls_mission_loads_anywhere_and_opens_sessions_only_with_a_deployment(
    with_deployment: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    m = decode_mission(TLS_MISSION)
    assert require_deployment(m) == load_deployment(with_deployment, m)
    monkeypatch.delenv(DEPLOYMENT_ENV)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    m = decode_mission(TLS_MISSION)  # checking a mission needs no certificate
    with pytest.raises(DeploymentError) as ei:
        require_deployment(m)
    assert ei.value.path == "$.security.transport"
    for words in (DEPLOYMENT_ENV, "zplatform keygen", str(default_deployment_path(m))):
        assert words in str(ei.value)
    with pytest.raises(DeploymentError):  # and so no session opens
        NodeSession(m, "cn")


def test_a_deployment_without_a_tls_node_is_refused_when_a_session_opens(
    pki: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    p = _write(tmp_path, pki, GOOD.replace("  gn: {cert: PKI/gn.pem, key: PKI/gn.key}\n", ""))
    monkeypatch.setenv(DEPLOYMENT_ENV, str(p))
    with pytest.raises(DeploymentError) as ei:
        require_deployment(decode_mission(TLS_MISSION))
    assert "'gn' has tls/ endpoints" in str(ei.value) and ei.value.path == "$.nodes"


def test_the_default_deployment_is_found_and_the_named_one_comes_first(
    pki: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(DEPLOYMENT_ENV, raising=False)
    monkeypatch.delenv(KEY_FILE_ENV, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    m = decode_mission(TLS_MISSION)
    default = tmp_path / "zplatform" / "keys" / "tlstest" / "deployment.yaml"
    assert default_deployment_path(m) == default and find_deployment(m) is None
    make_test_pki(default.parent, ["cn", "dn0", "gn"])
    assert find_deployment(m) == default
    assert require_deployment(m) == load_deployment(default)
    # Beside the key set ZPLATFORM_KEY_FILE names: its directory, or a file's.
    monkeypatch.setenv(KEY_FILE_ENV, str(pki))
    assert find_deployment(m) == pki / "deployment.yaml"
    monkeypatch.setenv(KEY_FILE_ENV, str(pki / "dn0.keys"))
    assert find_deployment(m) == pki / "deployment.yaml"
    monkeypatch.setenv(KEY_FILE_ENV, str(tmp_path / "keys-elsewhere"))
    assert find_deployment(m) is None
    monkeypatch.delenv(KEY_FILE_ENV)
    monkeypatch.setenv(DEPLOYMENT_ENV, str(pki / "deployment.yaml"))
    assert find_deployment(m) == pki / "deployment.yaml"
    monkeypatch.setenv(DEPLOYMENT_ENV, str(tmp_path / "absent.yaml"))  # named: never skipped
    with pytest.raises(DeploymentError, match="cannot read deployment file"):
        require_deployment(m)


def test_a_tool_that_may_not_command_is_refused_before_a_command_is_lost(
    with_deployment: Path,
) -> None:
    """The ACL would drop its requests unanswered: `cmd` says so at once."""
    m = decode_mission(TLS_MISSION)
    dep = load_deployment(with_deployment, m)
    assert dep.tool is not None and not dep.tool.may_command
    with pytest.raises(DeploymentError, match="may not command") as ei:
        NodeSession(m, None, deployment=dep, commands=True)
    assert ei.value.path == "$.tool.may_command"


def test_a_plain_mission_uses_no_deployment(with_deployment: Path) -> None:
    m = decode_mission(TLS_MISSION.replace("tls/", "tcp/"))
    assert not m.mtls and require_deployment(m) is None


def test_a_host_holds_only_its_own_key_and_it_must_be_private(pki: Path, tmp_path: Path) -> None:
    """The deployment names every node; a session checks the files of the
    identity it presents, and refuses a private key others can read."""
    for f in ("ca.pem", "deployment.yaml", "dn0.pem", "dn0.tls.key"):
        shutil.copy(pki / f, tmp_path / f)
    dep = load_deployment(tmp_path / "deployment.yaml", decode_mission(TLS_MISSION))
    assert tls_settings(dep, "dn0")["listen_private_key"] == str(tmp_path / "dn0.tls.key")
    with pytest.raises(DeploymentError, match="no such file") as ei:
        tls_settings(dep, "cn")
    assert ei.value.path == "$.nodes.cn.cert"
    (tmp_path / "dn0.tls.key").chmod(0o644)
    with pytest.raises(DeploymentError, match="readable by others") as ei:
        tls_settings(dep, "dn0")
    assert ei.value.path == "$.nodes.dn0.key" and "chmod 600" in str(ei.value)


@pytest.mark.parametrize(
    ("edit", "path", "words"),
    [
        (("cert: PKI/cn.pem", "certs: PKI/cn.pem"), "$.nodes.cn", "unknown field `certs`"),
        (("ca: PKI/ca.pem", "ca: PKI/none.pem"), "$.ca", "no such file"),
        (("ca: PKI/ca.pem", "ca: 7"), "$.ca", "Expected `str`"),
        (("ca: PKI/ca.pem\n", ""), "$", "missing required field `ca`"),
        (("nodes:", "access_control: maybe\nnodes:"), "$.access_control", "Expected `bool`"),
        (("  cn:", "  c9:"), "$.nodes", "'cn' has tls/ endpoints but no cert"),
    ],
)
def test_deployment_errors_name_the_yaml_path(
    pki: Path, tmp_path: Path, edit: tuple[str, str], path: str, words: str
) -> None:
    p = _write(tmp_path, pki, GOOD.replace(*edit))
    with pytest.raises(DeploymentError) as ei:
        load_deployment(p, decode_mission(TLS_MISSION))
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
    """Whether a node lets ``who`` send ``message`` on ``key`` (ingress), as
    zenoh decides it: an allow rule for the message whose key expression
    includes ``key`` (so a rule on ``rocket/cn/telemetry`` does not allow a
    subscriber on ``rocket/**``)."""
    k = zenoh.KeyExpr(key)
    return any(
        r["flows"] == ["ingress"]
        and message in r["messages"]
        and any(zenoh.KeyExpr(x).includes(k) for x in r["key_exprs"])
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
    assert _allowed(acl, "dn0", "reply", "rocket/dn0/to_cn")
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


# (who, message, key, allowed): every role declares only what it uses.
_DECLARATIONS = [
    # A tool watches telemetry, events and the downlink; nothing else, and
    # never the whole key space; it serves nothing, holds no token.
    ("tool", "declare_subscriber", "rocket/cn/telemetry", True),
    ("tool", "declare_subscriber", "rocket/*/events", True),
    ("tool", "declare_subscriber", "rocket/dn0/events", True),
    ("tool", "declare_subscriber", "rocket/cn/downlink", True),
    ("tool", "declare_subscriber", "rocket/**", False),
    ("tool", "declare_subscriber", "rocket/cn/*", False),
    ("tool", "declare_subscriber", "rocket/cn/to_dn0", True),  # a region's tap, exact key
    ("tool", "declare_subscriber", "rocket/dn0/to_cn", True),
    ("tool", "declare_subscriber", "rocket/*/to_cn", False),
    ("tool", "declare_subscriber", "rocket/gn/to_cn", False),
    ("tool", "declare_queryable", "rocket/dn0/to_cn", False),
    ("tool", "declare_queryable", "rocket/cn/clock", False),
    ("tool", "reply", "rocket/dn0/to_cn", False),
    ("tool", "liveliness_token", "rocket/dn0/alive", False),
    ("tool", "liveliness_query", "rocket/*/alive", True),
    ("tool", "declare_liveliness_subscriber", "rocket/*/alive", True),
    ("tool", "declare_liveliness_subscriber", "rocket/**", False),
    ("tool", "delete", "rocket/cn/telemetry", False),
    # The ground likewise, plus its own token, commands and the CN's clock.
    ("gn", "declare_subscriber", "rocket/cn/telemetry", True),
    ("gn", "declare_subscriber", "rocket/**", False),
    ("gn", "declare_queryable", "rocket/gn/to_cn", False),
    ("gn", "declare_queryable", "rocket/dn0/to_cn", False),
    ("gn", "liveliness_token", "rocket/gn/alive", True),
    ("gn", "liveliness_token", "rocket/cn/alive", False),
    ("gn", "put", "rocket/gn/to_cn", True),
    ("gn", "query", "rocket/cn/clock", True),
    # A device node serves its own two keys and subscribes to nothing.
    ("dn0", "declare_queryable", "rocket/dn0/to_cn", True),
    ("dn0", "declare_queryable", "rocket/dn0/probe", True),
    ("dn0", "declare_queryable", "rocket/dn0/**", False),
    ("dn0", "declare_queryable", "rocket/cn/clock", False),
    ("dn0", "declare_subscriber", "rocket/cn/to_dn0", False),
    ("dn0", "declare_subscriber", "rocket/**", False),
    ("dn0", "liveliness_token", "rocket/dn0/alive", True),
    ("dn0", "liveliness_token", "rocket/cn/alive", False),
    # The CN serves its clock, listens to commands, queries the DNs.
    ("cn", "declare_queryable", "rocket/cn/clock", True),
    ("cn", "declare_queryable", "rocket/dn0/to_cn", False),
    ("cn", "declare_subscriber", "rocket/gn/to_cn", True),
    ("cn", "declare_subscriber", "rocket/**", False),
    ("cn", "query", "rocket/*/to_cn", True),
]


@pytest.mark.parametrize(("who", "message", "key", "allowed"), _DECLARATIONS)
def test_each_role_declares_only_the_kinds_and_keys_it_uses(
    with_deployment: Path, who: str, message: str, key: str, allowed: bool
) -> None:
    m = decode_mission(TLS_MISSION)
    acl = access_control(m, load_deployment(with_deployment, m))
    assert _allowed(acl, who, message, key) is allowed


def test_bulk_readers_may_subscribe_to_their_channels_only(with_deployment: Path) -> None:
    m = decode_mission(
        TLS_MISSION + "bulk:\n  - {name: img, node: dn0, readers: [cn], type: 'u8[16]'}\n"
    )
    acl = access_control(m, load_deployment(with_deployment, m))
    assert _allowed(acl, "cn", "declare_subscriber", "rocket/dn0/bulk/img")
    assert not _allowed(acl, "gn", "declare_subscriber", "rocket/dn0/bulk/img")
    assert not _allowed(acl, "cn", "declare_subscriber", "rocket/dn0/bulk/*")
    assert _allowed(acl, "dn0", "put", "rocket/dn0/bulk/img")


def test_only_the_ground_and_the_tools_may_ask_the_cn_recorder(with_deployment: Path) -> None:
    key = "rocket/cn/recorder"
    m = decode_mission(TLS_MISSION)  # no flight recorder: nobody may ask
    acl = access_control(m, load_deployment(with_deployment, m))
    assert not any(_allowed(acl, who, "query", key) for who in ("cn", "dn0", "gn", "tool"))
    m = decode_mission(TLS_MISSION + "recorder: {}\n")
    acl = access_control(m, load_deployment(with_deployment, m))
    assert _allowed(acl, "gn", "query", key) and _allowed(acl, "tool", "query", key)
    assert not _allowed(acl, "dn0", "query", key)
    assert _allowed(acl, "cn", "reply", key)  # the CN answers on its own key


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


# ---------------------------------------------------------------------------
# security.transport: which missions run mutual TLS, and their endpoints

HAZARDOUS = """
mission: hz
nodes:
  cn:  {listen: ['tcp/10.0.0.1:7447']}
  dn0: {listen: ['tcp/10.0.0.2:7447'], connect: ['tcp/10.0.0.1:7447']}
  gn:  {connect: ['tcp/10.0.0.1:7447']}
regions:
  dn0_to_cn:
    - {name: v, type: f64}
commands:
  hazardous: [LAUNCH]
"""


def _endpoints(text: str) -> list[str]:
    m = decode_mission(text)
    return [ep for n in m.nodes.values() for ep in [*n.listen, *n.connect]]


def test_hazardous_commands_run_mutual_tls_by_default() -> None:
    m = decode_mission(HAZARDOUS)
    assert m.security.transport == "auto" and m.mtls
    assert (
        _endpoints(HAZARDOUS)
        == ["tls/10.0.0.1:7447", "tls/10.0.0.2:7447"] + ["tls/10.0.0.1:7447"] * 2
    )
    # Without hazardous commands auto is plain; mtls and plain say so outright.
    no_hazard = HAZARDOUS.replace("commands:\n  hazardous: [LAUNCH]\n", "")
    assert not decode_mission(no_hazard).mtls and _endpoints(no_hazard)[0].startswith("tcp/")
    mtls = no_hazard + "security: {transport: mtls}\n"
    assert decode_mission(mtls).mtls and _endpoints(mtls)[0].startswith("tls/")
    plain = HAZARDOUS + "security: {transport: plain}\n"
    assert not decode_mission(plain).mtls and _endpoints(plain)[0].startswith("tcp/")


@pytest.mark.parametrize(
    ("edit", "path", "words"),
    [
        (
            ("tcp/10.0.0.2:7447'], connect", "udp/10.0.0.2:7447'], connect"),
            "$.nodes.dn0.listen[0]",
            "cannot carry mutual TLS, which this mission's links run (security.transport is "
            "auto and the mission has hazardous commands)",
        ),
        (
            ("  gn:  {connect: ['tcp/", "  gn:  {connect: ['ws/"),
            "$.nodes.gn.connect[0]",
            "say security.transport: plain on a closed network",
        ),
        (
            ("commands:", "security: {transport: plain}\ncommands:"),
            None,
            None,
        ),
    ],
)
def test_endpoints_that_cannot_run_tls_are_refused_with_their_path(
    edit: tuple[str, str], path: str | None, words: str | None
) -> None:
    text = HAZARDOUS.replace(*edit)
    if path is None:  # plain: tls/ is the contradiction
        text = text.replace("tcp/10.0.0.1:7447']}\n  dn0", "tls/10.0.0.1:7447']}\n  dn0")
        path, words = "$.nodes.cn.listen[0]", "is tls/, but security.transport is plain"
    with pytest.raises(ConfigError) as ei:
        decode_mission(text)
    assert ei.value.path == path and words in ei.value.reason, str(ei.value)


def test_a_tcp_and_a_tls_listen_on_one_address_are_one_endpoint() -> None:
    text = HAZARDOUS.replace("tcp/10.0.0.2:7447'], connect", "tls/10.0.0.1:7447'], connect")
    with pytest.raises(ConfigError, match="also listened on by cn") as ei:
        decode_mission(text)
    assert ei.value.path == "$.nodes.dn0.listen[0]"


def test_tap_under_access_control_watches_only_what_a_tool_may(with_deployment: Path) -> None:
    from zplatform.ground.tap import tap_keys

    m = decode_mission(TLS_MISSION)
    # The nodes would drop a subscriber on the whole key space, silently:
    # tap subscribes to each key a tool may watch instead, and refuses a key
    # outside them with the list.
    assert tap_keys(m, None)[:3] == ["rocket/cn/telemetry", "rocket/*/events", "rocket/cn/downlink"]
    assert set(tap_keys(m, None)[3:]) == {
        f"rocket/{k}" for dn in m.device_nodes for k in (f"cn/to_{dn}", f"{dn}/to_cn")
    }
    assert tap_keys(m, "rocket/dn0/to_cn") == ["rocket/dn0/to_cn"]
    assert tap_keys(m, "rocket/dn0/events") == ["rocket/dn0/events"]
    with pytest.raises(CommandError, match="rocket/cn/telemetry, rocket/\\*/events"):
        tap_keys(m, "rocket/**")
    plain = decode_mission(TLS_MISSION.replace("tls/", "tcp/"))
    assert tap_keys(plain, None) == ["rocket/**"]
