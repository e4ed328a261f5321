"""The mission PKI (zplatform.security.pki) and `zplatform keygen`'s PKI step: what is
made, where, with which modes, and that a second run adds only what is missing."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from zplatform.mission.load import load_mission
from zplatform.security.deploy import (
    DEPLOYMENT_ENV,
    DeploymentError,
    default_deployment_path,
    load_deployment,
)
from zplatform.security.pki import ensure_mission_pki, ensure_pki

ROOT = Path(__file__).resolve().parents[2]
IGNITER = ROOT / "configs" / "recovery_igniter.yaml"


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.fixture
def config_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    monkeypatch.delenv(DEPLOYMENT_ENV, raising=False)
    return tmp_path / "config"


def test_a_mission_pki_certifies_every_node_by_name_privately(config_home: Path) -> None:
    m = load_mission(IGNITER)
    pki = ensure_mission_pki(m)
    d = config_home / "zplatform" / "keys" / "recovery_igniter"  # beside the key set
    assert Path(pki.directory) == d and Path(pki.deployment) == default_deployment_path(m)
    assert pki.made == ["ca", "cn", "dn0", "dn1", "gn", "tool"]
    assert _mode(d) == 0o700
    files = sorted(p.name for p in d.iterdir() if not p.name.startswith("."))
    assert all(_mode(d / f) == 0o600 for f in files), files
    ca = _cert(d / "ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for name in ("cn", "dn0", "dn1", "gn", "tool"):
        cert = _cert(d / f"{name}.pem")
        cert.verify_directly_issued_by(ca)  # raises if not signed by the mission CA
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert san.get_values_for_type(x509.DNSName) == [name]
        eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} <= set(eku)
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        # A board without a clock boots in the past; nothing expires mid-flight.
        assert cert.not_valid_before_utc.year == 2000 and cert.not_valid_after_utc.year == 9999
    dep = load_deployment(pki.deployment, m)
    assert sorted(dep.nodes) == pki.names == ["cn", "dn0", "dn1", "gn"]
    assert dep.tool is not None and dep.tool.may_command and dep.access_control


def test_a_second_run_keeps_everything_and_adds_only_a_new_node(
    tmp_path: Path, config_home: Path
) -> None:
    d = tmp_path / "pki"
    assert ensure_pki(d, ["cn", "dn0"]) == ["ca", "cn", "dn0", "tool"]
    before = {p.name: p.read_bytes() for p in d.iterdir()}
    assert ensure_pki(d, ["cn", "dn0"]) == []
    assert {p.name: p.read_bytes() for p in d.iterdir()} == before
    assert ensure_pki(d, ["cn", "dn0", "dn1"]) == ["dn1"]
    for f, data in before.items():
        if f != "deployment.yaml":
            assert (d / f).read_bytes() == data, f
    _cert(d / "dn1.pem").verify_directly_issued_by(_cert(d / "ca.pem"))
    assert sorted(load_deployment(d / "deployment.yaml").nodes) == ["cn", "dn0", "dn1"]
    # A host that holds the certificates but not the CA key cannot sign one.
    (d / "ca.key").unlink()
    with pytest.raises(DeploymentError, match="not its key"):
        ensure_pki(d, ["cn", "dn0", "dn1", "dn2"])


def test_two_first_uses_at_once_make_one_ca(tmp_path: Path) -> None:
    """Two `up` of one mission starting together share one CA (a lock)."""
    d = tmp_path / "pki"
    made: list[list[str]] = []
    threads = [
        threading.Thread(target=lambda: made.append(ensure_pki(d, ["cn", "dn0"]))) for _ in range(4)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(made) == [[], [], [], ["ca", "cn", "dn0", "tool"]]
    for name in ("cn", "dn0", "tool"):
        _cert(d / f"{name}.pem").verify_directly_issued_by(_cert(d / "ca.pem"))


def _keygen(target: str, home: Path) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("ZPLATFORM_")}
    env["XDG_CONFIG_HOME"] = str(home)
    return subprocess.run(
        [sys.executable, "-m", "zplatform", "keygen", target],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=60,
    )


def test_keygen_makes_the_pki_beside_the_key_set_and_says_which_file_goes_where(
    tmp_path: Path,
) -> None:
    r = _keygen(str(IGNITER), tmp_path)
    assert r.returncode == 0, r.stderr
    d = tmp_path / "zplatform" / "keys" / "recovery_igniter"
    lines = r.stdout.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("the PKI of its mutual TLS"))
    assert "hazardous commands" in lines[at] and "made ca, cn, dn0, dn1, gn, tool" in lines[at]
    rows = {
        line.split("->")[1].strip(): line.split("->")[0].split() for line in lines[at + 1 : at + 8]
    }
    assert rows == {
        "every host": ["deployment.yaml", "ca.pem"],
        "the control node's host": ["cn.pem", "cn.tls.key"],
        "dn0's host": ["dn0.pem", "dn0.tls.key"],
        "dn1's host": ["dn1.pem", "dn1.tls.key"],
        "the ground station (ground node, console, cmd)": ["gn.pem", "gn.tls.key"],
        "the operator's tools (tap, log, cmd, console)": ["tool.pem", "tool.tls.key"],
        "no other host (it signs certificates)": ["ca.key"],
    }
    # Each role's certificate and TLS key sit beside its key file.
    for role in ("cn", "dn0", "dn1", "gn", "tool"):
        assert {f"{role}.keys", f"{role}.pem", f"{role}.tls.key"} <= {p.name for p in d.iterdir()}
    dep = load_deployment(d / "deployment.yaml", load_mission(IGNITER))
    assert dep.nodes["dn0"].key == str(d / "dn0.tls.key")
    # A mission on plain links gets a key set and no certificates.
    r = _keygen(str(ROOT / "configs" / "minimal.yaml"), tmp_path)
    assert r.returncode == 0 and "no certificates: its links are plain" in r.stdout
    assert not (tmp_path / "zplatform" / "keys" / "minimal" / "deployment.yaml").exists()
