"""The console's history screens: an element over a time range, and the run picker.

:class:`HistoryScreen` shows one :class:`~.history.HistoryRequest`: its rows
from the archive (downsampled by the archive: ``every`` buckets, ``agg``
columns), plotted against seconds from the first row and listed below the
plot (scroll back with the mouse or PageUp). Its own line takes another
request (``ELEMENTS [FROM [TO]] [every=D|raw] [agg=A,B] [run=R]``); Ctrl+B /
Ctrl+F move a range given in seconds one span back / forward; Esc returns to
the live console. :class:`RunsScreen` lists the archive's runs (start, length,
loops, outcome, states); Enter on one opens it in a HistoryScreen. Both are
read-only: nothing here sends a command.

Every query runs in a worker thread (:mod:`.history`'s sources block); the
screen shows "querying..." meanwhile and the reason when the archive refuses
or cannot be reached, never an exception.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, ClassVar

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import VerticalScroll
from textual.screen import Screen
from textual.widgets import DataTable, Input, Static
from textual_plotext import PlotextPlot

from ..core.datavector import Layout
from ..errors import ArchiveError
from .history import HistoryRequest, HistorySource, parse_request

if TYPE_CHECKING:
    import pyarrow as pa

    from ..archive import RunInfo

__all__ = ["MAX_ROWS_SHOWN", "HistoryScreen", "RunsScreen", "clock", "whole_run"]

MAX_ROWS_SHOWN = 2000
"""Most rows listed under the plot (all are plotted)."""
RUN_BUCKETS = 300
"""A run picked whole is downsampled to about this many buckets."""


def clock(t_ns: int) -> str:
    """UTC time of day to the millisecond."""
    s, ns = divmod(t_ns, 1_000_000_000)
    return f"{(s // 3600) % 24:02d}:{(s // 60) % 60:02d}:{s % 60:02d}.{ns // 1_000_000:03d}"


def whole_run(elements: tuple[str, ...], info: RunInfo) -> HistoryRequest:
    """Run ``info`` whole, in about :data:`RUN_BUCKETS` buckets."""
    every = max(10_000_000, (info.end_ns - info.start_ns) // RUN_BUCKETS)
    return HistoryRequest(elements, info.run, None, None, f"{every}ns")


class HistoryScreen(Screen[None]):
    """One history request's rows, plotted and listed (module doc).

    After a query: :attr:`request`, :attr:`columns` (the value columns),
    :attr:`rows` (``(t_ns, values...)``) and :attr:`message` say what is
    shown; :attr:`error` the last refusal (None when the last query
    answered)."""

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("escape", "back", "back to live"),
        Binding("ctrl+b", "pan(-1)", "earlier", priority=True),
        Binding("ctrl+f", "pan(1)", "later", priority=True),
    ]
    DEFAULT_CSS = """
    HistoryScreen #h-title { height: auto; background: $boost; padding: 0 1; }
    HistoryScreen #h-msg { height: auto; padding: 0 1; }
    HistoryScreen #h-msg.error { background: $error; color: $text; }
    HistoryScreen #h-plot { height: 2fr; }
    HistoryScreen #h-rows { height: 1fr; border-top: solid $primary-darken-2; }
    HistoryScreen #h-input { dock: bottom; height: 1; border: none; padding: 0 1; }
    """

    def __init__(
        self,
        source: HistorySource,
        layout: Layout,
        request: HistoryRequest | None = None,
        *,
        run: int | None = None,
    ) -> None:
        super().__init__()
        self.source, self.dv_layout = source, layout
        self.request = request
        self.run_id = request.run if request is not None else run
        self.columns: list[str] = []
        self.rows: list[tuple[Any, ...]] = []
        self.message = ""
        self.error: str | None = None
        self.busy = False

    def compose(self) -> ComposeResult:
        yield Static("history", id="h-title")
        yield Static("", id="h-msg")
        yield PlotextPlot(id="h-plot")
        with VerticalScroll(id="h-rows"):
            yield Static("", id="h-table")
        yield Input(
            self.request.line() if self.request is not None else "",
            placeholder="ELEMENTS [FROM [TO]] [every=1s|raw] [agg=min,max,mean] [run=R]",
            id="h-input",
        )

    def on_mount(self) -> None:
        self.query_one("#h-input", Input).focus()
        if self.request is not None:
            self.ask(self.request)
        else:
            self._say(
                "type elements and a range (seconds from the run's start, ISO UTC or "
                "loop:N), then Enter; Esc: back to live"
            )

    # -- asking ------------------------------------------------------------------------
    def on_input_submitted(self, event: Input.Submitted) -> None:
        event.stop()
        try:
            req = parse_request(self.dv_layout, event.value, run=self.run_id)
        except ArchiveError as exc:
            self._refused(str(exc))
            return
        self.ask(req)

    def ask(self, req: HistoryRequest) -> None:
        """Query ``req`` in a worker thread; the screen says so meanwhile."""
        self.request, self.busy = req, True
        self.query_one("#h-input", Input).value = req.line()
        self._title()
        self._say("querying the archive...")
        self.run_worker(
            lambda: self._query(req),
            thread=True,
            exclusive=True,
            group="history",
            exit_on_error=False,
        )

    def _query(self, req: HistoryRequest) -> None:
        try:
            table = self.source.query(req.query())
        except ArchiveError as exc:
            self._call(self._refused, str(exc))
            return
        self._call(self._answered, req, table)

    def _call(self, fn: Any, *args: Any) -> None:
        try:
            self.app.call_from_thread(fn, *args)
        except RuntimeError:  # the app is gone: nobody to tell
            pass

    def action_pan(self, step: int) -> None:
        if self.request is None or self.busy:
            return
        moved = self.request.panned(step)
        if moved is None:
            self._say("Ctrl+B / Ctrl+F move a range given in seconds from the run's start (10 20)")
            return
        self.ask(moved)

    def action_back(self) -> None:
        self.dismiss()

    # -- showing -----------------------------------------------------------------------
    def _title(self) -> None:
        r = self.request
        if r is None:
            return
        run = "the last run" if r.run is None else f"run {r.run}"
        span = f"{r.start or 'start'} .. {r.end or 'end'}"
        how = f"every {r.every}, {','.join(r.agg)}" if r.every else "every row"
        self.query_one("#h-title", Static).update(
            f"history: {','.join(r.elements)}  {run}  {span}  {how}  ({self.source.where})  "
            "Esc: live  Ctrl+B/Ctrl+F: pan"
        )

    def _say(self, text: str, error: bool = False) -> None:
        self.message = text
        msg = self.query_one("#h-msg", Static)
        msg.update(text)
        msg.set_class(error, "error")

    def _refused(self, why: str) -> None:
        self.busy = False
        self.error = why
        self._say(f"refused: {why}", error=True)

    def _answered(self, req: HistoryRequest, table: pa.Table) -> None:
        self.busy = False
        self.run_id = req.run  # the run the view browses: the one that answered
        self.error = None
        tcol = "bucket_ns" if req.every is not None else "t_ns"
        self.columns = [
            c for c in table.column_names if c not in ("bucket_ns", "loop", "t_ns", "rx_ns")
        ]
        ts = table.column(tcol).to_pylist() if table.num_rows else []
        cols = [table.column(c).to_pylist() for c in self.columns]
        self.rows = [(t, *(c[i] for c in cols)) for i, t in enumerate(ts)]
        if not self.rows:
            self._say("no rows in this range (the archive holds closed files only)")
        else:
            first, last = clock(self.rows[0][0]), clock(self.rows[-1][0])
            more = len(self.rows) > MAX_ROWS_SHOWN
            self._say(
                f"{len(self.rows)} row(s) {first} .. {last} UTC"
                + (f"; the first {MAX_ROWS_SHOWN} listed" if more else "")
            )
        self._draw()

    def points(self, column: str) -> list[tuple[int, float]]:
        """``(t_ns, value)`` of a value column, its empty buckets left out."""
        i = self.columns.index(column) + 1
        return [(r[0], float(r[i])) for r in self.rows if r[i] is not None]

    def _draw(self) -> None:
        plot = self.query_one("#h-plot", PlotextPlot)
        plt = plot.plt
        plt.clear_data()
        if self.rows:
            t0 = self.rows[0][0]
            for c in self.columns:
                pts = self.points(c)
                if pts:
                    plt.plot([(t - t0) / 1e9 for t, _ in pts], [v for _, v in pts], label=c)
            plt.xlabel(f"s from {clock(t0)} UTC")
        plot.refresh()
        out = Text(no_wrap=True)
        widths = [max(14, len(c)) for c in self.columns]
        head = "  ".join(f"{c:>{w}}" for c, w in zip(self.columns, widths, strict=True))
        out.append(f"{'time (UTC)':12}  {head}\n", "bold")
        for r in self.rows[:MAX_ROWS_SHOWN]:
            cells = "  ".join(f"{_cell(v):>{w}}" for v, w in zip(r[1:], widths, strict=True))
            out.append(f"{clock(r[0])}  {cells}\n")
        self.query_one("#h-table", Static).update(out)


def _cell(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


class RunsScreen(Screen[None]):
    """The archive's runs, newest first; Enter opens one (module doc).
    :attr:`runs` holds them once listed; :attr:`error` why they could not be."""

    BINDINGS: ClassVar[list[BindingType]] = [Binding("escape", "back", "back to live")]
    DEFAULT_CSS = """
    RunsScreen #r-title { height: auto; background: $boost; padding: 0 1; }
    RunsScreen #r-msg { height: auto; padding: 0 1; }
    RunsScreen #r-msg.error { background: $error; color: $text; }
    RunsScreen DataTable { height: 1fr; }
    """

    def __init__(self, source: HistorySource, layout: Layout, elements: tuple[str, ...]) -> None:
        super().__init__()
        self.source, self.dv_layout, self.elements = source, layout, elements
        self.runs: list[RunInfo] = []
        self.error: str | None = None
        self.busy = True

    def compose(self) -> ComposeResult:
        yield Static(
            f"runs in the archive ({self.source.where})  Enter: browse it "
            f"({','.join(self.elements)})  Esc: live",
            id="r-title",
        )
        yield Static("reading the run list...", id="r-msg")
        yield DataTable(id="r-table", cursor_type="row")

    def on_mount(self) -> None:
        table = self.query_one("#r-table", DataTable)
        table.add_columns("run", "start (UTC)", "s", "loops", "outcome", "states", "commands")
        table.focus()
        self.run_worker(
            self._list, thread=True, exclusive=True, group="history", exit_on_error=False
        )

    def _list(self) -> None:
        try:
            runs = self.source.runs()
        except ArchiveError as exc:
            why = str(exc)
            self._call(self._refused, why)
            return
        self._call(self._listed, runs)

    def _call(self, fn: Any, *args: Any) -> None:
        try:
            self.app.call_from_thread(fn, *args)
        except RuntimeError:
            pass

    def _refused(self, why: str) -> None:
        self.busy, self.error = False, why
        msg = self.query_one("#r-msg", Static)
        msg.update(f"refused: {why}")
        msg.add_class("error")

    def _listed(self, runs: list[RunInfo]) -> None:
        self.busy, self.runs = False, list(reversed(runs))
        table = self.query_one("#r-table", DataTable)
        for r in self.runs:
            start = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(r.start_ns / 1e9))
            table.add_row(
                str(r.run),
                start,
                f"{(r.end_ns - r.start_ns) / 1e9:.2f}",
                str(r.loops),
                r.outcome,
                " > ".join(r.states),
                str(len(r.commands)),
                key=str(r.run),
            )
        self.query_one("#r-msg", Static).update(
            f"{len(runs)} run(s)" if runs else "the archive holds no run"
        )

    def on_data_table_row_selected(self, event: DataTable.RowSelected) -> None:
        event.stop()
        if not 0 <= event.cursor_row < len(self.runs):
            return
        self.open(self.runs[event.cursor_row])

    def open(self, info: RunInfo) -> None:
        """Browse run ``info`` whole (read-only) in a HistoryScreen."""
        self.app.push_screen(
            HistoryScreen(self.source, self.dv_layout, whole_run(self.elements, info))
        )

    def action_back(self) -> None:
        self.dismiss()
