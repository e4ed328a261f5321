"""A throwaway PKI for the TLS tests: a CA and node certs made with ``openssl``.

**Tests only, never for flight**: keys are unencrypted, the CA key sits next
to the certs, certs last 30 days and nothing is revocable. A flight
deployment's certificates come from the team's own CA (see
:mod:`zplatform.deploy` for the deployment file they go into).
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import msgspec

from zplatform.deploy import TOOL, Deployment, DeploymentError, load_deployment

__all__ = ["make_test_pki"]


def _openssl(*args: str, cwd: Path) -> None:
    r = subprocess.run(
        ["openssl", *args], cwd=cwd, capture_output=True, text=True, check=False, timeout=60
    )
    if r.returncode != 0:
        raise DeploymentError(f"openssl {args[0]} failed: {r.stderr.strip()[-500:]}")


def make_test_pki(
    directory: str | Path,
    nodes: Iterable[str],
    *,
    tool: bool = True,
    may_command: bool = False,
    ca_name: str = "zplatform test CA",
) -> Deployment:
    """Make a CA and one cert per node (common name = node name) in
    ``directory``, write ``deployment.yaml`` there and return it loaded.

    ``tool``: also a ``tool`` identity. **Tests and demos only, never for
    flight**: unencrypted keys, the CA key beside the certs, 30-day certs,
    no revocation. Needs the ``openssl`` command; raises DeploymentError
    without it or if it fails. Call again with another ``directory`` and
    ``ca_name`` for a second, foreign CA.
    """
    if shutil.which("openssl") is None:
        raise DeploymentError("make_test_pki needs the openssl command")
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    _openssl(
        "req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "30",
        "-subj", f"/CN={ca_name}",
        "-addext", "basicConstraints=critical,CA:TRUE",
        "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        cwd=d,
    )  # fmt: skip
    # rustls (zenoh's TLS) wants v3 end-entity certs with a SAN and both
    # server and client auth: a peer is both.
    names = [*nodes, *([TOOL] if tool else [])]
    for n in names:
        (d / f"{n}.ext").write_text(
            f"subjectAltName=DNS:{n}\nbasicConstraints=critical,CA:FALSE\n"
            "keyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n"
        )
        _openssl("req", *ec, "-keyout", f"{n}.key", "-out", f"{n}.csr", "-subj", f"/CN={n}", cwd=d)
        _openssl(
            "x509", "-req", "-in", f"{n}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
            "-CAcreateserial", "-out", f"{n}.pem", "-days", "30", "-extfile", f"{n}.ext",
            cwd=d,
        )  # fmt: skip
    raw: dict[str, Any] = {
        "ca": "ca.pem",
        "nodes": {n: {"cert": f"{n}.pem", "key": f"{n}.key"} for n in names if n != TOOL},
    }
    if tool:
        raw["tool"] = {"cert": f"{TOOL}.pem", "key": f"{TOOL}.key", "may_command": may_command}
    (d / "deployment.yaml").write_bytes(msgspec.yaml.encode(raw))
    return load_deployment(d / "deployment.yaml")
