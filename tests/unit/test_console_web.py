"""Who the web console admits (:class:`zplatform.console.web.Admission`), without a server."""

from __future__ import annotations

import pytest

pytest.importorskip("aiohttp")

from zplatform.console.web import Admission, is_loopback


@pytest.mark.parametrize(
    "host",
    [
        "127.0.0.1:8000",
        "localhost:8000",
        "LocalHost:8000",
        "[::1]:8000",
        "192.168.1.5:8000",  # an address literal cannot be rebound by DNS
        "ground.example:8000",  # the name the server was bound to
    ],
)
def test_hosts_that_name_this_server_pass(host: str) -> None:
    assert Admission("ground.example", 8000).host_refusal(host) is None


@pytest.mark.parametrize(
    ("host", "why"),
    [
        (None, "no Host header"),
        ("", "no Host header"),
        ("evil.example:8000", "DNS rebinding"),
        ("localhost.evil.example:8000", "DNS rebinding"),
        ("127.0.0.1.nip.io:8000", "DNS rebinding"),
        ("127.0.0.1:8001", "another port"),
        ("127.0.0.1", "another port"),  # no port: 80
        ("::1:8000", "malformed"),
        ("[::1:8000", "malformed"),
        ("[::1]x8000", "malformed"),
        ("user@127.0.0.1:8000", "malformed"),
        ("127.0.0.1:80a", "malformed"),
        ("127.0.0.1:８000", "malformed"),  # non-ASCII digits
    ],
)
def test_other_hosts_are_refused_with_the_reason(host: str | None, why: str) -> None:
    reason = Admission("127.0.0.1", 8000).host_refusal(host)
    assert reason is not None and why in reason


def test_origin_must_be_the_server_itself_and_a_websocket_must_say_it() -> None:
    a = Admission("127.0.0.1", 8000)
    host = "127.0.0.1:8000"
    assert a.origin_refusal("http://127.0.0.1:8000", host, required=True) is None
    assert a.origin_refusal("HTTP://127.0.0.1:8000", host, required=True) is None
    assert a.origin_refusal(None, host, required=False) is None  # a top-level navigation
    for origin in (
        "http://evil.example",
        "http://localhost:8000",  # another origin than the page's, even if it is this server
        "https://127.0.0.1:8000",
        "http://127.0.0.1:8001",
        "null",
    ):
        reason = a.origin_refusal(origin, host, required=True)
        assert reason is not None and "cross-origin" in reason, origin
    reason = a.origin_refusal(None, host, required=True)
    assert reason is not None and "without an Origin" in reason


def test_token_admits_one_session_once() -> None:
    a = Admission("127.0.0.1", 8000)
    assert len(a.token) >= 40  # 32 random bytes, URL-safe base64
    assert Admission("127.0.0.1", 8000).token != a.token
    assert a.redeem("wrong") is None
    assert a.redeem(a.token + "x") is None
    assert a.redeem("é") is None  # non-ASCII compares, never raises
    assert not a.admitted(None)
    session = a.redeem(a.token)
    assert session is not None and session != a.token
    assert a.admitted(session)
    assert a.redeem(a.token) is None  # spent
    assert not a.admitted(None)
    assert not a.admitted(a.token)
    assert not a.admitted(session[:-1])
    assert not a.admitted("")


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("127.0.0.1", True),
        ("127.0.0.2", True),
        ("::1", True),
        ("localhost", True),
        ("0.0.0.0", False),
        ("::", False),
        ("192.168.1.5", False),
        ("ground.example", False),
    ],
)
def test_loopback(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback


def test_an_ended_session_admits_nothing_and_its_token_stays_spent() -> None:
    a = Admission("127.0.0.1", 8000, token="t0ken")
    session = a.redeem("t0ken")
    assert session is not None and a.admitted(session)
    assert a.redeem("t0ken") is None  # spent while the session runs
    a.revoke()
    assert not a.admitted(session)  # its cookie admits nothing more
    assert a.redeem("t0ken") is None  # and the token stays spent
