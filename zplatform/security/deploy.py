"""Deployment files: the host-specific TLS settings a mission's zenoh links need.

A mission YAML is shared and versioned; certificate and key *paths* differ per
host and point at secrets, so they live in a per-host **deployment file**
(``ca``, ``nodes: {name: {cert, key}}``, optional ``tool`` with
``may_command``, ``access_control``), which ``zplatform keygen`` writes beside
the key set with the mission's PKI (:mod:`zplatform.security.pki`).

Contract: only a mission whose links run mutual TLS
(:attr:`zplatform.config.Mission.mtls`) needs one; every session finds it
through :func:`require_deployment` (``ZPLATFORM_DEPLOYMENT``, else
:func:`default_deployment_path`), which raises :class:`DeploymentError` naming
``$.security.transport`` and how to make one when there is none or it does not
fit. Loading a mission never needs it. :func:`tls_settings` checks a node's
cert and key when a session presents them (refusing a private key others may
read); :func:`access_control` builds the zenoh ACL (deny by default, keyed by
the peer cert's common name). Functions read files and block on that I/O only.

Format, rules and the ACL per role: docs/security.md#tls-and-access-control.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import msgspec

from ..config import Mission
from ..errors import ConfigError

__all__ = [
    "DEPLOYMENT_ENV",
    "ROUTER",
    "TOOL",
    "Deployment",
    "DeploymentError",
    "Identity",
    "ToolIdentity",
    "access_control",
    "check_deployment",
    "check_router_certificate",
    "check_tool_may_command",
    "decode_deployment",
    "default_deployment_path",
    "find_deployment",
    "load_deployment",
    "require_deployment",
    "router_identities",
    "router_identity",
    "router_rules",
    "tls_nodes",
    "tls_settings",
    "tool_watch_keys",
    "zenoh_settings",
]

DEPLOYMENT_ENV = "ZPLATFORM_DEPLOYMENT"
"""Environment variable naming the deployment file when none is passed."""
_T = TypeVar("_T")
TOOL = "tool"
"""Common name (and ACL subject) of the identity non-node tools present."""
ROUTER = "router"
"""The prefix of a router's identity (:func:`router_identity`). Before each
router had its own, every router of a mission presented this one; a
deployment's old ``router`` certificate is named by no access control now."""


def router_identity(name: str) -> str:
    """The identity router ``name`` of ``ground.routers`` presents: its
    certificate's common name and SAN, its ACL subject and its entry in the
    deployment's ``nodes`` (``router-pad``; ``-`` is in no node's or
    router's name, so it names nothing else)."""
    return f"{ROUTER}-{name}"


def router_identities(mission: Mission) -> list[str]:
    """The identities of ``mission``'s routers (``ground.routers``), in order."""
    g = mission.ground
    return [router_identity(r.name) for r in g.routers] if g is not None else []


_TLS_PROTOS = ("tls/",)


class DeploymentError(ConfigError):
    """The deployment file is missing, invalid, or does not fit the mission.

    A :class:`~zplatform.errors.ConfigError` (so every caller that reports a
    bad configuration reports this one too); ``path`` is the YAML path of the
    offending field in the deployment file (``$.nodes.cn.key``), or, for a
    mission that needs a deployment and has none, of the mission's first tls
    endpoint.
    """


class _Struct(msgspec.Struct, forbid_unknown_fields=True):
    pass


class Identity(_Struct):
    """One node's certificate and private key (PEM files)."""

    cert: str
    key: str


class ToolIdentity(_Struct):
    """The identity of tools (``tap``, ``log``, ``cmd``): cert, key, and
    whether it may put operator commands on ``{vehicle}/gn/to_cn``."""

    cert: str
    key: str
    may_command: bool = False


class Deployment(_Struct):
    """A decoded deployment file; paths are absolute after :func:`load_deployment`."""

    ca: str
    nodes: dict[str, Identity] = msgspec.field(default_factory=dict)
    tool: ToolIdentity | None = None
    access_control: bool = True

    def identity(self, node: str | None) -> Identity | ToolIdentity | None:
        """The identity ``node`` presents (``None``: the tool identity)."""
        return self.tool if node is None else self.nodes.get(node)


def tls_nodes(mission: Mission) -> list[str]:
    """Nodes that listen or connect over ``tls/`` (and so need an identity)."""
    return [
        name
        for name, n in mission.nodes.items()
        if any(ep.startswith(_TLS_PROTOS) for ep in [*n.listen, *n.connect])
    ]


def _absolute(raw: Any, base: Path) -> Any:
    """``raw`` with every relative ``ca``/``cert``/``key`` string made absolute."""
    if isinstance(raw, dict):
        return {
            k: (
                str((base / v).resolve())
                if k in ("ca", "cert", "key") and isinstance(v, str) and v
                else _absolute(v, base)
            )
            for k, v in raw.items()
        }
    return raw


def _convert(raw: Any, type_: type[_T], source: str, prefix: str) -> _T:
    try:
        return msgspec.convert(raw, type=type_)
    except msgspec.ValidationError as exc:
        # msgspec says "... - at `$.tool.cert`" (or nothing for the top level).
        msg, _, where = str(exc).rpartition(" - at `")
        if not msg:
            msg, where = str(exc), "$`"
        raise DeploymentError(f"{source}: {msg}", prefix + where.rstrip("`")[1:]) from exc


def decode_deployment(
    text: bytes | str, base: str | Path = ".", source: str = "<string>"
) -> Deployment:
    """Decode deployment YAML; relative paths are taken from ``base``.

    Raises DeploymentError naming the YAML path. Checks the schema and that
    the CA file exists (a node's cert and key are checked where they are
    used, :func:`tls_settings`: a host holds only its own); not the fit with
    a mission (see :func:`check_deployment`).
    """
    try:
        raw = msgspec.yaml.decode(text)
    except msgspec.DecodeError as exc:
        raise DeploymentError(f"{source}: not valid YAML: {exc}") from exc
    if not isinstance(raw, dict):
        raise DeploymentError(f"{source}: expected a mapping at the top level")
    raw = _absolute(raw, Path(base))
    # msgspec names a dict value `$.nodes[...]`: check each node on its own
    # first, so the error names the node.
    nodes = raw.get("nodes")
    if isinstance(nodes, dict):
        for name, ident in nodes.items():
            _convert(ident, Identity, source, f"$.nodes.{name}")
    dep = _convert(raw, Deployment, source, "$")
    if not Path(dep.ca).is_file():
        raise DeploymentError(f"{source}: no such file {dep.ca!r}", "$.ca")
    return dep


def check_deployment(dep: Deployment, mission: Mission, source: str = "<deployment>") -> None:
    """Raise DeploymentError unless ``dep`` fits ``mission``: every node with a
    tls endpoint has an identity, and with access control every endpoint is
    tls. Identities of nodes the mission does not have are unused (one PKI
    may serve variants of a mission with fewer nodes)."""
    for name in tls_nodes(mission):
        if name not in dep.nodes:
            raise DeploymentError(
                f"{source}: node {name!r} has tls/ endpoints but no cert and key here"
                + (
                    f" (`zplatform keygen {mission.mission}` adds the missing ones to the "
                    "mission's PKI)"
                    if Path(source) == default_deployment_path(mission)
                    else ""
                ),
                "$.nodes",
            )
    if dep.access_control and tls_nodes(mission):
        # The ACL names peers by their certificate: a peer on a tcp/ link has
        # none and would be denied everything.
        plain = [
            f"{name}: {ep}"
            for name, n in mission.nodes.items()
            for ep in [*n.listen, *n.connect]
            if not ep.startswith(_TLS_PROTOS)
        ]
        if plain:
            raise DeploymentError(
                f"{source}: access_control needs every endpoint on tls/ (peers are known by "
                f"their certificate), but {plain} are not; set access_control: false",
                "$.access_control",
            )


def check_tool_may_command(dep: Deployment) -> None:
    """DeploymentError (at ``$.tool.may_command``) unless the deployment's
    tool identity may put operator commands: a tool that may not would have
    every request dropped by the nodes' access control, unanswered."""
    if dep.access_control and (dep.tool is None or not dep.tool.may_command):
        raise DeploymentError(
            "this deployment's tool identity may not command (tool.may_command is not true): "
            "the nodes' access control would drop every request; command from a host whose "
            "deployment allows it",
            "$.tool.may_command",
        )


def load_deployment(path: str | Path, mission: Mission | None = None) -> Deployment:
    """Read a deployment file (relative paths relative to it) and, given a
    mission, check that it fits (:func:`check_deployment`).

    Blocks on file I/O. Raises DeploymentError naming the YAML path.
    """
    p = Path(path)
    try:
        text = p.read_bytes()
    except OSError as exc:
        raise DeploymentError(f"cannot read deployment file {str(p)!r}: {exc.strerror}") from exc
    dep = decode_deployment(text, base=p.resolve().parent, source=str(p))
    if mission is not None:
        check_deployment(dep, mission, source=str(p))
    return dep


def default_deployment_path(mission: Mission | str) -> Path:
    """``deployment.yaml`` beside this host's key set: in the directory
    ``ZPLATFORM_KEY_FILE`` names (or the directory of the key file it
    names), else in the mission's key set directory
    (:func:`zplatform.core.auth.default_key_dir`, ``~/.config/zplatform/keys/
    <mission>/``). ``keygen`` and ``up`` put the mission's PKI there
    (:mod:`zplatform.security.pki`), each role's certificate beside its key file.
    Reads nothing but the environment and whether the named path is a
    directory."""
    from ..core.auth import KEY_FILE_ENV, default_key_dir

    named = os.environ.get(KEY_FILE_ENV)
    if named:
        p = Path(named)
        return (p if p.is_dir() else p.parent) / "deployment.yaml"
    return default_key_dir(mission) / "deployment.yaml"


def find_deployment(mission: Mission) -> Path | None:
    """The deployment file a session of ``mission`` would use: the one named
    by ``ZPLATFORM_DEPLOYMENT`` (whether or not it exists: reading it says),
    else the mission's default one if it exists, else None. Reads nothing."""
    named = os.environ.get(DEPLOYMENT_ENV)
    if named:
        return Path(named)
    default = default_deployment_path(mission)
    return default if default.is_file() else None


def require_deployment(mission: Mission) -> Deployment | None:
    """The deployment every session of ``mission`` runs with (module doc):
    None for a mission with plain links; for an mtls mission the file
    :func:`find_deployment` names, read and checked to fit. Raises
    DeploymentError (at ``$.security.transport``) when an mtls mission has
    none, saying how to make one, or the YAML path of what does not fit.
    Blocks on file I/O."""
    if not mission.mtls:
        return None
    path = find_deployment(mission)
    if path is None:
        name = mission.mission
        raise DeploymentError(
            f"mission {name!r} runs its links over mutual TLS (security.transport: "
            f"{mission.security.transport}) and this host has no deployment for it at "
            f"{default_deployment_path(mission)}: make one with `zplatform keygen MISSION_FILE` "
            f"(`zplatform up` does on first use) and copy each host its files, or name one "
            f"with {DEPLOYMENT_ENV}; say security.transport: plain only on a closed network",
            "$.security.transport",
        )
    return load_deployment(path, mission)


# ---------------------------------------------------------------------------
# zenoh config pieces


def tls_settings(dep: Deployment, node: str | None) -> dict[str, Any]:
    """The ``transport/link/tls`` section for ``node`` (None: a tool).

    mTLS both ways: the node presents its cert when listening and when
    connecting, and asks every peer for one signed by the mission CA. Names
    are not verified on connect: endpoints are addresses, and identity is the
    CA signature plus the common name, which the ACL checks.
    Raises DeploymentError if the deployment has no identity for ``node``,
    if its files are missing on this host, or if its private key is readable
    by anyone but its owner.
    """
    ident = dep.identity(node)
    where = "$.tool" if node is None else f"$.nodes.{node}"
    if ident is None:
        who = f"node {node!r}" if node is not None else "tools (tap, log, cmd)"
        if node is not None and node.startswith(f"{ROUTER}-"):
            who = (
                f"router {node[len(ROUTER) + 1 :]!r} ({node}: each router presents its own "
                "certificate; `zplatform keygen MISSION_FILE` makes it, copy it to that "
                "router's host)"
            )
        raise DeploymentError(
            f"the deployment gives no cert and key for {who}",
            "$.tool" if node is None else "$.nodes",
        )
    _check_identity_files(ident, where)
    return {
        "root_ca_certificate": dep.ca,
        "listen_certificate": ident.cert,
        "listen_private_key": ident.key,
        "connect_certificate": ident.cert,
        "connect_private_key": ident.key,
        "enable_mtls": True,
        "verify_name_on_connect": False,
        # An expired cert ends the link, not only new handshakes.
        "close_link_on_expiration": True,
    }


def check_router_certificate(dep: Deployment, identity: str) -> None:
    """Refuse (DeploymentError at ``$.nodes.<identity>.cert``) a router's
    certificate whose common name is not ``identity``: another router's or
    a node's, copied or named in its place. The vehicle's access control
    would take it as the identity it names (a node's rights, or that other
    router's, whose removal from the mission would then cut this one off):
    a router presents its own or does not start. Reads the file; a missing
    or unreadable one is :func:`tls_settings`' error."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    ident = dep.nodes.get(identity)
    if ident is None or not Path(ident.cert).is_file():
        return  # tls_settings says what is missing
    try:
        cert = x509.load_pem_x509_certificate(Path(ident.cert).read_bytes())
    except (OSError, ValueError) as exc:
        raise DeploymentError(
            f"cannot read the certificate {ident.cert!r}: {exc}", f"$.nodes.{identity}.cert"
        ) from exc
    names = [str(a.value) for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
    if names != [identity]:
        raise DeploymentError(
            f"the certificate {ident.cert!r} is {', '.join(names) or 'nameless'}'s, not "
            f"{identity}'s: a router presents its own (`zplatform keygen MISSION_FILE` makes "
            "one per router)",
            f"$.nodes.{identity}.cert",
        )


def _check_identity_files(ident: Identity | ToolIdentity, where: str) -> None:
    """The identity's cert and key exist here, and the key is private (0600
    or stricter, as ssh wants of its keys): another local user who can read
    it can be this node on the network."""
    for field, path in (("cert", ident.cert), ("key", ident.key)):
        if not Path(path).is_file():
            raise DeploymentError(
                f"no such file {path!r} on this host (each host holds its own node's cert "
                "and key, copied from where the mission's PKI was made)",
                f"{where}.{field}",
            )
    mode = os.stat(ident.key).st_mode
    if mode & 0o077:
        raise DeploymentError(
            f"private key {ident.key!r} is readable by others (mode {mode & 0o777:04o}): "
            f"`chmod 600 {ident.key}`",
            f"{where}.key",
        )


_ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]


def tool_watch_keys(mission: Mission) -> list[str]:
    """The key expressions a tool (``tap``, ``log``, ``cmd``, ``ground``) may
    subscribe to under access control: the CN's telemetry, every node's
    events, the CN's radio downlink (``ground --record``) and each sync
    region's tap (``cn/to_dnX``, ``dnX/to_cn``, exact keys). Never the
    whole key space: each of a peer's subscribers is a declaration every
    node it reaches must take in and route to (docs/architecture.md#key-space)."""
    from .keyspace import key_of  # the table every key comes from

    v = mission.vehicle
    # Each sync region's tap, by its exact key (never a wildcard): what the
    # DNs and the CN put for taps, the first thing a person looks at.
    regions = [
        key_of(row, v, dn=dn) for dn in mission.device_nodes for row in ("cn_to_dn", "dn_to_cn")
    ]
    return [key_of("telemetry", v), key_of("all_events", v), key_of("downlink", v), *regions]


def access_control(mission: Mission, dep: Deployment) -> dict[str, Any]:
    """The zenoh ``access_control`` section every node of ``mission`` runs.

    Subjects are certificate common names (module doc for the rules). Ingress
    rules say what a node accepts from each identity, message kind by
    message kind: a declaration (subscriber, queryable, liveliness token or
    subscriber) on a key its role does not use is dropped where it comes in,
    so it never enters the node's routing tables (tests/faults/test_acl_declarations.py
    shows it). zenoh allows a message when a rule's key expression
    *includes* the message's (a subscriber on ``{vehicle}/**`` is denied by
    a rule on ``{vehicle}/cn/telemetry``). Egress is allowed to every known
    identity (a node's own sends are its code, not a peer's).
    """
    v = mission.vehicle
    nodes = list(mission.nodes)
    known = [*nodes, TOOL]
    rules: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def rule(rid: str, messages: list[str], keys: list[str], flow: str = "ingress") -> str:
        rules.append(
            {
                "id": rid,
                "permission": "allow",
                "flows": [flow],
                "messages": messages,
                "key_exprs": keys,
            }
        )
        return rid

    def bulk_read(n: str) -> list[str]:
        return [f"{v}/{ch.node}/bulk/{ch.name}" for ch in mission.bulk if n in ch.readers]

    recorder = "cn" in mission.recording_nodes
    archive = [f"{v}/archive/query"] if mission.has_ground and mission.archive.enabled else []
    common = [
        rule("egress-all", _ALL_MESSAGES, [f"{v}/**"], flow="egress"),
        rule(
            "liveliness-watch",
            ["declare_liveliness_subscriber", "liveliness_query"],
            [f"{v}/*/alive", f"{v}/*/standby"],
        ),
    ]
    for n in nodes:
        control = n in mission.control_nodes
        ids = [
            *common,
            # Its own key space: taps, events, bulk samples, telemetry.
            rule(f"{n}-put", ["put"], [f"{v}/{n}/**"]),
            rule(
                f"{n}-alive",
                ["liveliness_token"],
                [f"{v}/{n}/alive", *([f"{v}/{n}/standby"] if control else [])],
            ),
        ]
        watch = bulk_read(n)
        serve: list[str] = []
        ask: list[str] = []
        if control:
            watch.append(f"{v}/gn/to_cn")  # operator commands
            if mission.standby is not None:
                watch.append(f"{v}/cn/mirror")  # the standby follows the commander
            serve += [f"{v}/cn/clock", *([f"{v}/cn/recorder"] if recorder else [])]
            dn_keys = [f"{v}/{d}/to_cn" for d in mission.device_nodes]
            if dn_keys:
                # The wildcard sync query (transport.sync_query) is one get on
                # {vehicle}/*/to_cn; only dnX answer it (their own keys).
                ask += [*dn_keys, f"{v}/*/to_cn"]
            if mission.standby is not None:
                # Either control node may command: it writes the commander's
                # keys ({vehicle}/cn/...: telemetry, the mirror), probes the
                # device nodes, and, as the standby, sets its clock by the
                # commander's.
                ids.append(rule(f"{n}-command", ["put"], [f"{v}/cn/**"]))
                ask += [*(f"{v}/{d}/probe" for d in mission.device_nodes), f"{v}/cn/clock"]
        elif n in mission.device_nodes:
            serve += [f"{v}/{n}/to_cn", f"{v}/{n}/probe"]
            ask.append(f"{v}/cn/clock")
        else:  # the ground node
            watch += tool_watch_keys(mission)
            ask += [f"{v}/cn/clock", *([f"{v}/cn/recorder"] if recorder else []), *archive]
            serve += archive  # its archive, for other stations and tools
        if watch:
            ids.append(rule(f"{n}-watch", ["declare_subscriber"], watch))
        if serve:
            # A reply comes in on the key of the queryable that sent it.
            ids.append(rule(f"{n}-serve", ["declare_queryable", "reply"], serve))
        if ask:
            ids.append(rule(f"{n}-ask", ["query"], ask))
        policies.append({"id": f"p-{n}", "rules": ids, "subjects": [f"s-{n}"]})
    tool_rules = [
        *common,
        rule("tool-watch", ["declare_subscriber"], tool_watch_keys(mission)),
        # The run hello (zplatform.runtime.clocksync.RunAsker): a tool learns the
        # commander's run on its clock's queryable, as the ground node does.
        rule("tool-run", ["query"], [f"{v}/cn/clock"]),
    ]
    if recorder:  # `zplatform log` fills its gaps too
        tool_rules.append(rule("tool-recorder", ["query"], [f"{v}/cn/recorder"]))
    if archive:  # `zplatform archive --remote`
        tool_rules.append(rule("tool-archive", ["query"], archive))
    if dep.tool is not None and dep.tool.may_command and mission.has_ground:
        tool_rules.append(rule("tool-command", ["put"], [f"{v}/gn/to_cn"]))
    policies.append({"id": f"p-{TOOL}", "rules": tool_rules, "subjects": [f"s-{TOOL}"]})
    routers = router_identities(mission)
    if routers:
        # One subject per router's certificate (its own common name): a
        # router removed from the mission is named by no subject, so its
        # certificate is denied everything, and the others' are untouched.
        # Each gets the same forwarding-only rules.
        known += routers
        policies.append(
            {
                "id": f"p-{ROUTER}",
                "rules": router_rules(mission, rule, common),
                "subjects": [f"s-{r}" for r in routers],
            }
        )
    subjects = [{"id": f"s-{k}", "cert_common_names": [k]} for k in known]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def router_rules(mission: Mission, rule: Callable[..., str], common: list[str]) -> list[str]:
    """A router's rules (what any node or router takes from one): forwarding
    only, the stations' side of the key space and the vehicle's answers to
    it. It may carry telemetry, events, the downlink and the sync taps
    (:func:`tool_watch_keys`) and the stations' requests (``gn/to_cn``), the
    subscriptions to them, run hellos, recorder and archive queries and their
    replies, and liveliness tokens; never a device node's sync key, a sync
    query, a probe, the mirror or a bulk channel, so a router (or whoever
    holds its key) can neither drive the vehicle's loop nor pose as a node.
    ``rule`` adds one rule and returns its id (:func:`access_control`)."""
    v = mission.vehicle
    recorder = "cn" in mission.recording_nodes
    archive = [f"{v}/archive/query"] if mission.has_ground and mission.archive.enabled else []
    carried = [*tool_watch_keys(mission), *([f"{v}/gn/to_cn"] if mission.has_ground else [])]
    served = [f"{v}/cn/clock", *([f"{v}/cn/recorder"] if recorder else []), *archive]
    alive = [f"{v}/*/alive", f"{v}/*/standby"]
    # Both ways (egress too, unlike a node's policy): in zenoh's router mode
    # a router's subscriptions are not the only thing that routes samples to
    # it, so what a node sends a router is bounded here as well.
    both = ["ingress", "egress"]
    return [
        *(c for c in common if c != "egress-all"),  # its own egress rules below
        *(
            rule(f"{ROUTER}-{what}-{flow}", messages, keys, flow)
            for flow in both
            for what, messages, keys in (
                ("put", ["put"], carried),
                ("watch", ["declare_subscriber"], carried),
                ("serve", ["declare_queryable", "reply"], served),
                ("ask", ["query"], served),
                ("alive", ["liveliness_token"], alive),
            )
        ),
        rule(
            f"{ROUTER}-liveliness-egress",
            ["declare_liveliness_subscriber", "liveliness_query"],
            alive,
            "egress",
        ),
    ]


def zenoh_settings(mission: Mission, dep: Deployment, node: str | None) -> dict[str, Any]:
    """The zenoh config pieces for ``node`` (None: a tool), as
    ``{config key: value}``: ``transport/link/tls`` and, when the deployment
    asks for it, ``access_control``. Empty for a mission without tls
    endpoints (the deployment has nothing to secure there).
    """
    if not tls_nodes(mission):
        return {}
    out: dict[str, Any] = {"transport/link/tls": tls_settings(dep, node)}
    if dep.access_control:
        out["access_control"] = access_control(mission, dep)
    return out
