"""The ground console against a running mission, driven by textual's pilot.

One recovery_igniter cluster (real node processes on free ports) serves two
console sessions: a large screen (200x60) that sees values move, refuses
and then confirms the hazardous LAUNCH (ARM, LAUNCH, both verdicts) and
shows the CN's event with its severity; and a small one (80x24) that shows
loss of signal once the CN is stopped. A WRITE of a protected element asks
first too, then goes ARM n, WRITE n+1, its verdict shown with the CN's
detail; so does a PRM_SET of a hazardous parameter, shown in the parameter
view (``params``). Every wait is on what the screen shows, bounded; nothing sleeps for
a peer.

The flight mission (``configs/flight.yaml``) live in the console: launched
from its command line (confirmed: ARM, LAUNCH), it shows the CN's state
changes SAFE -> ARMED -> BOOST -> COAST, COAST on the status line, and the
EKF's altitude (``nav_h_m``) climbing in the Data Vector pane.

A key press costs the pilot up to 2 s when the test process is busy (it
waits for the process to idle, at most 1 s, twice): a test whose own ground
link decodes the telemetry beside the console's is never idle. The flight
test has the console's link only, and types its one command at once.

The browser test serves the console with ``zplatform ground --web``, opens
the address it prints (with its token) in headless Chromium and reads the
page, and every request it makes (skipped, with the reason, without
Chromium). The web server's admission and lifetime: test_console_web.py.
"""

from __future__ import annotations

import asyncio
import io
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("textual")
pytest.importorskip("textual_plotext")

from rich.console import Console
from rich.table import Table
from textual import events
from textual.widgets import Static

from tests.waits import wait_until
from zplatform.console import ConfirmScreen, ConsoleApp, ConsoleModel, Link
from zplatform.core.events import Severity
from zplatform.runtime.transport import rewrite_endpoints

from .harness import CONFIGS, ROOT, Cluster

pytestmark = pytest.mark.timeout(240)


def _text(app: ConsoleApp, wid: str) -> str:
    content = app.query_one(wid, Static).content
    if isinstance(content, Table):  # drawn as the screen would
        console = Console(width=200, record=True, file=io.StringIO())
        console.print(content)
        return console.export_text()
    return str(content)


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


async def _paste(pilot: Any, text: str, *keys: str) -> None:
    """Paste ``text`` into the focused widget (the command line), then press
    ``keys``: as an operator pastes a line. Typing it key by key costs the
    pilot's wait for an idle process after every key (a tenth of a second
    or more beside a console at 100 Hz): the test types where typing is
    what it tests (completion, history, a value)."""
    pilot.app.post_message(events.Paste(text))
    await pilot.press(*keys)


async def _answer(pilot: Any, app: ConsoleApp, line: str, key: str) -> None:
    """Enter ``line``; the console asks first: answer ``key`` (y or n)."""
    await _paste(pilot, line, "enter")
    await _until(pilot, lambda: isinstance(app.screen, ConfirmScreen), "the confirmation")
    await pilot.press(key)


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

        # A WRITE of a protected element asks first, then goes ARM n, WRITE n+1.
        await _answer(pilot, app, "write dn0_ign_armed true", "y")
        await _until(
            pilot,
            lambda: "WRITE #2: ACCEPTED (dn0_ign_armed = True)" in _text(app, "#events-text"),
            "the protected WRITE's verdict, with the CN's detail",
        )
        assert "ARM #1: ACCEPTED" in _text(app, "#events-text")

        # The parameter view; a hazardous parameter's PRM_SET asks first too.
        await _paste(pilot, "params", "enter")
        await _until(pilot, lambda: app.query_one("#params").has_class("shown"), "parameters")
        await _until(pilot, lambda: "deploy_altitude_m (ARM)" in _text(app, "#params-table"),
                     "the parameter, marked hazardous")  # fmt: skip
        table = _text(app, "#params-table")
        assert "[60, 390] m" in table and "SAFE" in table, table
        await _paste(pilot, "prm_set depl", "tab")
        assert app.query_one("#cmd").value == "prm_set deploy_altitude_m "  # type: ignore[attr-defined]
        await _paste(pilot, "300", "enter")
        await _until(pilot, lambda: isinstance(app.screen, ConfirmScreen), "the confirmation")
        await pilot.press("y")
        await _until(
            pilot,
            lambda: (
                "PRM_SET #4: ACCEPTED (deploy_altitude_m = 300.0, was 250.0)"
                in _text(app, "#events-text")
            ),
            "the PRM_SET's verdict",
        )
        await _until(pilot, lambda: " 300 " in _text(app, "#params-table"), "the new value")

        # A hazardous command asks first; "n" sends nothing.
        await _answer(pilot, app, "launch", "n")
        await _until(pilot, lambda: "LAUNCH cancelled" in _text(app, "#events-text"), "cancel")
        with model.lock:
            assert model.dv.get_name("cn_state") == "SAFE"

        # Confirmed: ARM n, LAUNCH n+1, both accepted, the state moves on.
        await _answer(pilot, app, "launch", "y")
        await _until(
            pilot, lambda: "LAUNCH #6: ACCEPTED" in _text(app, "#events-text"), "LAUNCH's verdict"
        )
        assert "ARM #5: ACCEPTED" in _text(app, "#events-text")
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
        await _paste(pilot, "noo", "tab")
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
        await _paste(pilot, "plot cn_loop", "enter")
        await _until(pilot, lambda: app.query_one("#plot").has_class("shown"), "the plot")
        c.kill("cn")
        # After 0.3 s of silence (how soon the redraw shows it is the box's:
        # a latency, not asserted here; the wait is a hang detector).
        await _until(pilot, lambda: "LOSS OF SIGNAL" in _text(app, "#status"), "LOS", 60)
        await pilot.press("ctrl+q")


# With the soaks (-m slow): the console live in the default suite is
# test_console_shows_the_flight_live (link, confirmed commands, verdicts, the
# CN's state changes); LOS and the views are tests/unit/test_console_model.py's.
@pytest.mark.slow
def test_console_against_running_mission(tmp_path: Path) -> None:
    with Cluster(CONFIGS / "recovery_igniter.yaml", tmp_path) as c:
        for n in ("world", "dn0", "dn1", "cn"):
            c.spawn(n)
        c.advance(5)
        # The consoles have links of their own: the test's stops reading (its
        # intake would take every snapshot beside them, in this process).
        c.rx.close()
        asyncio.run(_big_screen(c))
        asyncio.run(_small_screen(c))


def _shown(app: ConsoleApp, element: str) -> str | None:
    """The value the Data Vector pane shows for ``element``."""
    for line in _text(app, "#dv-table").splitlines():
        words = line.split()
        if len(words) == 2 and words[0] == element:
            return words[1]
    return None


async def _flight_screen(c: Cluster) -> None:
    model = ConsoleModel(c.mission)
    app = ConsoleApp(model, Link(model, timeout_s=20))
    async with app.run_test(size=(160, 50)) as pilot:
        await _until(pilot, lambda: " LINK " in _text(app, "#status"), "the link up")
        assert "NO STANDBY" in _text(app, "#status")  # cn_b is not running
        app.query_one("#cmd").value = "launch"  # type: ignore[attr-defined]
        await pilot.press("enter")
        await _until(pilot, lambda: isinstance(app.screen, ConfirmScreen), "the confirmation")
        await pilot.press("y")
        states: list[str] = []
        heights: list[float] = []

        def coasting() -> bool:
            s, h = _state_shown(app), _shown(app, "nav_h_m")
            if s is not None and (not states or states[-1] != s):
                states.append(s)
            if h is not None and (not heights or heights[-1] != float(h)):
                heights.append(float(h))
            # in flight: the altitude redrawn three times at least (the
            # redraws' pace is the box's: one at each screen refresh)
            return s == "COAST" and len([x for x in heights if x > 1.0]) >= 3

        await _until(pilot, coasting, "COAST, the altitude climbing")

        def moves() -> list[str]:
            return [x.split("state ", 1)[1].split(" (")[0]
                    for x in _text(app, "#events-text").splitlines()
                    if "state_change: state " in x]  # fmt: skip

        # The state machine's changes as the CN's events, in order (the status
        # line shows the current state; ARMED lasts 2 s, which a press on a
        # busy box may outlast). The status line's state comes with
        # telemetry, which a busy console takes before events, and an event
        # zenoh dropped on the way to a starved console is filled from the
        # CN's recorder: so the pane may show them a little after COAST.
        try:
            want = {"SAFE -> ARMED", "ARMED -> BOOST", "BOOST -> COAST"}
            # every one of the three, a filled one in its place (the next
            # move may come live before a dropped one is filled)
            await _until(pilot, lambda: want <= set(moves()), "the three state changes")
        except AssertionError as exc:
            raise AssertionError(f"{exc}: {_text(app, '#events-text')}") from None
        events = _text(app, "#events-text")
        assert "ARM #1: ACCEPTED" in events and "LAUNCH #2: ACCEPTED" in events, events
        # (the flight goes on meanwhile: DROGUE and MAIN may follow)
        assert moves()[:3] == ["SAFE -> ARMED", "ARMED -> BOOST", "BOOST -> COAST"], events
        assert states[-1] == "COAST", states
        climb = [h for h in heights if h > 1.0]
        assert climb == sorted(climb) and climb[-1] > 50.0, heights  # past burnout, up
        await pilot.press("ctrl+q")


def test_console_shows_the_flight_live(tmp_path: Path) -> None:
    with Cluster(CONFIGS / "flight.yaml", tmp_path) as c:
        for n in ("world", "dn0", "dn1", "cn"):
            c.spawn(n)
        asyncio.run(_flight_screen(c))


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


async def _read_page(
    devtools_port: int, url: str, want: list[str], timeout_s: float
) -> tuple[str, list[tuple[str, str]]]:
    """Open ``url`` in the browser; the terminal text once it has every ``want``.

    Also every network event of the page: (``request``, URL) for each request
    and WebSocket, (``failed``, reason) and (``status``, code and URL).
    """
    import aiohttp

    events: list[tuple[str, str]] = []
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
                    p = msg.get("params", {})
                    match msg.get("method"):
                        case "Network.requestWillBeSent":
                            events.append(("request", p["request"]["url"]))
                        case "Network.webSocketCreated":
                            events.append(("request", p["url"]))
                        case "Network.loadingFailed":
                            why = f"{p.get('errorText')} {p.get('blockedReason')}"
                            events.append(("failed", why))
                        case "Network.responseReceived":
                            r = p["response"]
                            events.append(("status", f"{r['status']} {r['url']}"))

            await call("Network.enable")
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
                    return text, events
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
    """`zplatform ground MISSION --web 0`, opened in headless Chromium at the printed address.

    The console shows; every request the page makes goes to the server
    itself and succeeds (no font or script from the internet, nothing
    refused); the token leaves the address bar.
    """
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("chromium is not installed (Debian: apt-get install -y chromium)")
    pytest.importorskip("textual_serve")
    pytest.importorskip("aiohttp")
    mission = tmp_path / "mission.yaml"
    rewrite_endpoints(CONFIGS / "led_test.yaml", mission)
    procs: list[subprocess.Popen[bytes]] = []
    logs = [open(tmp_path / n, "wb") for n in ("serve.log", "chromium.log")]  # noqa: SIM115
    try:
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "zplatform", "ground", str(mission), "--web", "0"],
                cwd=ROOT,
                stdout=logs[0],
                stderr=subprocess.STDOUT,
                env=dict(os.environ, PYTHONUNBUFFERED="1"),
                start_new_session=True,  # the server's console children go with it
            )
        )
        address = re.compile(r"(http://[^/\s]+)/\?token=\S+")

        def printed() -> re.Match[str] | None:  # the server's output; failing if it exited
            assert procs[0].poll() is None, _read(tmp_path / "serve.log")
            return address.search(_read(tmp_path / "serve.log"))

        m = wait_until(printed, 60, "the server's address")
        url, origin = m.group(0), m.group(1)
        profile = tmp_path / "chromium"
        procs.append(
            subprocess.Popen(
                [
                    chromium,
                    *CHROMIUM_FLAGS,
                    f"--user-data-dir={profile}",
                    "--remote-debugging-port=0",
                    "--window-size=1200,1600",  # the Data Vector pane, health and all
                    "about:blank",
                ],
                stdout=logs[1],
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        )
        active = profile / "DevToolsActivePort"

        def opened() -> bool:  # the file chromium writes; failing if it exited
            assert procs[1].poll() is None, _read(tmp_path / "chromium.log")[-2000:]
            return active.exists() and bool(active.read_text().strip())

        wait_until(opened, 30, "chromium's DevTools port")
        devtools = int(active.read_text().split()[0])
        text, events = asyncio.run(
            _read_page(devtools, url, ["NO SIGNAL", "waiting for ", "cn_loop"], 60)
        )
        assert "b_timer_done" in text  # a mission element, from the Data Vector pane
        requests = [u for kind, u in events if kind == "request"]
        assert requests[0] == url and f"{origin}/" in requests  # the token, then the page
        ws = "ws" + origin.removeprefix("http")
        assert any(u.startswith(f"{ws}/ws?") for u in requests), requests
        outside = [u for u in requests if not u.startswith((f"{origin}/", f"{ws}/"))]
        assert outside == [], outside
        assert [e for e in events if e[0] == "failed"] == []
        refused = [e for e in events if e[0] == "status" and not e[1].startswith(("200", "303"))]
        assert refused == [], refused
    finally:
        for p in reversed(procs):
            _stop(p)
        for f in logs:
            f.close()


def _read(path: Path) -> str:
    return path.read_text(errors="replace")
