"""The ground's logs: telemetry snapshots as CSV, events as JSON lines beside it.

:class:`TelemetryLog` writes what a :class:`~.link.GroundLink` accepts: one
CSV row per snapshot (:class:`~zplatform.telemetry.logs.CsvLogger`: the CSV
format is :mod:`zplatform.telemetry.logs`'s) and one JSON line per event
(:class:`~zplatform.telemetry.logs.EventWriter`), in ``tm.csv`` and
``tm.events.jsonl``. :func:`log_summary_line` says what a run
logged, for ``zplatform log`` and ``up``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from ..core.datavector import DataVector, Layout
from ..core.events import EV, EventLog, EventType
from ..telemetry.logs import CsvLogger, EventWriter, events_path
from ..telemetry.records import EventRecord
from ..telemetry.summary import GnSummary

__all__ = ["TelemetryLog", "log_summary_line"]

log = logging.getLogger("zplatform.ground")


class TelemetryLog:
    """A telemetry CSV (``csv``, optional) and an events file (``events``,
    optional; :func:`~zplatform.telemetry.logs.events_path` beside the CSV is the
    convention). Files are created (truncated) at construction; with
    ``append`` (a station's, which a restart reopens), what is there is kept
    and this log goes after it (:mod:`zplatform.telemetry.logs`: the rows
    of another layout go to a numbered CSV, :attr:`csv_path`). Each row and
    each event is flushed to the file as it is written (one write a snapshot:
    a ground or station killed with SIGKILL loses no row it took, and
    ``tail -f`` shows the last). A file that cannot take a row or an event
    (a full or failing disk) never stops the ground: each one lost is
    counted (:attr:`errors`), the first of a spell and the recovery logged
    and evented (:meth:`tick`: ``ground_log_failed``, ``ground_log_resumed``),
    and the next is tried again (the archive keeps its own copy).
    :meth:`close` closes them, idempotent. One thread writes and ticks."""

    def __init__(
        self,
        layout: Layout,
        csv: str | Path | None,
        events: str | Path | None,
        *,
        append: bool = False,
    ) -> None:
        self._csv = CsvLogger(csv, layout, append=append) if csv is not None else None
        self._events = EventWriter(events, append=append) if events is not None else None
        self.csv_path = self._csv.path if self._csv is not None else None
        self.events_path = Path(events) if events is not None else None
        self.errors = 0
        """Rows and events the files could not take (class doc)."""
        # The file each spell of failed writes is on (a path in it: failing),
        # each its own: a full CSV beside an events file that still takes
        # writes must not end and start a spell at every row.
        self._failing: set[str] = set()
        # What tick() tells the ground's event log: a spell's start and end.
        self._notes: list[tuple[EventType, dict[str, Any]]] = []

    @classmethod
    def beside(cls, layout: Layout, csv: str | Path | None) -> TelemetryLog:
        """The CSV and its events file beside it (``tm.csv``, ``tm.events.jsonl``)."""
        return cls(layout, csv, events_path(csv) if csv is not None else None)

    @property
    def rows(self) -> int:
        return self._csv.rows if self._csv is not None else 0

    @property
    def event_count(self) -> int:
        return self._events.count if self._events is not None else 0

    def snapshot(self, rx_ns: int, dv: DataVector) -> None:
        if self._csv is not None:
            try:
                self._csv.write(rx_ns, dv)
                self._csv.flush()
            except OSError as exc:
                self._failed(str(self.csv_path), exc)
                return
            if self._failing:
                self._recovered(str(self.csv_path))

    def event(self, rec: EventRecord) -> None:
        if self._events is not None:
            try:
                self._events.write(rec)
            except OSError as exc:
                self._failed(str(self.events_path), exc)
                return
            if self._failing:
                self._recovered(str(self.events_path))

    def tick(self, now_ns: int, events: EventLog) -> None:
        """Tell ``events`` (the ground's) a spell of failed writes as it
        starts and as it ends, once each (class doc). Never raises."""
        notes = self._notes
        if notes:
            for ev, args in notes:
                events.emit(ev, now_ns, **args)
            notes.clear()

    def _failed(self, path: str, exc: OSError) -> None:
        self.errors += 1
        if path not in self._failing:
            self._failing.add(path)
            error = str(exc.strerror or exc)[:200]
            log.warning(
                "the ground's log (%s) cannot be written: %s; what it cannot take is counted "
                "and lost from it (the archive keeps its own copy)",
                path,
                error,
            )
            self._notes.append((EV.GROUND_LOG_FAILED, {"path": path, "error": error}))

    def _recovered(self, path: str) -> None:
        if path not in self._failing:
            return
        self._failing.discard(path)
        log.warning(
            "the ground's log (%s) is written again, %d row(s) or event(s) lost",
            path,
            self.errors,
        )
        self._notes.append((EV.GROUND_LOG_RESUMED, {"path": path, "lost": self.errors}))

    def close(self) -> None:
        for f, path in ((self._csv, self.csv_path), (self._events, self.events_path)):
            if f is None:
                continue
            try:
                f.close()
            except OSError as exc:  # the last buffered bytes: a full disk at the end
                self._failed(str(path), exc)


def log_summary_line(s: GnSummary, csv: str | Path | None, events: str | Path | None) -> str:
    """``logged 1000 snapshot(s) (loops 1..1000), 0 gap(s), 0 bad or refused ->
    tm.csv; 12 event(s) -> tm.events.jsonl``; gaps filled from the CN's flight
    recorder are counted after the gaps (``500 gap(s) (500 filled from the
    CN's recorder, 0 not)``)."""
    loops = f" (loops {s.first_seq}..{s.last_seq})" if s.telemetry_received else ""
    refused = ", ".join(f"{k} {n}" for k, n in s.telemetry_refused.items() if n)
    fill = ""
    if s.telemetry_filled or s.telemetry_unfilled or s.telemetry_not_run:
        never = f", {s.telemetry_not_run} never ran" if s.telemetry_not_run else ""
        fill = (
            f" ({s.telemetry_filled} filled from the CN's recorder, "
            f"{s.telemetry_unfilled} not{never})"
        )
    text = (
        f"logged {s.telemetry_received} snapshot(s){loops}, {s.telemetry_gaps} gap(s){fill}, "
        f"{s.telemetry_bad} bad or refused{f' ({refused})' if refused else ''}"
    )
    if csv is not None:
        text += f" -> {csv}"
    if events is not None:
        text += f"; {s.events_logged} event(s) -> {events}"
    if s.events_missed:
        text += (
            f"; {s.events_missed} event(s) did not arrive, {s.events_filled} of them filled "
            "from the CN's recorder"
        )
    return text
