"""The key space as one table: every zenoh key expression the platform uses.

:data:`KEYSPACE` has a row per key expression pattern (``{vehicle}/{dn}/to_cn``):
who may put on it, who declares its subscribers, queryables or liveliness
tokens, who may query it, and per kind of frame it carries the auth channel
whose key tags it, the freshness and rate rules its receiver keeps, whether
it is bound to a run, and the intake that guards it. It is the single source
of the keys: :class:`zplatform.runtime.transport.KeySpace` builds every key from it
(:func:`key_of`), docs/keyspace.md is generated from it
(:func:`keyspace_markdown`), and ``tests/unit/test_keyspace.py`` refuses a
zenoh call in ``zplatform/`` whose key comes from no row.

Contract: :func:`expand_keys` is pure (the rows a mission uses, placeholders
filled in per device node, node and bulk channel). Nothing here blocks,
allocates after import, or touches the network; :func:`key_of` raises
:class:`KeyError` for a row that does not exist (a new channel cannot get a
key without its row) and ValueError for a missing placeholder.

Placeholders and role names: docs/keyspace.md, docs/architecture.md#key-space.
"""

from __future__ import annotations

import re
import string
from collections.abc import Iterable

import msgspec

from ..config import Mission
from ..core.auth import link_of
from ..core.messages import wildcard_sync_for

__all__ = [
    "KEYSPACE",
    "ExpandedKey",
    "KeyFrames",
    "KeyRow",
    "expand_keys",
    "key_of",
    "key_row",
    "keyspace_markdown",
    "match_key",
]


class KeyFrames(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One kind of frame a key carries, and how its receiver guards it.

    ``kind``: ``query`` (a get's payload), ``reply``, ``sample`` (a put) or
    ``token`` (liveliness: no payload). ``channel``: the auth channel whose
    key tags the frame (:func:`zplatform.core.auth.link_of`), with the row's
    placeholders; empty when untagged, and then ``link`` says why
    (``none: liveliness``, ``none: CRC only``, ...). ``intake``: the dotted
    name of the class (or method) that guards it and, after a space, the
    node that runs it; ``none`` when no node takes the frame (a tap)."""

    kind: str
    channel: str
    link: str
    intake: str
    fresh: str
    rate: str
    run_bound: bool = False

    @property
    def tagged(self) -> bool:
        return bool(self.channel)


class KeyRow(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One key expression pattern (module doc). ``when``: the missions that
    use it (``always``, ``ground``, ``standby``, ``recorder``, ``archive``, ``downlink``,
    ``wildcard``, ``bulk``, ``health``)."""

    name: str
    key: str
    puts: tuple[str, ...]
    declares: tuple[str, ...]
    queries: tuple[str, ...]
    frames: tuple[KeyFrames, ...]
    when: str
    what: str


_STAMP = (
    "stamped later than any admitted and at most the clock bound and a period ahead of "
    "the receiver's clock"
)
_NONCE = "nonce echo: the reply to this exchange's query only"
_NONCE_TIMES = _NONCE + ", its t1 the query's, t2 <= t3, within a day (QUERY_SPAN_NS) of t1"

KEYSPACE: tuple[KeyRow, ...] = (
    KeyRow(
        "dn_to_cn",
        "{vehicle}/{dn}/to_cn",
        puts=("{dn}",),
        declares=("{dn}",),
        queries=("control",),
        frames=(
            KeyFrames(
                "query",
                "cn_to_{dn}",
                "cn-{dn}",
                "zplatform.control.intake.TriggerIntake {dn}",
                _STAMP + " (the trigger's t_ns; with a standby, admitted of its own term: the "
                "newest term or the one before)",
                "mailbox of BACKLOG, newest wins; older answered may_run=False",
            ),
            KeyFrames(
                "reply",
                "{dn}_to_cn",
                "cn-{dn}",
                "zplatform.control.intake.ReplyCheck control",
                "the loop asked, stamped within the clock bound plus a period",
                "one reply per DN per loop; only the session that proved it is the DN",
            ),
        ),
        when="always",
        what="region `{dn}_to_cn` (dnX's queryable; also put for taps); the CN's query "
        "carries region `cn_to_{dn}`",
    ),
    KeyRow(
        "sync_all",
        "{vehicle}/*/to_cn",
        puts=(),
        declares=(),
        queries=("control",),
        frames=(
            KeyFrames(
                "query",
                "cn_to_{dn}",
                "cn-{dn}",
                "zplatform.control.intake.TriggerIntake {dn}",
                _STAMP + " (each DN's own entry of the bundle)",
                "mailbox of BACKLOG, newest wins",
            ),
        ),
        when="wildcard",
        what="one query per loop, a bundle of every DN's `cn_to_dnX` frame "
        "(`transport.sync_query: wildcard`)",
    ),
    KeyRow(
        "cn_to_dn",
        "{vehicle}/cn/to_{dn}",
        puts=("commander",),
        declares=("gn", "tool"),
        queries=(),
        frames=(
            KeyFrames(
                "sample",
                "cn_to_{dn}",
                "cn-{dn}",
                "none",
                "none: a tap, no node takes it",
                "none: a tap",
            ),
        ),
        when="always",
        what="region `cn_to_{dn}`, put for taps",
    ),
    KeyRow(
        "telemetry",
        "{vehicle}/cn/telemetry",
        puts=("commander",),
        declares=("gn", "tool"),
        queries=(),
        frames=(
            KeyFrames(
                "sample",
                "telemetry",
                "downlink",
                "zplatform.control.intake.TelemetryIntake gn",
                "(run, term, stamp) later than any admitted; at most max_age ahead of its "
                "arrival; a new run or term only stamped within max_age of it",
                "mailbox, newest wins",
                run_bound=True,
            ),
        ),
        when="always",
        what="the whole CN Data Vector every `telemetry_divisor` loops, while someone "
        "subscribes; the same tagged bytes also go through iceoryx2 to a ground node on the "
        "CN's host (`transport.intra_host` not `zenoh`), which takes each frame once",
    ),
    KeyRow(
        "downlink",
        "{vehicle}/cn/downlink",
        puts=("commander",),
        declares=("gn", "tool"),
        queries=(),
        frames=(
            KeyFrames(
                "sample",
                "",
                "none: CRC only (a read-only radio downlink)",
                "zplatform.telemetry.ccsds.CcsdsDecoder gn",
                "CCSDS sequence counts",
                "none: read-only",
            ),
        ),
        when="downlink",
        what="CCSDS space packets of telemetry (`downlink:`)",
    ),
    KeyRow(
        "gn_to_cn",
        "{vehicle}/gn/to_cn",
        puts=("gn", "tool"),
        declares=("commander",),
        queries=(),
        frames=(
            KeyFrames(
                "sample",
                "gn_to_cn",
                "uplink",
                "zplatform.control.intake.RequestIntake commander",
                "this CN run (its epoch), numbered above every number seen",
                "mailbox of INBOX, newest wins",
                run_bound=True,
            ),
        ),
        when="ground",
        what="region `gn_to_cn`: one operator command request",
    ),
    KeyRow(
        "events",
        "{vehicle}/{node}/events",
        puts=("{node}",),
        declares=("gn", "tool"),
        queries=(),
        frames=(
            KeyFrames(
                "sample",
                "events_{node}",
                "events-{node}",
                "zplatform.core.events.EventReader gn",
                "per node, seq or t_ns above every record taken, t_ns within max_age of "
                "the ground's clock",
                "mailbox of the ground link, newest kept",
            ),
        ),
        when="always",
        what="event records (severity, id, text, time)",
    ),
    KeyRow(
        "all_events",
        "{vehicle}/*/events",
        puts=(),
        declares=("gn", "tool"),
        queries=(),
        frames=(
            KeyFrames(
                "sample",
                "events_{node}",
                "events-{node}",
                "zplatform.core.events.EventReader gn",
                "per node, seq or t_ns above every record taken, t_ns within max_age of "
                "the ground's clock",
                "mailbox of the ground link, newest kept",
            ),
        ),
        when="always",
        what="the ground's subscription to every node's events",
    ),
    KeyRow(
        "clock",
        "{vehicle}/cn/clock",
        puts=(),
        declares=("commander",),
        queries=("{asker}", "gn", "tool"),
        frames=(
            KeyFrames(
                "query",
                "clock_{asker}_to_cn",
                "cn-{dn}; cn-cn_b for the standby",
                "zplatform.runtime.clocksync.ClockResponder commander",
                "stamped within a day (QUERY_SPAN_NS) of the CN's clock and at most "
                "FRESH_NS older than the asker's newest (against the CN's clock), its nonce "
                "not among the asker's last answered_kept",
                "per asker after the tag, ask_bound (two start-ups, clock.exchanges and "
                "the residual's drift_exchanges each, and a re-sync series, then one series "
                "a re-sync period); refused in "
                "zenoh's callback, unanswered; checked ones: one serving thread, at most "
                "CLOCK_BACKLOG queued, the rest dropped and counted",
            ),
            KeyFrames(
                "reply",
                "clock_cn_to_{asker}",
                "cn-{dn}; cn-cn_b for the standby",
                "zplatform.runtime.clocksync.ClockLink {asker}",
                _NONCE_TIMES,
                "screened in zenoh's callback (header tag, nonce); the first valid reply "
                "ends the exchange",
            ),
            KeyFrames(
                "query",
                "run_hello",
                "downlink",
                "zplatform.runtime.clocksync.ClockResponder commander",
                "any (a run hello names no run; its nonce echoed): none of the last "
                "HELLO_KEPT nonces seen",
                "after the header tag and the nonces: HELLO_BURST, then one every "
                "HELLO_EVERY_NS; the clock's serving thread and backlog",
            ),
            KeyFrames(
                "reply",
                "run_answer",
                "downlink",
                "zplatform.runtime.clocksync.RunAsker gn",
                _NONCE + " (the latest hello's), its run the tag's",
                "one answer per hello; a hello every FIRST_HELLO_S until the first run, "
                "then at most once a RELEARN_S",
            ),
        ),
        when="always",
        what="clock-sync exchanges, per asker: each DN, and a standby as `peer`; the "
        "ground's and the tools' run hello (they learn the commander's run)",
    ),
    KeyRow(
        "alive",
        "{vehicle}/{node}/alive",
        puts=(),
        declares=("{node}",),
        queries=(),
        frames=(
            KeyFrames(
                "token",
                "",
                "none: liveliness",
                "none",
                "zenoh's liveliness",
                "zenoh's liveliness",
            ),
        ),
        when="always",
        what="the node's liveliness token (declared once it is ready)",
    ),
    KeyRow(
        "all_alive",
        "{vehicle}/*/alive",
        puts=(),
        declares=("any",),
        queries=("any",),
        frames=(
            KeyFrames(
                "token",
                "",
                "none: liveliness",
                "none",
                "zenoh's liveliness",
                "zenoh's liveliness",
            ),
        ),
        when="always",
        what="liveliness subscribers and gets: who is alive",
    ),
    KeyRow(
        "standby",
        "{vehicle}/{cn}/standby",
        puts=(),
        declares=("{cn}", "control"),
        queries=(),
        frames=(
            KeyFrames(
                "token",
                "",
                "none: liveliness",
                "none",
                "zenoh's liveliness",
                "zenoh's liveliness",
            ),
        ),
        when="standby",
        what="a control node's token while it follows as a ready standby",
    ),
    KeyRow(
        "health_probe",
        "{vehicle}/{node}/health/probe",
        puts=(),
        declares=("self",),
        queries=("self",),
        frames=(
            KeyFrames(
                "query",
                "",
                "none: local to its session",
                "none",
                "none: local",
                "one probe in flight",
            ),
        ),
        when="health",
        what="the node's own probe of zenoh's runtime (`zplatform.node.health`), session-local",
    ),
    KeyRow(
        "bulk",
        "{vehicle}/{owner}/bulk/{channel}",
        puts=("{owner}",),
        declares=("any",),
        queries=(),
        frames=(
            KeyFrames(
                "sample",
                "bulk_{channel}/{reader}",
                "bulk-{channel}-{reader}",
                "zplatform.runtime.bulk.BulkReader {reader}",
                "header first (its own tag of the sample's, one per reader): numbered or "
                "stamped later than the last taken, stamped at most the clock bound and a "
                "period ahead of the reader's clock; then one pass over the array",
                "one slot, the newest whose header passed wins (zenoh's callback checks "
                "it first), one per poll; RATE_BURST ahead of one every rate_divisor loops",
                run_bound=True,
            ),
        ),
        when="bulk",
        what="bulk channel samples (large arrays), a tag per reader on a link only the "
        "owner and that reader hold; the same tagged bytes go through iceoryx2 to "
        "readers on the owner's host",
    ),
    KeyRow(
        "recorder",
        "{vehicle}/cn/recorder",
        puts=(),
        declares=("commander",),
        queries=("gn", "tool"),
        frames=(
            KeyFrames(
                "query",
                "telemetry",
                "downlink",
                "zplatform.recorder.server.RecorderServer commander",
                "stamped within the clock bound of the CN's clock, not one of the last "
                "REMEMBERED served",
                "REQUEST_BURST, then one every REQUEST_EVERY_NS, before any read; at most "
                "MAX_PENDING in hand, replies paced to serve_bps",
            ),
            KeyFrames(
                "reply",
                "telemetry",
                "downlink",
                "zplatform.ground.gapfill.GapFill gn",
                "screened in zenoh's callback (ReplyScreen: the request in flight, its kind, "
                "the first frame's header tag and run, a loop of the range; the END whole, "
                "tagged, with the request's stamp); the run followed, a loop in the range "
                "asked not yet taken, stamped at most the clock bound after the ask",
                "the gap fill's bounded hold",
                run_bound=True,
            ),
            KeyFrames(
                "reply",
                "events_cn",
                "events-cn",
                "zplatform.ground.gapfill.GapFill gn",
                "the run followed, a number of an event gap being filled, not taken yet "
                "(live or filled); the loops' other records skipped",
                "one event gap asked at a time, its records held until its end",
                run_bound=True,
            ),
        ),
        when="recorder",
        what="the CN's flight recorder: recorded telemetry, or the CN's recorded events, for a "
        "loop range (gap fill)",
    ),
    KeyRow(
        "archive",
        "{vehicle}/archive/query",
        puts=(),
        declares=("gn",),
        queries=("gn", "tool"),
        frames=(
            KeyFrames(
                "query",
                "telemetry",
                "downlink",
                "zplatform.archive.server.ArchiveServer gn",
                "a hello (tagged in no run) is answered with the server's session; an ask (of "
                "a kind: a query, the run list or a run's events; another kind is answered "
                "with the reason) is tagged in that session, its cookie younger than the ask "
                "window, its (cookie, asker, nonce) not one taken; an authentic ask or hello "
                "of another version gets one error reply naming the versions",
                "at most MAX_PENDING in hand (anyone's), archive.serve_per_asker per asker "
                "(tagged asks only), replies paced "
                "to archive.serve_bps, per asker archive.serve_asker_bps, at most "
                "archive.serve_max_bytes per answer (more: an error saying so), one version "
                "error reply a second",
                run_bound=True,
            ),
            KeyFrames(
                "reply",
                "telemetry",
                "downlink",
                "zplatform.archive.server.ArchiveAsk tool",
                "screened in zenoh's callback (ArchiveAsk.screen: size, header tag, session, "
                "nonce, kind, index); the hello's nonce (the session), then the session and "
                "the ask's nonce, each chunk index once, within the count announced",
                "the asker's mailbox, bounded by replies and bytes (REPLY_BACKLOG, "
                "REPLY_BACKLOG_BYTES), junk refused before it",
                run_bound=True,
            ),
        ),
        when="archive",
        what="the ground archive: a query's rows, the run list or a run's events as Arrow IPC "
        "stream chunks (`zplatform archive MISSION query|runs|events --remote`, the console's "
        "remote history)",
    ),
    KeyRow(
        "mirror",
        "{vehicle}/cn/mirror",
        puts=("commander",),
        declares=("control",),
        queries=(),
        frames=(
            KeyFrames(
                "sample",
                "mirror",
                "cn-cn_b",
                "zplatform.control.intake.MirrorIntake control",
                "from the other control node, term and loop in range, (term, loop) "
                "later than every mirror admitted; at most the clock bound and a period "
                "ahead of the standby's clock (Standby.mirror)",
                "mailbox of MIRRORS, newest kept; junk and stale refused before it "
                "(counted: cn_mirror_refused)",
            ),
        ),
        when="standby",
        what="the commander's whole Data Vector every loop, for the standby",
    ),
    KeyRow(
        "probe",
        "{vehicle}/{dn}/probe",
        puts=(),
        declares=("{dn}",),
        queries=("control",),
        frames=(
            KeyFrames(
                "query",
                "probe_cn_to_{dn}",
                "cn-{dn}",
                "zplatform.control.intake.ProbeIntake {dn}",
                _STAMP + " from the same control node",
                "per asker after the tag and freshness (PROBE_BURST, then one a period; "
                "without authentication per channel before any copy); mailbox of PROBES",
            ),
            KeyFrames(
                "reply",
                "probe_{dn}_to_cn",
                "cn-{dn}",
                "zplatform.control.failover.Standby.answer control",
                _NONCE,
                "screened in zenoh's callback (header tag, node, nonce), then the round's "
                "bounded mailbox, one reply taken per DN",
            ),
        ),
        when="standby",
        what="a control node's question: which term do you run, will you promise the next",
    ),
    KeyRow(
        "everything",
        "{vehicle}/**",
        puts=(),
        declares=("gn", "tool"),
        queries=(),
        frames=(
            KeyFrames(
                "sample",
                "",
                "none: each key's own",
                "zplatform.ground.tap.TapDecoder tool",
                "each key's own",
                "the tap's bounded mailbox",
            ),
        ),
        when="always",
        what="`zplatform tap`'s default subscription (each sample checked by its key's channel)",
    ),
)
"""Every key expression pattern of the platform (module doc)."""

_BY_NAME = {r.name: r for r in KEYSPACE}
assert len(_BY_NAME) == len(KEYSPACE), "a row name is used twice"


def key_row(name: str) -> KeyRow:
    """The row called ``name``; KeyError naming the rows when there is none."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(
            f"no row {name!r} in zplatform.security.keyspace.KEYSPACE (rows: {', '.join(_BY_NAME)})"
        ) from None


def _fields(pattern: str) -> set[str]:
    return {f for _, f, _, _ in string.Formatter().parse(pattern) if f}


def key_of(name: str, vehicle: str, **params: str) -> str:
    """The key of row ``name`` for ``vehicle`` with ``params`` filled in
    (``key_of("probe", "rocket", dn="dn0")`` -> ``rocket/dn0/probe``).
    KeyError for an unknown row, ValueError for a missing or unknown
    placeholder. Allocates the key string: call it when a key is declared,
    never in a loop."""
    r = key_row(name)
    want = _fields(r.key) - {"vehicle"}
    if set(params) != want:
        raise ValueError(f"row {name!r} ({r.key}) takes {sorted(want)}, got {sorted(params)}")
    return r.key.format(vehicle=vehicle, **params)


class ExpandedKey(msgspec.Struct, frozen=True):
    """One row for one mission, its placeholders filled in: ``key`` and,
    per frame kind of the row, ``channels`` (empty string: untagged) and
    ``links``. ``params``: what was filled in (``(("dn", "dn0"),)``)."""

    row: KeyRow
    key: str
    params: tuple[tuple[str, str], ...]
    channels: tuple[str, ...]
    links: tuple[str, ...]

    @property
    def id(self) -> str:
        """A short unique name: the row and its parameters (``dn_to_cn[dn0]``)."""
        if not self.params:
            return self.row.name
        return f"{self.row.name}[{','.join(v for _, v in self.params)}]"


def _present(r: KeyRow, mission: Mission) -> bool:
    w = r.when
    if w == "always":
        return True
    if w == "ground":
        return mission.has_ground
    if w == "standby":
        return mission.standby is not None
    if w == "recorder":
        return mission.recorder is not None
    if w == "archive":
        return mission.has_ground and mission.archive.enabled
    if w == "downlink":
        return bool(mission.downlink.ccsds)
    if w == "wildcard":
        return wildcard_sync_for(mission)
    if w == "bulk":
        return bool(mission.bulk)
    if w == "health":
        return mission.health is not None
    raise ValueError(f"row {r.name!r}: unknown condition {w!r}")


def _nodes(mission: Mission) -> list[str]:
    return [*mission.control_nodes, *mission.device_nodes, *(["gn"] if mission.has_ground else [])]


def _bindings(r: KeyRow, mission: Mission) -> list[dict[str, str]]:
    fields = _fields(r.key) | {f for fr in r.frames for f in _fields(fr.channel)}
    fields.discard("vehicle")
    if not fields:
        return [{}]
    if fields == {"dn"}:
        return [{"dn": dn} for dn in mission.device_nodes]
    if fields == {"node"}:
        return [{"node": n} for n in _nodes(mission)]
    if fields == {"asker"}:
        peer = ["peer"] if mission.standby is not None else []
        return [{"asker": a} for a in [*mission.device_nodes, *peer]]
    if fields == {"cn"}:
        return [{"cn": n} for n in mission.control_nodes]
    if fields == {"owner", "channel"}:
        return [{"owner": b.node, "channel": b.name} for b in mission.bulk]
    if fields == {"owner", "channel", "reader"}:
        return [
            {"owner": b.node, "channel": b.name, "reader": r}
            for b in mission.bulk
            for r in b.readers
        ]
    raise ValueError(f"row {r.name!r}: no expansion for placeholders {sorted(fields)}")


def expand_keys(mission: Mission, rows: Iterable[KeyRow] = KEYSPACE) -> tuple[ExpandedKey, ...]:
    """The rows ``mission`` uses, one per binding of their placeholders (per
    device node, per node, per control node, per bulk channel and reader), in table
    order. A wildcard row whose frames name a device node or a node
    (``sync_all``, ``all_events``) expands once per such node, with the
    same key. Pure."""
    out: list[ExpandedKey] = []
    for r in rows:
        if not _present(r, mission):
            continue
        for b in _bindings(r, mission):
            kb = {k: v for k, v in b.items() if k in _fields(r.key)}
            chans = tuple(f.channel.format(**b) for f in r.frames)
            out.append(
                ExpandedKey(
                    r,
                    r.key.format(vehicle=mission.vehicle, **kb),
                    tuple(b.items()),
                    chans,
                    tuple(
                        link_of(c) if c else f.link for c, f in zip(chans, r.frames, strict=True)
                    ),
                )
            )
    return tuple(out)


def _regex(pattern: str, literal: bool) -> re.Pattern[str]:
    # literal: the pattern's wildcards match only themselves (a wildcard key
    # is an instance of a wildcard row, not of every row it would match).
    out = []
    for lit, field, _, _ in string.Formatter().parse(pattern):
        esc = re.escape(lit)
        if not literal:
            esc = esc.replace(r"\*\*", ".+").replace(r"\*", "[^/]+")
        out.append(esc)
        if field:
            out.append("[^/*]+")
    return re.compile("".join(out))


_REGEXES = tuple((r, _regex(r.key, False), _regex(r.key, True)) for r in KEYSPACE)


def match_key(key: str) -> KeyRow | None:
    """The row whose pattern ``key`` is an instance of; the most specific
    when several are (``rocket/gn/to_cn`` is ``gn_to_cn``, not
    ``dn_to_cn`` nor ``everything``). A key with wildcards matches only a
    row with the same wildcards (``rocket/*/alive`` is ``all_alive``).
    None when no row has it."""
    wild = "*" in key
    found = [r for r, rx, lit in _REGEXES if (lit if wild else rx).fullmatch(key)]
    found.sort(key=lambda r: ("*" in r.key, len(_fields(r.key))))
    return found[0] if found else None


def _cell(items: Iterable[str]) -> str:
    s = ", ".join(f"`{i}`" if "{" in i or i in ("commander", "control") else i for i in items)
    return s or "-"


def keyspace_markdown() -> str:
    """docs/keyspace.md, generated from :data:`KEYSPACE` (``zplatform schema
    --keyspace`` prints it; ``tests/unit/test_keyspace.py`` checks the file)."""
    lines = [
        "# The key space",
        "",
        "<!-- Generated from zplatform/security/keyspace.py by `zplatform schema --keyspace`;"
        " do not edit. -->",
        "",
        "Every zenoh key expression the platform uses, one row per pattern, from",
        "the table in `zplatform/security/keyspace.py` that the transport builds its keys",
        "from. The [architecture](architecture.md#key-space) explains them;",
        "`{vehicle}` is the mission's `vehicle`, `{dn}` a device node, `{node}`",
        "any node, `{cn}` a control node, `{asker}` who asks the clock (a device",
        "node, or `peer`: the standby); `commander` is whichever control node",
        "commands, `control` either control node. Who puts, queries, declares a",
        "queryable or holds a token is what the access-control list of a mutual-TLS",
        "mission allows (`tests/unit/test_keyspace.py` checks it).",
        "",
        "## Who uses which key",
        "",
        "| row | key | when | puts | declares | queries | what |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in KEYSPACE:
        lines.append(
            f"| {r.name} | `{r.key}` | {r.when} | {_cell(r.puts)} | {_cell(r.declares)} | "
            f"{_cell(r.queries)} | {r.what} |"
        )
    lines += [
        "",
        "## What guards each frame",
        "",
        "| row | frame | channel | link | intake | fresh when | rate | run-bound |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in KEYSPACE:
        for f in r.frames:
            ch = f"`{f.channel}`" if f.channel else "-"
            intake = f"`{f.intake}`" if f.intake != "none" else "none"
            lines.append(
                f"| {r.name} | {f.kind} | {ch} | {f.link} | {intake} | {f.fresh} | "
                f"{f.rate} | {'yes' if f.run_bound else 'no'} |"
            )
    return "\n".join(lines) + "\n"
