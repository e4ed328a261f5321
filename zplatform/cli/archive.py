"""``zplatform archive MISSION runs|query|events|export``: the archive from a shell.

Each action opens the mission's archive (:func:`~zplatform.archive.archive_dir`,
or ``--dir``) through :class:`~.query.Archive` and prints: ``runs`` a table
(``--json``: the run records), ``query`` CSV in the telemetry log's format
(so its rows equal the ground's CSV log's), ``events`` JSON lines in the
events file's format, ``export`` a run into a CSV or Parquet file.
``runs``, ``query`` and ``events`` with ``--remote`` ask the mission's
ground node over zenoh instead (zplatform/archive/server.py) and print the
same.

Contract: a bad argument or query is refused before anything is written
(:class:`~zplatform.errors.ArchiveError`, exit 2, one line); damage the
archive skipped is told on stderr, one line each.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import msgspec
import pyarrow as pa
import pyarrow.parquet as pq

from ..archive import archive_dir, store
from ..archive.query import AGGREGATES, Archive, Query
from ..config import Mission
from ..core.datavector import Layout
from ..errors import ArchiveError
from ..mission.load import load_mission
from ..telemetry.logs import MAX_ARRAY_COLUMNS, formatter
from .args import check_output, mission_verb

__all__ = [
    "archive_run",
    "ask_remote",
    "event_line",
    "is_archive",
    "log_from_archive",
    "register",
    "write_csv",
]


def _run_arg(text: str) -> int:
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"expected a run id (an integer: `runs`), got {text!r}")
    return int(text)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = mission_verb(
        sub,
        "archive",
        help="the ground archive: list runs, query elements over a time range, events, export",
        description="Read the ground archive the ground node writes (docs/archive.md). Times "
        "are ISO UTC (2026-12-07T03:20:00Z), seconds from the run's first loop (12.5) or "
        "loop numbers (loop:1234).",
    )
    p.add_argument("--dir", metavar="DIR", help="the archive directory (default: the mission's)")
    acts = p.add_subparsers(
        dest="action",
        required=True,
        metavar="ACTION",
        help="runs, query, events, export or merge",
    )
    r = acts.add_parser("runs", help="every run kept: times, loops, states, outcome")
    r.add_argument("--json", action="store_true", help="the run records as JSON")
    _remote_args(r)
    q = acts.add_parser("query", help="elements of a run over a time range, as CSV")
    _run_and_range(q)
    q.add_argument(
        "--elements", required=True, metavar="GLOBS", help="comma-separated names or globs"
    )
    q.add_argument("--every", metavar="DURATION", help="aggregate into buckets (100ms, 1s)")
    q.add_argument(
        "--agg",
        default="min,max,mean",
        metavar="LIST",
        help=f"with --every: of {', '.join(AGGREGATES)} (default min,max,mean)",
    )
    q.add_argument("--loops", action="store_true", help="also the loop and t_ns columns, first")
    q.add_argument("--out", metavar="FILE", help="write the CSV here (default: stdout)")
    _remote_args(q)
    e = acts.add_parser("events", help="a run's events, as JSON lines")
    e.add_argument("--run", type=_run_arg, metavar="R", help="the run (default: the last)")
    e.add_argument("--severity", metavar="LIST", help="only these severities (WARNING_HI,FATAL)")
    _remote_args(e)
    x = acts.add_parser("export", help="a run (or some elements of it) into one file")
    _run_and_range(x)
    x.add_argument("--elements", default="*", metavar="GLOBS", help="default: every element")
    x.add_argument("--format", required=True, choices=("csv", "parquet"))
    x.add_argument("--out", required=True, metavar="FILE")
    g = acts.add_parser(
        "merge",
        help="take in other stations' archives (or copies): each run one run, each loop once",
        description="Take into this archive (--dir, or the mission's) every run the archive "
        "directories SRC hold: loops and events it does not hold yet (by run and loop; by "
        "node, seq and stamp), read from their raw segments. Run it again: nothing is taken "
        "twice. Not while a ground node writes this archive.",
    )
    g.add_argument("sources", nargs="+", metavar="SRC", help="another archive (DIR/<mission>)")
    g.add_argument("--run", type=_run_arg, metavar="R", help="only this run (default: every one)")
    p.set_defaults(func=cmd_archive)


def _remote_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--remote",
        action="store_true",
        help="ask the mission's ground node over zenoh (as a tool) instead of reading a directory",
    )
    p.add_argument("--timeout", type=float, default=30.0, metavar="S", help="with --remote")


def _run_and_range(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run", type=_run_arg, metavar="R", help="the run (default: the last)")
    p.add_argument("--from", dest="start", metavar="T", help="from this time (inclusive)")
    p.add_argument("--to", dest="end", metavar="T", help="to this time (inclusive)")


def cmd_archive(args: argparse.Namespace) -> int:
    mission = load_mission(args.mission, code=False)
    if getattr(args, "remote", False):
        return _remote(mission, args)
    root = Path(args.dir) if args.dir else archive_dir(mission)
    if args.action == "merge":
        return _merge(mission, root, args)
    out = getattr(args, "out", None)
    if out is not None:
        check_output(out, "output")
    with Archive(mission, root) as a:
        rc = _ACTIONS[args.action](a, args)
        for problem in a.problems:
            print(f"zplatform: archive: {problem}", file=sys.stderr)
    return rc


def _merge(mission: Mission, root: Path, args: argparse.Namespace) -> int:
    """``merge SRC...``: :func:`.store.merge` of each, under the archive's lock."""
    import os

    from ..archive.writer import lock_archive

    srcs = [Path(s) for s in args.sources]
    for s in srcs:
        if not is_archive(s):
            raise ArchiveError(f"{s} is not an archive directory (it holds no runs/ nor tm/)")
        if s.resolve() == root.resolve():
            raise ArchiveError(f"{s} is this archive: nothing to merge")
    try:
        fd = lock_archive(root)
    except OSError as exc:
        raise ArchiveError(f"cannot open the archive {root}: {exc}") from None
    if fd is None:
        raise ArchiveError(f"a ground node writes the archive {root}: merge when it stopped")
    layout = Layout.for_node(mission, "cn")
    problems: list[str] = []
    try:
        store.recover(root, layout, mission.mission, mission.vehicle, problems.append)
        for s in srcs:
            got = store.merge(
                root,
                s,
                layout,
                mission.mission,
                mission.vehicle,
                problems.append,
                runs=None if args.run is None else [args.run],
            )
            for c in got:
                print(
                    f"{s}: run {c.run}: {c.rows} row(s) and {c.events} event(s) taken, "
                    f"{c.duplicate_rows} row(s) and {c.duplicate_events} event(s) held already"
                )
    finally:
        os.close(fd)
    for line in problems:
        print(f"zplatform: archive: {line}", file=sys.stderr)
    return 0


def _runs(a: Archive, args: argparse.Namespace) -> int:
    return _print_runs(a.runs(), args.json, str(a.root))


def _print_runs(runs: list[store.RunInfo], as_json: bool, where: str) -> int:
    if as_json:
        print(json.dumps([msgspec.to_builtins(r) for r in runs], indent=1))
        return 0
    if not runs:
        print(f"no run in the archive {where}")
        return 0
    print(f"{'run':>20}  {'start (UTC)':19}  {'s':>8}  {'loops':>8}  outcome      states")
    for r in runs:
        start = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(r.start_ns / 1e9))
        dur = (r.end_ns - r.start_ns) / 1e9
        print(
            f"{r.run:>20}  {start}  {dur:8.2f}  {r.loops:>8}  {r.outcome:11}  "
            f"{' > '.join(r.states)} ({len(r.commands)} command event(s))"
        )
    return 0


def _query(a: Archive, args: argparse.Namespace) -> int:
    agg = [s.strip() for s in args.agg.split(",") if s.strip()]
    q = Query(args.elements, run=args.run, start=args.start, end=args.end, every=args.every)
    q.agg = agg
    table = a.query(q)
    with _open(args.out) as f:
        if args.every is not None:
            _plain_csv(table, f)
        else:
            write_csv(a.layout, table, f, loops=args.loops)
    return 0


def _remote(mission: Mission, args: argparse.Namespace) -> int:
    """``runs|query|events --remote``: the same, answered by the ground node."""
    from ..archive.server import EventsAsk, RunsAsk, runs_from_table

    if args.action == "runs":
        table = ask_remote(mission, RunsAsk(), args.timeout)
        return _print_runs(runs_from_table(table), args.json, f"of {mission.vehicle}'s ground")
    if args.action == "events":
        ask = EventsAsk(run=args.run, severity=_severities(args.severity))
        _print_events(ask_remote(mission, ask, args.timeout))
        return 0
    if args.out is not None:
        check_output(args.out, "output")
    q = Query(args.elements, run=args.run, start=args.start, end=args.end, every=args.every)
    q.agg = [s.strip() for s in args.agg.split(",") if s.strip()]
    table = ask_remote(mission, q, args.timeout)
    layout = Layout.for_node(mission, "cn")
    with _open(args.out) as f:
        if args.every is not None:
            _plain_csv(table, f)
        else:
            write_csv(layout, table, f, loops=args.loops)
    return 0


def ask_remote(mission: Mission, ask: Any, timeout_s: float) -> pa.Table:
    """One ask (a Query, RunsAsk or EventsAsk) of the mission's ground node
    over zenoh, as a tool (its own link, closed after); blocks up to
    ``timeout_s`` for each of the hello and the ask. ArchiveError: no
    answer, or the station's refusal with its reason."""
    import secrets

    from ..archive.server import remote_query
    from ..core.auth import channel
    from ..ground.link import GroundLink

    link = GroundLink(mission, telemetry=False, events=False)
    try:
        return remote_query(
            link.ns.session,
            link.keys.archive,
            channel(link.link_keys, "telemetry"),
            ask,
            nonce=secrets.randbits(64),
            timeout_s=timeout_s,
        )
    finally:
        link.close()


def _severities(text: str | None) -> list[str] | None:
    return [s.strip() for s in text.split(",") if s.strip()] if text else None


def _events(a: Archive, args: argparse.Namespace) -> int:
    _print_events(a.events(args.run, severity=_severities(args.severity)))
    return 0


def _print_events(table: pa.Table) -> None:
    for row in table.to_pylist():
        print(event_line(row))


def event_line(row: dict[str, Any]) -> str:
    """An archived event (a row of :meth:`Archive.events`) as the events
    file's JSON line."""
    return json.dumps(
        {
            "rx_time_ns": row["rx_ns"],
            "node": row["node"],
            "seq": row["seq"],
            "t_ns": row["t_ns"],
            "severity": row["severity"],
            "id": row["id"],
            "text": row["text"],
            "verified": row["verified"],
            "filled": bool(row.get("filled", False)),
        }
    )


def is_archive(path: str | Path) -> bool:
    """Whether ``path`` is a mission's archive directory (``DIR/<mission>``:
    it holds ``runs/`` or ``tm/``), not a recording or a file."""
    p = Path(path)
    return (p / "runs").is_dir() or (p / "tm").is_dir()


def archive_run(text: str | int | None) -> int | None:
    """A ``--run`` for the archive: an id, or ``last``/None for the last run."""
    if text is None or text == "last":
        return None
    if isinstance(text, int):
        return text
    if not text.isdigit():
        raise ArchiveError(f"--run {text!r}: a run id (an integer: `archive runs`) or last")
    return int(text)


def log_from_archive(
    mission: Mission,
    root: str | Path,
    run: int | None,
    out_csv: str | Path | TextIO,
    events_out: str | Path | None = None,
    *,
    elements: str = "*",
) -> tuple[store.RunInfo, int, int, list[str]]:
    """Run ``run`` (None: the last) of the archive at ``root`` as the
    ground's log: the telemetry CSV (the format ``log`` and ``up --log``
    write, so ``plot`` reads it) into ``out_csv`` (a path, or an open text
    file) and its events as JSON lines into ``events_out`` (None: not
    written). Returns the run's record, the rows and events written, and
    the damage the archive skipped. Raises ArchiveError for a bad run or
    glob, OSError when a file cannot be written."""
    with Archive(mission, root) as a:
        info = a.run(run)
        table = a.query(Query(elements, run=info.run))
        if isinstance(out_csv, str | Path):
            with open(out_csv, "w", encoding="ascii", newline="") as f:
                write_csv(a.layout, table, f, loops=False)
        else:
            write_csv(a.layout, table, out_csv, loops=False)
        n_ev = 0
        if events_out is not None:
            evs = a.events(info.run).to_pylist()
            with open(events_out, "w", encoding="utf-8") as f:
                for row in evs:
                    f.write(event_line(row) + "\n")
            n_ev = len(evs)
        return info, table.num_rows, n_ev, list(a.problems)


def _export(a: Archive, args: argparse.Namespace) -> int:
    table = a.query(Query(args.elements, run=args.run, start=args.start, end=args.end))
    if args.format == "parquet":
        pq.write_table(table, args.out, compression="zstd")
    else:
        with _open(args.out) as f:
            write_csv(a.layout, table, f, loops=False)
    print(f"{table.num_rows} row(s) of run {a.run(args.run).run} -> {args.out}", file=sys.stderr)
    return 0


_ACTIONS: dict[str, Callable[[Archive, argparse.Namespace], int]] = {
    "runs": _runs,
    "query": _query,
    "events": _events,
    "export": _export,
}


class _open:
    """``path`` opened for writing, or stdout (not closed) for None."""

    def __init__(self, path: str | None) -> None:
        self.path = path
        self.f: TextIO = sys.stdout

    def __enter__(self) -> TextIO:
        if self.path is not None:
            self.f = open(self.path, "w", encoding="ascii", newline="")
        return self.f

    def __exit__(self, *exc: object) -> None:
        if self.path is not None:
            self.f.close()


def write_csv(layout: Layout, table: pa.Table, f: TextIO, *, loops: bool) -> None:
    """``table`` (a query's rows) as the telemetry log's CSV: ``rx_time_ns``
    and the elements (an array of at most 16 items as one column per item,
    a longer one left out), formatted as the log formats them."""
    names = [n for n in table.column_names if n not in ("loop", "t_ns", "rx_ns")]
    header = ["loop", "t_ns"] if loops else []
    header.append("rx_time_ns")
    cells: list[tuple[str, Callable[[Any], str], int]] = []
    for n in names:
        e = layout.element(n)
        if e.count > MAX_ARRAY_COLUMNS:
            continue
        fmt = formatter(e)
        if e.count:
            header.extend(f"{n}[{i}]" for i in range(e.count))
        else:
            header.append(n)
        cells.append((n, fmt, e.count))
    f.write(",".join(header) + "\n")
    for batch in table.to_batches(10_000):
        cols = {n: batch.column(n).to_pylist() for n, _, _ in cells}
        lead = [batch.column(c).to_pylist() for c in (["loop", "t_ns"] if loops else [])]
        rx = batch.column("rx_ns").to_pylist()
        for i in range(batch.num_rows):
            row = [str(c[i]) for c in lead]
            row.append(str(rx[i]))
            for n, fmt, count in cells:
                v = cols[n][i]
                row.extend([fmt(x) for x in v] if count else [fmt(v)])
            f.write(",".join(row) + "\n")


def _plain_csv(table: pa.Table, f: TextIO) -> None:
    f.write(",".join(table.column_names) + "\n")
    for row in table.to_pylist():
        f.write(",".join("" if v is None else repr(v) for v in row.values()) + "\n")
