"""The console's history over zenoh (issue 28): two in-process sessions on
loopback, a ground's archive of run 7 (loops 1..300) served by the archive's
server, read by a console elsewhere through :class:`RemoteHistory` with a
tool's key: it fills on open (telemetry and events), shows a range and the
run list, and says in the UI why a stranger's ask gets no answer and why
the station refused an answer too big."""

from __future__ import annotations

import asyncio
import sys
import threading
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

pytest.importorskip("textual")
pytest.importorskip("textual_plotext")

from tests.faults.peers import peer_config
from tests.unit.test_archive import PERIOD, T0, feed
from tests.waits import wait_matching
from zplatform.archive import Archive, ArchiveWriter, RunInfo
from zplatform.archive.server import ArchiveServer
from zplatform.console import ConsoleApp, ConsoleModel
from zplatform.console.history import RemoteHistory
from zplatform.console.historyview import HistoryScreen, RunsScreen
from zplatform.console.model import LogLine
from zplatform.core.auth import KeySet
from zplatform.core.datavector import DataVector, Layout
from zplatform.mission.load import load_mission
from zplatform.runtime.transport import free_port
from zplatform.telemetry.records import EventRecord

ROOT = Path(__file__).resolve().parents[2]
MISSION = load_mission(ROOT / "configs" / "flight.yaml", code=False)
LAYOUT = Layout.for_node(MISSION, "cn")
KEYS = KeySet.from_master(MISSION, bytes(range(32)))
KEYEXPR = "rocket/archive/query"
STAMP = T0 + 10**9  # the server's clock and the asker's: within the bound
START = T0 + PERIOD


@pytest.fixture
def station(tmp_path: Path) -> Iterator[Any]:
    w = ArchiveWriter(MISSION, LAYOUT, tmp_path)
    feed(w, DataVector(LAYOUT), range(1, 301))
    # One event before the console's 2 s of history (history_s), one within.
    w.event(EventRecord(T0 + PERIOD, "gn", 1, T0 + PERIOD, "COMMAND", "cmd_sent", "ARM sent"))
    at = T0 + 250 * PERIOD
    w.event(EventRecord(at, "cn", 2, at, "WARNING_LO", "bad_frame", "a frame refused"))
    w.close()
    with Archive(MISSION, tmp_path) as local:
        runs = local.runs()
    ep = f"tcp/127.0.0.1:{free_port()}"
    a = zenoh.open(peer_config([ep]))
    b = zenoh.open(peer_config(connect=[ep]))
    server = ArchiveServer(
        a,
        KEYEXPR,
        lambda: Archive(MISSION, tmp_path, recover=False),
        KEYS.channel("telemetry"),
        now_ns=lambda: STAMP,
        max_age_ns=2 * 10**9,
        serve_bps=50_000_000,
        max_bytes=20_000,
    )
    querier = b.declare_querier(KEYEXPR)
    wait_matching(querier, 10, "the archive's queryable, declared to b")
    querier.undeclare()

    # Generous: a busy host (a CPU hog and a real-time mission beside it)
    # can hold the station's first DuckDB query for seconds; behaviour, not speed.
    def source(keys: KeySet, timeout_s: float = 30.0) -> RemoteHistory:
        return RemoteHistory(
            LAYOUT, b, KEYEXPR, keys.channel("telemetry"), lambda: STAMP, timeout_s=timeout_s
        )

    try:
        yield source, server, runs
    finally:
        server.close()
        b.close()
        a.close()


def _server_state(server: ArchiveServer) -> str:
    """What the station did, and where its serving thread is now: the
    failure's diagnosis (it was seen twice in hogged CI runs, with both
    asks unanswered for their 30 s and the cause not shown)."""
    stacks = {t.name: t.ident for t in threading.enumerate()}
    frames = sys._current_frames()
    ident = stacks.get("archive-serve")
    where = (
        "".join(traceback.format_stack(frames[ident]))
        if ident is not None and ident in frames
        else "no archive-serve thread"
    )
    return (
        f"the station: served {server.served}, hellos {server.hellos}, refused "
        f"{server.refused} (stale {server.stale}, busy {server.busy}, over bound "
        f"{server.over_bound}, last: {server.last_refusal!r}); its serving thread:\n{where}"
    )


async def _settle(pilot: Any) -> None:
    for _ in range(2):
        await pilot.app.workers.wait_for_complete()
        await pilot.pause()


def test_the_console_reads_history_over_zenoh_and_tells_every_refusal(station: Any) -> None:
    source, server, archived = station
    tool = KEYS.for_node("tool")  # a read-only station's keys
    model = ConsoleModel(MISSION, los_s=3600.0, history_s=2.0)
    model.set_plot(["apogee_target_m"])
    now = T0 + 300 * PERIOD + 5_000_000
    app = ConsoleApp(model, None, history=source(tool), now_ns=lambda: now)

    async def body(pilot: Any) -> None:
        await _settle(pilot)
        # Filled on open: loops 101..300 in 50 ms buckets, each one's last value.
        with model.lock:
            series = model.plot_series()
            said = model.status().history
        assert "apogee_target_m" in series, (
            f"the fill on open did not land: {said}; {_server_state(server)}"
        )
        xs, ys = series["apogee_target_m"]
        step = 50_000_000
        assert list(zip(xs, ys, strict=True)) == [
            ((START + k * step) / 1e9, (5 * k + 5) / 4) for k in range(20, 60)
        ]
        assert said.startswith("history 0.0333333 min: 40 point(s) of apogee_target_m to ")
        assert said.endswith(", 1 event(s)")  # the one within the span, served over zenoh
        with model.lock:
            shown = model.events()
        assert LogLine(T0 + 250 * PERIOD, "WARNING_LO", "cn", "bad_frame: a frame refused") in shown
        assert not any("ARM sent" in line.text for line in shown)

        app.run_command("history apogee_target_m loop:10 loop:250 every=raw")
        await _settle(pilot)
        view = app.screen
        assert isinstance(view, HistoryScreen) and view.error is None
        assert view.rows == [(T0 + i * PERIOD, i / 4) for i in range(10, 251)]
        # More than this station serves: its reason, word for word.
        await _input(pilot, view, "cn_* every=raw")
        assert view.error is not None
        assert view.error.startswith("the station refused the query: the answer holds ")
        assert "more than this station serves (20000): narrow the range" in view.error
        await pilot.press("escape")
        await pilot.pause()

        app.run_command("runs")
        await _settle(pilot)
        runs = app.screen
        assert isinstance(runs, RunsScreen)
        assert runs.error is None and runs.runs == archived  # the station's records, exactly
        assert [(r.run, r.loops, r.events) for r in runs.runs] == [(7, 300, 2)]
        assert isinstance(runs.runs[0], RunInfo)
        await pilot.press("escape")
        await pilot.pause()

        # A station without the mission's key: dropped unanswered by the server; said.
        app.history = source(KeySet.generate(MISSION), timeout_s=1.0)
        app.run_command("history cn_state 0 1")
        await _settle(pilot)
        view = app.screen
        assert isinstance(view, HistoryScreen)
        assert view.error is not None
        assert view.error.startswith(f"no station answered on {KEYEXPR} within 1 s")
        assert "hold the telemetry key" in view.error
        assert view.message == f"refused: {view.error}"

    asyncio.run(_run(app, body))
    # the fill's query and events, the range, the refusal, the run list
    assert server.served == 5 and server.refused == 1


async def _input(pilot: Any, view: HistoryScreen, line: str) -> None:
    from textual.widgets import Input

    view.query_one("#h-input", Input).value = line
    await pilot.press("enter")
    await _settle(pilot)


async def _run(app: ConsoleApp, body: Any) -> None:
    async with app.run_test(size=(160, 50)) as pilot:
        await body(pilot)
