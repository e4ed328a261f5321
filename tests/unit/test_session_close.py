"""A node's session close is bounded: zenoh's close over mutual TLS can take
its own 10 s on a busy host (eclipse-zenoh/zenoh issue 2675), longer than the
stop grace ``up`` gives a node, which then killed it (-9) after a clean run."""

from __future__ import annotations

import threading
import time

import pytest

from zplatform.runtime import transport
from zplatform.runtime.transport import NodeSession, sessions_left_open


class _HangingSession:
    def __init__(self) -> None:
        self.release = threading.Event()
        self.closing = threading.Event()

    def close(self) -> None:
        self.closing.set()
        self.release.wait(30)


def _session(fake: object) -> NodeSession:
    ns = object.__new__(NodeSession)
    ns.node = "dn0"
    ns.session = fake  # type: ignore[assignment]
    ns._closed = False
    ns._token = None
    return ns


def test_a_hanging_close_returns_after_the_bound_and_is_counted(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(transport, "SESSION_CLOSE_S", 0.2)
    fake = _HangingSession()
    before = sessions_left_open()
    t0 = time.monotonic()
    try:
        _session(fake).close()
        assert fake.closing.is_set()  # the close was started...
        assert time.monotonic() - t0 < 10  # ...and not waited for to its end
        assert sessions_left_open() == before + 1
        assert "did not finish within 0.2 s" in caplog.text
    finally:
        fake.release.set()


def test_a_prompt_close_is_not_counted() -> None:
    fake = _HangingSession()
    fake.release.set()
    before = sessions_left_open()
    ns = _session(fake)
    ns.close()
    ns.close()  # idempotent
    assert fake.closing.is_set() and sessions_left_open() == before
