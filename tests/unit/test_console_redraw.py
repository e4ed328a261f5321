"""The console's redraw: what it costs per snapshot, without zenoh.

The screen redraws 10 times a second and the Data Vector's values move with
every snapshot. A redraw gives a pane new content only when what it shows
changed and lays the screen out again only when a pane's height changed
(the Data Vector pane: one line per region and element, cut to the pane's
width, never wrapped). A redraw that laid out the whole screen, measuring a
125-row table each time, kept a core busy and made the operator's keys wait.
Every assertion here is on what was drawn or asked for, not on time.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("textual")

from textual.widget import Widget
from textual.widgets import Static

from zplatform import load_mission
from zplatform.console import ConsoleApp, ConsoleModel
from zplatform.core.datavector import DataVector

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
MISSION = load_mission(CONFIGS / "recovery_igniter.yaml", code=False)
HOUR = 3600.0  # no loss of signal while a test looks at the screen


def _feed(model: ConsoleModel, loop: int) -> None:
    dv = DataVector(model.layout)
    dv.set("cn_loop", loop)
    dv.set("cn_time_ns", time.time_ns())
    with model.lock:
        model.on_snapshot(dv, time.time_ns())


def _lines(app: ConsoleApp, wid: str) -> list[str]:
    return str(app.query_one(wid, Static).content).split("\n")


def _dv_line(app: ConsoleApp, name: str) -> str:
    return next(x for x in _lines(app, "#dv-table") if x.split()[:1] == [name])


def test_new_values_redraw_the_data_vector_without_a_layout(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    model = ConsoleModel(MISSION, los_s=HOUR)
    rows = sum(1 + len(r.elements) for r in model.layout.regions.values() if r.elements)

    async def run() -> None:
        app = ConsoleApp(model, None)
        async with app.run_test(size=(120, 40)) as pilot:
            _feed(model, 1)
            app.refresh_view()
            await pilot.pause()
            dv = app.query_one("#dv-table", Static)
            assert dv.content_size.height == rows == len(_lines(app, "#dv-table"))
            assert _dv_line(app, "cn_loop").split() == ["cn_loop", "1"]

            layouts: list[str | None] = []
            refresh = Widget.refresh

            def spy(self: Widget, *regions: Any, **kw: Any) -> Any:
                if kw.get("layout"):
                    layouts.append(self.id)
                return refresh(self, *regions, **kw)

            monkeypatch.setattr(Widget, "refresh", spy)
            for loop in range(2, 30):
                _feed(model, loop)
                app.refresh_view()
                assert _dv_line(app, "cn_loop").split() == ["cn_loop", str(loop)]
            await pilot.pause()
            assert layouts == [], f"a redraw of new values laid the screen out: {layouts}"
            assert dv.content_size.height == rows
            monkeypatch.undo()
            await pilot.press("ctrl+q")

    asyncio.run(run())


def test_the_status_bar_grows_when_its_text_wraps_and_the_pane_follows_a_resize() -> None:
    model = ConsoleModel(MISSION, los_s=HOUR)

    async def run() -> None:
        app = ConsoleApp(model, None)
        async with app.run_test(size=(80, 24)) as pilot:
            _feed(model, 1)
            await pilot.pause()
            app.refresh_view()
            await pilot.pause()
            bar = app.query_one("#status", Static)
            assert bar.content_size.height == 2  # the link line, the counters line
            with model.lock:
                model.last_command = "LAUNCH #6: ACCEPTED " + "x" * 60
                model.version += 1
            app.refresh_view()
            await pilot.pause()
            assert bar.content_size.height == 3, "the long status line wraps: one line more"

            dv = app.query_one("#dv-table", Static)
            for size in ((120, 30), (60, 24)):
                await pilot.resize_terminal(*size)
                await pilot.pause()
                app.refresh_view()
                await pilot.pause()
                width = dv.content_size.width
                lines = _lines(app, "#dv-table")
                assert max(len(x) for x in lines) <= width, (width, lines)
                assert _dv_line(app, "cn_loop").split() == ["cn_loop", "1"]
            # At 60 columns the long names are cut, with an ellipsis.
            assert any(x.rstrip().endswith("…") for x in _lines(app, "#dv-table"))
            await pilot.press("ctrl+q")

    asyncio.run(run())
