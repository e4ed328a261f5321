"""The mission's PKI: a CA, a certificate per node and router, one for the tools.

A mission whose links run mutual TLS (:attr:`zplatform.config.Mission.mtls`)
needs, on each host, a deployment file (:mod:`zplatform.security.deploy`)
naming the mission CA and that host's certificate and key.
:func:`ensure_mission_pki` makes all of it beside the host's key set
(:func:`zplatform.security.deploy.default_deployment_path`): ``ca.pem``,
``ca.key`` (which never leaves this host), ``NAME.pem`` and ``NAME.tls.key``
per node and per router (``router-<name>``: each its own), ``tool.pem`` and
``tool.tls.key`` for the tools, ``deployment.yaml`` (common name: the
identity's name). ``zplatform keygen`` calls it and says which files go to
which host (:func:`host_files`); ``zplatform up`` calls it on first use.

Contract: keys are ECDSA P-256, mode 0600 in a 0700 directory; nothing that
exists is overwritten (a second call adds only what is missing, signed by the
CA already there); certificates never expire. Concurrent callers serialise
on a lock file. Blocks on file I/O and key generation (a few ms per key).

Certificate profile, rotation, where each file goes: docs/security.md#tls-and-access-control.
"""

from __future__ import annotations

import datetime
import fcntl
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import msgspec

from ..config import Mission
from .deploy import (
    TOOL,
    DeploymentError,
    default_deployment_path,
    router_identities,
    router_identity,
)

__all__ = [
    "DEPLOYMENT_FILE",
    "MissionPki",
    "ensure_mission_pki",
    "ensure_pki",
    "host_files",
    "leaf_files",
]

DEPLOYMENT_FILE = "deployment.yaml"
_NOT_BEFORE = datetime.datetime(2000, 1, 1, tzinfo=datetime.UTC)
_NOT_AFTER = datetime.datetime(9999, 12, 31, 23, 59, 59, tzinfo=datetime.UTC)


class MissionPki(msgspec.Struct, frozen=True):
    """What :func:`ensure_mission_pki` found and made.

    ``directory``: where the files are; ``deployment``: its deployment
    file; ``made``: the identities made by this call (``"ca"`` first when
    the CA was), empty when everything existed; ``names``: every node
    identity the deployment names (sorted), ``tool`` apart."""

    directory: str
    deployment: str
    made: list[str]
    names: list[str]


def _write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` (mode 0600) through a temporary file and a
    rename, so a reader never sees half a file."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _new_key() -> Any:
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )


def _key_usage(*, ca: bool) -> Any:
    """A CA signs certificates (and CRLs); a node's key only signs handshakes."""
    from cryptography import x509

    return x509.KeyUsage(
        digital_signature=not ca,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=ca,
        crl_sign=ca,
        encipher_only=False,
        decipher_only=False,
    )


def _make_ca(d: Path, ca_name: str) -> None:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.x509.oid import NameOID

    key = _new_key()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, ca_name)])
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(_NOT_BEFORE)
        .not_valid_after(_NOT_AFTER)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    # The key first: a ca.pem without its key would look like a copied host's.
    _write_private(d / "ca.key", _key_pem(key))
    _write_private(d / "ca.pem", cert.public_bytes(serialization.Encoding.PEM))


def _load_ca(d: Path) -> tuple[Any, Any]:
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    try:
        key = serialization.load_pem_private_key((d / "ca.key").read_bytes(), None)
    except FileNotFoundError:
        raise DeploymentError(
            f"{d} has the mission CA's certificate but not its key (ca.key), so it cannot "
            "sign a certificate for a new node: run `zplatform keygen` on the host that "
            "made the PKI and copy the new files here"
        ) from None
    except (OSError, ValueError) as exc:
        raise DeploymentError(f"cannot read the CA key {d / 'ca.key'}: {exc}") from exc
    try:
        cert = x509.load_pem_x509_certificate((d / "ca.pem").read_bytes())
    except (OSError, ValueError) as exc:
        raise DeploymentError(f"cannot read the CA certificate {d / 'ca.pem'}: {exc}") from exc
    return key, cert


def _make_leaf(d: Path, name: str, ca_key: Any, ca_cert: Any) -> None:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = _new_key()
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(_NOT_BEFORE)
        .not_valid_after(_NOT_AFTER)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(x509.SubjectAlternativeName([x509.DNSName(name)]), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    cert_file, key_file = leaf_files(name)
    _write_private(d / key_file, _key_pem(key))
    _write_private(d / cert_file, cert.public_bytes(serialization.Encoding.PEM))


def leaf_files(name: str) -> tuple[str, str]:
    """The certificate's and the private key's file names of identity
    ``name`` (a node or ``tool``) in a PKI directory: ``NAME.pem`` and
    ``NAME.tls.key`` (not ``NAME.key``, which would sit confusably beside
    the role's key file ``NAME.keys``)."""
    return f"{name}.pem", f"{name}.tls.key"


def _read_deployment(path: Path) -> dict[str, Any]:
    """The deployment file's mapping as written (empty if there is none)."""
    try:
        raw = msgspec.yaml.decode(path.read_bytes())
    except FileNotFoundError:
        return {}
    except (OSError, msgspec.DecodeError) as exc:
        raise DeploymentError(f"cannot read {path}: {exc}") from exc
    if not isinstance(raw, dict):
        raise DeploymentError(f"{path}: expected a mapping at the top level")
    return raw


def ensure_pki(
    directory: str | Path,
    nodes: Iterable[str],
    *,
    tool: bool = True,
    may_command: bool = True,
    ca_name: str = "zplatform mission CA",
) -> list[str]:
    """Make (or complete) a PKI in ``directory``: the CA if it has none, a
    cert and key for every name of ``nodes`` (and ``tool``) that has none,
    and ``deployment.yaml`` naming them all (module doc).

    Returns the identities made (``"ca"`` first if the CA was). Existing
    files are kept, ``tool``'s ``may_command`` included once written.
    Raises DeploymentError when a certificate must be made and this host has
    no CA key, or a file cannot be read or written.
    """
    d = Path(directory)
    names = [*nodes, *([TOOL] if tool else [])]
    try:
        if not d.is_dir():
            d.mkdir(parents=True, mode=0o700, exist_ok=True)  # another caller may race us
            os.chmod(d, 0o700)  # whatever the umask
        lock_fd = os.open(d / ".lock", os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    except OSError as exc:
        raise DeploymentError(f"cannot make the mission's PKI in {d}: {exc.strerror}") from exc
    try:
        fcntl.flock(lock_fd, fcntl.LOCK_EX)
        return _ensure_locked(d, names, tool, may_command, ca_name)
    except OSError as exc:
        raise DeploymentError(f"cannot write the mission's PKI in {d}: {exc}") from exc
    finally:
        os.close(lock_fd)  # releases the lock


def _ensure_locked(
    d: Path, names: list[str], tool: bool, may_command: bool, ca_name: str
) -> list[str]:
    made: list[str] = []
    if not (d / "ca.pem").exists():
        _make_ca(d, ca_name)
        made.append("ca")
    missing = [n for n in names if not all((d / f).exists() for f in leaf_files(n))]
    if missing:
        ca_key, ca_cert = _load_ca(d)
        for n in missing:
            _make_leaf(d, n, ca_key, ca_cert)
        made += missing
    dep_path = d / DEPLOYMENT_FILE
    raw = _read_deployment(dep_path)
    before = msgspec.yaml.encode(raw)
    raw.setdefault("ca", "ca.pem")
    known = raw.setdefault("nodes", {})
    for n in names:
        cert, key = leaf_files(n)
        if n != TOOL:
            known.setdefault(n, {"cert": cert, "key": key})
        else:
            raw.setdefault("tool", {"cert": cert, "key": key, "may_command": may_command})
    after = msgspec.yaml.encode(raw)
    if after != before:
        _write_private(dep_path, after)
    return made


def ensure_mission_pki(mission: Mission, directory: str | Path | None = None) -> MissionPki:
    """The PKI of ``mission`` in ``directory`` (default: beside this host's
    key set, :func:`~zplatform.security.deploy.default_deployment_path`):
    :func:`ensure_pki` with every mission node and the tool, which may
    command (the operator's ``cmd`` and console present it). Raises
    DeploymentError (see there)."""
    path = (
        Path(directory) / DEPLOYMENT_FILE
        if directory is not None
        else default_deployment_path(mission)
    )
    # Each of the mission's routers (ground.routers) has its own identity.
    routers = router_identities(mission)
    made = ensure_pki(
        path.parent, [*mission.nodes, *routers], ca_name=f"zplatform {mission.mission} CA"
    )
    raw = _read_deployment(path)
    nodes = raw.get("nodes")
    return MissionPki(
        directory=str(path.parent),
        deployment=str(path),
        made=made,
        names=sorted(nodes) if isinstance(nodes, dict) else [],
    )


def host_files(mission: Mission) -> list[tuple[str, list[str]]]:
    """Which files of the mission's PKI go where, as ``(who, files)`` rows:
    every host, each host role's host (:func:`zplatform.core.auth.host_roles`,
    in words :func:`~zplatform.core.auth.role_host`) its certificate and key,
    and the CA key, which stays on the host that made it."""
    from ..core.auth import host_roles, role_host

    rows: list[tuple[str, list[str]]] = [("every host", [DEPLOYMENT_FILE, "ca.pem"])]
    for r in host_roles(mission):
        # Every operator's tool presents the tool certificate (cmd and the
        # console too, whose frames the gn key set signs): it may command.
        who = "the operator's tools (tap, log, cmd, console)" if r == TOOL else role_host(r)
        rows.append((who, list(leaf_files(r))))
    g = mission.ground
    for rt in g.routers if g is not None else []:
        rows.append((f"router {rt.name}'s host", list(leaf_files(router_identity(rt.name)))))
    rows.append(("no other host (it signs certificates)", ["ca.key"]))
    return rows
