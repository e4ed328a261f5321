"""The web console's server and its console processes, over real HTTP and pipes.

``zplatform ground MISSION --web 0`` runs as a process; the tests read the
address it prints, talk to it with aiohttp (no browser: the page itself is
tested in test_console.py), and find its console processes with psutil.
Admission: no token, a wrong or spent token, a wrong Host, a cross-origin
WebSocket are refused, and no console starts. Lifetime: the console ends
when its WebSocket closes or drops, when the server is killed with SIGKILL
(mid-telemetry), and, with its pipes held open by someone else, when only
its parent dies (the parent-death signal); a console whose stdin ends or
whose stdout breaks exits by itself and says why. Every wait is on a
condition (a printed line, a frame, a process gone), bounded.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("textual")
pytest.importorskip("textual_serve")
pytest.importorskip("aiohttp")
pytest.importorskip("psutil")

import aiohttp
import psutil

from tests.waits import wait_until
from zplatform.console.web import COOKIE, KILL_GRACE_S, QUIT_GRACE_S
from zplatform.console.webdriver import EXIT_GRACE_S
from zplatform.runtime.process import PARENT_ENV
from zplatform.runtime.transport import rewrite_endpoints

from .harness import CONFIGS, ROOT, Cluster

pytestmark = pytest.mark.timeout(180)

# A console ends cleanly in about a second; these bounds are what the code
# allows before it escalates, plus room for a loaded machine.
SESSION_END_S = QUIT_GRACE_S + KILL_GRACE_S + 10
SERVER_GONE_S = EXIT_GRACE_S + 10


class Served:
    """``zplatform ground MISSION --web 0 [extra]`` with its printed address and its consoles."""

    def __init__(self, mission: Path, tmp: Path, *extra: str) -> None:
        self.out_path = tmp / "serve.out"
        self.err_path = tmp / "serve.err"
        with open(self.out_path, "wb") as out, open(self.err_path, "wb") as err:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "zplatform", "ground", str(mission), "--web", "0", *extra],
                cwd=ROOT,
                stdout=out,
                stderr=err,
                env=dict(os.environ, PYTHONUNBUFFERED="1"),
                start_new_session=True,
            )

        def address() -> re.Match[str] | None:  # the server's output; failing if it exited
            assert self.proc.poll() is None, f"server exited: {self.err()}"
            return re.search(r"http://\S+/\?token=(\S+)", self.out())

        m = wait_until(address, 60, "the server's address")
        self.url = m.group(0)
        self.token = m.group(1)
        self.base = self.url.split("/?")[0]
        self.host = self.base.removeprefix("http://")
        self.ws_url = f"{self.base}/ws?width=100&height=30"

    def out(self) -> str:
        return self.out_path.read_text(errors="replace")

    def err(self) -> str:
        return self.err_path.read_text(errors="replace")

    def consoles(self) -> list[psutil.Process]:
        return psutil.Process(self.proc.pid).children(recursive=True)

    def close(self) -> None:
        """SIGKILL the server's whole session (it and anything it left)."""
        leftover = [] if self.proc.poll() is not None else self.consoles()
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait()
        for p in leftover:  # re-parented children are in the same session
            try:
                p.kill()
            except psutil.NoSuchProcess:
                pass


def _mission(tmp: Path) -> Path:
    """led_test on free ports; no node runs (the console shows NO SIGNAL)."""
    path = tmp / "mission.yaml"
    rewrite_endpoints(CONFIGS / "led_test.yaml", path)
    return path


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    s = Served(_mission(tmp_path), tmp_path)
    try:
        yield s
    finally:
        s.close()


async def _session(http: aiohttp.ClientSession, s: Served) -> str:
    """Redeem the token; the session cookie's value."""
    async with http.get(s.url, allow_redirects=False) as r:
        assert r.status == 303, await r.text()
        assert r.headers["Location"] == "/"
        cookie = r.cookies[COOKIE]
        assert cookie["httponly"] and cookie["samesite"] == "Strict", cookie.output()
        return cookie.value


async def _refused(r: aiohttp.ClientResponse, status: int, why: str) -> None:
    text = await r.text()
    assert r.status == status, (r.status, text)
    assert why in text and text.count("\n") == 1, text


async def _first_frame(ws: aiohttp.ClientWebSocketResponse) -> None:
    """Wait for the console's first screen bytes (its process runs by then)."""
    while True:
        msg = await asyncio.wait_for(ws.receive(), 60)
        assert msg.type is not aiohttp.WSMsgType.CLOSED, "the session closed before any screen"
        if msg.type is aiohttp.WSMsgType.BINARY:
            return


def _gone(p: psutil.Process, within_s: float) -> None:
    try:
        p.wait(timeout=within_s)
    except psutil.TimeoutExpired:
        raise AssertionError(f"console {p.pid} still runs {within_s:.0f} s later") from None


# -- admission -------------------------------------------------------------------


@pytest.mark.no_mission
def test_no_console_without_the_token_right_host_and_same_origin(served: Served) -> None:
    s = served

    async def go() -> None:
        async with aiohttp.ClientSession() as http:
            # No token, a wrong one: 401, and the page is not served.
            async with http.get(f"{s.base}/") as r:
                await _refused(r, 401, "no session")
            async with http.get(f"{s.base}/?token=not-{s.token}") as r:
                await _refused(r, 401, "wrong or spent token")
            # The right token with a Host that is not this server (DNS rebinding): 403,
            # and the token is not spent by it.
            rebound = {"Host": f"evil.example:{s.url.split(':')[2].split('/')[0]}"}
            async with http.get(s.url, headers=rebound, allow_redirects=False) as r:
                await _refused(r, 403, "DNS rebinding")
            # The WebSocket without a session, then with one but from another origin.
            good = {"Origin": s.base}
            async with http.get(s.ws_url, headers=_upgrade(good)) as r:
                await _refused(r, 401, "no session")
            cookie = await _session(http, s)
            with_cookie = {"Cookie": f"{COOKIE}={cookie}"}
            for origin, why in (
                (
                    {"Origin": "http://evil.example"},
                    "cross-origin request from 'http://evil.example'",
                ),
                ({}, "without an Origin"),
            ):
                async with http.get(s.ws_url, headers=_upgrade({**with_cookie, **origin})) as r:
                    await _refused(r, 403, why)
            with pytest.raises(aiohttp.WSServerHandshakeError) as exc:
                await http.ws_connect(
                    s.ws_url, headers={**with_cookie, "Origin": "http://evil.example"}
                )
            assert exc.value.status == 403
            # The token is spent: another browser gets nothing with it.
            async with aiohttp.ClientSession() as other, other.get(s.url) as r:
                await _refused(r, 401, "wrong or spent token")
            # The session itself is admitted (the page, then a console).
            async with http.get(f"{s.base}/", headers=with_cookie) as r:
                assert r.status == 200
                assert r.headers["X-Frame-Options"] == "DENY"
                assert "frame-ancestors 'none'" in r.headers["Content-Security-Policy"]
            assert s.consoles() == []  # nothing refused ever started a console
            async with http.ws_connect(s.ws_url, headers={**with_cookie, **good}) as ws:
                await _first_frame(ws)
                assert len(s.consoles()) == 1

    asyncio.run(go())
    log = s.err()
    for why in ("no session", "DNS rebinding", "cross-origin", "without an Origin"):
        assert re.search(rf"zplatform\.console\.web WARNING refused GET /\S* .*{why}", log), why
    assert s.token not in log  # the log never shows the token
    assert "warning: the web console listens" not in log  # 127.0.0.1: no warning


@pytest.mark.no_mission
def test_listening_beyond_loopback_warns_once(tmp_path: Path) -> None:
    s = Served(_mission(tmp_path), tmp_path, "--host", "0.0.0.0")
    try:
        assert s.base.startswith("http://127.0.0.1:")  # the address printed works here

        async def go() -> None:
            async with aiohttp.ClientSession() as http:
                await _session(http, s)

        asyncio.run(go())
        assert s.err().count("zplatform: warning: the web console listens on 0.0.0.0:") == 1
    finally:
        s.close()


def _upgrade(headers: dict[str, str]) -> dict[str, str]:
    """A WebSocket handshake's headers, for a plain GET that reads the refusal."""
    return {
        **headers,
        "Connection": "Upgrade",
        "Upgrade": "websocket",
        "Sec-WebSocket-Version": "13",
        "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
    }


@pytest.mark.no_mission
def test_page_and_assets_load_only_from_the_server(served: Served) -> None:
    """The page names no other origin; every asset it names is served here."""
    s = served

    async def go() -> None:
        async with aiohttp.ClientSession() as http:
            headers = {"Cookie": f"{COOKIE}={await _session(http, s)}"}
            async with http.get(f"{s.base}/", headers=headers) as r:
                page = await r.text()
            refs = re.findall(r'(?:href|src)="([^"]*)"|url\("?([^")]*)"?\)', page)
            paths = [a or b for a, b in refs]
            assert {"/static/js/textual.js", "/static/css/xterm.css"} <= set(paths), paths
            assert f'data-session-websocket-url="ws://{s.host}/ws"' in page
            for path in paths:
                if path.startswith("data:"):
                    continue  # inline (the empty icon): loads nothing
                assert path.startswith("/") and not path.startswith("//"), path
                async with http.get(f"{s.base}{path}", headers=headers) as r:
                    assert r.status == 200, path
                    body = await r.read()
                if path.endswith(".css"):
                    css = re.sub(rb"/\*.*?\*/", b"", body, flags=re.S)  # comments load nothing
                    assert not re.search(rb"url\(|@import|https?:", css), path
                if path.endswith(".js"):
                    assert not re.search(rb"https?://", body), path
            assert not re.search(r"https?://|//fonts|@import", page)

    asyncio.run(go())


# -- lifetime --------------------------------------------------------------------


@pytest.mark.parametrize("how", ["close", "drop"])
@pytest.mark.no_mission
def test_console_ends_with_its_websocket(served: Served, how: str) -> None:
    """A closed WebSocket, or a connection dropped without a close, ends its console."""
    s = served

    async def go() -> psutil.Process:
        http = aiohttp.ClientSession()
        try:
            headers = {"Cookie": f"{COOKIE}={await _session(http, s)}", "Origin": s.base}
            ws = await http.ws_connect(s.ws_url, headers=headers)
            await _first_frame(ws)
            (console,) = s.consoles()
            if how == "close":
                await ws.close()
        finally:
            await http.close()  # "drop": the TCP connection ends without a close frame
        return console

    console = asyncio.run(go())
    _gone(console, SESSION_END_S)
    wait_until(lambda: f"console {console.pid} ended" in s.err(), 10, "the console's end")
    assert f"console {console.pid} ended (exit code 0)" in s.err()  # it quit; nobody killed it
    # One browser, once: with its session over, the server has nothing left to
    # serve (it used to keep serving a spent token and a live cookie).
    assert s.proc.wait(timeout=SESSION_END_S) == 0, s.err()
    assert "the console ended and its token is spent" in s.out()


def test_console_ends_when_its_server_is_killed(tmp_path: Path) -> None:
    """SIGKILL to the server, telemetry flowing: its console closes its sessions and exits."""
    with Cluster(CONFIGS / "recovery_igniter.yaml", tmp_path) as c:
        for n in ("dn0", "dn1", "cn"):
            c.spawn(n)
        c.advance(5)
        s = Served(c.path, tmp_path)
        try:

            async def go() -> psutil.Process:
                async with aiohttp.ClientSession() as http:
                    headers = {"Cookie": f"{COOKIE}={await _session(http, s)}", "Origin": s.base}
                    async with http.ws_connect(s.ws_url, headers=headers) as ws:
                        # The console draws live telemetry, then its server dies.
                        screen = b""
                        while b" LINK " not in screen:
                            msg = await asyncio.wait_for(ws.receive(), 60)
                            assert msg.type is not aiohttp.WSMsgType.CLOSED
                            if msg.type is aiohttp.WSMsgType.BINARY:
                                screen += msg.data
                        (console,) = s.consoles()
                        os.kill(s.proc.pid, signal.SIGKILL)
                        s.proc.wait()
                return console

            console = asyncio.run(go())
            _gone(console, SERVER_GONE_S)
            # It ended the clean way (the app unmounted, its Link closed), not by the hard exit.
            assert "web console closed: " in s.err(), s.err()
            assert "cut short" not in s.err()
        finally:
            s.close()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.no_mission
def test_server_stopped_ends_its_consoles_then_itself(served: Served, sig: int) -> None:
    """Ctrl-C or SIGTERM to the server alone: its console quits, the server exits 0."""
    s = served

    async def go() -> psutil.Process:
        async with aiohttp.ClientSession() as http:
            headers = {"Cookie": f"{COOKIE}={await _session(http, s)}", "Origin": s.base}
            async with http.ws_connect(s.ws_url, headers=headers) as ws:
                await _first_frame(ws)
                (console,) = s.consoles()
                os.kill(s.proc.pid, sig)
                # Like a browser: read on, answering the server's close.
                while (await asyncio.wait_for(ws.receive(), 60)).type not in (
                    aiohttp.WSMsgType.CLOSE,
                    aiohttp.WSMsgType.CLOSED,
                ):
                    pass
        return console

    console = asyncio.run(go())
    assert s.proc.wait(timeout=SESSION_END_S) == 0, s.err()
    _gone(console, 10)
    assert f"console {console.pid} ended (exit code 0)" in s.err()


def _console_argv(mission: Path) -> list[str]:
    return [sys.executable, "-m", "zplatform", "ground", str(mission), "--console"]


def _console_env(parent: int | None = None) -> dict[str, str]:
    env = dict(os.environ, TEXTUAL_DRIVER="zplatform.console.webdriver:ConsoleWebDriver")
    if parent is not None:
        env[PARENT_ENV] = str(parent)
    return env


def _console(tmp: Path) -> subprocess.Popen[bytes]:
    """A console on pipes to this test, as a server starts it; its stderr in console.err."""
    with open(tmp / "console.err", "wb") as err:
        return subprocess.Popen(
            _console_argv(_mission(tmp)),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=err,
            env=_console_env(),
            cwd=ROOT,
        )


def _until_drawn(fd: int) -> None:
    """Read the console's stdout until it has drawn its screen (it runs, settled)."""
    buf = b""
    while b"NO SIGNAL" not in buf:
        chunk = os.read(fd, 65536)
        assert chunk, "the console ended before it drew its screen"
        buf += chunk


def _drain(fd: int) -> threading.Thread:
    def run() -> None:
        while True:
            try:
                if not os.read(fd, 65536):
                    return
            except OSError:
                return

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def _packet(meta: dict[str, object]) -> bytes:
    data = json.dumps(meta).encode()
    return b"M" + len(data).to_bytes(4, "big") + data


@pytest.mark.parametrize("end", ["stdin", "stdout"])
@pytest.mark.no_mission
def test_console_exits_when_its_pipe_to_the_server_ends(tmp_path: Path, end: str) -> None:
    """End of stdin, or a broken stdout, ends the console cleanly and says why.

    textual's own WebDriver keeps the app running in both cases.
    """
    p = _console(tmp_path)
    try:
        assert p.stdin is not None and p.stdout is not None
        _until_drawn(p.stdout.fileno())
        if end == "stdin":
            reader = _drain(p.stdout.fileno())
            p.stdin.close()
        else:
            p.stdout.close()
            # A resize makes the console draw, into the broken pipe.
            p.stdin.write(_packet({"type": "resize", "width": 90, "height": 30}))
            p.stdin.flush()
        assert p.wait(timeout=SERVER_GONE_S) == 0
        why = "its stdin closed" if end == "stdin" else "its screen pipe broke"
        assert f"web console closed: {why}" in (tmp_path / "console.err").read_text()
        if end == "stdin":
            reader.join(timeout=10)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


# Waits out the 10 s hard exit: with the soaks (-m slow); the other ends of
# the console's life (socket, server killed, stdin) are in the default suite.
@pytest.mark.slow
@pytest.mark.no_mission
def test_console_that_cannot_exit_is_cut_short(tmp_path: Path) -> None:
    """A quit right after a resize, as the console starts, ends it within the grace.

    This is what a browser that connects and goes at once sends. textual
    (8.2) may then spin instead of exiting, deaf to SIGTERM (see
    zplatform.console.webdriver); whether it spins depends on timing, and
    either way the console ends, within EXIT_GRACE_S.
    """
    p = _console(tmp_path)
    try:
        assert p.stdin is not None and p.stdout is not None
        buf = b""
        while b"__GANGLION__" not in buf:
            chunk = os.read(p.stdout.fileno(), 65536)
            assert chunk, "the console ended before it started"
            buf += chunk
        _drain(p.stdout.fileno())
        p.stdin.write(_packet({"type": "resize", "width": 90, "height": 30}))
        p.stdin.write(_packet({"type": "quit"}))
        p.stdin.flush()
        p.wait(timeout=EXIT_GRACE_S + 10)
        assert re.search(
            r"web console (closed: |cut short: not closed \d+ s after )the browser session ended",
            (tmp_path / "console.err").read_text(),
        )
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


@pytest.mark.no_mission
def test_console_dies_with_its_server_even_with_its_pipes_open(tmp_path: Path) -> None:
    """The parent-death signal alone ends a console whose server died.

    A stand-in server starts the console on pipes that this test also holds
    (so neither end of file nor a broken pipe tells the console), prints the
    console's PID and waits; it is then killed with SIGKILL.
    """
    console_in, to_console = os.pipe()
    console_out, from_console = os.pipe()
    with open(tmp_path / "console.err", "wb") as err:
        stand_in = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "import os, subprocess, sys\n"
                f"env = dict(os.environ, {PARENT_ENV}=str(os.getpid()))\n"
                f"p = subprocess.Popen(sys.argv[1:], stdin={console_in}, "
                f"stdout={from_console}, env=env)\n"
                "print(p.pid, flush=True)\n"
                "p.wait()\n",
                *_console_argv(_mission(tmp_path)),
            ],
            stdout=subprocess.PIPE,
            stderr=err,
            env=_console_env(),
            pass_fds=(console_in, from_console),
            cwd=ROOT,
        )
    os.close(console_in)
    os.close(from_console)
    console: psutil.Process | None = None
    try:
        assert stand_in.stdout is not None
        console = psutil.Process(int(stand_in.stdout.readline()))
        _until_drawn(console_out)
        reader = _drain(console_out)  # keep reading: the console must not block on its screen
        stand_in.kill()
        stand_in.wait()
        _gone(console, SERVER_GONE_S)
        reader.join(timeout=10)  # its stdout ended with it
        assert "web console closed: it got SIGTERM" in (tmp_path / "console.err").read_text()
    finally:
        if console is not None and console.is_running():
            console.kill()
        if stand_in.poll() is None:
            stand_in.kill()
            stand_in.wait()
        os.close(to_console)
        os.close(console_out)
