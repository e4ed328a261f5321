"""Live: the console's history from a running ground node's archive (issue 28).

led_test runs under ``up`` (free ports, its archive in the test's directory,
a Parquet file closed every second so a running run shows soon). A console
in process, with its live link, reads this host's archive
(:func:`history_source` finds it): ``plot cn_loop`` fills the plot from the
archive before the live points, in order; ``runs`` lists the running run;
and the ground node's archive asked over zenoh with the mission's keys
(:class:`RemoteHistory`, a tool's ask) gives the same rows as the files.
Every wait is on what the console shows or the archive answers, bounded.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("textual")
pytest.importorskip("textual_plotext")

from textual.widgets import Static

from tests.live_runs import LED_YAML, ROOT
from zplatform.archive import ARCHIVE_DIR_ENV, Query
from zplatform.console import ConsoleApp, ConsoleModel, Link
from zplatform.console.history import LocalHistory, RemoteHistory, history_source
from zplatform.console.historyview import RunsScreen
from zplatform.mission.load import load_mission
from zplatform.runtime.transport import rewrite_endpoints

pytestmark = pytest.mark.timeout(240)


async def _until(pilot: Any, pred: Any, what: str, timeout_s: float = 40) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        await pilot.pause(0.1)
    raise AssertionError(f"the console never showed {what}")


async def _settle(pilot: Any) -> None:
    for _ in range(2):
        await pilot.app.workers.wait_for_complete()
        await pilot.pause()


# With the soaks (-m slow): the console's history over zenoh stays in the
# default suite (tests/integration/test_console_history_remote.py).
@pytest.mark.slow
def test_console_history_from_a_running_ground(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "mission.yaml"
    rewrite_endpoints(LED_YAML, path)
    path.write_text(path.read_text() + "\narchive:\n  file_s: 1\n  row_group_s: 0.5\n")
    monkeypatch.setenv(ARCHIVE_DIR_ENV, str(tmp_path / "archive"))
    up = subprocess.Popen(
        [sys.executable, "-m", "zplatform", "up", str(path), "--duration", "40", "--quiet"],
        cwd=ROOT,
        env={**os.environ},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        mission = load_mission(path, code=False)
        model = ConsoleModel(mission, los_s=1.0, history_s=60.0)
        link = Link(model)
        app = ConsoleApp(model, link, history=None)

        async def body(pilot: Any) -> None:
            await _until(
                pilot, lambda: " LINK " in str(app.query_one("#status", Static).content), "live"
            )
            src = history_source(mission)  # the ground node writes it on this host by now
            assert isinstance(src, LocalHistory)
            app.history = src

            def filled() -> bool:
                with model.lock:
                    said = model.status().history
                return said.startswith("history 1 min: ") and " 0 point(s)" not in said

            deadline = time.monotonic() + 40
            while not filled():  # until the ground has closed a file of this run
                assert time.monotonic() < deadline, model.status().history
                app.run_command("plot cn_loop")
                await _settle(pilot)
            with model.lock:
                said = model.status().history
                xs, ys = model.plot_series()["cn_loop"]
            assert " point(s) of cn_loop to " in said, said
            archived = int(said.split(": ")[1].split(" point(s)")[0])
            assert 0 < archived <= len(ys)
            assert xs == sorted(xs) and len(set(xs)) == len(xs)  # one time line, in order
            assert ys[:archived] == sorted(set(ys[:archived]))  # the archive's loops, rising
            await _until(pilot, lambda: len(model.plot_series()["cn_loop"][1]) > archived, "live")
            ys = model.plot_series()["cn_loop"][1]
            assert ys[archived] > ys[archived - 1]  # live after the archive

            app.run_command("runs")
            await _settle(pilot)
            runs = app.screen
            assert isinstance(runs, RunsScreen) and runs.error is None
            (run,) = runs.runs
            assert run.outcome == "open" and run.loops > 0

            q = Query("cn_loop,cn_state", run=run.run, start="loop:1", end="loop:100")
            remote = RemoteHistory.for_mission(mission)
            try:
                over_zenoh = await asyncio.to_thread(remote.query, q)
            finally:
                remote.close()
            local = src.query(q)
            assert over_zenoh.equals(local) and 0 < local.num_rows <= 100

        async def go() -> None:
            async with app.run_test(size=(160, 50)) as pilot:
                await body(pilot)

        asyncio.run(go())
    finally:
        if up.poll() is None:
            os.killpg(up.pid, 15)
        try:
            up.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(up.pid, 9)
            up.wait()
