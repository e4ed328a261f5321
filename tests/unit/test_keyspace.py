"""The key space is one table (zplatform/security/keyspace.py), and nothing uses a key
or a channel without its row.

* every zenoh call in ``zplatform/`` (declare a publisher, subscriber,
  queryable, querier or liveliness token; a session's get or put; a
  liveliness get or subscriber) takes its key from the table-backed
  builders (:class:`zplatform.runtime.transport.KeySpace`, :func:`key_of`,
  :func:`zplatform.runtime.bulk.bulk_key`), found by a static scan that follows
  names, attributes and parameters back to where the key was made;
* every auth channel name the code builds a channel for belongs to a row,
  and every row's channel is tagged by the link the row says;
* docs/keyspace.md is the table's own rendering.

A new channel therefore fails here until its row is in the table, and then
tests/faults/test_keyspace_faults.py until its fault recipe is written.
"""

from __future__ import annotations

import ast
import functools
import importlib
import inspect
import re
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import zenoh

from zplatform.cli.main import main
from zplatform.config import Mission
from zplatform.core import auth
from zplatform.mission.load import load_mission
from zplatform.runtime.transport import KeySpace
from zplatform.security.deploy import access_control
from zplatform.security.keyspace import (
    KEYSPACE,
    ExpandedKey,
    expand_keys,
    key_of,
    key_row,
    keyspace_markdown,
    match_key,
)

ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "zplatform"
DOC = ROOT / "docs" / "keyspace.md"
MISSIONS = [ROOT / "configs" / n for n in ("flight.yaml", "recovery_igniter.yaml", "camera.yaml")]

# -- the table and its rendering ------------------------------------------------------


def test_docs_keyspace_md_is_generated_from_the_table() -> None:
    assert DOC.read_text() == keyspace_markdown(), (
        "docs/keyspace.md is out of date; regenerate it:\n"
        f"    zplatform schema --keyspace --out {DOC.relative_to(ROOT)}"
    )


def test_schema_keyspace_writes_the_table(tmp_path: Path) -> None:
    out = tmp_path / "ks.md"
    assert main(["schema", "--keyspace", "--out", str(out)]) == 0
    assert out.read_text() == keyspace_markdown()


def test_a_key_without_a_row_cannot_be_built() -> None:
    with pytest.raises(KeyError, match="no row 'nope'"):
        key_of("nope", "rocket")
    with pytest.raises(ValueError, match="takes \\['dn'\\]"):
        key_of("probe", "rocket")
    with pytest.raises(ValueError):
        key_of("telemetry", "rocket", dn="dn0")
    assert key_of("probe", "rocket", dn="dn0") == "rocket/dn0/probe"


def _keyspace_members() -> Iterator[tuple[str, str]]:
    """``(member, key)`` for every public KeySpace member, with placeholder args."""
    ks = KeySpace("v")
    for name, attr in inspect.getmembers(KeySpace):
        if name.startswith("_") or name == "vehicle":
            continue
        if isinstance(attr, property):
            yield name, getattr(ks, name)
        elif name == "region":
            for region in ("cn_to_dn0", "dn0_to_cn", "gn_to_cn"):
                yield f"region({region})", ks.region(region)
        else:
            n = len(inspect.signature(attr).parameters) - 1
            yield name, getattr(ks, name)(*(["dn0", "cam"][:n]))


def test_every_keyspace_member_builds_a_key_of_a_row() -> None:
    seen = set()
    for member, key in _keyspace_members():
        r = match_key(key)
        assert r is not None, f"KeySpace.{member} -> {key!r}: no row in KEYSPACE"
        seen.add(r.name)
    # And each row is reachable through the transport's builder.
    assert seen == {r.name for r in KEYSPACE}


def test_keyspace_members_call_key_of_only() -> None:
    """KeySpace builds no key by hand: every method's key is key_of's."""
    src = (PKG / "runtime/transport.py").read_text()
    cls = next(
        n for n in ast.walk(ast.parse(src)) if isinstance(n, ast.ClassDef) and n.name == "KeySpace"
    )
    for fn in cls.body:
        if not isinstance(fn, ast.FunctionDef):
            continue
        for ret in ast.walk(fn):
            if isinstance(ret, ast.Return) and ret.value is not None:
                for node in ast.walk(ret.value):
                    assert not isinstance(node, ast.JoinedStr | ast.BinOp), (
                        f"KeySpace.{fn.name} formats a key by hand"
                    )


@pytest.mark.parametrize("path", MISSIONS, ids=lambda p: p.stem)
def test_expanded_rows_map_back_to_their_row_and_link(path: Path) -> None:
    m = load_mission(path)
    keys = expand_keys(m)
    assert len({k.id for k in keys}) == len(keys)
    used_links: set[str] = set()
    for k in keys:
        assert match_key(k.key) is k.row, k.id
        for f, ch, link in zip(k.row.frames, k.channels, k.links, strict=True):
            if f.tagged:
                assert auth.link_of(ch) == link, k.id
                used_links.add(link)
            else:
                assert link.startswith("none"), f"{k.id}: an untagged frame says why ({link!r})"
    # Every link a host holds tags some row's frames: no key without a use.
    held = {ln for role in auth.host_roles(m) for ln in auth.role_links(m, role)}
    assert held <= used_links, sorted(held - used_links)


def test_every_intake_a_row_names_exists() -> None:
    for r in KEYSPACE:
        for f in r.frames:
            if f.intake == "none":
                continue
            dotted = f.intake.split()[0]
            mod, _, attr = dotted.rpartition(".")
            try:
                obj = importlib.import_module(mod)
            except ModuleNotFoundError:  # Class.method
                mod, _, cls = mod.rpartition(".")
                obj = getattr(importlib.import_module(mod), cls)
            assert hasattr(obj, attr), f"row {r.name}: {dotted} does not exist"


def test_match_key_prefers_the_most_specific_row() -> None:
    assert key_row("gn_to_cn") is match_key("rocket/gn/to_cn")
    assert key_row("dn_to_cn") is match_key("rocket/dn3/to_cn")
    assert key_row("sync_all") is match_key("rocket/*/to_cn")
    assert key_row("everything") is match_key("rocket/x/y")
    assert match_key("rocket") is None


# -- the static scan: every zenoh call's key comes from the table --------------------

_DECLARES = {
    "declare_publisher",
    "declare_subscriber",
    "declare_queryable",
    "declare_querier",
    "declare_token",
}
# The builders backed by the table.
_BUILDERS = {"key_of", "bulk_key"}
_KS_MEMBERS = {n for n in dir(KeySpace) if not n.startswith("_") and n != "vehicle"}
_KS_RECEIVER = re.compile(r"(^|\.)(_?keys|space)$|^KeySpace\(.*\)$")
# Keys a person chooses, not the platform: each with why it is safe.
_CHOSEN = {
    ("zplatform/ground/tap.py", "run_tap", "keyexpr"): (
        "`zplatform tap MISSION KEYEXPR`: a read-only tool subscribes to the "
        "operator's key expression (row everything when none is given)"
    ),
    ("zplatform/ground/tap.py", "run_tap", "k"): (
        "each key `tap_keys` gives: the operator's key expression, or under access "
        "control the rows a tool may watch (deploy.tool_watch_keys, built with key_of)"
    ),
}


class _Module:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.rel = str(path.relative_to(ROOT))
        self.tree = ast.parse(path.read_text())

    @functools.cached_property
    def parent(self) -> dict[ast.AST, ast.AST]:
        # Made when first asked (a call's key to resolve), not for every
        # module at collection: the walk is most of this file's import time.
        return {c: n for n in ast.walk(self.tree) for c in ast.iter_child_nodes(n)}

    def enclosing(self, node: ast.AST, kind: type | tuple[type, ...]) -> ast.AST | None:
        while node in self.parent:
            node = self.parent[node]
            if isinstance(node, kind):
                return node
        return None


MODULES = [_Module(p) for p in sorted(PKG.rglob("*.py"))]


def _zenoh_calls() -> Iterator[tuple[_Module, ast.Call, ast.expr]]:
    for mod in MODULES:
        for node in ast.walk(mod.tree):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
                continue
            name = node.func.attr
            recv = ast.unparse(node.func.value)
            if name in _DECLARES or (
                name in ("get", "put") and re.search(r"(session|liveliness\(\))$", recv)
            ):
                if name == "declare_subscriber" and "handlers" in recv:
                    continue
                key = node.args[0] if node.args else None
                for kw in node.keywords:
                    if kw.arg == "key_expr":
                        key = kw.value
                assert key is not None, f"{mod.rel}:{node.lineno}: {name} without a key"
                yield mod, node, key


_FN = (ast.FunctionDef, ast.AsyncFunctionDef)


def _resolve(
    mod: _Module, expr: ast.expr, at: ast.AST, depth: int = 0, seen: frozenset[object] = frozenset()
) -> list[str]:
    """Why ``expr`` (at ``at``) is not a table-built key: [] when it is.
    ``seen``: the locals being followed (``k = k or ...`` refers to the
    parameter, not to itself)."""
    where = f"{mod.rel}:{getattr(expr, 'lineno', '?')}"
    if depth > 8:
        return [f"{where}: {ast.unparse(expr)} (too deep to follow)"]
    if isinstance(expr, ast.Call):
        f = expr.func
        if isinstance(f, ast.Name) and f.id in _BUILDERS:
            return []
        if isinstance(f, ast.Attribute) and f.attr in _BUILDERS:
            return []
        if (
            isinstance(f, ast.Attribute)
            and f.attr in _KS_MEMBERS
            and _KS_RECEIVER.search(ast.unparse(f.value))
        ):
            return []
        return [f"{where}: {ast.unparse(expr)}"]
    if isinstance(expr, ast.Attribute):
        if expr.attr in _KS_MEMBERS and _KS_RECEIVER.search(ast.unparse(expr.value)):
            return []
        if isinstance(expr.value, ast.Name) and expr.value.id == "self":
            return _self_attr(mod, expr.attr, at, depth)
        return [f"{where}: {ast.unparse(expr)}"]
    if isinstance(expr, ast.Subscript):
        return _resolve(mod, expr.value, at, depth + 1, seen)
    if isinstance(expr, ast.ListComp | ast.GeneratorExp):
        return _resolve(mod, expr.elt, at, depth + 1, seen)
    if isinstance(expr, ast.BoolOp):
        return [w for v in expr.values for w in _resolve(mod, v, at, depth + 1, seen)]
    if isinstance(expr, ast.IfExp):
        return _resolve(mod, expr.body, at, depth + 1, seen) + _resolve(
            mod, expr.orelse, at, depth + 1, seen
        )
    if isinstance(expr, ast.Name):
        return _name(mod, expr.id, at, depth, seen)
    return [f"{where}: {ast.unparse(expr)}"]


def _self_attr(mod: _Module, attr: str, at: ast.AST, depth: int) -> list[str]:
    cls = mod.enclosing(at, ast.ClassDef)
    assert isinstance(cls, ast.ClassDef)
    values = [
        (n.value, n)
        for n in ast.walk(cls)
        if isinstance(n, ast.Assign | ast.AnnAssign)
        and n.value is not None
        and any(
            isinstance(t, ast.Attribute) and t.attr == attr and ast.unparse(t.value) == "self"
            for t in (n.targets if isinstance(n, ast.Assign) else [n.target])
        )
    ]
    if not values:
        return [f"{mod.rel}: self.{attr} is never assigned in {cls.name}"]
    return [w for v, n in values for w in _resolve(mod, v, n, depth + 1)]


def _name(
    mod: _Module, name: str, at: ast.AST, depth: int, seen: frozenset[object] = frozenset()
) -> list[str]:
    fn = mod.enclosing(at, _FN)
    if fn is None:
        return [f"{mod.rel}: {name} is no local"]
    assert isinstance(fn, _FN)
    if (mod.rel, fn.name, name) in _CHOSEN:
        return []  # a key a person chooses (the table's reason)
    me = (mod.rel, fn.lineno, name)
    assigned = [
        (n.value, n)
        for n in ast.walk(fn)
        if isinstance(n, ast.Assign)
        and any(isinstance(t, ast.Name) and t.id == name for t in n.targets)
    ]
    if assigned and me not in seen:
        return [w for v, n in assigned for w in _resolve(mod, v, n, depth + 1, seen | {me})]
    params = [a.arg for a in [*fn.args.posonlyargs, *fn.args.args, *fn.args.kwonlyargs]]
    if name not in params:
        # A closure's free variable: the enclosing function's.
        outer = mod.enclosing(fn, _FN)
        if outer is not None:
            return _name(mod, name, fn, depth + 1)
        return [f"{mod.rel}:{fn.lineno}: {name} in {fn.name} comes from nowhere"]
    return _callers(mod, fn, name, depth)


def _callers(
    mod: _Module, fn: ast.FunctionDef | ast.AsyncFunctionDef, param: str, depth: int
) -> list[str]:
    """Resolve ``param`` of ``fn`` at every call site in zplatform/."""
    cls = mod.enclosing(fn, ast.ClassDef)
    callee = cls.name if fn.name == "__init__" and isinstance(cls, ast.ClassDef) else fn.name
    args = [a.arg for a in [*fn.args.posonlyargs, *fn.args.args]]
    if args and args[0] in ("self", "cls"):
        args = args[1:]
    pos = args.index(param) if param in args else None
    out: list[str] = []
    found = 0
    for m in MODULES:
        for node in ast.walk(m.tree):
            if not isinstance(node, ast.Call):
                continue
            f = node.func
            if _callee(f) != callee:
                continue
            if not _fits(fn, node):
                continue  # another function of the same name
            value = next((k.value for k in node.keywords if k.arg == param), None)
            if value is None and pos is not None and pos < len(node.args):
                value = node.args[pos]
            if value is None:
                continue
            found += 1
            out += _resolve(m, value, node, depth + 1)
    if not found:
        out.append(f"{mod.rel}:{fn.lineno}: nobody in zplatform/ calls {callee} with {param}")
    return out


def _callee(f: ast.expr) -> str:
    return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""


def _fits(fn: ast.FunctionDef | ast.AsyncFunctionDef, call: ast.Call) -> bool:
    """Whether ``call`` can be a call of ``fn`` (by its arguments' count and names)."""
    a = fn.args
    params = [x.arg for x in [*a.posonlyargs, *a.args]]
    if params and params[0] in ("self", "cls"):
        params = params[1:]
    required = len(params) - len(a.defaults)
    if len(call.args) > len(params) and a.vararg is None:
        return False
    names = set(params) | {x.arg for x in a.kwonlyargs}
    if a.kwarg is None and any(k.arg not in names for k in call.keywords if k.arg):
        return False
    given = len(call.args) + sum(1 for k in call.keywords if k.arg in params)
    return given >= required


CALLS = {f"{m.rel}:{c.lineno}": (m, c, k) for m, c, k in _zenoh_calls()}


def test_the_scan_sees_every_kind_of_zenoh_call() -> None:
    kinds = {call.func.attr for _, call, _ in CALLS.values()}  # type: ignore[attr-defined]
    assert kinds >= _DECLARES - {"declare_querier"} | {"get"}, kinds
    # Every get goes through zplatform.runtime.queries.ask (one call site, whose key
    # parameter the scan follows to each caller), so fewer sites than calls.
    assert len(CALLS) >= 20


@pytest.mark.parametrize("site", sorted(CALLS))
def test_every_zenoh_call_takes_its_key_from_the_table(site: str) -> None:
    mod, call, key = CALLS[site]
    why = _resolve(mod, key, call)
    assert not why, (
        f"{site}: a zenoh call whose key is not built from zplatform/security/keyspace.py "
        f"(add the key's row to KEYSPACE and build it with KeySpace/key_of): {why}"
    )


def test_the_scan_refuses_a_key_made_by_hand(tmp_path: Path) -> None:
    """The scan's own check: a key formatted in place is caught."""
    p = tmp_path / "rogue.py"
    p.write_text(
        "def open_it(session, vehicle, keys):\n"
        "    session.declare_subscriber(f'{vehicle}/cn/secret')\n"
        "    session.declare_subscriber(keys.telemetry)\n"
        "    k = keys.probe('dn0')\n"
        "    session.get(k)\n"
    )
    mod = _Module.__new__(_Module)
    mod.path, mod.rel, mod.tree = p, "rogue.py", ast.parse(p.read_text())
    mod.parent = {c: n for n in ast.walk(mod.tree) for c in ast.iter_child_nodes(n)}
    calls = [
        n
        for n in ast.walk(mod.tree)
        if isinstance(n, ast.Call)
        and isinstance(n.func, ast.Attribute)
        and n.func.attr in ("declare_subscriber", "get")
    ]
    verdicts = [bool(_resolve(mod, c.args[0], c)) for c in calls if c.args]
    assert sorted(verdicts) == [False, False, True]


# -- every auth channel belongs to a row ----------------------------------------------


def _channel_names() -> Iterator[tuple[str, str]]:
    """``(site, name pattern)`` of every channel the code makes: string and
    f-string arguments of ``channel(keys, NAME)``, ``keys.channel(NAME)``,
    ``Channel(key, vehicle, NAME)``, and auth.PEER_CHANNELS. An f-string's
    fields become ``{}``."""

    def pattern(e: ast.expr) -> str | None:
        if isinstance(e, ast.Constant) and isinstance(e.value, str):
            return e.value
        if isinstance(e, ast.JoinedStr):
            return "".join(str(v.value) if isinstance(v, ast.Constant) else "{}" for v in e.values)
        return None

    for mod in MODULES:
        for node in ast.walk(mod.tree):
            if not isinstance(node, ast.Call):
                continue
            f = node.func
            name = _callee(f)
            arg: ast.expr | None = None
            # channel(keys, NAME[, run]) and keys.channel(NAME[, run])
            if name == "channel" and isinstance(f, ast.Name) and len(node.args) in (2, 3):
                arg = node.args[1]
            elif name == "channel" and isinstance(f, ast.Attribute) and len(node.args) in (1, 2):
                arg = node.args[0]
            elif name == "Channel" and len(node.args) >= 3:
                arg = node.args[2]
            if arg is None:
                continue
            p = pattern(arg)
            if p is not None:
                yield f"{mod.rel}:{node.lineno}", p
    for name in sorted(auth.PEER_CHANNELS):
        yield "zplatform/core/auth.py:PEER_CHANNELS", name


# What each placeholder of a row's channel may stand for (``{}``: a code's f-string field).
_HOLDS = {
    "dn": r"dn[0-9]+|\{\}",
    "node": r"cn|cn_b|gn|dn[0-9]+|\{\}",
    "asker": r"dn[0-9]+|peer|\{\}",
    "channel": r"[a-z][a-z0-9_]*|\{\}",
    "reader": r"cn|cn_b|gn|dn[0-9]+|\{\}",
}


def _row_channel_regexes() -> list[re.Pattern[str]]:
    out = []
    for r in KEYSPACE:
        for f in r.frames:
            if f.tagged:
                rx = re.sub(
                    r"\\\{([a-z]+)\\\}",
                    lambda m: f"(?:{_HOLDS[m.group(1)]})",
                    re.escape(f.channel),
                )
                out.append(re.compile(rx))
    return out


def test_every_auth_channel_belongs_to_a_row() -> None:
    rows = _row_channel_regexes()
    names = list(_channel_names())
    assert len(names) >= 15
    missing = [(site, n) for site, n in names if not any(rx.fullmatch(n) for rx in rows)]
    assert not missing, f"channels without a row in zplatform/security/keyspace.py: {missing}"


@pytest.mark.parametrize("path", MISSIONS, ids=lambda p: p.stem)
def test_every_channel_a_mission_keys_has_a_row(path: Path) -> None:
    """The mission's channels, as the expanded rows list them, are every
    channel whose link a host holds."""
    m = load_mission(path)
    chans = {c for k in expand_keys(m) for c in k.channels if c}
    if m.has_ground:
        assert "gn_to_cn" in chans
    assert {"telemetry", *(f"cn_to_{dn}" for dn in m.device_nodes)} <= chans
    assert {f"events_{n}" for n in [*m.control_nodes, *m.device_nodes]} <= chans
    if m.standby is not None:
        assert chans >= auth.PEER_CHANNELS
    assert {f"bulk_{ch.name}/{r}" for ch in m.bulk for r in ch.readers} <= chans


# -- the who-columns are what the access-control list allows -------------------------


def _roles(m: Mission, k: ExpandedKey, who: tuple[str, ...]) -> set[str]:
    """The host roles a who-column names, for one expanded row."""
    out: set[str] = set()
    params = dict(k.params)
    for w in who:
        if w in ("commander", "control"):
            out |= set(m.control_nodes)
        elif w.startswith("{"):
            name = params.get(w.strip("{}"))
            if name is not None and name != "peer":
                out.add(name)
            elif name == "peer":
                out |= set(m.control_nodes)
        elif w == "gn":
            out |= {"gn"} if m.has_ground else set()
        elif w == "tool":
            out.add("tool")
        elif w == "any":
            out |= {*m.nodes, "tool"}
    return out


def _acl_allows(acl: dict[str, Any], who: str, message: str, key: str) -> bool:
    (pol,) = [p for p in acl["policies"] if p["subjects"] == [f"s-{who}"]]
    by_id = {r["id"]: r for r in acl["rules"]}
    want = zenoh.KeyExpr(key)
    return any(
        r["flows"] == ["ingress"]
        and message in r["messages"]
        and any(zenoh.KeyExpr(ke).includes(want) for ke in r["key_exprs"])
        for r in (by_id[i] for i in pol["rules"])
    )


@pytest.mark.parametrize("path", MISSIONS, ids=lambda p: p.stem)
def test_the_who_columns_are_what_the_access_control_list_allows(path: Path) -> None:
    """Who puts, queries, declares a queryable or holds a liveliness token on
    each key, by the table, is allowed it by the access-control list of the
    mission's mutual-TLS deployment (a tool that may command)."""
    m = load_mission(path)
    dep: Any = SimpleNamespace(tool=SimpleNamespace(may_command=True))
    acl = access_control(m, dep)
    checked = 0
    for k in expand_keys(m):
        kinds = {f.kind for f in k.row.frames}
        wants = [("put", w) for w in _roles(m, k, k.row.puts)]
        ask = "liveliness_query" if kinds == {"token"} else "query"
        wants += [(ask, w) for w in _roles(m, k, k.row.queries) if "self" not in k.row.queries]
        if "query" in kinds and "self" not in k.row.declares:
            wants += [("declare_queryable", w) for w in _roles(m, k, k.row.declares)]
        if kinds == {"token"} and "*" not in k.key:
            wants += [("liveliness_token", w) for w in _roles(m, k, k.row.declares[:1])]
        for message, who in wants:
            assert _acl_allows(acl, who, message, k.key), f"{k.id}: {who} may not {message}"
            checked += 1
    assert checked >= 20
