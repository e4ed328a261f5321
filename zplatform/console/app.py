"""The ground console: a textual App over :class:`ConsoleModel` (terminal or browser).

Layout (fits 80x24, uses more room when there is more): a status bar (link,
loop, state and time in state, loop rate, fault, last command, per-DN
misses/late and clock offsets), the Data Vector grouped by region with
limit colours, the event pane (filtered by severity), an optional live
plot, an optional parameter view (``params``: every parameter's value,
default, bounds, the states it may change in, hazardous ones marked), and
the command line (history on up/down, completion on tab).

The screen redraws at :data:`REFRESH_HZ` whatever the loop rate: it reads
the model under its lock, which the link's threads update at the telemetry
rate. Hazardous commands (``commands.hazardous``), WRITEs of protected
elements (``commands.protected``) and PRM_SETs of hazardous parameters open
a confirmation dialog; confirmed, they go ARM n then COMMAND n+1. History
(:mod:`.history`; docs/operations.md): the last ``model.history_s`` is filled
by a worker thread, never the live path; ``history`` and ``runs`` open
:mod:`.historyview`'s screens.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

from rich.table import Table
from rich.text import Text
from textual import events
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.css.query import NoMatches
from textual.screen import ModalScreen
from textual.suggester import Suggester
from textual.widgets import Button, Input, Label, Static
from textual_plotext import PlotextPlot

from ..errors import ArchiveError, CommandError, DataVectorError
from ..telemetry.records import ParamRow
from .history import HistorySource, fill_query, parse_request
from .historyview import HistoryScreen, RunsScreen
from .link import Link
from .model import (
    HELP,
    LOCAL_COMMANDS,
    ConsoleModel,
    Status,
    archived_event_line,
    severity_style,
)

__all__ = ["REFRESH_HZ", "ConfirmScreen", "ConsoleApp"]

REFRESH_HZ = 10.0


class _Suggest(Suggester):
    def __init__(self, model: ConsoleModel) -> None:
        super().__init__(use_cache=False, case_sensitive=True)
        self.model = model

    async def get_suggestion(self, value: str) -> str | None:
        return self.model.complete(value)


class CommandLine(Input):
    """An Input with history (up/down) and tab completion."""

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("up", "history(-1)", "previous", show=False),
        Binding("down", "history(1)", "next", show=False),
        Binding("tab", "complete", "complete", show=False, priority=True),
    ]

    def __init__(self, model: ConsoleModel, **kw: Any) -> None:
        super().__init__(suggester=_Suggest(model), **kw)
        self.model = model
        self.history: list[str] = []
        self._pos = 0

    def remember(self, line: str) -> None:
        if line and (not self.history or self.history[-1] != line):
            self.history.append(line)
        self._pos = len(self.history)

    def action_history(self, step: int) -> None:
        if not self.history:
            return
        self._pos = max(0, min(len(self.history), self._pos + step))
        self.value = self.history[self._pos] if self._pos < len(self.history) else ""
        self.cursor_position = len(self.value)

    def action_complete(self) -> None:
        done = self.model.complete(self.value)
        if done is not None:
            self.value = done + " "
            self.cursor_position = len(self.value)


class ConfirmScreen(ModalScreen[bool]):
    """Asks before a command that needs ARM first: y confirms, n / Esc cancels."""

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("y", "answer(True)", "yes"),
        Binding("n,escape", "answer(False)", "no"),
    ]
    DEFAULT_CSS = """
    ConfirmScreen { align: center middle; }
    #dialog { width: 80%; max-width: 100; height: auto; border: thick $error; padding: 1 2;
              background: $panel; }
    /* The question wraps inside the dialog: a Label is as wide as its text
       by default, which cut a long ARM question at the screen's edge. */
    #question { width: 100%; }
    #dialog Horizontal { height: auto; align: center middle; }
    #dialog Button { margin: 1 2 0 2; }
    """

    def __init__(self, question: str) -> None:
        super().__init__()
        self.question = question

    def compose(self) -> ComposeResult:
        with Vertical(id="dialog"):
            yield Label(self.question, id="question")
            with Horizontal():
                yield Button("Yes (y)", variant="error", id="yes")
                yield Button("No (n)", variant="primary", id="no")

    def on_mount(self) -> None:
        self.query_one("#no", Button).focus()

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "yes")

    def action_answer(self, yes: bool) -> None:
        self.dismiss(yes)


class ConsoleApp(App[int]):
    """The console. ``link`` is None for a model fed by someone else (tests);
    ``history``: where history is read (None: no history); ``now_ns``: the
    clock (default: the link's, else the host's)."""

    TITLE = "zplatform ground"
    CSS = """
    #status { height: auto; background: $boost; padding: 0 1; }
    #status.los { background: $error; color: $text; }
    #body { height: 1fr; }
    #dv { width: 1fr; min-width: 30; border-right: solid $primary-darken-2; }
    #right { width: 1fr; }
    #events { height: 1fr; }
    #plot { height: 1fr; display: none; }
    #plot.shown { display: block; }
    #params { height: auto; max-height: 50%; display: none; border-top: solid $primary-darken-2; }
    #params.shown { display: block; }
    #cmd { dock: bottom; height: 1; border: none; padding: 0 1; }
    """
    BINDINGS: ClassVar[list[BindingType]] = [Binding("ctrl+q", "quit", "quit")]

    def __init__(
        self,
        model: ConsoleModel,
        link: Link | None = None,
        *,
        history: HistorySource | None = None,
        now_ns: Callable[[], int] | None = None,
    ) -> None:
        super().__init__()
        self.model = model
        self.link = link
        self.history = history
        self._clock = now_ns
        self.history_elements: tuple[str, ...] = ("cn_state",)
        """What the run picker opens a run with: the last history view's elements."""
        self._drawn = -1
        self._shown: dict[str, object] = {}  # what each pane shows now (refresh_view)
        self._rows: list[tuple[str, list[tuple[str, str, str]]]] = []
        self.title = f"zplatform ground - {model.mission.mission}"

    # -- layout --------------------------------------------------------------
    def compose(self) -> ComposeResult:
        yield Static("connecting...", id="status")
        with Horizontal(id="body"):
            with VerticalScroll(id="dv"):
                yield Static("", id="dv-table")
            with Vertical(id="right"):
                with VerticalScroll(id="events"):
                    yield Static("", id="events-text")
                yield PlotextPlot(id="plot")
                with VerticalScroll(id="params"):
                    yield Static("", id="params-table")
        yield CommandLine(self.model, id="cmd", placeholder="command (tab completes, help)")

    def on_mount(self) -> None:
        if self.history is not None and self.model.history_s > 0:
            self.fill_history(list(self.model.plotted), events=True)
        if self.link is not None:
            self.link.start()
        self.query_one("#cmd", CommandLine).focus()
        self.set_interval(1.0 / REFRESH_HZ, self.refresh_view)
        self.refresh_view()

    def on_unmount(self) -> None:
        if self.link is not None:
            self.link.close()
        if self.history is not None:
            self.history.close()

    def now_ns(self) -> int:
        if self._clock is not None:
            return self._clock()
        if self.link is not None:
            return self.link.now_ns()
        import time

        return time.time_ns()

    # -- history -------------------------------------------------------------
    def fill_history(self, elements: list[str], *, events: bool) -> None:
        """Fill ``elements``' plot series (and with ``events``, the event
        pane) with the last ``model.history_s`` of the archive, in a worker
        thread; returns at once. The status line says how it went."""
        m, src = self.model, self.history
        if src is None or m.history_s <= 0 or not (elements or events):
            return
        with m.lock:
            m.history = "filling history..."
            m.version += 1
        now, span = self.now_ns(), int(m.history_s * 1e9)
        step_s = m.plot_step_ns / 1e9

        def work() -> None:
            said: list[str] = []
            got: dict[str, list[tuple[float, float]]] = {}
            lines = []
            if elements:
                try:
                    t = src.query(fill_query(elements, now, span, m.plot_step_ns))
                    ts = [b / 1e9 for b in t.column("bucket_ns").to_pylist()]
                    for n in elements:
                        if not ts:  # no file closed yet: the answer has no columns but the time
                            got[n] = []
                            continue
                        vs = t.column(f"{n}_last").to_pylist()
                        pts = zip(ts, vs, strict=True)
                        got[n] = [(x, float(v)) for x, v in pts if v is not None]
                except (ArchiveError, KeyError) as exc:
                    said.append(f"telemetry: {exc}")
            if events:
                try:
                    rows = src.events(None).to_pylist()
                    lines = [archived_event_line(r) for r in rows if r["t_ns"] >= now - span]
                except (ArchiveError, KeyError) as exc:
                    said.append(f"events: {exc}")
            with m.lock:
                kept = {n: m.seed_series(n, pts, step_s) for n, pts in got.items()}
                added = m.seed_events(lines) if events else 0
                # Where each series' archive ends: a running run shows only up
                # to the last row group the ground wrote (docs/archive.md).
                xs = {n: m.plot_series()[n][0] for n, v in kept.items() if v}
                done = [
                    f"{v} point(s) of {n}"
                    + (f" to {_clock(round(xs[n][v - 1] * 1e9))}" if v else "")
                    for n, v in kept.items()
                ]
                if events and not any(s.startswith("events:") for s in said):
                    done.append(f"{added} event(s)")
                head = f"history {m.history_s / 60:g} min: " + (", ".join(done) or "nothing")
                m.history = "; ".join([head, *said])
                m.version += 1

        self.run_worker(work, thread=True, group="fill", exit_on_error=False)

    # -- drawing -------------------------------------------------------------
    def refresh_view(self) -> None:
        """Redraw what changed since the last call (:data:`REFRESH_HZ` times a second).

        A pane gets new content only when what it shows changed, and the
        screen is laid out again only when a pane's height changed: the Data
        Vector's values move with every snapshot, but its lines (one per
        region and per element, never wrapped) stay. The Data Vector is drawn
        as lines of text cut to the pane's width, not as a table, which rich
        would measure cell by cell at every redraw: redrawn that way, with a
        layout each time, a 125-element mission kept a core busy and the
        operator's keys waited behind the redraws."""
        m = self.model
        with m.lock:
            m.tick(self.now_ns())
            status = m.status()
            changed = m.version != self._drawn
            if changed:
                self._drawn = m.version
                self._rows = m.region_rows()
                lines = m.events()[-200:]
                series = m.plot_series()
                plotted = list(m.plotted)
                params = m.param_rows() if m.show_params else None
        try:
            bar = self.query_one("#status", Static)
        except NoMatches:  # the app is closing (its timer outlived the screen): nothing to draw
            return
        text = _status_text(status)
        if status.history:
            text.append(f"\n{status.history}", style="dim")
        if text != self._shown.get("status"):
            self._shown["status"] = text
            _show(bar, text)
        bar.set_class(status.los, "los")
        dv = self.query_one("#dv-table", Static)
        key = (dv.content_size.width, self._rows)  # a resize redraws it too
        if key != self._shown.get("dv"):
            self._shown["dv"] = key
            shown = _dv_text(self._rows, key[0])
            _show(dv, shown, len(shown.plain.split("\n")) if self._rows else None)
        if not changed:
            return
        if lines != self._shown.get("events"):
            self._shown["events"] = lines
            text = Text(no_wrap=False)
            for x in lines:
                text.append(f"{_clock(x.t_ns)} ", style="dim")
                text.append(f"{x.severity:<11} ", style=severity_style(x.severity) or None)
                text.append(f"{x.source:<7} {x.text}\n")
            self.query_one("#events-text", Static).update(text)
            self.query_one("#events", VerticalScroll).scroll_end(animate=False)
        self.query_one("#params", VerticalScroll).set_class(params is not None, "shown")
        if params is None:
            self._shown.pop("params", None)
        elif params != self._shown.get("params"):
            self._shown["params"] = params
            self.query_one("#params-table", Static).update(_params_table(params))
        plot = self.query_one("#plot", PlotextPlot)
        plot.set_class(bool(plotted), "shown")
        if plotted:
            plt = plot.plt
            plt.clear_data()
            for name in plotted:
                xs, ys = series.get(name, ([], []))
                if xs:
                    x0 = xs[-1]
                    plt.plot([x - x0 for x in xs], ys, label=name)
            plt.xlabel("s before now")
            plot.refresh()

    # -- commands ------------------------------------------------------------
    def on_input_submitted(self, event: Input.Submitted) -> None:
        line = event.value.strip()
        cmdline = self.query_one("#cmd", CommandLine)
        cmdline.remember(line)
        cmdline.value = ""
        if line:
            self.run_command(line)

    def _note(self, text: str, severity: str = "ACTIVITY_LO") -> None:
        with self.model.lock:
            self.model.note(self.now_ns(), text, severity)
        self.refresh_view()

    def run_command(self, line: str) -> None:
        """One command line: a console command, or a command for the vehicle."""
        from ..control.uplink import validate_words
        from ..ground.logic import needs_arm

        words = line.split()
        head = words[0].lower()
        args = words[1:]
        try:
            if head in LOCAL_COMMANDS:
                self._local(head, args)
                return
            checked = validate_words(self.model.mission, head, args)
        except (CommandError, DataVectorError) as exc:
            self._note(f"refused: {exc}", "WARNING_HI")
            return
        shown = " ".join([checked.command, *args])
        with self.model.lock:
            refused = self.model.refusal(
                checked.command,
                target=checked.element,
                ref=int(checked.value) if checked.command == "APPROVE" else 0,
            )
        if refused is not None:  # the CN would refuse it: said here, in its words, not sent
            self._note(f"{shown} by {self.model.operator}: {refused} (not sent)", "WARNING_HI")
            return
        why = needs_arm(self.model.mission, checked.command, args[0] if args else None)
        if why is not None:

            def answered(yes: bool | None) -> None:
                if not yes:
                    self._note(f"{shown} cancelled", "ACTIVITY_HI")
                elif self.link is None:
                    self._note(f"no link: {shown} not sent", "WARNING_HI")
                else:
                    self._note(f"sending ARM then {shown}", "COMMAND")
                    self.link.send(checked, shown, True)

            self.push_screen(ConfirmScreen(f"{why}. Send ARM, then {shown}?"), answered)
            return
        if self.link is None:
            self._note(f"no link: {shown} not sent", "WARNING_HI")
            return
        self._note(f"sending {shown}", "COMMAND")
        self.link.send(checked, shown, False)

    def _local(self, head: str, args: list[str]) -> None:
        m = self.model
        if head == "quit":
            self.exit(0)
            return
        if head == "help":
            self._note(HELP)
            return
        if head in ("history", "runs"):
            self._open_history(head, args)
            return
        with m.lock:
            if head == "filter":
                msg = m.set_filter(args)
            elif head == "plot":
                msg = m.set_plot(args)
            elif head == "params":
                msg = m.toggle_params()
            else:  # clear
                m.log.clear()
                m.version += 1
                msg = "events cleared"
        self._note(msg)
        if head == "plot":  # outside the lock: the fill takes it
            self.fill_history(list(m.plotted), events=False)

    def _open_history(self, head: str, args: list[str]) -> None:
        """``history [LINE]`` or ``runs``: open the view (read-only)."""
        if self.history is None:
            self._note(f"{head}: this console has no archive to read", "WARNING_HI")
            return
        layout = self.model.layout
        if head == "runs":
            self.push_screen(RunsScreen(self.history, layout, self.history_elements))
            return
        if not args:
            self.push_screen(HistoryScreen(self.history, layout))
            return
        try:
            req = parse_request(layout, " ".join(args))
        except ArchiveError as exc:
            self._note(f"refused: {exc}", "WARNING_HI")
            return
        self.history_elements = req.elements
        self.push_screen(HistoryScreen(self.history, layout, req))

    async def on_key(self, event: events.Key) -> None:
        # Typing anywhere on the live screen goes to the command line.
        if self.screen is not self.default_screen:
            return
        cmd = self.query_one("#cmd", CommandLine)
        if not cmd.has_focus and event.is_printable and not isinstance(self.screen, ModalScreen):
            cmd.focus()


def _show(widget: Static, content: Any, height: int | None = None) -> None:
    """Give ``widget`` new content; lay the screen out again only when its
    height changes (``height``: the content's, when known without measuring)."""
    widget.update(content, layout=False)
    width = widget.content_size.width
    if not width:  # not laid out yet
        widget.refresh(layout=True)
        return
    if height is None:
        height = widget.get_content_height(widget.size, widget.size, width)
    if height != widget.content_size.height:
        widget.refresh(layout=True)


def _status_text(s: Status) -> Text:
    t = Text()
    if not s.connected:
        t.append(" NO SIGNAL ", style="bold white on red")
        t.append(" waiting for " + ("the vehicle's run" if s.waiting_for_run else "telemetry"))
        return t
    if s.los:
        t.append(" LOSS OF SIGNAL ", style="bold white on red")
        t.append(f" {s.silence_s or 0:.1f} s ")
    else:
        t.append(" LINK ", style="bold black on green")
    hz = "-" if s.loop_hz is None else f"{s.loop_hz:.1f}"
    t.append(f" loop {s.loop} {hz} Hz  ")
    t.append(f"{s.state}", style="bold")
    t.append(f" {s.time_in_state_s:.1f} s  ")
    if s.fault != "NONE":
        t.append(f"FAULT {s.fault}  ", style="bold red")
    t.append(f"cmd #{s.cmd_seq} {s.cmd_status}  last: {s.last_command}\n")
    if s.commander:  # a redundant mission: who commands, in which term, the standby
        t.append(f"{s.commander} commands, term {s.term}  ", style="bold")
        if s.standby_ready:
            t.append("standby ready  ")
        else:
            t.append("NO STANDBY", style="bold yellow")
            t.append("  ")
    if s.operator or s.lock:  # command authority: who this console is, who holds the lock
        t.append(f"as {s.operator or 'viewer'}  ", style="bold")
        t.append(f"{s.lock}  ")
    if s.pending_arm:
        t.append(f"{s.pending_arm}  ", style="bold yellow")
    if s.stations:  # every station of the mission: its right, the holder, when last heard
        t.append("stations: " + "; ".join(r.text() for r in s.stations) + "\n")
    t.append(f"tm {s.received} gap {s.gaps} bad {s.bad}")
    if s.events_missed:
        t.append(f" ev missed {s.events_missed}")
    for dn, rx, missed, late, off in s.per_dn:
        style = "yellow" if missed or late else None
        # rx/missed/late counts, then the clock offset the CN applies.
        t.append(f"  {dn} {rx}/{missed}/{late}", style=style)
        t.append(f" {off / 1e6:+.2f}ms")
    return t


def _params_table(rows: list[ParamRow]) -> Table:
    table = Table(expand=True, box=None, padding=(0, 1), show_edge=False)
    for col in ("parameter", "value", "default", "bounds", "states"):
        table.add_column(col, no_wrap=True, overflow="ellipsis")
    for r in rows:
        name = Text(r.name, style="bold red" if r.hazardous else "")
        if r.hazardous:
            name.append(" (ARM)", style="red")
        table.add_row(name, r.value, r.default, r.bounds, ",".join(r.states))
    return table


def _clock(t_ns: int) -> str:
    """UTC time of day to the tenth of a second (event and note times are epoch ns)."""
    s, ns = divmod(t_ns, 1_000_000_000)
    return f"{(s // 3600) % 24:02d}:{(s // 60) % 60:02d}:{s % 60:02d}.{ns // 100_000_000}"


_LEVEL_STYLES = {"red": "bold white on red", "yellow": "black on yellow", "": ""}


def _dv_text(rows: list[tuple[str, list[tuple[str, str, str]]]], width: int) -> Text:
    """The Data Vector pane: each region's name, then a line per element,
    its name in the first three fifths of ``width`` and its value (in its
    limit colour) in the rest, each cut with an ellipsis, never wrapped."""
    width = max(width, 3)
    name_w = max(1, (width - 1) * 3 // 5)
    value_w = max(1, width - 1 - name_w)
    out: list[Text] = []
    for region, elements in rows:
        head = Text(region, style="bold underline")
        head.truncate(width, overflow="ellipsis")
        out.append(head)
        for name, value, level in elements:
            cell = Text(name)
            cell.truncate(name_w, overflow="ellipsis", pad=True)
            shown = Text(value, style=_LEVEL_STYLES[level])
            shown.truncate(value_w, overflow="ellipsis")
            out.append(Text.assemble(cell, " ", shown))
    return Text("\n", no_wrap=True, overflow="ellipsis").join(out)
