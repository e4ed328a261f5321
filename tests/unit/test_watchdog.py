"""The watchdog plug-in with fake devices: a FIFO and a file for /dev/watchdog,
a datagram socket for systemd's NOTIFY_SOCKET. It strokes while every watched
thread checks in and stops the moment one does not."""

from __future__ import annotations

import os
import socket
import threading
from pathlib import Path
from typing import Any

import pytest
import yaml

from zplatform import EV, ConfigError, EventLog, NodeError, decode_mission
from zplatform.config import WatchdogConfig
from zplatform.control.watchdog import Watchdog
from zplatform.core.health import THREAD_NAMES, Heartbeat, Liveness

MS = 1_000_000


class _Clock:
    def __init__(self) -> None:
        self.t = 10_000 * MS

    def __call__(self) -> int:
        return self.t


def _rig(
    cfg: WatchdogConfig, environ: dict[str, str] | None = None
) -> tuple[Watchdog, _Clock, Heartbeat, Heartbeat, EventLog]:
    clock = _Clock()
    live = Liveness({n: 500 * MS for n in THREAD_NAMES})
    loop = live.add(Heartbeat("loop", clock))
    board = live.add(Heartbeat("board", clock))
    events = EventLog("dn0")
    wd = Watchdog(cfg, "dn0", live, events, environ=environ or {}, clock=clock)
    return wd, clock, loop, board, events


def _run(wd: Watchdog, clock: _Clock, loop: Heartbeat, ms: int, step_ms: int = 10) -> None:
    """The loop at 100 Hz for ``ms``: it checks in and offers a stroke each loop."""
    for _ in range(ms // step_ms):
        clock.t += step_ms * MS
        loop.beat()
        wd.stroke(clock(), clock())


def test_a_device_is_stroked_every_interval_and_not_once_a_thread_stalls(tmp_path: Path) -> None:
    dev = tmp_path / "watchdog"
    dev.touch()
    wd, clock, loop, board, events = _rig(
        WatchdogConfig(kind="device", device=str(dev), interval_ms=100)
    )
    wd.open()
    _run(wd, clock, loop, 1000)  # the board thread is silent from here on
    assert dev.read_bytes() == b"\0" * 5  # every 100 ms while it was alive (0..500 ms)
    assert wd.withheld and wd.strokes == 5
    ev = events.drain()
    assert [(e.id, e.text) for e in ev] == [
        (
            "watchdog_withheld",
            f"dn0: watchdog no longer stroked, thread(s) board stalled; {dev} resets the host "
            "when its timeout runs out",
        )
    ]
    assert ev[0].severity == EV.WATCHDOG_WITHHELD.severity
    # The thread recovers before the hardware fired: strokes resume.
    board.beat()
    _run(wd, clock, loop, 300)
    assert not wd.withheld and wd.strokes == 8
    assert [e.id for e in events.drain()] == ["watchdog_resumed"]
    wd.close()
    assert dev.read_bytes() == b"\0" * 8 + b"V"  # a clean stop disarms it (magic close)


def test_a_stop_after_a_crash_leaves_the_watchdog_armed(tmp_path: Path) -> None:
    dev = tmp_path / "watchdog"
    dev.touch()
    wd, clock, loop, _, _ = _rig(WatchdogConfig(kind="device", device=str(dev)))
    wd.open()
    _run(wd, clock, loop, 200)
    wd.close(clean=False)
    assert b"V" not in dev.read_bytes() and dev.read_bytes()


def test_a_fifo_reader_sees_the_strokes_stop(tmp_path: Path) -> None:
    fifo = tmp_path / "wdfifo"
    os.mkfifo(fifo)
    got = bytearray()
    opened = threading.Event()

    def reader() -> None:
        with open(fifo, "rb", buffering=0) as f:
            opened.set()
            while chunk := f.read(64):
                got.extend(chunk)

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    wd, clock, loop, _, _ = _rig(WatchdogConfig(kind="device", device=str(fifo)))
    wd.open()  # blocks until the reader has opened its end
    assert opened.wait(5)
    _run(wd, clock, loop, 400)
    strokes = wd.strokes
    assert strokes == 4
    _run(wd, clock, loop, 1000)  # board silent past its 500 ms deadline
    assert wd.strokes == strokes + 1  # the 500 ms stroke, then none
    wd.close()
    t.join(5)
    assert bytes(got) == b"\0" * (strokes + 1) + b"V"


def test_only_the_watched_threads_count(tmp_path: Path) -> None:
    dev = tmp_path / "watchdog"
    dev.touch()
    wd, clock, loop, _, _ = _rig(WatchdogConfig(kind="device", device=str(dev), threads=["loop"]))
    wd.open()
    _run(wd, clock, loop, 2000)  # the board is stalled, but not watched
    assert wd.strokes == 20 and not wd.withheld
    wd.close()


def _notify_socket(tmp: Path) -> tuple[socket.socket, str]:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp / "notify.sock")
    s.bind(path)
    s.settimeout(5)
    return s, path


def _received(s: socket.socket) -> list[bytes]:
    out = []
    s.setblocking(False)
    try:
        while True:
            out.append(s.recv(64))
    except BlockingIOError:
        pass
    s.settimeout(5)
    return out


def test_systemd_gets_ready_watchdog_strokes_and_stopping(tmp_path: Path) -> None:
    s, path = _notify_socket(tmp_path)
    with s:
        wd, clock, loop, board, events = _rig(
            WatchdogConfig(kind="systemd", interval_ms=100), {"NOTIFY_SOCKET": path}
        )
        wd.open()
        assert s.recv(64) == b"READY=1"
        _run(wd, clock, loop, 1000)
        assert _received(s) == [b"WATCHDOG=1"] * 5
        assert [e.id for e in events.drain()] == ["watchdog_withheld"]
        assert "systemd acts when the unit's WatchdogSec runs out" in wd.consequence
        board.beat()
        _run(wd, clock, loop, 100)
        wd.close()
        assert _received(s) == [b"WATCHDOG=1", b"STOPPING=1"]


def test_systemd_abstract_socket(tmp_path: Path) -> None:
    name = f"zplatform-test-{os.getpid()}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind("\0" + name)
    s.settimeout(5)
    with s:
        wd, clock, loop, _, _ = _rig(WatchdogConfig(kind="systemd"), {"NOTIFY_SOCKET": "@" + name})
        wd.open()
        assert s.recv(64) == b"READY=1"
        _run(wd, clock, loop, 100)
        assert s.recv(64) == b"WATCHDOG=1"
        wd.close(clean=False)


def test_a_watchdog_that_is_not_there_refuses_to_start(tmp_path: Path) -> None:
    wd, *_ = _rig(WatchdogConfig(kind="systemd"), {})
    with pytest.raises(NodeError, match=r"\$NOTIFY_SOCKET is not set"):
        wd.open()
    wd, *_ = _rig(WatchdogConfig(kind="device", device=str(tmp_path / "nope")))
    with pytest.raises(NodeError, match="cannot open watchdog device"):
        wd.open()


def test_a_stroke_that_cannot_be_written_is_counted_not_waited_for(tmp_path: Path) -> None:
    s, path = _notify_socket(tmp_path)
    wd, clock, loop, board, _ = _rig(WatchdogConfig(kind="systemd"), {"NOTIFY_SOCKET": path})
    wd.open()
    s.close()  # systemd's end is gone
    os.unlink(path)
    board.beat()
    _run(wd, clock, loop, 300)
    assert wd.errors == 3 and wd.strokes == 0
    wd.close()


BASE: dict[str, Any] = {
    "mission": "wd",
    "nodes": {"cn": {}, "dn0": {}, "gn": {}},
    "regions": {"cn": [{"name": "x", "type": "u8"}]},
}


@pytest.mark.parametrize(
    ("node", "wd", "path", "words"),
    [
        (
            "dn0",
            {"kind": "device", "threads": ["loop", "lopo"]},
            "$.nodes.dn0.watchdog.threads[1]",
            "no thread named 'lopo'",
        ),
        ("dn0", {"kind": "device", "device": ""}, "$.nodes.dn0.watchdog.device", "device path"),
        ("gn", {"kind": "systemd"}, "$.nodes.gn.watchdog", "ground node"),
        ("cn", {"kind": "hw"}, "$.nodes.cn.watchdog.kind", "Invalid enum value"),
        ("cn", {"kind": "systemd", "interval_ms": 1}, "$.nodes.cn.watchdog.interval_ms", ">= 10"),
    ],
)
def test_a_bad_watchdog_names_its_path(
    node: str, wd: dict[str, Any], path: str, words: str
) -> None:
    raw = yaml.safe_load(yaml.safe_dump(BASE))
    raw["nodes"][node]["watchdog"] = wd
    with pytest.raises(ConfigError) as ei:
        decode_mission(yaml.safe_dump(raw))
    assert ei.value.path == path, ei.value
    assert words in str(ei.value)
