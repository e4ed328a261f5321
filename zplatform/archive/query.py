"""The archive's reading side: one front door for runs, queries, events, exports.

:class:`Archive` opens a mission's archive (recovering what a crash left when
no writer holds it) and answers :class:`Query` objects with DuckDB, in
process, over the closed Parquet files: only the files of the asked run and
hours, only the asked columns. Times (:func:`parse_time`) are ISO UTC
(``2026-12-07T03:20:00Z``), seconds from the run's first loop (``12.5``,
``12.5s``) or loop numbers (``loop:1234``); elements are comma-separated
globs checked against the layout, with the "did you mean" of ``check``.

Contract: every method returns a ``pyarrow.Table`` (or a list) and raises
:class:`~zplatform.errors.ArchiveError` with the reason for a bad query (an
unknown run or element, a reversed range, an aggregation of an array); it
never raises anything else for the archive's contents: an unreadable file
is skipped and told in :attr:`Archive.problems`.
"""

from __future__ import annotations

import fnmatch
import math
import os
import re
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

import msgspec
import pyarrow as pa
import pyarrow.parquet as pq

from ..config import Mission
from ..control.uplink import did_you_mean
from ..core.datavector import Layout
from ..core.events import Severity
from ..errors import ArchiveError
from . import store

__all__ = ["AGGREGATES", "Archive", "Query", "parse_every", "parse_time"]

AGGREGATES = {
    "min": "min({c})",
    "max": "max({c})",
    "mean": "avg({c})",
    "first": "arg_min({c}, loop)",
    "last": "arg_max({c}, loop)",
    "count": "count({c})",
}
"""The aggregations ``--agg`` takes, and their DuckDB expression."""
MAX_ELEMENTS = 10_000


class Query(msgspec.Struct, forbid_unknown_fields=True):
    """One telemetry query (the CLI's ``query``, the zenoh queryable's body).

    ``run``: a run id, or None for the last; ``start``/``end``: times as
    :func:`parse_time` reads them (None: the run's first/last loop);
    ``elements``: comma-separated globs; ``every``: a bucket (``100ms``,
    ``1s``) with ``agg`` (names of :data:`AGGREGATES`), or None for every row."""

    elements: str
    run: int | None = None
    start: str | None = None
    end: str | None = None
    every: str | None = None
    agg: list[str] = msgspec.field(default_factory=lambda: ["min", "max", "mean"])


_UNITS = {"ns": 1, "us": 1_000, "ms": 1_000_000, "s": 1_000_000_000, "min": 60_000_000_000}


def parse_every(text: str) -> int:
    """``100ms``, ``1s``, ``2min`` (ns, us, ms, s, min) into nanoseconds (> 0)."""
    m = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?)\s*(ns|us|ms|s|min)\s*", text)
    if not m:
        raise ArchiveError(f"--every {text!r}: expected a duration such as 100ms, 1s or 2min")
    ns = round(float(m.group(1)) * _UNITS[m.group(2)])
    if ns <= 0:
        raise ArchiveError(f"--every {text!r}: must be longer than 0")
    return ns


def parse_time(text: str, info: store.RunInfo) -> tuple[str, int]:
    """``text`` as ``("loop", n)`` or ``("t_ns", vehicle time)``: ISO UTC,
    seconds from the run's first loop, or ``loop:N``."""
    t = text.strip()
    if t.startswith("loop:"):
        n = t[5:]
        if not n.isdigit():
            raise ArchiveError(f"time {text!r}: a loop number is loop:N, N an integer")
        return "loop", int(n)
    m = re.fullmatch(r"([+-]?[0-9]+(?:\.[0-9]*)?)s?", t)
    if m:
        s = float(m.group(1))
        if not math.isfinite(s):
            raise ArchiveError(f"time {text!r} is not a finite number of seconds")
        return "t_ns", info.start_ns + round(s * 1e9)
    try:
        dt = datetime.fromisoformat(t.replace("Z", "+00:00"))
    except ValueError:
        raise ArchiveError(
            f"time {text!r}: expected ISO UTC (2026-12-07T03:20:00Z), seconds from the "
            "run's start (12.5) or a loop number (loop:1234)"
        ) from None
    if dt.tzinfo is None:
        raise ArchiveError(f"time {text!r}: say the time zone (Z for UTC)")
    return "t_ns", round(dt.timestamp() * 1e9)


class Archive:
    """A mission's archive at ``root`` for reading (module doc).

    ``recover``: when no writer holds the archive, first finish what a crash
    left (:func:`.store.recover`). Raises ArchiveError when ``root`` holds
    no archive."""

    def __init__(self, mission: Mission, root: str | Path, *, recover: bool = True) -> None:
        import duckdb  # here: the ground node's writer never needs it

        from .writer import lock_archive

        self.mission, self.root = mission, Path(root)
        self.layout = Layout.for_node(mission, "cn")
        self.problems: list[str] = []
        if not self.root.is_dir():
            raise ArchiveError(f"no archive of mission {mission.mission!r} at {self.root}")
        if recover and os.access(self.root, os.W_OK):
            fd = lock_archive(self.root)
            if fd is not None:
                try:
                    store.recover(
                        self.root, self.layout, mission.mission, mission.vehicle, self._problem
                    )
                finally:
                    os.close(fd)
        self._db = duckdb.connect(":memory:")
        self._db.execute("SET threads TO 2")  # a ground station's tool, not its server
        # A closed file never changes (written as .tmp, renamed): its footer,
        # parsed once, serves every later query of this Archive.
        self._db.execute("SET parquet_metadata_cache = true")

    def _problem(self, text: str) -> None:
        if text not in self.problems:
            self.problems.append(text)

    def runs(self) -> list[store.RunInfo]:
        """Every run's record, oldest first (by run id: the CN's epoch). A
        record a newer zplatform wrote is left out and told in
        :attr:`problems`."""
        out = []
        for r in store.runs_on_disk(self.root):
            try:
                info = store.read_run(self.root, r)
            except ArchiveError as exc:
                self._problem(str(exc))
                continue
            if info is not None:
                out.append(info)
        return out

    def run(self, run: int | None) -> store.RunInfo:
        """Run ``run``'s record (None: the last). ArchiveError when unknown,
        or when a newer zplatform wrote it (the error says so)."""
        if run is not None:
            store.read_run(self.root, run)  # raises for a newer record
        runs = self.runs()
        if not runs:
            raise ArchiveError(f"the archive {self.root} holds no run")
        if run is None:
            return runs[-1]
        for info in runs:
            if info.run == run:
                return info
        ids = ", ".join(str(i.run) for i in runs[-5:])
        raise ArchiveError(f"no run {run} in the archive (the last: {ids})")

    def elements(self, globs: str) -> list[str]:
        """The layout's elements matching the comma-separated ``globs``, in
        layout order. ArchiveError for a glob that matches none."""
        names = list(self.layout.elements)
        want: set[str] = set()
        pats = [g.strip() for g in globs.split(",") if g.strip()]
        if not pats:
            raise ArchiveError("--elements is empty: name elements or globs (dn0_*,cn_state)")
        for g in pats:
            hit = fnmatch.filter(names, g)
            if not hit:
                raise ArchiveError(f"no element matches {g!r}{did_you_mean(g, names)}")
            want.update(hit)
        if len(want) > MAX_ELEMENTS:
            raise ArchiveError(f"{len(want)} elements asked, at most {MAX_ELEMENTS}")
        return [n for n in names if n in want]

    def _files(
        self, kind: str, run: int, *, deep: bool = False, groups: Sequence[int] = (0,)
    ) -> list[list[str]]:
        """Run ``run``'s closed files of ``kind`` that look whole (Parquet's
        magic at both ends; ``deep``: their footer reads, slower), one list
        per file group of ``groups`` (:func:`.store.column_groups`), aligned:
        a part is taken only when each of its groups' files looks whole.
        The others are skipped and told in :attr:`problems`."""
        out: list[list[str]] = [[] for _ in groups]
        for part in store.parquet_files(self.root, kind, run):
            paths = [store.group_path(part, k) for k in groups]
            try:
                for f in paths:
                    if deep:
                        pq.read_metadata(f)
                        continue
                    with open(f, "rb") as fh:
                        head = fh.read(4)
                        fh.seek(-4, os.SEEK_END)
                        if head != b"PAR1" or fh.read(4) != b"PAR1":
                            raise OSError(f"{f.name}: not a whole Parquet file")
            except (OSError, pa.ArrowException) as exc:
                self._problem(f"{part}: unreadable Parquet file skipped ({exc})")
                continue
            for lst, f in zip(out, paths, strict=True):
                lst.append(str(f))
        return out

    def _sql(
        self,
        sql: str,
        kind: str,
        run: int,
        params: Sequence[object],
        empty: pa.Table,
        groups: Sequence[int] = (0,),
    ) -> pa.Table:
        """``sql`` over run ``run``'s files of ``kind`` (its first parameters:
        one list of files per group of ``groups``); a file DuckDB cannot read
        (a damaged footer) is found, skipped and told, and the query run
        again without it."""
        import duckdb

        files = self._files(kind, run, groups=groups)
        try:
            if not files[0]:
                return empty
            return self._db.sql(sql, params=[*files, *params]).to_arrow_table()
        except duckdb.Error:
            files = self._files(kind, run, deep=True, groups=groups)
            if not files[0]:
                return empty
            return self._db.sql(sql, params=[*files, *params]).to_arrow_table()

    def _groups(self, info: store.RunInfo, names: list[str]) -> tuple[list[int], str]:
        """The file groups holding ``names`` (group 0 first, always: the
        loop and the times) and the FROM clause reading them, row beside
        row (a group file holds its group-0 file's rows, in order)."""
        groups = store.column_groups(self.layout, info.group_columns)
        if len(groups) == 1:
            return [0], "read_parquet(?)"
        where = {n: k for k, g in enumerate(groups) for n in g}
        need = sorted({0} | {where[n] for n in names})
        return need, " POSITIONAL JOIN ".join("read_parquet(?)" for _ in need)

    def _where(self, q: Query, info: store.RunInfo) -> tuple[str, list[int]]:
        conds, params = [], []
        bounds: dict[str, list[int]] = {}
        for text, op in ((q.start, ">="), (q.end, "<=")):
            if text is None:
                continue
            col, v = parse_time(text, info)
            conds.append(f"{col} {op} ?")
            params.append(v)
            bounds.setdefault(col, []).append(v)
        for vs in bounds.values():
            if len(vs) == 2 and vs[0] > vs[1]:
                raise ArchiveError(f"the range is reversed: --from {q.start} is after --to {q.end}")
        return (" WHERE " + " AND ".join(conds)) if conds else "", params

    def query(self, q: Query) -> pa.Table:
        """Rows of run ``q.run``: ``loop``, ``t_ns``, ``rx_ns`` and the asked
        elements, in loop order; with ``q.every``, one row per bucket
        (``bucket_ns``: its start) and per element one column per
        aggregation (``cn_state_max``)."""
        info = self.run(q.run)
        names = self.elements(q.elements)
        where, params = self._where(q, info)
        cols = ", ".join(f'"{n}"' for n in names)
        if q.every is None:
            # Rows written in loop order come back in it (DuckDB keeps the
            # files' order): sorting them again costs a third of the query.
            order = "" if info.in_order and info.outcome != "open" else " ORDER BY loop"
            groups, src = self._groups(info, names)
            sql = f"SELECT loop, t_ns, rx_ns, {cols} FROM {src}{where}{order}"
            return self._sql(sql, "tm", info.run, params, self._empty(names), groups)
        every = parse_every(q.every)
        aggs = []
        for a in q.agg:
            if a not in AGGREGATES:
                raise ArchiveError(f"no aggregation {a!r}{did_you_mean(a, list(AGGREGATES))}")
            aggs.append(a)
        if not aggs:
            raise ArchiveError("--agg is empty: name min, max, mean, first, last or count")
        for n in names:
            if self.layout.element(n).count:
                raise ArchiveError(f"{n} is an array: aggregate scalar elements only")
        exprs = ", ".join(
            AGGREGATES[a].format(c=self._scalar(n)) + f' AS "{n}_{a}"' for n in names for a in aggs
        )
        groups, src = self._groups(info, names)
        sql = (
            f"SELECT {info.start_ns} + (t_ns - {info.start_ns}) // {every} * {every} AS bucket_ns, "
            f"{exprs} FROM {src}{where} GROUP BY 1 ORDER BY 1"
        )
        empty = pa.table({"bucket_ns": pa.array([], pa.int64())})
        return self._sql(sql, "tm", info.run, params, empty, groups)

    def _scalar(self, name: str) -> str:
        """Element ``name`` as an aggregatable column (a bool as 0/1)."""
        if self.layout.element(name).scalar.kind == "bool":
            return f'CAST("{name}" AS TINYINT)'
        return f'"{name}"'

    def _empty(self, names: list[str]) -> pa.Table:
        """No rows, the columns of ``names``: built from those alone (the
        whole layout's schema costs 70 ms per query at 10,000 elements)."""
        fields = [pa.field("loop", pa.uint64()), pa.field("t_ns", pa.int64())]
        fields.append(pa.field("rx_ns", pa.int64()))
        fields.extend(pa.field(n, store._arrow_type(self.layout, n)) for n in names)
        return pa.schema(fields).empty_table()

    def events(self, run: int | None = None, *, severity: list[str] | None = None) -> pa.Table:
        """Run ``run``'s events in receive order, those of ``severity`` (names)
        only, in :data:`~.store.EVENT_SCHEMA` (``filled`` False for events an
        archive written before the column kept)."""
        info = self.run(run)
        sevs = [s.upper() for s in severity or []]
        known = [s.name for s in Severity]
        for s in sevs:
            if s not in known:
                raise ArchiveError(f"no severity {s!r}{did_you_mean(s, known)}")
        where = ""
        if sevs:
            where = " WHERE severity IN (" + ", ".join("?" * len(sevs)) + ")"
        # union_by_name: a run's files from before the ``filled`` column
        # beside newer ones (the column is then null for the older rows).
        sql = (
            f"SELECT * FROM read_parquet(?, union_by_name = true){where} ORDER BY rx_ns, node, seq"
        )
        t = self._sql(sql, "ev", info.run, list(sevs), store.EVENT_SCHEMA.empty_table())
        return store.events_in_schema(t)

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Archive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
