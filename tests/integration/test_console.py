"""The ground console against a running mission, driven by textual's pilot.

One recovery_igniter cluster (real node processes on free ports) serves two
console sessions: a large screen (200x60) that sees values move, refuses
and then confirms the hazardous LAUNCH (ARM, LAUNCH, both verdicts) and
shows the CN's event with its severity; and a small one (80x24) that shows
loss of signal once the CN is stopped. Every wait is on what the screen
shows, bounded; nothing sleeps for a peer.

The browser test serves the console with ``zplatform ground --web`` and
reads the page in headless Chromium (skipped, with the reason, without it).
"""

from __future__ import annotations

import asyncio
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

pytest.importorskip("textual")
pytest.importorskip("textual_plotext")

from textual.widgets import Static

from zplatform.console import ConfirmScreen, ConsoleApp, ConsoleModel, Link
from zplatform.events import Severity
from zplatform.transport import free_port

from .harness import CONFIGS, ROOT, Cluster

pytestmark = pytest.mark.timeout(240)


def _text(app: ConsoleApp, wid: str) -> str:
    return str(app.query_one(wid, Static).content)


async def _until(pilot: object, pred: Callable[[], bool], what: str, timeout_s: float = 30) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        await pilot.pause(0.1)  # type: ignore[attr-defined]
    raise AssertionError(f"console never showed {what}")


def _state_shown(app: ConsoleApp) -> str | None:
    words = _text(app, "#status").split()
    return words[words.index("Hz") + 1] if "Hz" in words else None


def _loop_shown(app: ConsoleApp) -> int:
    words = _text(app, "#status").split()
    return int(words[words.index("loop") + 1]) if "loop" in words else -1


async def _big_screen(c: Cluster) -> None:
    model = ConsoleModel(c.mission, limits={"cn_loop": {"yellow": [None, 1], "red": [None, 2]}})
    app = ConsoleApp(model, Link(model, timeout_s=20))
    async with app.run_test(size=(200, 60)) as pilot:
        await _until(pilot, lambda: " LINK " in _text(app, "#status"), "the link up")
        first = _loop_shown(app)
        await _until(pilot, lambda: _loop_shown(app) > first + 20, "the loop advancing")
        with model.lock:
            rows = dict(model.region_rows())
        assert ("cn_loop", str(int(model.dv.get("cn_loop"))), "red") in rows["cn"]

        # A hazardous command asks first; "n" sends nothing.
        await pilot.press(*"launch", "enter")
        await _until(pilot, lambda: isinstance(app.screen, ConfirmScreen), "the confirmation")
        await pilot.press("n")
        await _until(pilot, lambda: "LAUNCH cancelled" in _text(app, "#events-text"), "cancel")
        assert c.tm.get_name("cn_state") == "SAFE"

        # Confirmed: ARM n, LAUNCH n+1, both accepted, the state moves on.
        await pilot.press(*"launch", "enter")
        await _until(pilot, lambda: isinstance(app.screen, ConfirmScreen), "the confirmation")
        await pilot.press("y")
        await _until(
            pilot,
            lambda: "LAUNCH #2 ACCEPTED" in _text(app, "#events-text"),
            "LAUNCH's verdict",
        )
        events = _text(app, "#events-text")
        assert "ARM #1 ACCEPTED" in events
        # The CN's own event about the command: time, severity name, node, id.
        await _until(pilot, lambda: "cmd_accepted" in _text(app, "#events-text"), "the CN's event")
        line = next(x for x in _text(app, "#events-text").splitlines() if "cmd_accepted" in x)
        assert line.split()[1] in Severity.__members__, line
        # LAUNCH leaves SAFE for ARMED; the simulated flight runs on the
        # boards' own clock from start-up, so on a busy box (a slow console
        # start) it may already be past apogee, and ARMED gives way to FIRE
        # in the next loop: wait for the state the command left behind.
        await _until(pilot, lambda: _state_shown(app) not in ("SAFE", None), "SAFE left")
        with model.lock:
            assert model.dv.get_name("cn_state") in ("ARMED", "FIRE", "DEPLOYED", "NO_FIRE")

        # Completion and history on the command line.
        await pilot.press(*"noo", "tab")
        assert app.query_one("#cmd").value == "noop "  # type: ignore[attr-defined]
        await pilot.press("enter", "up")
        assert app.query_one("#cmd").value == "noop"  # type: ignore[attr-defined]
        await pilot.press("ctrl+q")


async def _small_screen(c: Cluster) -> None:
    model = ConsoleModel(c.mission, los_s=0.3)
    app = ConsoleApp(model, Link(model, timeout_s=20))
    async with app.run_test(size=(80, 24)) as pilot:
        await _until(pilot, lambda: " LINK " in _text(app, "#status"), "the link up")
        first = _loop_shown(app)
        await _until(pilot, lambda: _loop_shown(app) > first + 10, "the loop advancing")
        await pilot.press(*"plot cn_loop", "enter")
        await _until(pilot, lambda: app.query_one("#plot").has_class("shown"), "the plot")
        c.kill("cn")
        # After 0.3 s of silence (how soon the redraw shows it is the box's:
        # a latency, not asserted here; the wait is a hang detector).
        await _until(pilot, lambda: "LOSS OF SIGNAL" in _text(app, "#status"), "LOS", 60)
        await pilot.press("ctrl+q")


def test_console_against_running_mission(tmp_path: Path) -> None:
    with Cluster(CONFIGS / "recovery_igniter.yaml", tmp_path) as c:
        for n in ("dn0", "dn1", "cn"):
            c.spawn(n)
        c.advance(5)
        asyncio.run(_big_screen(c))
        asyncio.run(_small_screen(c))


# -- browser -------------------------------------------------------------------

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def _wait_port(port: int, proc: subprocess.Popen[bytes], timeout_s: float = 30) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"server exited ({proc.returncode})")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)  # a port, not a peer: nothing else to wait on
    raise AssertionError(f"nothing listens on {port}")


# Textual-serve draws the terminal on a canvas: the page's DOM has no text.
# So the page is read through the DevTools protocol: a script installed
# before the page loads keeps every byte the console sends to the page's
# terminal, and the test reads them back.
_KEEP_TERMINAL_BYTES = """
(() => {
  const Native = window.WebSocket;
  window.__zp = [];
  window.WebSocket = function (url, protocols) {
    const ws = new Native(url, protocols);
    ws.addEventListener("message", (e) => {
      if (typeof e.data !== "string")
        window.__zp.push(new TextDecoder().decode(new Uint8Array(e.data)));
    });
    return ws;
  };
  window.WebSocket.prototype = Native.prototype;
})();
"""


async def _read_page(devtools_port: int, url: str, want: list[str], timeout_s: float) -> str:
    """Open ``url`` in the browser; return the terminal text once it has every ``want``."""
    import aiohttp

    async with aiohttp.ClientSession() as http:
        async with http.put(f"http://127.0.0.1:{devtools_port}/json/new?about:blank") as r:
            target = await r.json(content_type=None)
        async with http.ws_connect(target["webSocketDebuggerUrl"], max_msg_size=0) as ws:
            ids = iter(range(1, 1_000_000))

            async def call(method: str, **params: object) -> dict[str, object]:
                n = next(ids)
                await ws.send_json({"id": n, "method": method, "params": params})
                while True:
                    msg = await ws.receive_json()
                    if msg.get("id") == n:
                        return msg.get("result", {})  # type: ignore[no-any-return]

            await call("Page.enable")
            await call("Page.addScriptToEvaluateOnNewDocument", source=_KEEP_TERMINAL_BYTES)
            await call("Page.navigate", url=url)
            deadline = time.monotonic() + timeout_s
            text = ""
            while time.monotonic() < deadline:
                res = await call(
                    "Runtime.evaluate",
                    expression="window.__zp ? window.__zp.join('') : ''",
                    returnByValue=True,
                )
                text = str(res.get("result", {}).get("value", ""))  # type: ignore[attr-defined]
                if all(w in text for w in want):
                    return text
                await asyncio.sleep(0.2)  # polling the page, not waiting on a peer
            raise AssertionError(f"the page never showed {want}; it showed {text[-2000:]!r}")


def _stop(p: subprocess.Popen[bytes]) -> None:
    if p.poll() is None:
        os.killpg(p.pid, 15)
    try:
        p.wait(timeout=10)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, 9)
        p.wait()


def test_console_in_browser(tmp_path: Path) -> None:
    """`zplatform ground MISSION --web PORT`, opened in headless Chromium, shows the console."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("chromium is not installed (Debian: apt-get install -y chromium)")
    pytest.importorskip("textual_serve")
    pytest.importorskip("aiohttp")
    port = free_port()
    procs: list[subprocess.Popen[bytes]] = []
    logs = [open(tmp_path / n, "wb") for n in ("serve.log", "chromium.log")]  # noqa: SIM115
    try:
        procs.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "zplatform",
                    "ground",
                    str(CONFIGS / "led_test.yaml"),
                    "--web",
                    str(port),
                ],
                cwd=ROOT,
                stdout=logs[0],
                stderr=subprocess.STDOUT,
                env=dict(os.environ, PYTHONUNBUFFERED="1"),
                start_new_session=True,  # the server's console children go with it
            )
        )
        _wait_port(port, procs[0])
        profile = tmp_path / "chromium"
        procs.append(
            subprocess.Popen(
                [
                    chromium,
                    *CHROMIUM_FLAGS,
                    f"--user-data-dir={profile}",
                    "--remote-debugging-port=0",
                    "--window-size=1200,800",
                    "about:blank",
                ],
                stdout=logs[1],
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        )
        active = profile / "DevToolsActivePort"
        deadline = time.monotonic() + 30
        while not (active.exists() and active.read_text().strip()):
            assert procs[1].poll() is None, (tmp_path / "chromium.log").read_text()[-2000:]
            assert time.monotonic() < deadline, "chromium never opened its DevTools port"
            time.sleep(0.05)
        devtools = int(active.read_text().split()[0])
        text = asyncio.run(
            _read_page(
                devtools,
                f"http://127.0.0.1:{port}/",
                ["NO SIGNAL", "waiting for telemetry", "cn_loop"],
                60,
            )
        )
        assert "b_timer_done" in text  # a mission element, from the Data Vector pane
    finally:
        for p in reversed(procs):
            _stop(p)
        for f in logs:
            f.close()
