"""The web console: ``zplatform ground MISSION --web PORT`` serves the console to a browser.

Holds :class:`WebConsole` (an aiohttp server: each browser session is one
console process, ``ground MISSION --console`` under
:class:`~zplatform.console.webdriver.ConsoleWebDriver`, whose screen
textual-serve's front end draws) and :class:`Admission` (sans-IO: a one-time
token compared in constant time, then a session cookie; the Host and Origin
checks). Whoever holds a session commands the vehicle, so the server admits
only the operator and ties every console's life to the session and the server.

Contract: :meth:`WebConsole.serve` blocks until SIGINT or SIGTERM (or its console
ends), then ends every console and the server. A refused request gets a one-line 401/403 and
one log warning (never the token); every response forbids framing and any
other origin; the page loads nothing from the internet. A console is started
without a shell and ended when its WebSocket closes: asked to quit, then
SIGTERM after :data:`QUIT_GRACE_S`, SIGKILL after :data:`KILL_GRACE_S`.

Admission, lifetime, and why not textual-serve's server:
docs/architecture.md#ground (the web console); its use: docs/operations.md.
"""

from __future__ import annotations

import asyncio
import hmac
import html
import ipaddress
import json
import logging
import os
import secrets
import signal
import sys
from collections.abc import Sequence
from contextlib import suppress
from pathlib import Path
from typing import Any

from aiohttp import WSCloseCode, WSMsgType, hdrs, web

from ..errors import CommandError
from ..runtime.process import PARENT_ENV

__all__ = [
    "COOKIE",
    "HEARTBEAT_S",
    "KILL_GRACE_S",
    "QUIT_GRACE_S",
    "Admission",
    "WebConsole",
    "is_loopback",
]

log = logging.getLogger("zplatform.console.web")

COOKIE = "zplatform_console"
# A browser that vanished without closing its WebSocket is noticed within
# about twice this (aiohttp pings, then waits as long for the pong).
HEARTBEAT_S = 15.0
QUIT_GRACE_S = 5.0  # a console asked to quit has this long before SIGTERM,
KILL_GRACE_S = 3.0  # then this long before SIGKILL
_MAX_MESSAGE = 64 * 1024  # one browser message (keys, a paste, a resize)
_MAX_PACKET = 16 * 1024 * 1024  # one screen update from a console
_DRIVER = "zplatform.console.webdriver:ConsoleWebDriver"

# textual-serve's front end, as its wheel ships it under static/.
_ASSETS = (
    "js/textual.js",
    "css/xterm.css",
    "fonts/RobotoMono-VariableFont_wght.ttf",
    "fonts/RobotoMono-Italic-VariableFont_wght.ttf",
)
_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; font-src 'self'; connect-src 'self'; frame-ancestors 'none'; "
    "base-uri 'none'; form-action 'none'"
)
# textual-serve's page, less its Google font link, its Start button and its
# inline script; "Restart" is a plain link. xterm.js injects styles, hence
# style-src 'unsafe-inline'; scripts come only from /static.
_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{title}</title>
<link rel="icon" href="data:,">
<link rel="stylesheet" href="/static/css/xterm.css">
<style>
@font-face {{ font-family: "Roboto Mono"; font-style: normal; font-weight: 100 700;
  src: url("/static/fonts/RobotoMono-VariableFont_wght.ttf") format("truetype"); }}
@font-face {{ font-family: "Roboto Mono"; font-style: italic; font-weight: 100 700;
  src: url("/static/fonts/RobotoMono-Italic-VariableFont_wght.ttf") format("truetype"); }}
body {{ background: #0c181f; margin: 0; }}
.dialog-container {{ position: absolute; width: 100vw; height: 100vh; display: flex;
  align-items: center; justify-content: center; z-index: 10; }}
.intro {{ width: 640px; height: 240px; z-index: 20; font: 16px "Roboto Mono", monospace;
  color: rgba(255, 255, 255, 0.95); background-color: #12232d; display: flex;
  flex-direction: column; align-items: center; justify-content: center; }}
.intro a {{ padding: 16px 32px; margin: 16px; background-color: #5e0ba7;
  color: rgba(255, 255, 255, 0.95); text-decoration: none; }}
body.-first-byte .intro-dialog {{ display: none; }}
.closed-dialog {{ display: none; }}
body.-closed .closed-dialog {{ display: flex; }}
body .textual-terminal {{ opacity: 0; }}
body.-first-byte .textual-terminal {{ opacity: 1; }}
</style>
<script src="/static/js/textual.js"></script>
</head>
<body>
<div class="dialog-container intro-dialog"><div class="intro">{title}</div></div>
<div class="dialog-container closed-dialog"><div class="intro">
<div>Session ended.</div><a href="/">Restart</a></div></div>
<div id="terminal" class="textual-terminal" data-session-websocket-url="{ws_url}"
  data-font-size="16"></div>
</body>
</html>
"""


def is_loopback(host: str) -> bool:
    """True when ``host`` (an address or name to listen on) reaches only this machine."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _split_host(value: str) -> tuple[str, int] | None:
    """A Host header's name (lower case, IPv6 without brackets) and port (80 if none)."""
    if value.startswith("["):
        name, bracket, rest = value[1:].partition("]")
        if not bracket or (rest and not rest.startswith(":")):
            return None
        port = rest[1:]
    else:
        name, _, port = value.partition(":")
        if ":" in port:  # an IPv6 address without brackets
            return None
    if not name or any(c in name for c in "@/\\?# \t"):
        return None
    if port == "":
        return name.lower(), 80
    if not (port.isascii() and port.isdigit()):
        return None
    return name.lower(), int(port)


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


class Admission:
    """Who may open a console (see the module doc): headers in, a reason to refuse or None out.

    ``host`` and ``port``: what the server listens on (``port`` is set once
    known when the server was given 0). :attr:`token` is made here unless
    given. Not thread-safe: the server's event loop owns it.
    """

    def __init__(self, host: str, port: int, token: str | None = None) -> None:
        self.host = host.lower().strip("[]")
        self.port = port
        self.token = token if token is not None else secrets.token_urlsafe(32)
        self._session: str | None = None
        self._spent = False

    def host_refusal(self, host: str | None) -> str | None:
        """Why a request with this Host header is refused (403), or None."""
        if not host:
            return "no Host header"
        parts = _split_host(host)
        if parts is None:
            return f"malformed Host header {host!r}"
        name, port = parts
        if port != self.port:
            return f"Host {host!r} names another port than this server's ({self.port})"
        if name in ("localhost", self.host) or _is_ip(name):
            return None
        return f"Host {host!r} is not this server's address (DNS rebinding?)"

    def origin_refusal(self, origin: str | None, host: str, *, required: bool) -> str | None:
        """Why a request from ``origin`` to ``host`` (checked already) is refused (403), or None."""
        if origin is None:
            return "a WebSocket without an Origin header" if required else None
        if origin.lower() != f"http://{host.lower()}":
            return f"cross-origin request from {origin!r}"
        return None

    def redeem(self, token: str) -> str | None:
        """A new session for the right token, the first time only; else None."""
        right = hmac.compare_digest(token.encode(), self.token.encode())
        if not right or self._spent:
            return None
        self._spent = True
        self._session = secrets.token_urlsafe(32)
        return self._session

    def revoke(self) -> None:
        """End the session: its cookie admits nothing more, and the token stays spent."""
        self._session = None

    def admitted(self, session: str | None) -> bool:
        """True for the session cookie the token was redeemed for."""
        if session is None or self._session is None:
            return False
        return hmac.compare_digest(session.encode(), self._session.encode())


def _static_dir() -> Path:
    """textual-serve's static files (the page's script, styles and fonts); checked."""
    import textual_serve

    root = Path(textual_serve.__file__ or "").parent / "static"
    missing = [a for a in _ASSETS if not (root / a).is_file()]
    if missing:
        raise CommandError(
            f"textual-serve at {root.parent} lacks the console page's {', '.join(missing)}"
        )
    return root


def _cells(value: object, default: int) -> int:
    """A terminal width or height from the browser, within reason."""
    if isinstance(value, str) and value.isascii() and value.isdigit():
        value = int(value)
    return value if isinstance(value, int) and 1 <= value <= 1000 else default


def _meta_type(payload: bytes) -> object:
    """The ``type`` of a console's meta packet (None if it has none)."""
    meta = json.loads(payload)
    return meta.get("type") if isinstance(meta, dict) else None


class _Console:
    """One console process and its pipes.

    textual's web-driver packets both ways: a type byte (``D`` screen data or
    keys, ``M`` JSON meta, ``P`` packed file chunks), a 4-byte big-endian
    length, the payload. The console says ``__GANGLION__`` before its first.
    """

    def __init__(self, proc: asyncio.subprocess.Process) -> None:
        self.proc = proc
        self.pid = proc.pid
        self._ending: asyncio.Task[int] | None = None

    @classmethod
    async def start(cls, argv: Sequence[str], env: dict[str, str]) -> _Console:
        # No shell between: the console is the server's own child, so its
        # parent-death signal follows the server. stderr is the server's.
        proc = await asyncio.create_subprocess_exec(
            *argv, stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE, env=env
        )
        return cls(proc)

    async def send(self, kind: bytes, payload: bytes) -> bool:
        """Write one packet to the console; False when its stdin is closed."""
        stdin = self.proc.stdin
        if stdin is None or stdin.is_closing():
            return False
        stdin.write(kind + len(payload).to_bytes(4, "big") + payload)
        try:
            await stdin.drain()
        except ConnectionError:
            return False
        return True

    async def meta(self, data: dict[str, object]) -> bool:
        return await self.send(b"M", json.dumps(data).encode())

    async def screen_to(self, ws: web.WebSocketResponse) -> None:
        """Forward the console's screen to ``ws`` until the console ends; then close ``ws``."""
        out = self.proc.stdout
        assert out is not None
        try:
            while (line := await out.readline()) != b"__GANGLION__\n":
                if not line:
                    return
            while True:
                head = await out.readexactly(5)
                size = int.from_bytes(head[1:], "big")
                if size > _MAX_PACKET:
                    log.error("console %d sent a %d-byte packet; ending it", self.pid, size)
                    return
                payload = await out.readexactly(size)
                if head[:1] == b"D":
                    await ws.send_bytes(payload)
                elif head[:1] == b"M" and _meta_type(payload) == "exit":
                    return
                # Other packets (open a URL, deliver a file) have no business
                # in the operator's browser: dropped.
        except (asyncio.IncompleteReadError, ConnectionError, ValueError):
            return  # the console ended (or garbled its pipe), or the browser went
        finally:
            await ws.close()

    async def end(self) -> int:
        """End the console (quit, end of file, SIGTERM, SIGKILL); its exit code. Idempotent."""
        if self._ending is None:
            self._ending = asyncio.ensure_future(self._end())
        return await asyncio.shield(self._ending)

    async def _end(self) -> int:
        proc = self.proc
        if proc.returncode is None:
            await self.meta({"type": "quit"})
            if proc.stdin is not None:
                proc.stdin.close()  # end of file: a console that missed the quit ends too
            for grace, escalate in ((QUIT_GRACE_S, proc.terminate), (KILL_GRACE_S, proc.kill)):
                try:
                    return await asyncio.wait_for(proc.wait(), grace)
                except TimeoutError:
                    log.warning(
                        "console %d still runs %.0f s after %s",
                        self.pid,
                        grace,
                        "quit" if escalate == proc.terminate else "SIGTERM",
                    )
                    with suppress(ProcessLookupError):
                        escalate()
        return await proc.wait()


class WebConsole:
    """The web console server (see the module doc).

    ``argv``: the console command, started once per browser session.
    :meth:`start` binds and returns; :meth:`close` ends every console, then
    the server; :meth:`serve` does both around SIGINT/SIGTERM and blocks.
    """

    def __init__(
        self,
        argv: Sequence[str],
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        title: str = "zplatform ground",
    ) -> None:
        self.argv = list(argv)
        self.host = host
        self.admission = Admission(host, port)
        self.title = title
        self.consoles: set[_Console] = set()
        self._static = _static_dir()
        self._runner: web.AppRunner | None = None
        self.ended = asyncio.Event()
        """Set when the one session's console has ended: the server has nothing
        left to serve (:meth:`serve` returns)."""

    @property
    def port(self) -> int:
        return self.admission.port

    @property
    def url(self) -> str:
        """The address the operator opens, token included."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        if host == "::":
            host = "::1"
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.port}/?token={self.admission.token}"

    # -- serving ---------------------------------------------------------------
    async def start(self) -> None:
        """Listen; raises :class:`CommandError` when the address cannot be used."""
        app = web.Application(middlewares=[self._gate], client_max_size=_MAX_MESSAGE)
        app.router.add_get("/", self._page)
        app.router.add_get("/ws", self._websocket)
        app.router.add_static("/static", self._static)
        app.on_response_prepare.append(_harden)
        # No access log: its request lines would carry the token.
        self._runner = web.AppRunner(app, access_log=None, shutdown_timeout=KILL_GRACE_S)
        await self._runner.setup()
        try:
            await web.TCPSite(self._runner, self.host, self.port).start()
        except OSError as exc:
            await self._runner.cleanup()
            raise CommandError(
                f"cannot listen on {self.host}:{self.port}: {exc.strerror or exc}"
            ) from None
        self.admission.port = self._runner.addresses[0][1]

    async def close(self) -> None:
        """End every console, then stop listening."""
        await asyncio.gather(*(c.end() for c in list(self.consoles)))
        if self._runner is not None:
            await self._runner.cleanup()

    def serve(self) -> None:
        """Serve until SIGINT or SIGTERM; print the address (stdout) and any warning (stderr)."""
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await self.start()
        if not is_loopback(self.host):
            print(
                f"zplatform: warning: the web console listens on {self.host}:{self.port}, "
                "beyond this machine: whoever reaches it with the token commands the "
                "vehicle, and the token and the console cross the network unencrypted "
                "(no TLS); prefer --host 127.0.0.1 and an SSH tunnel "
                f"(ssh -L {self.port}:127.0.0.1:{self.port} THIS_HOST)",
                file=sys.stderr,
                flush=True,
            )
        print(f"{self.title}: {self.url}", flush=True)
        print(
            "  open that address in a browser: its token admits one browser, once "
            "(restart for another); Ctrl-C stops the server and its consoles",
            flush=True,
        )
        waits = [asyncio.ensure_future(e.wait()) for e in (stop, self.ended)]
        try:
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            if self.ended.is_set():
                print(
                    f"{self.title}: the console ended and its token is spent; "
                    "start `zplatform ground --web` again for another",
                    flush=True,
                )
        finally:
            for w in waits:
                w.cancel()
            await self.close()

    # -- requests ----------------------------------------------------------------
    def _refuse(self, request: web.Request, status: int, why: str) -> web.Response:
        # request.path has no query string: the token never reaches the log.
        log.warning("refused %s %s from %s: %s", request.method, request.path, request.remote, why)
        return web.Response(status=status, text=f"{why}\n")

    @web.middleware
    async def _gate(self, request: web.Request, handler: Any) -> web.StreamResponse:
        host = request.headers.get(hdrs.HOST)
        why = self.admission.host_refusal(host)
        if why is None:
            assert host is not None
            why = self.admission.origin_refusal(
                request.headers.get(hdrs.ORIGIN), host, required=request.path == "/ws"
            )
        if why is not None:
            return self._refuse(request, 403, why)
        response: web.StreamResponse = await handler(request)
        return response

    async def _page(self, request: web.Request) -> web.Response:
        if self.admission.admitted(request.cookies.get(COOKIE)):
            if "token" in request.query:
                return web.Response(status=303, headers={hdrs.LOCATION: "/"})
            return web.Response(
                text=_PAGE.format(
                    title=html.escape(self.title),
                    ws_url=html.escape(f"ws://{request.host}/ws"),
                ),
                content_type="text/html",
            )
        token = request.query.get("token")
        if token is None:
            return self._refuse(
                request, 401, "no session: open the address with ?token= that --web printed"
            )
        session = self.admission.redeem(token)
        if session is None:
            return self._refuse(
                request, 401, "wrong or spent token: restart `zplatform ground --web` for a new one"
            )
        log.info("token redeemed by %s", request.remote)
        response = web.Response(status=303, headers={hdrs.LOCATION: "/"})
        response.set_cookie(COOKIE, session, httponly=True, samesite="Strict", path="/")
        return response

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        if not self.admission.admitted(request.cookies.get(COOKIE)):
            return self._refuse(request, 401, "no session: open the address --web printed first")
        ws = web.WebSocketResponse(heartbeat=HEARTBEAT_S, max_msg_size=_MAX_MESSAGE)
        await ws.prepare(request)
        env = dict(
            os.environ,
            TEXTUAL_DRIVER=_DRIVER,
            TEXTUAL_COLOR_SYSTEM="truecolor",
            TERM_PROGRAM="textual",
            COLUMNS=str(_cells(request.query.get("width"), 80)),
            ROWS=str(_cells(request.query.get("height"), 24)),
        )
        env[PARENT_ENV] = str(os.getpid())
        try:
            console = await _Console.start(self.argv, env)
        except OSError as exc:
            log.error("the console did not start: %s", exc)
            await ws.close(code=WSCloseCode.INTERNAL_ERROR, message=b"the console did not start")
            return ws
        self.consoles.add(console)
        log.info("console %d started for %s", console.pid, request.remote)
        screen = asyncio.create_task(console.screen_to(ws))
        try:
            await _keys(ws, console)
        finally:
            code = await console.end()
            screen.cancel()
            with suppress(asyncio.CancelledError):
                await screen
            self.consoles.discard(console)
            log.info("console %d ended (exit code %s)", console.pid, code)
            # One browser, once: with its console gone the session ends, so
            # neither its cookie nor the token opens another console.
            self.admission.revoke()
            if not self.consoles:
                self.ended.set()
        return ws


async def _keys(ws: web.WebSocketResponse, console: _Console) -> None:
    """The browser's keys, size and focus to the console, until either side closes."""
    async for msg in ws:
        if msg.type is not WSMsgType.TEXT:
            continue
        try:
            kind, *args = json.loads(msg.data)
        except (ValueError, TypeError):
            continue  # not a console message
        arg = args[0] if args else None
        if kind == "stdin" and isinstance(arg, str):
            sent = await console.send(b"D", arg.encode())
        elif kind == "resize" and isinstance(arg, dict):
            size = {"width": _cells(arg.get("width"), 80), "height": _cells(arg.get("height"), 24)}
            sent = await console.meta({"type": "resize", **size})
        elif kind in ("focus", "blur"):
            sent = await console.meta({"type": kind})
        elif kind == "ping":
            try:
                await ws.send_json(["pong", arg])
            except ConnectionError:
                return
            sent = True
        else:
            sent = True
        if not sent:
            return


async def _harden(request: web.Request, response: web.StreamResponse) -> None:
    response.headers[hdrs.CONTENT_SECURITY_POLICY] = _CSP
    response.headers[hdrs.X_FRAME_OPTIONS] = "DENY"
    response.headers["Referrer-Policy"] = "no-referrer"
    response.headers[hdrs.X_CONTENT_TYPE_OPTIONS] = "nosniff"
    response.headers[hdrs.CACHE_CONTROL] = "no-store"
