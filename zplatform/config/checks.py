"""The mission file's structural checks: cross-field validation naming YAML paths.

:func:`parse_mission` decodes YAML into the :class:`~zplatform.config.schema.Mission`
tree, checks the structure (the thesis, ch. 4.1.1 (Data Vector), 4.2.1
(network) and the topology rules of docs/architecture.md, the size limits,
names, endpoints, failover, bulk channels, parameters, initial values) and
adds the platform elements (:mod:`zplatform.config.platform`). Every failure
is a :class:`~zplatform.errors.ConfigError` whose message names the YAML path
of the bad field and what was expected.
"""

from __future__ import annotations

import math
import os
import re
import unicodedata
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import msgspec

from ..errors import ConfigError
from .platform import HEALTH_METRICS, _add_platform_elements, element_spec
from .schema import (
    _DN_RE,
    ARCHIVE_QUEUE_BYTES,
    ARCHIVE_QUEUE_S,
    ARCHIVE_ROW_GROUP_BYTES,
    ARCHIVE_ROW_GROUP_S,
    MAX_ARRAY_COUNT,
    MAX_CHANNEL_BYTES,
    MAX_REGION_BYTES,
    MAX_VECTOR_BYTES,
    MISSION_NAME_MAX,
    STANDBY,
    BulkChannelConfig,
    ElementConfig,
    Mission,
    NodeConfig,
    Scalar,
    StateConfig,
    Value,
    _parse_or_raise,
)
from .types import SCALAR_TYPES, ScalarType, parse_type

# Names checked with fullmatch, never match: `$` also matches before a
# trailing newline, so "cn_loop\n" would pass a match().
_NAME_RE = re.compile(r"^[a-z][a-z0-9_]*$")
_ENUM_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
# Characters with a meaning in zenoh key expressions (wildcards, separators,
# the `$*` chunk syntax, `#` reserved): never part of a name that may go
# into a key or a file name.
_KEY_SPECIALS = frozenset("*$?#/")

_FLOAT_WORDS = ("nan", "inf", "+inf", "-inf", "infinity", "-infinity")
_EXP_FLOAT_RE = re.compile(r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)e[-+]?[0-9]+$")


def _new_name(name: str, seen: set[str], what: str, where: str, *, label: str = "name") -> None:
    """Check that ``name`` (of a ``what``: "bulk channel", "parameter",
    "device", ...) is a valid name (:data:`_NAME_RE`, fullmatch) not in
    ``seen``, then add it. Raises ConfigError at ``where``; ``label`` opens
    the first message."""
    if not _NAME_RE.fullmatch(name):
        raise ConfigError(f"{label} {name!r} must match {_NAME_RE.pattern}", where)
    if name in seen:
        raise ConfigError(f"duplicate {what} name {name!r}", where)
    seen.add(name)


def check_bulk_channels(
    channels: Sequence[BulkChannelConfig], nodes: Collection[str], where: str = "$.bulk"
) -> None:
    """Check the mission's ``bulk`` list against its ``nodes``.

    Raises :class:`ConfigError` naming the YAML path of the first bad field
    (``$.bulk[0].type``): a bad or duplicate name, an unknown owner or reader,
    the owner among its readers, a repeated reader, an invalid type or one
    larger than :data:`MAX_CHANNEL_BYTES`. Pure: touches no zenoh.
    """
    seen: set[str] = set()
    for i, ch in enumerate(channels):
        w = f"{where}[{i}]"
        _new_name(ch.name, seen, "bulk channel", f"{w}.name")
        if ch.node not in nodes:
            raise ConfigError(f"no node named {ch.node!r}; nodes: {sorted(nodes)}", f"{w}.node")
        scalar, shape = _parse_or_raise(ch.type, f"{w}.type")
        nbytes = scalar.size * math.prod(shape)
        if nbytes > MAX_CHANNEL_BYTES:
            raise ConfigError(
                f"{ch.type} is {nbytes} bytes; a bulk channel holds at most "
                f"{MAX_CHANNEL_BYTES} bytes",
                f"{w}.type",
            )
        if ch.rate_phase >= ch.rate_divisor:
            raise ConfigError(
                f"rate_phase {ch.rate_phase} must be below rate_divisor {ch.rate_divisor}",
                f"{w}.rate_phase",
            )
        readers: set[str] = set()
        for j, r in enumerate(ch.readers):
            if r not in nodes:
                raise ConfigError(
                    f"no node named {r!r}; nodes: {sorted(nodes)}", f"{w}.readers[{j}]"
                )
            if r == ch.node:
                raise ConfigError(
                    f"{r!r} owns channel {ch.name!r} and cannot also read it", f"{w}.readers[{j}]"
                )
            if r in readers:
                raise ConfigError(f"reader {r!r} is listed twice", f"{w}.readers[{j}]")
            readers.add(r)


# ---------------------------------------------------------------------------
# loading


def parse_mission(text: bytes | str, source: str = "<string>") -> Mission:
    """Decode YAML text into a :class:`Mission`: schema, structural checks, platform elements.

    Raises :class:`ConfigError` naming the YAML path of the first bad field.
    Runs no semantic check (state machine, commands, controller and device
    classes): use :func:`zplatform.mission.load.decode_mission`, which calls this
    and then those, unless you are one of those checks.
    """
    try:
        raw = msgspec.yaml.decode(text)
    except msgspec.DecodeError as exc:
        raise ConfigError(f"{source}: not valid YAML: {exc}", "$") from exc
    if raw is None or raw == {}:
        raise ConfigError(f"{source}: mission config is empty", "$")
    _check_duplicate_keys(text)
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level", "$")
    try:
        mission = msgspec.convert(raw, type=Mission)
    except msgspec.ValidationError as exc:
        msg, _, where = str(exc).partition(" - at `")
        raise ConfigError(msg, _name_the_key(raw, where.rstrip("`") or "$")) from exc
    _check_mission(mission)
    # Structural checks of controllers/devices come before the platform
    # elements are added: a repeated controller name must be reported as
    # such, not as the repeated `<name>_mode` element it would create.
    _check_control_sections(mission)
    _check_recorder(mission)
    _check_archive(mission)
    _check_params(mission)
    _check_ground(mission)
    n_platform = _add_platform_elements(mission)
    vector_bytes = _check_elements(mission, n_platform)
    if mission.archive.enabled:
        archive_sizing(mission, vector_bytes)
    return mission


def _keyed_sections() -> tuple[tuple[tuple[str, ...], Any], ...]:
    """The mappings of the schema keyed by user names, and their value types."""
    return (
        (("nodes",), NodeConfig),
        (("regions",), list[ElementConfig]),
        (("state_machine", "states"), StateConfig),
        (("commands", "whitelist"), list[str]),
        (("commands", "write_states"), list[str]),
    )


def _name_the_key(raw: dict[str, Any], where: str) -> str:
    """Replace msgspec's ``[...]`` (a key it does not name) with the key at fault.

    msgspec reports an error inside a ``dict`` value as ``$.nodes[...].cpu``;
    the user needs ``$.nodes.cn.cpu``. The values of that mapping are
    converted one by one, and the first that fails names the key (and the
    path inside it). Returns ``where`` unchanged when it cannot tell.
    """
    for keys, value_type in _keyed_sections():
        prefix = "$." + ".".join(keys)
        if not where.startswith(prefix + "[...]"):
            continue
        mapping: Any = raw
        for k in keys:
            mapping = mapping.get(k) if isinstance(mapping, dict) else None
        if not isinstance(mapping, dict):
            return where
        for key, value in mapping.items():
            try:
                msgspec.convert(value, type=value_type)
            except msgspec.ValidationError as exc:
                at = str(exc).partition(" - at `")[2].rstrip("`")
                return f"{prefix}.{key}{at[1:] if at.startswith('$') else ''}"
        return where
    return where


def _check_duplicate_keys(text: bytes | str) -> None:
    """Refuse a key given twice in one mapping (two regions ``cn:``, two
    ``name:`` in one element): YAML loaders silently keep the last one."""
    import yaml

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    root = yaml.compose(text, Loader=loader)  # already parsed once: no YAMLError here
    stack: list[tuple[yaml.Node, str]] = [(root, "$")] if root is not None else []
    seen_nodes: set[int] = set()  # aliases share nodes, and may even be recursive
    while stack:
        node, path = stack.pop()
        if id(node) in seen_nodes:
            continue
        seen_nodes.add(id(node))
        if isinstance(node, yaml.MappingNode):
            seen: set[object] = set()
            for k, v in node.value:
                key = k.value if isinstance(k, yaml.ScalarNode) else id(k)
                where = f"{path}.{key}"
                if key in seen:
                    raise ConfigError(
                        f"key {key!r} is given twice (line {k.start_mark.line + 1})", where
                    )
                seen.add(key)
                stack.append((v, where))
        elif isinstance(node, yaml.SequenceNode):
            stack += [(v, f"{path}[{i}]") for i, v in enumerate(node.value)]


def _unsafe_name_reason(name: str) -> str | None:
    """Why ``name`` cannot be a name (empty, control characters, key specials), or None."""
    if not name:
        return "is empty"
    for ch in name:
        if unicodedata.category(ch)[0] == "C":  # Cc control (NUL, \n), Cf, Cs, Co, Cn
            return f"contains the control character {ch!r}"
        if ch in _KEY_SPECIALS:
            return f"contains {ch!r}, which has a meaning in zenoh key expressions"
    return None


def check_mission_name(name: str) -> None:
    """Refuse a mission name that cannot name keys, files and registry
    entries (ConfigError at ``$.mission``): the rule every mission file's
    ``mission:`` obeys, for tools that take a bare name (``keygen``)."""
    why = _unsafe_name_reason(name)
    if why is not None:
        raise ConfigError(f"mission name {name!r} {why}", "$.mission")
    if len(name) > MISSION_NAME_MAX:
        raise ConfigError(
            f"mission name is {len(name)} characters long; at most {MISSION_NAME_MAX}",
            "$.mission",
        )


def resolve_pythonpath(entries: Sequence[str] | None, base_dir: str | Path | None) -> list[str]:
    """The absolute directories a mission's ``pythonpath`` names.

    Relative entries are relative to ``base_dir`` (the mission file's
    directory; None: the current directory). ``entries`` None (the key not
    given) means ``[base_dir]``, or nothing without a ``base_dir`` (a mission
    decoded from text). Pure: checks no directory.
    """
    if entries is None:
        return [] if base_dir is None else [os.path.abspath(base_dir)]
    base = os.path.abspath(base_dir if base_dir is not None else os.curdir)
    return [os.path.normpath(os.path.join(base, e)) for e in entries]


def relocate_mission(raw: dict[str, Any], source: str | Path) -> None:
    """Make a mission mapping read from file ``source`` mean the same from
    any other directory: its ``pythonpath`` (or the default, ``source``'s
    directory) and its recorder and archive ``dir`` become absolute. For copies
    of a mission file (``up --free-ports``, a recording). A malformed ``pythonpath`` is left for the
    loader to refuse with its YAML path."""
    entries = raw.get("pythonpath")
    if entries is None or (isinstance(entries, list) and all(isinstance(e, str) for e in entries)):
        raw["pythonpath"] = resolve_pythonpath(entries, Path(source).parent)
    for section in ("recorder", "archive"):
        rec = raw.get(section)
        if isinstance(rec, dict) and isinstance(rec.get("dir"), str) and rec["dir"]:
            rec["dir"] = os.path.join(os.path.abspath(Path(source).parent), rec["dir"])


def _check_mission(m: Mission) -> None:
    check_mission_name(m.mission)
    for i, d in enumerate(m.pythonpath or ()):
        if not d or "\x00" in d:
            raise ConfigError(
                "a pythonpath entry must be a non-empty directory path", f"$.pythonpath[{i}]"
            )
    if not _NAME_RE.fullmatch(m.vehicle):
        raise ConfigError(
            f"vehicle key prefix must match {_NAME_RE.pattern}, got {m.vehicle!r}", "$.vehicle"
        )
    if not m.nodes:
        raise ConfigError("a mission needs at least the control node 'cn'", "$.nodes")
    if "cn" not in m.nodes:
        raise ConfigError("the control node 'cn' is missing", "$.nodes")
    for name in m.nodes:
        if name not in ("cn", "gn", STANDBY) and not _DN_RE.fullmatch(name):
            raise ConfigError(
                f"node name {name!r} is not one of cn, {STANDBY} (a standby control node), gn, "
                "dn0, dn1, ...",
                f"$.nodes.{name}",
            )
    _check_failover(m)
    dns = m.device_nodes
    if [int(d[2:]) for d in dns] != list(range(len(dns))):
        raise ConfigError(
            f"device nodes must be numbered dn0..dn{len(dns) - 1} without gaps, got {dns}",
            "$.nodes",
        )
    mtls = m.mtls  # before any endpoint is rewritten
    why = transport_reason(m)
    seen: dict[str, str] = {}
    for name, node in m.nodes.items():
        for i, ep in enumerate(node.listen):
            where = f"$.nodes.{name}.listen[{i}]"
            check_endpoint(ep, where)
            ep = node.listen[i] = _link_endpoint(ep, mtls, why, where)
            if ep in seen:
                raise ConfigError(f"endpoint {ep!r} is also listened on by {seen[ep]}", where)
            seen[ep] = name
        for i, ep in enumerate(node.connect):
            where = f"$.nodes.{name}.connect[{i}]"
            check_endpoint(ep, where)
            node.connect[i] = _link_endpoint(ep, mtls, why, where)
    # One dialer per pair (zplatform.runtime.transport.dial_ranks): two nodes that
    # dial each other can leave their zenoh session split after a stall.
    for name, node in m.nodes.items():
        for i, ep in enumerate(node.connect):
            peer = seen.get(ep)
            if peer is not None and peer != name and set(m.nodes[peer].connect) & set(node.listen):
                raise ConfigError(
                    f"{name} and {peer} connect to each other: let one of them connect to the "
                    "other, never both ways (a split zenoh session, eclipse-zenoh/zenoh#2806)",
                    f"$.nodes.{name}.connect[{i}]",
                )
    if m.sync_timeout_ms * 1e6 >= m.period_ns:
        raise ConfigError(
            f"sync_timeout_ms {m.sync_timeout_ms} must be shorter than the loop period "
            f"({1000.0 / m.loop_hz:g} ms)",
            "$.sync_timeout_ms",
        )
    valid = set(m.region_names())
    for region, elements in m.regions.items():
        where = f"$.regions.{region}"
        if region not in valid:
            raise ConfigError(
                f"region {region!r} does not match the node topology; valid regions: "
                f"{m.region_names()}",
                where,
            )
        if not elements:
            raise ConfigError("a region must have at least one element", where)
    check_bulk_channels(m.bulk, m.nodes)


_IDENT_RE = re.compile(r"^[a-z][a-z0-9_]{0,31}$")


def _check_ground(m: Mission) -> None:
    """Structural checks of ``ground:`` (names, references, what it needs);
    the two-person list is checked against the commands by
    :func:`zplatform.control.authority.check_config`."""
    g = m.ground
    if g is None:
        return
    if not m.has_ground:
        raise ConfigError("a `ground:` section needs the ground node 'gn' in `nodes`", "$.ground")
    if not m.security.auth and not g.single_operator:
        raise ConfigError(
            "operators are known by their keys: `ground:` needs `security.auth` (or "
            "`single_operator: true`)",
            "$.ground",
        )
    named = (
        ("stations", [s.name for s in g.stations]),
        ("operators", [o.name for o in g.operators]),
    )
    for section, names_ in named:
        if not names_:
            raise ConfigError(f"`ground.{section}` lists none", f"$.ground.{section}")
        seen: set[str] = set()
        for i, name_ in enumerate(names_):
            where = f"$.ground.{section}[{i}].name"
            if not _IDENT_RE.fullmatch(name_):
                raise ConfigError(f"name {name_!r} must match {_IDENT_RE.pattern}", where)
            _new_name(name_, seen, section[:-1], where)
    if not any(s.may == "command" for s in g.stations):
        raise ConfigError("no station may command", "$.ground.stations")
    for i, op in enumerate(g.operators):
        where = f"$.ground.operators[{i}].roles"
        if not op.roles:
            raise ConfigError(f"operator {op.name!r} has no role", where)
        if len(set(op.roles)) != len(op.roles):
            raise ConfigError(f"operator {op.name!r} lists a role twice", where)
        if "viewer" in op.roles and len(op.roles) > 1:
            raise ConfigError(
                f"operator {op.name!r} is a viewer and something more: a viewer never commands",
                where,
            )
    if not any({"flight_director", "operator"} & set(op.roles) for op in g.operators):
        raise ConfigError("no operator may command (flight_director, operator)", "$.ground")
    names = {op.name: op for op in g.operators}
    for i, r in enumerate(g.revoked):
        name, sep, kid = r.partition("#")
        where = f"$.ground.revoked[{i}]"
        if name not in names:
            raise ConfigError(f"{name!r} is not an operator; operators: {sorted(names)}", where)
        if sep and (not kid.isdigit() or not 1 <= int(kid) <= 65535):
            raise ConfigError(f"{r!r}: expected NAME or NAME#KEY_ID (1..65535)", where)
    if len(set(g.approving_roles)) != len(g.approving_roles):
        raise ConfigError("a role is listed twice", "$.ground.approving_roles")
    seen_routers: set[str] = set(m.nodes)
    for i, rt in enumerate(g.routers):
        where = f"$.ground.routers[{i}]"
        if not _IDENT_RE.fullmatch(rt.name):
            raise ConfigError(f"name {rt.name!r} must match {_IDENT_RE.pattern}", where + ".name")
        _new_name(rt.name, seen_routers, "router or node", where + ".name")
        if not rt.listen and not rt.connect:
            raise ConfigError(f"router {rt.name!r} neither listens nor connects", where)
        for field, eps in (("listen", rt.listen), ("connect", rt.connect)):
            for j, ep in enumerate(eps):
                check_endpoint(ep, f"{where}.{field}[{j}]")
    for i, st in enumerate(g.stations):
        for j, ep in enumerate(st.connect):
            check_endpoint(ep, f"$.ground.stations[{i}].connect[{j}]")
        if st.operator is not None and st.operator not in names:
            raise ConfigError(
                f"station {st.name!r} runs as {st.operator!r}, who is no operator; operators: "
                f"{sorted(names)}",
                f"$.ground.stations[{i}].operator",
            )
        if st.operator is not None and not st.start:
            raise ConfigError(
                f"station {st.name!r}: `operator` is who the station `up` starts runs as; "
                "say `start: true` too, or drop it",
                f"$.ground.stations[{i}].operator",
            )


def _check_failover(m: Mission) -> None:
    """A `failover` section needs a standby; its takeover fits the DN watchdog."""
    if m.standby is None:
        if m.failover is not None:
            raise ConfigError(
                f"failover settings need a standby control node `{STANDBY}` in `nodes`",
                "$.failover",
            )
        return
    if not m.device_nodes:
        raise ConfigError(
            f"a standby control node ({STANDBY}) needs device nodes: they decide when it may "
            "take command (docs/architecture.md#failover)",
            f"$.nodes.{STANDBY}",
        )
    f = m.takeover
    if f.lease_loops > f.takeover_loops:
        raise ConfigError(
            f"lease_loops ({f.lease_loops}) must be at most takeover_loops "
            f"({f.takeover_loops}): the device nodes would refuse every takeover the standby "
            "asks for when it asks",
            "$.failover.lease_loops",
        )
    wd = m.faults.dn_watchdog_loops
    if f.takeover_loops + 3 > wd:
        raise ConfigError(
            f"takeover_loops ({f.takeover_loops}) plus the ask and the new term's first loop "
            f"must end before the device nodes' watchdog (faults.dn_watchdog_loops = {wd}): "
            f"at most {wd - 3}",
            "$.failover.takeover_loops",
        )
    if m.nodes[STANDBY].board:
        raise ConfigError("a control node has no board", f"$.nodes.{STANDBY}.board")
    for i, ch in enumerate(m.bulk):
        if ch.node in ("cn", STANDBY) or "cn" in ch.readers or STANDBY in ch.readers:
            raise ConfigError(
                f"bulk channel {ch.name!r} ends on a control node: a mission with a standby "
                "control node mirrors the Data Vector, not bulk arrays, so a takeover would "
                "lose it (keep bulk channels between device nodes)",
                f"$.bulk[{i}]",
            )


_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|unixsock-stream|ws)/(.+)$")


def check_endpoint(ep: str, where: str) -> None:
    m = _ENDPOINT_RE.fullmatch(ep)
    if m is None:
        raise ConfigError(
            f"endpoint {ep!r} is not '<proto>/<address>' (e.g. tcp/10.0.0.1:7447)", where
        )
    if m.group(1) == "quic":
        # quic needs the same certificate settings as tls; zplatform's
        # deployment file (zplatform.security.deploy) is tested with tls/ only.
        raise ConfigError(
            f"endpoint {ep!r}: quic/ needs TLS certificate settings from a deployment file, "
            "which zplatform does not support for quic yet; use tcp/ (it runs as tls/ with "
            "mutual TLS under security.transport: mtls, see zplatform.security.deploy)",
            where,
        )
    # A tls/ endpoint is structurally fine here; its certificate settings come
    # from the deployment file, which the session reads (zplatform.security.deploy).
    if m.group(1) in ("tcp", "udp", "tls", "quic", "ws"):
        host, sep, port = m.group(2).rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise ConfigError(f"endpoint {ep!r} needs host:port with a port 0-65535", where)


def transport_reason(m: Mission) -> str:
    """Why the mission's links run mutual TLS, or plain (for messages):
    ``security.transport is auto and the mission has hazardous commands``."""
    if m.security.transport != "auto":
        return f"security.transport is {m.security.transport}"
    if not m.mtls:
        return "security.transport is auto and the mission has no hazardous command"
    return "security.transport is auto and the mission has " + (
        "hazardous commands" if m.commands.hazardous else "a tls/ endpoint"
    )


def _link_endpoint(ep: str, mtls: bool, why: str, where: str) -> str:
    """The endpoint a node actually uses under the mission's transport:
    ``tcp/`` runs as ``tls/`` under mtls (zplatform.security.deploy supplies the
    certificates); ConfigError for an endpoint that cannot (``udp/``, ``ws/``,
    a unix socket) or for ``tls/`` in a mission that says ``plain``."""
    proto = ep.partition("/")[0]
    if not mtls:
        if proto == "tls":
            raise ConfigError(
                f"endpoint {ep!r} is tls/, but security.transport is plain: say "
                "security.transport: mtls (or auto), or use tcp/",
                where,
            )
        return ep
    if proto == "tcp":
        return "tls/" + ep[4:]
    if proto == "tls":
        return ep
    raise ConfigError(
        f"endpoint {ep!r} cannot carry mutual TLS, which this mission's links run ({why}): "
        "use tcp/ (it runs as tls/), or say security.transport: plain on a closed network",
        where,
    )


def _element_path(m: Mission, region: str, i: int, n_platform: int, name: str) -> str:
    """The YAML path of the ``i``-th element of a region after platform elements
    were prepended: the index the user wrote, or where a platform element
    comes from (``cn_state`` from the state machine, ``<c>_mode`` from a
    controller, ``dnX_board_*`` from the node's board)."""
    if i >= n_platform:
        return f"$.regions.{region}[{i - n_platform}]"
    if name == "cn_state":
        return "$.state_machine"
    if any(p.name == name for p in m.params):
        return _param_path(m, name)
    dn = region.removesuffix("_to_cn")
    if dn != region and name.startswith(f"{dn}_board_"):
        return f"$.nodes.{dn}.board"
    if m.health is not None and any(name.endswith(f"_{t.name}") for t in HEALTH_METRICS):
        return "$.health"
    for j, c in enumerate(m.controllers):
        if name == f"{c.name}_mode":
            return f"$.controllers[{j}]"
    return f"$.regions.{region}"


def _param_path(m: Mission, name: str) -> str:
    """The YAML path of parameter ``name`` (``$.params[i]``)."""
    return f"$.params[{next(j for j, p in enumerate(m.params) if p.name == name)}]"


def _check_params(m: Mission) -> None:
    """Structural checks of ``params`` (each entry alone): name, a scalar
    type, bounds for numbers (finite, fitting the type, in order), a default
    that fits and lies within them. States and the whitelist are checked by
    :func:`zplatform.control.params.check_config`."""
    names: set[str] = set()
    for i, p in enumerate(m.params):
        w = f"$.params[{i}]"
        _new_name(p.name, names, "parameter", f"{w}.name", label="parameter name")
        st = SCALAR_TYPES.get(p.type)
        if st is None:
            raise ConfigError(
                f"parameter type {p.type!r} is not a scalar type; expected one of "
                f"{', '.join(SCALAR_TYPES)}",
                f"{w}.type",
            )
        if st.kind == "bool":
            for key in ("min", "max"):
                if getattr(p, key) is not None:
                    raise ConfigError("a bool parameter has no bounds", f"{w}.{key}")
            if not isinstance(p.default, bool):
                raise ConfigError(f"expected true or false, got {p.default!r}", f"{w}.default")
            continue
        for key in ("min", "max", "default"):
            v = getattr(p, key)
            if v is None:
                raise ConfigError(
                    f"a {p.type} parameter needs `{key}`: PRM_SET may set only values "
                    "within [min, max]",
                    f"{w}.{key}",
                )
            not_finite = isinstance(v, float) and not math.isfinite(v)
            if isinstance(v, bool) or not_finite or not st.fits(v):
                rng = f" (range {st.lo}..{st.hi})" if st.kind == "int" else ""
                raise ConfigError(f"{v!r} is not a finite {p.type}{rng}", f"{w}.{key}")
        assert p.min is not None and p.max is not None
        if p.min > p.max:
            raise ConfigError(f"min {p.min!r} is above max {p.max!r}", f"{w}.min")
        if not p.min <= p.default <= p.max:
            raise ConfigError(
                f"default {p.default!r} is outside [{p.min!r}, {p.max!r}]", f"{w}.default"
            )


def _check_elements(m: Mission, n_platform: dict[str, int]) -> int:
    """Names, types, sizes and initial values of every element; returns the
    control node's vector's bytes (every region)."""
    seen: dict[str, tuple[str, str]] = {}
    vector_bytes = 0
    for region, elements in m.regions.items():
        n = n_platform.get(region, 0)
        region_bytes = 0
        for i, e in enumerate(elements):
            where = _element_path(m, region, i, n, e.name)
            if not _NAME_RE.fullmatch(e.name):
                raise ConfigError(
                    f"element name {e.name!r} must match {_NAME_RE.pattern}", f"{where}.name"
                )
            if e.name in seen and any(p.name == e.name for p in m.params):
                raise ConfigError(
                    f"parameter {e.name!r} has the name of an element; a parameter is an "
                    "element of its own (region cn): rename one of them",
                    f"{_param_path(m, e.name)}.name",
                )
            if e.name in seen:
                first_region, first_where = seen[e.name]
                # Blame the element the user declared: when this one is a
                # platform element, the user's earlier one is the culprit.
                culprit = first_where if i < n else where
                raise ConfigError(
                    f"duplicate element name {e.name!r} (also in region "
                    f"{first_region if culprit == where else region!r}; "
                    "platform elements are added automatically, do not declare them)",
                    f"{culprit}.name",
                )
            seen[e.name] = (region, where)
            _check_element_type(e, where)
            # Sizes before initial values: `u8[99999999999]` must fail here
            # with its path, not in a list of that many initial values.
            st, count = element_spec(e)
            size = st.size * max(count, 1)
            region_bytes += size
            vector_bytes += size
            if region_bytes > MAX_REGION_BYTES:
                raise ConfigError(
                    f"region {region!r} grows to {region_bytes} bytes with element {e.name!r}; "
                    f"a region holds at most {MAX_REGION_BYTES} bytes (256 MiB)",
                    f"{where}.type",
                )
            if vector_bytes > MAX_VECTOR_BYTES:
                raise ConfigError(
                    f"the control node's Data Vector (every region) grows to {vector_bytes} "
                    f"bytes with element {e.name!r}; at most {MAX_VECTOR_BYTES} bytes (256 MiB)",
                    f"{where}.type",
                )
            e.initial = _check_initial(e, where)
    return vector_bytes


def _check_element_type(e: ElementConfig, where: str) -> None:
    if e.type == "enum" and e.enum is None:
        raise ConfigError(
            f"element {e.name!r} needs a `type` ({', '.join(SCALAR_TYPES)}, an array like "
            "'f32[3]') or a list of `enum` names",
            f"{where}.type",
        )
    if e.type == "enum" or e.enum is not None:
        if not e.enum:
            raise ConfigError("an enum needs a non-empty list of names in `enum`", f"{where}.enum")
        if e.type != "enum":
            parsed = parse_type(e.type)
            if parsed is None or parsed[0].kind != "int" or parsed[1] != 0:
                raise ConfigError(
                    f"an element with `enum` names must have type 'enum', got {e.type!r}",
                    f"{where}.type",
                )
            e.type = "enum"
        names = e.enum
        for j, n in enumerate(names):
            if not _ENUM_NAME_RE.fullmatch(n):
                raise ConfigError(f"enum name {n!r} is not an identifier", f"{where}.enum[{j}]")
        if len(set(names)) != len(names):
            raise ConfigError(f"enum names repeat: {names}", f"{where}.enum")
        if len(names) > 65536:
            raise ConfigError("an enum holds at most 65536 names", f"{where}.enum")
        return
    parsed = parse_type(e.type)
    if parsed is None:
        raise ConfigError(
            f"invalid element type {e.type!r}; expected one of "
            f"{', '.join(SCALAR_TYPES)}, an array like 'f32[3]', or 'enum'",
            f"{where}.type",
        )
    if parsed[1] > MAX_ARRAY_COUNT:
        raise ConfigError(
            f"array {e.type!r} has {parsed[1]} items; an array holds at most "
            f"{MAX_ARRAY_COUNT} (16 Mi)",
            f"{where}.type",
        )


def _coerce_scalar(st: ScalarType, v: object, where: str, enum: list[str] | None) -> Scalar:
    if enum is not None:
        if isinstance(v, str):
            if v not in enum:
                raise ConfigError(f"{v!r} is not one of the enum names {enum}", where)
            return enum.index(v)
        if isinstance(v, int) and not isinstance(v, bool) and 0 <= v < len(enum):
            return v
        raise ConfigError(f"expected one of the enum names {enum}, got {v!r}", where)
    if st.kind == "float" and isinstance(v, str):
        # YAML has no literal for nan/inf in flow style everyone writes; accept
        # the spelled-out names and nothing else (a "1.5" string is a typo).
        # PyYAML (YAML 1.1) also reads an exponent without a dot (`1e-3`) as
        # a string: accept that form too, then range-check it like a number.
        word = v.strip().lower()
        if word in _FLOAT_WORDS:
            return float(v)
        if not _EXP_FLOAT_RE.match(word):
            raise ConfigError(f"expected a number for {st.name}, got {v!r}", where)
        v = float(word)
    if not st.fits(v):
        if st.kind == "int":
            raise ConfigError(
                f"initial value {v!r} does not fit {st.name} (range {st.lo}..{st.hi})", where
            )
        raise ConfigError(f"initial value {v!r} does not fit {st.name}", where)
    if st.kind == "bool":
        return bool(v)
    if st.kind == "int":
        assert isinstance(v, int | float)
        return int(v)
    assert isinstance(v, int | float)
    return float(v)


def _check_initial(e: ElementConfig, where: str) -> Value:
    st, count = element_spec(e)
    v = e.initial
    w = f"{where}.initial"
    if v is None:
        v = 0 if e.enum else (False if st.kind == "bool" else (0.0 if st.kind == "float" else 0))
        return [v] * count if count else v
    if count == 0:
        if isinstance(v, list):
            raise ConfigError(f"a scalar {e.type} element needs a scalar initial value", w)
        return _coerce_scalar(st, v, w, e.enum)
    if isinstance(v, list):
        if len(v) != count:
            raise ConfigError(f"expected {count} initial values for {e.type}, got {len(v)}", w)
        return [_coerce_scalar(st, x, f"{w}[{j}]", None) for j, x in enumerate(v)]
    return [_coerce_scalar(st, v, w, None)] * count


def _check_archive(m: Mission) -> None:
    """The archive's directory is a path."""
    a = m.archive
    if a.dir is not None and (not a.dir or "\x00" in a.dir):
        raise ConfigError("the archive directory must be a non-empty path", "$.archive.dir")


class ArchiveSizing(NamedTuple):
    """What the ground archive holds in memory for a mission (:func:`archive_sizing`)."""

    row_group_rows: int
    """Snapshots per row group: the open one is a preallocated block of these rows."""
    queue_rows: int
    """Snapshots the hand-off queue (a preallocated ring) holds."""
    vector_bytes: int
    """Bytes of one snapshot (the control node's Data Vector)."""

    @property
    def block_bytes(self) -> int:
        return self.row_group_rows * self.vector_bytes

    @property
    def queue_bytes(self) -> int:
        return self.queue_rows * self.vector_bytes


def archive_sizing(m: Mission, vector_bytes: int) -> ArchiveSizing:
    """The archive's row group and queue for ``m`` whose control node's
    vector is ``vector_bytes`` long: ``archive.row_group_s`` and
    ``archive.queue_s`` of snapshots at the telemetry rate, as set, or when
    unset their defaults cut to what :data:`ARCHIVE_ROW_GROUP_BYTES` and
    :data:`ARCHIVE_QUEUE_BYTES` hold. Raises ConfigError (naming the field
    and the most that fits) when a value set needs more than that, and when
    ``file_s`` is shorter than a row group."""
    a = m.archive
    size = max(vector_bytes, 1)
    per_s = m.loop_hz / m.telemetry_divisor
    mib = 2**20

    def refuse(what: str, s: float, rows: int, cap: int, least: int, path: str) -> ConfigError:
        most = max(cap // size, least)
        return ConfigError(
            f"{what} of {s:g} s is {rows} snapshots of the control node's {size}-byte vector "
            f"at {per_s:g} Hz, {rows * size / mib:.0f} MiB: more than the {cap // mib} MiB the "
            f"archive holds for it; at most {most / per_s:g} s ({most} snapshots), or unset "
            "for the most that fits",
            path,
        )

    if a.row_group_s is None:
        rg = max(1, min(int(ARCHIVE_ROW_GROUP_S * per_s), ARCHIVE_ROW_GROUP_BYTES // size))
    else:
        rg = max(1, int(a.row_group_s * per_s))
        if rg * size > ARCHIVE_ROW_GROUP_BYTES:
            raise refuse(
                "a row group", a.row_group_s, rg, ARCHIVE_ROW_GROUP_BYTES, 1,
                "$.archive.row_group_s",
            )  # fmt: skip
    least = max(1, min(16, ARCHIVE_QUEUE_BYTES // size))  # the ring takes a few at a time
    if a.queue_s is None:
        queue = max(least, min(int(ARCHIVE_QUEUE_S * per_s), ARCHIVE_QUEUE_BYTES // size))
    else:
        want = int(a.queue_s * per_s)
        if want * size > ARCHIVE_QUEUE_BYTES:
            raise refuse(
                "a queue", a.queue_s, want, ARCHIVE_QUEUE_BYTES, least, "$.archive.queue_s"
            )
        queue = max(least, want)
    if rg > int(a.file_s * per_s):
        raise ConfigError(
            f"each row group ({rg / per_s:g} s) is written as closed files when it fills, and "
            f"every file_s ({a.file_s:g} s) the files written since the last pass are compacted "
            "into one and retention runs: a pass would find at most one row group's files to "
            "compact (file_s must be at least a row group)",
            "$.archive.row_group_s" if a.row_group_s is not None else "$.archive.file_s",
        )
    return ArchiveSizing(rg, queue, size)


def _check_recorder(m: Mission) -> None:
    """The recorder's nodes exist and record, and its ring holds two files."""
    r = m.recorder
    if r is None:
        return
    if r.dir is not None and (not r.dir or "\x00" in r.dir):
        raise ConfigError("the recorder directory must be a non-empty path", "$.recorder.dir")
    for i, n in enumerate(r.nodes or ()):
        if n not in m.nodes or n == "gn":
            raise ConfigError(
                f"{n!r} is not the control node or a device node of this mission "
                "(the ground node keeps its own log)",
                f"$.recorder.nodes[{i}]",
            )
    if r.nodes is not None and len(set(r.nodes)) != len(r.nodes):
        raise ConfigError("a node is listed twice", "$.recorder.nodes")
    if r.max_bytes < 2 * r.file_bytes:
        raise ConfigError(
            f"max_bytes ({r.max_bytes}) must hold at least two files of file_bytes "
            f"({r.file_bytes}): the ring removes the oldest file to start a new one",
            "$.recorder.max_bytes",
        )


def _check_control_sections(m: Mission) -> None:
    """Structural checks of the control sections; semantic checks that need
    the whole Data Vector are done by the owning modules' ``check_config``
    (run by :func:`zplatform.mission.load.check_mission` afterwards)."""
    for section in ("controllers", "devices"):
        names: set[str] = set()
        for i, c in enumerate(getattr(m, section)):
            where = f"$.{section}[{i}]"
            _new_name(c.name, names, section[:-1], f"{where}.name")
            if c.node not in m.nodes or c.node in ("gn", STANDBY):
                raise ConfigError(
                    f"{section[:-1]} {c.name!r} is placed on {c.node!r}; "
                    "expected cn or a device node"
                    + (
                        " (the standby runs cn's controllers when it commands)"
                        if c.node == STANDBY
                        else ""
                    ),
                    f"{where}.node",
                )
            if section == "devices" and c.node == "cn":
                raise ConfigError("devices run on device nodes only", f"{where}.node")
            if ":" not in c.cls:
                raise ConfigError(
                    f"class {c.cls!r} must be 'package.module:ClassName'", f"{where}.class"
                )
