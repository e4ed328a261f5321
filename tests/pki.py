"""A throwaway PKI for the TLS tests, made by the platform's own code
(:func:`zplatform.security.pki.ensure_pki`, what ``zplatform keygen`` runs).

**Tests only**: the CA key sits next to the certs in a temporary directory.
A flight deployment's certificates come from ``zplatform keygen`` (or the
team's own CA; see :mod:`zplatform.security.deploy` for the deployment file they go
into).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from zplatform.security.deploy import Deployment, load_deployment
from zplatform.security.pki import DEPLOYMENT_FILE, ensure_pki

__all__ = ["make_test_pki"]


def make_test_pki(
    directory: str | Path,
    nodes: Iterable[str],
    *,
    tool: bool = True,
    may_command: bool = False,
    ca_name: str = "zplatform test CA",
) -> Deployment:
    """Make a CA and one cert per node (common name = node name) in
    ``directory``, plus a ``tool`` cert (``tool=True``) that may command
    only with ``may_command``, and ``deployment.yaml`` naming them; return
    the loaded deployment. Call again with another ``directory`` and
    ``ca_name`` for a second, foreign CA.
    """
    ensure_pki(directory, nodes, tool=tool, may_command=may_command, ca_name=ca_name)
    return load_deployment(Path(directory) / DEPLOYMENT_FILE)
