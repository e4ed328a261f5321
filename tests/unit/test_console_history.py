"""The console's history (issue 28), driven by textual's pilot, in process.

An archive written by the archive's own writer in a tmp dir (the flight
mission, run 7: loops 1..3000, 10 ms apart, ``apogee_target_m`` = loop / 4,
``cn_state`` = loop // 100 % 4; three events) is read by a console with no
link: it opens with the last 20 s filled (the exact buckets and events),
shows an element over a range as the archive downsampled it (exact points)
and moves the range back, lists the runs and browses a past one, and says
why for every bad input or unreachable archive instead of raising.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("textual")
pytest.importorskip("textual_plotext")

from textual.widgets import DataTable, Input, Static

from tests.unit.test_archive import PERIOD, T0, feed
from zplatform.archive import ArchiveWriter
from zplatform.console import ConsoleApp, ConsoleModel
from zplatform.console.app import _clock
from zplatform.console.history import (
    HistoryRequest,
    LocalHistory,
    match_elements,
    parse_request,
)
from zplatform.console.historyview import HistoryScreen, RunsScreen
from zplatform.core.datavector import DataVector, Layout
from zplatform.errors import ArchiveError
from zplatform.mission.load import load_mission
from zplatform.telemetry.records import EventRecord

ROOT = Path(__file__).resolve().parents[2]
MISSION = load_mission(ROOT / "configs" / "flight.yaml", code=False)
LAYOUT = Layout.for_node(MISSION, "cn")
HOUR = 3600.0
START = T0 + PERIOD  # run 7's first loop's vehicle time
NOW = T0 + 3000 * PERIOD + 5_000_000  # 5 ms after the last loop: no bound on a loop


@pytest.fixture
def archive(tmp_path: Path) -> Path:
    w = ArchiveWriter(MISSION, LAYOUT, tmp_path)
    dv = DataVector(LAYOUT)
    feed(w, dv, range(1, 101), epoch=5)  # an older run
    feed(w, dv, range(1, 3001), epoch=7)
    for seq, loop, sev, text in (
        (1, 500, "ACTIVITY_HI", "before the window"),
        (2, 2000, "COMMAND", "command LAUNCH accepted"),
        (3, 2500, "WARNING_HI", "chamber pressure high"),
    ):
        t = T0 + loop * PERIOD
        w.event(EventRecord(t + 3, "cn", seq, t, sev, "ev", text))
    w.close()
    return tmp_path


def _drive(
    app: ConsoleApp, body: Callable[[Any], Coroutine[Any, Any, None]], size: tuple[int, int]
) -> None:
    async def go() -> None:
        async with app.run_test(size=size) as pilot:
            await body(pilot)

    asyncio.run(go())


async def _settle(pilot: Any) -> None:
    """Every worker done and what it handed to the screen shown."""
    await pilot.app.workers.wait_for_complete()
    await pilot.pause()
    await pilot.app.workers.wait_for_complete()
    await pilot.pause()


async def _enter(pilot: Any, line: str) -> None:
    """``line`` on the focused Input, then Enter (as pasted)."""
    focused = pilot.app.focused
    assert isinstance(focused, Input)
    focused.value = line
    await pilot.press("enter")


def _console(root: Path, **kw: Any) -> tuple[ConsoleApp, ConsoleModel]:
    model = ConsoleModel(MISSION, los_s=HOUR, **kw)
    return ConsoleApp(model, None, history=LocalHistory(MISSION, root), now_ns=lambda: NOW), model


def test_the_console_opens_with_the_last_seconds_filled(archive: Path) -> None:
    app, model = _console(archive, history_s=20.0)
    model.set_plot(["apogee_target_m"])
    # A live frame came before the fill: it stays, the archive's points go before it.
    live = DataVector(LAYOUT)
    live.set("cn_time_ns", T0 + 2990 * PERIOD)
    live.set("apogee_target_m", -1.0)
    model.on_snapshot(live, NOW)

    async def body(pilot: Any) -> None:
        await _settle(pilot)
        with model.lock:
            series = model.plot_series()["apogee_target_m"]
            shown = [(x.source, x.severity, x.text) for x in model.events()]
            status = model.status().history
        # The last 20 s (loops 1001..3000) in 50 ms buckets (the plot's step),
        # each bucket's last value: loops 1005, 1010, ..., 2985 before the live
        # point at loop 2990 (its bucket and later ones are live's).
        step = 50_000_000
        want = [((START + k * step) / 1e9, (5 * k + 5) / 4) for k in range(200, 597)]
        assert model.plot_step_ns == step
        assert list(zip(*series, strict=True)) == [*want, ((T0 + 2990 * PERIOD) / 1e9, -1.0)]
        assert shown == [
            ("cn", "COMMAND", "ev: command LAUNCH accepted"),
            ("cn", "WARNING_HI", "ev: chamber pressure high"),
        ]
        to = _clock(START + 596 * step)
        assert (
            status == f"history 0.333333 min: 397 point(s) of apogee_target_m to {to}, 2 event(s)"
        )
        app.refresh_view()
        assert status in str(app.query_one("#status", Static).content)

    _drive(app, body, (160, 50))


def test_plot_fills_the_new_elements_series_from_the_archive(archive: Path) -> None:
    app, model = _console(archive, history_s=20.0)

    async def body(pilot: Any) -> None:
        await _settle(pilot)  # the open fill: events only (nothing plotted)
        app.run_command("plot cn_state")
        await _settle(pilot)
        with model.lock:
            xs, ys = model.plot_series()["cn_state"]
        assert len(xs) == 400 and xs[0] == (START + 200 * 50_000_000) / 1e9
        assert ys[0] == 1005 // 100 % 4 and ys[-1] == 3000 // 100 % 4

    _drive(app, body, (160, 50))


def test_history_view_shows_the_archives_buckets_and_pans_back(archive: Path) -> None:
    app, model = _console(archive)  # no fill: history_s 0

    async def body(pilot: Any) -> None:
        await _settle(pilot)
        assert model.status().history == ""  # opened without history: none asked
        app.run_command("history apogee_target_m 10 20 every=1s agg=min,max")
        await _settle(pilot)
        screen = app.screen
        assert isinstance(screen, HistoryScreen)
        assert screen.error is None and screen.request is not None
        assert screen.columns == ["apogee_target_m_min", "apogee_target_m_max"]
        # Loops 1001..2001 (10 s .. 20 s from loop 1), 1 s buckets of 100 loops.
        want = [
            (START + k * 10**9, (100 * k + 1) / 4, min(100 * k + 100, 2001) / 4)
            for k in range(10, 21)
        ]
        assert screen.rows == want
        assert screen.points("apogee_target_m_max")[-1] == (START + 20 * 10**9, 2001 / 4)
        assert "11 row(s)" in screen.message
        await pilot.press("ctrl+b")  # one span back: 0 .. 10 s
        await _settle(pilot)
        assert screen.request.start == "0" and screen.request.end == "10"
        assert screen.rows == [
            (START + k * 10**9, (100 * k + 1) / 4, min(100 * k + 100, 1001) / 4) for k in range(11)
        ]
        await pilot.press("escape")
        await pilot.pause()
        assert app.screen is app.default_screen

    _drive(app, body, (160, 50))


def test_the_run_picker_lists_the_runs_and_browses_a_past_one(archive: Path) -> None:
    app, _ = _console(archive)

    async def body(pilot: Any) -> None:
        await _settle(pilot)
        app.run_command("runs")
        await _settle(pilot)
        screen = app.screen
        assert isinstance(screen, RunsScreen) and screen.error is None
        assert [(r.run, r.loops, r.outcome) for r in screen.runs] == [
            (7, 3000, "ended"),
            (5, 100, "ended"),
        ]  # newest first
        table = screen.query_one(DataTable)
        assert table.row_count == 2
        await pilot.press("down", "enter")  # run 5
        await _settle(pilot)
        view = app.screen
        assert isinstance(view, HistoryScreen) and view.request is not None
        assert view.request.run == 5 and view.request.elements == ("cn_state",)
        # Run 5 whole (990 ms) in 10 ms buckets (the least): one loop each.
        assert [r[0] for r in view.rows] == [START + i * PERIOD for i in range(100)]
        assert [r[1:] for r in view.rows] == [(0, 0, 0.0)] * 99 + [(1, 1, 1.0)]  # loop 100
        assert len(view.rows) == 100 and view.error is None
        # Read-only, and the same way: another element of run 5 from its line.
        await _enter(pilot, "apogee_target_m loop:10 loop:12 every=raw")
        await _settle(pilot)
        assert view.request.run == 5
        assert view.rows == [(T0 + i * PERIOD, i / 4) for i in (10, 11, 12)]

    _drive(app, body, (160, 50))


def test_bad_input_is_told_never_raised(archive: Path) -> None:
    app, model = _console(archive)

    async def body(pilot: Any) -> None:
        await _settle(pilot)
        app.run_command("history cn_stat 0 10")  # unknown: check's "did you mean"
        await pilot.pause()
        assert app.screen is app.default_screen
        with model.lock:
            last = model.events()[-1]
        assert (last.severity, last.text) == (
            "WARNING_HI",
            "refused: no element matches 'cn_stat'; did you mean cn_state, dn1_state, dn0_state?",
        )
        app.run_command("history apogee_target_m 20 10")  # reversed: the archive says so
        await _settle(pilot)
        screen = app.screen
        assert isinstance(screen, HistoryScreen)
        assert screen.error == "the range is reversed: --from 20 is after --to 10"
        assert screen.message == f"refused: {screen.error}" and screen.rows == []
        for line, why in (
            ("cn_state 0 10 every=soon", "--every 'soon': expected a duration"),
            ("cn_state 0 10 agg=median", "no aggregation 'median'; did you mean"),
            ("cn_state 0 10 run=99", "no run 99 in the archive (the last: 5, 7)"),
            ("nav_* 0 1 2", "at most two times"),
            ("cn_state 0 10 evry=1s", "unknown option evry=1s; did you mean every?"),
            ("cn_state banana", "time 'banana': expected ISO UTC"),
        ):
            await _enter(pilot, line)
            await _settle(pilot)
            assert screen.error is not None and why in screen.error, (line, screen.error)
        assert app.is_running

    _drive(app, body, (160, 50))


def test_an_unreachable_archive_is_said_in_the_ui(tmp_path: Path) -> None:
    gone = tmp_path / "nothing-here"
    app, model = _console(gone, history_s=60.0)
    model.set_plot(["apogee_target_m"])

    async def body(pilot: Any) -> None:
        await _settle(pilot)
        status = model.status().history
        where = f"no archive of mission 'flight' at {gone}"
        assert status.startswith("history 1 min: nothing; telemetry: ")
        assert where in status and "events: " in status
        app.run_command("runs")
        await _settle(pilot)
        assert isinstance(app.screen, RunsScreen)
        assert app.screen.error is not None and where in app.screen.error
        assert "refused: " in str(app.screen.query_one("#r-msg", Static).content)

    _drive(app, body, (100, 30))


def test_parse_request_and_pan() -> None:
    r = parse_request(LAYOUT, "apogee_target_m,cn_sta* 2026-12-07T03:20:00Z 30 every=raw run=4")
    # Globs as the archive reads them, in layout order.
    elements = ("cn_state", "apogee_target_m", "cn_standby_ready")
    assert r == HistoryRequest(elements, 4, "2026-12-07T03:20:00Z", "30", None)
    assert (
        r.line()
        == "cn_state,apogee_target_m,cn_standby_ready 2026-12-07T03:20:00Z 30 every=raw run=4"
    )
    assert parse_request(LAYOUT, "cn_state start 5").start is None
    req = HistoryRequest(("cn_state",), None, "5", "15")
    assert req.panned(-1) == HistoryRequest(("cn_state",), None, "0", "5")
    assert req.panned(1) == HistoryRequest(("cn_state",), None, "15", "25")
    assert HistoryRequest(("cn_state",), None, "loop:1", "loop:9").panned(1) is None
    with pytest.raises(ArchiveError, match="nav_cov is an array: plot scalar elements only"):
        parse_request(LAYOUT, "nav_cov 0 10")
    assert match_elements(LAYOUT, "nav_cov") == ["nav_cov"]
    model = ConsoleModel(MISSION)
    assert model.complete("history apogee_t") == "history apogee_target_m"
    assert model.complete("ru") == "runs"


def test_a_refresh_after_the_screen_is_gone_draws_nothing() -> None:
    """The redraw timer may fire once more while the app closes: it found no
    status bar and raised NoMatches (seen while a test's app closed)."""
    model = ConsoleModel(MISSION, los_s=HOUR)
    app = ConsoleApp(model, None)

    async def body(pilot: Any) -> None:
        await pilot.pause()

    _drive(app, body, (80, 24))
    app.refresh_view()  # the screen is gone


def test_ground_takes_history_minutes_and_plotted_elements(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import zplatform.console as console
    from zplatform.cli.main import _load_extras, build_parser

    _load_extras()  # the verbs beyond check/keygen/schema/ps, as main() loads them
    got: dict[str, Any] = {}
    monkeypatch.setattr(console, "run_console", lambda path, **kw: got.update(kw) or 0)
    flight = str(ROOT / "configs" / "flight.yaml")
    args = build_parser().parse_args(
        ["ground", flight, "--console", "--history", "2.5", "--plot", "nav_h_m", "cn_state"]
    )
    assert args.func(args) == 0
    assert (got["history_min"], got["plot"]) == (2.5, ["nav_h_m", "cn_state"])
    args = build_parser().parse_args(["ground", flight, "--console"])
    assert args.func(args) == 0 and got["history_min"] is None  # the default: 10 min
    for bad in ("-1", "nan", "soon"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["ground", flight, "--history", bad])
    assert "--history: must be 0..1000000 minutes, got -1" in capsys.readouterr().err


def test_history_reads_this_hosts_archive_else_asks_over_zenoh(
    archive: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from zplatform.archive import ARCHIVE_DIR_ENV
    from zplatform.console.history import RemoteHistory, history_source

    # The ground node writes DIR/<mission>/: here, the console reads it.
    (tmp_path / "here").mkdir()
    (tmp_path / "here" / "flight").symlink_to(archive)
    monkeypatch.setenv(ARCHIVE_DIR_ENV, str(tmp_path / "here"))
    src = history_source(MISSION)
    assert isinstance(src, LocalHistory) and src.where == str(tmp_path / "here" / "flight")
    assert [r.run for r in src.runs()] == [5, 7]
    monkeypatch.setenv(ARCHIVE_DIR_ENV, str(tmp_path / "elsewhere"))
    remote = history_source(MISSION)  # no archive on this host: the ground node's
    assert isinstance(remote, RemoteHistory) and remote.where == "rocket/archive/query"
    # (its runs, events and queries are asked over zenoh:
    # tests/integration/test_console_history_remote.py)
    remote.close()  # nothing opened yet (the link opens on the first query): nothing to close


def test_a_run_with_no_file_closed_yet_fills_nothing_and_says_so(tmp_path: Path) -> None:
    """A running run before the ground closed its first Parquet file: the
    archive answers an aggregated query with ``bucket_ns`` alone (no value
    columns); the fill said 'Field "cn_state_last" does not exist'."""
    w = ArchiveWriter(MISSION, LAYOUT, tmp_path)
    feed(w, DataVector(LAYOUT), range(1, 201))  # flushed to the open file, none closed
    try:
        app, model = _console(tmp_path, history_s=20.0)
        model.set_plot(["cn_state"])

        async def body(pilot: Any) -> None:
            await _settle(pilot)
            with model.lock:
                assert model.status().history == (
                    "history 0.333333 min: 0 point(s) of cn_state, 0 event(s)"
                )

        _drive(app, body, (100, 30))
    finally:
        w.close()


class _Gated:
    """A history source whose answers wait for the test: the fill in flight."""

    where = "gated"

    def __init__(self, inner: LocalHistory) -> None:
        import threading

        self.inner, self.gate, self.asked = inner, threading.Event(), threading.Event()

    def runs(self) -> Any:
        return self.inner.runs()

    def query(self, q: Any) -> Any:
        self.asked.set()
        assert self.gate.wait(60)
        return self.inner.query(q)

    def events(self, run: int | None) -> Any:
        return self.inner.events(run)

    def close(self) -> None:
        self.gate.set()


def test_live_frames_are_shown_while_the_fill_waits_then_it_merges(archive: Path) -> None:
    model = ConsoleModel(MISSION, los_s=HOUR, history_s=20.0)
    model.set_plot(["apogee_target_m"])
    src = _Gated(LocalHistory(MISSION, archive))
    app = ConsoleApp(model, None, history=src, now_ns=lambda: NOW)

    async def body(pilot: Any) -> None:
        await pilot.pause()
        assert src.asked.wait(30)  # the worker asks; the archive has not answered
        live = DataVector(LAYOUT)
        for loop in (2991, 2992):  # live frames, as the link feeds them
            live.set("cn_loop", loop)
            live.set("cn_time_ns", T0 + loop * PERIOD)
            live.set("apogee_target_m", -float(loop))
            with model.lock:
                model.on_snapshot(live, NOW)
        app.refresh_view()
        status = str(app.query_one("#status", Static).content)
        assert "loop 2992" in status and "filling history..." in status
        with model.lock:
            assert model.plot_series()["apogee_target_m"][1] == [-2991.0]  # live only, so far
        src.gate.set()
        await _settle(pilot)
        with model.lock:
            xs, ys = model.plot_series()["apogee_target_m"]
            said = model.status().history
        # Buckets ending at or before loop 2991's time, then the live point.
        assert ys == [(5 * k + 5) / 4 for k in range(200, 598)] + [-2991.0]
        assert xs == sorted(xs)
        assert said.startswith("history 0.333333 min: 398 point(s) of apogee_target_m")

    _drive(app, body, (160, 50))


def test_seeds_merge_before_live_and_events_once() -> None:
    from zplatform.console.model import LogLine

    model = ConsoleModel(MISSION, los_s=HOUR, plot_window_s=1.0)  # 20 points of 50 ms
    assert model.seed_series("cn_state", [(1.0, 1.0)]) == 0  # not plotted: nothing
    model.set_plot(["cn_state"])
    live = DataVector(LAYOUT)
    live.set("cn_time_ns", 10 * 10**9)
    live.set("cn_state", 3)
    model.on_snapshot(live, 10**9)
    kept = model.seed_series(
        "cn_state", [(9.96 - i / 20, float(i)) for i in range(30, -1, -1)], 0.05
    )
    xs, ys = model.plot_series()["cn_state"]
    # The bucket at 9.96 s reaches the live point (10 s): dropped; the window
    # (20 points) keeps the newest archived 19 and the live one.
    assert kept == 19 and len(xs) == 20 and ys[-2:] == [1.0, 3.0] and xs == sorted(xs)
    old = [LogLine(5, "COMMAND", "cn", "ev: a"), LogLine(6, "WARNING_HI", "cn", "ev: b")]
    model.on_event(EventRecord(7, "cn", 3, 7, "FATAL", "ev", "c"))
    model.log.append(old[1])  # the live pane has b already (seen live)
    assert model.seed_events(old) == 1
    assert [x.text for x in model.events()] == ["ev: a", "ev: c", "ev: b"]
