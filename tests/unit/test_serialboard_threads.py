"""SerialBoard's two threads, deterministically: the loop thread's step and
the I/O thread that owns the port, over an in-memory port with the protocol's
simulated device behind it (no pty, no process, no timing luck)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest

from tests.serial_port import MemoryPort
from zplatform.boards import BoardError
from zplatform.boards import serialboard as sb
from zplatform.boards.serialboard import SerialBoard

pytestmark = pytest.mark.timeout(60)

WAIT_S = 30.0  # hang detectors, not speed limits


@pytest.fixture
def ports() -> list[MemoryPort]:
    return []


@pytest.fixture
def board(ports: list[MemoryPort]) -> Iterator[SerialBoard]:
    def factory(*args: Any, **kwargs: Any) -> MemoryPort:
        p = MemoryPort()
        ports.append(p)
        return p

    b = SerialBoard(
        {
            "port": "/dev/memory",
            "digital_pins": 8,
            "reply_timeout_ms": 50,
            "reconnect_min_ms": 5,
            "reconnect_max_ms": 20,
            "safe_after": 1,
        },
        serial_factory=factory,
    )
    b.open()
    assert b.wait_connected(WAIT_S), b.health()
    try:
        yield b
    finally:
        b.close()


def test_a_failed_write_takes_the_link_down_at_once_and_it_is_reopened(
    board: SerialBoard, ports: list[MemoryPort]
) -> None:
    """A port whose writes fail while its reads stay quiet: the step that
    saw the failure reports the link down (health says so at once, not when
    the I/O thread happens to notice: it may never, its reads do not fail),
    and the I/O thread closes the port and opens it again."""
    board.step(0)
    assert board.health().ok
    ports[0].fail_writes = True
    with pytest.raises(BoardError, match="write failed"):
        board.step(1)
    h = board.health()
    assert not h.connected and not h.ok and h.safe_active, h
    with pytest.raises(BoardError, match="link down"):
        board.step(2)
    assert board.wait_connected(WAIT_S), board.health()
    assert len(ports) == 2 and ports[0].closed
    board.step(3)
    h = board.health()
    assert h.ok and h.connected and h.reconnects == 1 and not h.safe_active, h


def test_an_answer_to_an_abandoned_write_is_never_latched_as_the_next_steps(
    board: SerialBoard, ports: list[MemoryPort], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Step 1 gives up on its INPUTS; it arrives while step 2 begins. The
    I/O thread is held right after parsing it (inside the INPUTS decoding)
    until step 2 has sent its WRITE: step 2 must not take step 1's inputs for
    its own. It is counted late, and step 2 gets its own answer."""
    port = ports[0]
    board.step(0)
    port.hold = True
    port.device.board.inject_digital(5, True)  # what step 1's INPUTS will say
    with pytest.raises(BoardError, match="no INPUTS"):
        board.step(1)

    parsed = threading.Event()  # the I/O thread holds step 1's answer
    go = threading.Event()  # step 2's WRITE is out: let it go on
    returned = threading.Event()  # step 2 is over
    real = sb._U64

    class Paused:
        """The I/O thread's INPUTS decoding: held with step 1's answer until
        step 2 is waiting; and, should that answer have been handed over as
        step 2's, held again before step 2's own until step 2 returned (so
        that step 2 cannot be saved by its own answer overwriting it)."""

        def unpack_from(self, buf: Any, offset: int = 0) -> tuple[int, ...]:
            out = real.unpack_from(buf, offset)
            if not parsed.is_set():
                parsed.set()
                assert go.wait(WAIT_S)
            elif board._reply.is_set():
                assert returned.wait(WAIT_S)
            return out

        def __getattr__(self, name: str) -> Any:
            return getattr(real, name)

    monkeypatch.setattr(sb, "_U64", Paused())
    port.hold = False
    port.release()  # step 1's INPUTS reaches the I/O thread, which pauses in it
    assert parsed.wait(WAIT_S)
    port.device.board.inject_digital(5, False)  # step 2's INPUTS will say otherwise
    real_write = port.write

    def write_then_go(data: Any) -> int:
        n = real_write(data)  # the device answers step 2 into the buffer
        go.set()  # the I/O thread resumes with step 1's answer first
        return n

    port.write = write_then_go  # type: ignore[method-assign]
    late0 = board.health().late_replies
    try:
        board.step(2)
    finally:
        returned.set()
    assert board.get_digital(5) is False, "step 2 latched step 1's inputs"
    assert board.health().late_replies == late0 + 1
