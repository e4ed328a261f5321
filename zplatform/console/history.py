"""The console's history: the ground archive read for the screen (issue 28).

A :class:`HistorySource` answers the console's questions of the archive:
:meth:`~HistorySource.runs`, :meth:`~HistorySource.query` (a
:class:`~zplatform.archive.Query`, downsampled by the archive with
``every``) and :meth:`~HistorySource.events`. :class:`LocalHistory` reads
the archive the ground node writes on this host, read-only (never recovers);
:class:`RemoteHistory` asks the ground node over zenoh
(``{vehicle}/archive/query``) with this station's telemetry key: the
same three questions, each one ask (zplatform/archive/server.py). :func:`history_source` picks
one; :func:`parse_request` reads the history view's line.

Contract: every method blocks (disk or network: call it from a worker
thread, never from textual's loop or a zenoh callback) and raises only
:class:`~zplatform.errors.ArchiveError`, with a reason an operator can
read (an unknown element with ``check``'s "did you mean", a reversed range,
an unreachable station, a refusal's reason, an I/O or zenoh error). A
source serialises its calls (one lock). Guide: docs/operations.md.
"""

from __future__ import annotations

import fnmatch
import secrets
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from ..archive import Archive, Query, RunInfo, archive_dir
from ..config import Mission
from ..control.uplink import did_you_mean
from ..core.datavector import Layout
from ..errors import ArchiveError, ZPlatformError

if TYPE_CHECKING:
    import pyarrow as pa

__all__ = [
    "DEFAULT_HISTORY_MIN",
    "HistoryRequest",
    "HistorySource",
    "LocalHistory",
    "RemoteHistory",
    "fill_query",
    "history_source",
    "iso_utc",
    "match_elements",
    "parse_request",
]

DEFAULT_HISTORY_MIN = 10.0
"""Minutes of history the console opens with (``--history MIN``; 0: none)."""
REMOTE_TIMEOUT_S = 10.0
"""How long an ask over zenoh waits for the station's answer."""


class HistorySource(Protocol):
    """Where the console reads history from (module doc). Every method blocks
    and raises ArchiveError only."""

    where: str
    """Said to the operator: the archive's directory, or the station's key."""

    def runs(self) -> list[RunInfo]: ...

    def query(self, q: Query) -> pa.Table: ...

    def events(self, run: int | None) -> pa.Table: ...

    def close(self) -> None: ...


def iso_utc(t_ns: int) -> str:
    """``t_ns`` (epoch ns) as the archive's ISO UTC time, to the microsecond."""
    s, ns = divmod(t_ns, 1_000_000_000)
    dt = datetime.fromtimestamp(s, UTC).replace(microsecond=ns // 1000)
    return dt.isoformat().replace("+00:00", "Z")


def match_elements(layout: Layout, globs: str, *, scalar: bool = False) -> list[str]:
    """The layout's elements matching comma-separated ``globs`` (the rule of
    :meth:`Archive.elements`, checked here before anything is asked);
    ``scalar``: arrays are refused. ArchiveError with ``check``'s "did you
    mean" for a glob that matches none."""
    names = list(layout.elements)
    pats = [g.strip() for g in globs.split(",") if g.strip()]
    if not pats:
        raise ArchiveError("name elements or globs (dn0_*,cn_state)")
    want: set[str] = set()
    for g in pats:
        hit = fnmatch.filter(names, g)
        if not hit:
            raise ArchiveError(f"no element matches {g!r}{did_you_mean(g, names)}")
        want.update(hit)
    out = [n for n in names if n in want]
    if scalar:
        for n in out:
            if layout.element(n).count:
                raise ArchiveError(f"{n} is an array: plot scalar elements only")
    return out


@dataclass(frozen=True, slots=True)
class HistoryRequest:
    """One history view: ``elements`` (checked names), the run (None: the
    last), ``start``/``end`` as the archive reads times (None: the run's
    ends), ``every`` (None: every row) and ``agg``."""

    elements: tuple[str, ...]
    run: int | None = None
    start: str | None = None
    end: str | None = None
    every: str | None = "1s"
    agg: tuple[str, ...] = ("min", "max", "mean")

    def query(self) -> Query:
        q = Query(",".join(self.elements), run=self.run, start=self.start, end=self.end)
        q.every = self.every
        q.agg = list(self.agg)
        return q

    def line(self) -> str:
        """The request as the operator would type it."""
        words = [",".join(self.elements)]
        if self.start is not None or self.end is not None:
            words.append(self.start if self.start is not None else "start")
        if self.end is not None:
            words.append(self.end)
        words.append(f"every={self.every or 'raw'}")
        if self.every is not None:
            words.append(f"agg={','.join(self.agg)}")
        if self.run is not None:
            words.append(f"run={self.run}")
        return " ".join(words)

    def panned(self, step: int) -> HistoryRequest | None:
        """The same span moved ``step`` spans later (negative: back), when
        both ends are seconds from the run's start; else None."""
        try:
            a = float(str(self.start).removesuffix("s"))
            b = float(str(self.end).removesuffix("s"))
        except ValueError:
            return None
        span = b - a
        if span <= 0:
            return None
        a, b = a + step * span, b + step * span
        if b <= 0:
            return None
        a = max(a, 0.0)
        return HistoryRequest(self.elements, self.run, f"{a:g}", f"{b:g}", self.every, self.agg)


def parse_request(layout: Layout, text: str, *, run: int | None = None) -> HistoryRequest:
    """``ELEMENTS [FROM [TO]] [every=D|raw] [agg=A,B] [run=R]`` (FROM and TO as
    the archive reads times; ``start`` for the run's start). ``run``: the run
    when the line names none. ArchiveError with the reason for a bad line."""
    words = text.split()
    if not words:
        raise ArchiveError("history ELEMENTS [FROM [TO]] [every=1s|raw] [agg=min,max,mean] [run=R]")
    every: str | None = "1s"
    agg: tuple[str, ...] = ("min", "max", "mean")
    times: list[str | None] = []
    for w in words[1:]:
        key, eq, value = w.partition("=")
        if not eq:
            times.append(None if w == "start" else w)
            continue
        if key == "every":
            every = None if value == "raw" else value
        elif key == "agg":
            agg = tuple(a.strip() for a in value.split(",") if a.strip())
            if not agg:
                raise ArchiveError("agg= is empty: name min, max, mean, first, last or count")
        elif key == "run":
            if not value.isdigit():
                raise ArchiveError(f"run={value!r}: a run id is an integer (the runs list)")
            run = int(value)
        else:
            hint = did_you_mean(key, ["every", "agg", "run"])
            raise ArchiveError(f"unknown option {key}={value}{hint}")
    if len(times) > 2:
        raise ArchiveError(f"at most two times (FROM TO), got {len(times)}")
    times += [None] * (2 - len(times))
    elements = match_elements(layout, words[0], scalar=True)  # the view plots them
    return HistoryRequest(tuple(elements), run, times[0], times[1], every, agg)


def fill_query(elements: Sequence[str], now_ns: int, span_ns: int, step_ns: int) -> Query:
    """The open-time fill: ``elements``' last value per ``step_ns`` over the
    last run's ``span_ns`` before ``now_ns`` (vehicle time), downsampled by
    the archive."""
    q = Query(",".join(elements), start=iso_utc(now_ns - span_ns), end=iso_utc(now_ns))
    q.every = f"{step_ns}ns"
    q.agg = ["last"]
    return q


def _guarded(what: str, fn: Callable[[], Any]) -> Any:
    """``fn()``, any failure but a refusal said as an ArchiveError."""
    try:
        return fn()
    except ArchiveError:
        raise
    except ZPlatformError as exc:
        raise ArchiveError(f"{what}: {exc}") from None
    except Exception as exc:  # duckdb, pyarrow, OSError, zenoh: told, never a crash
        raise ArchiveError(f"{what} failed: {type(exc).__name__}: {exc}") from None


class LocalHistory:
    """The archive at ``root`` on this host, read-only (module doc). Each
    call opens it afresh (so a file the ground node closed since is seen)."""

    def __init__(self, mission: Mission, root: str | Path) -> None:
        self.mission, self.root = mission, Path(root)
        self.where = str(self.root)
        self._lock = threading.Lock()

    def _with(self, what: str, fn: Callable[[Archive], Any]) -> Any:
        def go() -> Any:
            with Archive(self.mission, self.root, recover=False) as a:
                return fn(a)

        with self._lock:
            return _guarded(f"the archive {self.root}: {what}", go)

    def runs(self) -> list[RunInfo]:
        return list(self._with("runs", lambda a: a.runs()))

    def query(self, q: Query) -> pa.Table:
        return self._with("query", lambda a: a.query(q))

    def events(self, run: int | None) -> pa.Table:
        return self._with("events", lambda a: a.events(run))

    def close(self) -> None:
        pass


class RemoteHistory:
    """The ground node's archive over zenoh (module doc).

    ``session``, ``key_expr``, ``channel``, ``now_ns``: an open zenoh session,
    the archive's key, the telemetry channel (None without authentication)
    and the clock stamping each ask; :meth:`for_mission` opens them as
    ``zplatform archive query --remote`` does (a tool's link, the mission's
    keys), on first use."""

    def __init__(
        self,
        layout: Layout,
        session: Any,
        key_expr: str,
        channel: Any,
        now_ns: Callable[[], int],
        *,
        timeout_s: float = REMOTE_TIMEOUT_S,
        on_close: Callable[[], None] | None = None,
    ) -> None:
        self.layout = layout
        self.where = key_expr
        self._key = key_expr
        self._session, self._channel, self._now = session, channel, now_ns
        self.timeout_s = timeout_s
        self._on_close = on_close
        self._mission: Mission | None = None  # for_mission's: the link to open
        self._lock = threading.Lock()

    @classmethod
    def for_mission(cls, mission: Mission, *, timeout_s: float = REMOTE_TIMEOUT_S) -> RemoteHistory:
        """A source that opens its link (one zenoh session) on its first query."""
        from ..runtime.transport import KeySpace

        key = KeySpace(mission.vehicle).archive
        src = RemoteHistory(
            Layout.for_node(mission, "cn"), None, key, None, lambda: 0, timeout_s=timeout_s
        )
        src._mission = mission
        return src

    def _connect(self) -> None:
        if self._session is not None or self._mission is None:
            return
        from ..core.auth import channel
        from ..ground.link import GroundLink

        link = GroundLink(self._mission, telemetry=False, events=False)
        self._key = link.keys.archive
        self._session = link.ns.session
        self._channel = channel(link.link_keys, "telemetry")
        self._now, self._on_close = link.clock.now_ns, link.close

    def runs(self) -> list[RunInfo]:
        """The station's run list (a ``runs`` ask), oldest first."""
        from ..archive.server import RunsAsk, runs_from_table

        return list(runs_from_table(self._ask(RunsAsk())))

    def events(self, run: int | None) -> pa.Table:
        """Run ``run``'s events (None: the last) as the station's archive holds them."""
        from ..archive.server import EventsAsk

        return self._ask(EventsAsk(run=run))

    def query(self, q: Query) -> pa.Table:
        match_elements(self.layout, q.elements, scalar=q.every is not None)
        return self._ask(q)

    def _ask(self, what: Any) -> pa.Table:
        """One ask of ``what`` (a Query, RunsAsk or EventsAsk) of the station,
        under the lock; ArchiveError only."""
        from ..archive.server import remote_query

        def go() -> pa.Table:
            self._connect()
            try:
                return remote_query(
                    self._session,
                    self._key,
                    self._channel,
                    what,
                    now_ns=self._now(),
                    nonce=secrets.randbits(64),
                    timeout_s=self.timeout_s,
                )
            except ArchiveError as exc:
                if "no station answered" in str(exc):
                    raise ArchiveError(
                        f"{exc}: is the ground node up and reachable, and does this station "
                        "hold the telemetry key (a stranger's ask is dropped unanswered)?"
                    ) from None
                raise

        with self._lock:
            return _guarded(f"the archive over zenoh ({self.where})", go)

    def close(self) -> None:
        """Close the link this source opened. Does not wait for a query in
        flight (it fails, said, with the session closed): the console quits
        at once."""
        done, self._on_close = self._on_close, None
        if done is not None:
            done()


def history_source(mission: Mission) -> HistorySource:
    """The local archive when the ground node writes one on this host
    (its directory exists), else the ground node's over zenoh."""
    if mission.archive.enabled:
        root = archive_dir(mission)
        if root.is_dir():
            return LocalHistory(mission, root)
    return RemoteHistory.for_mission(mission)
