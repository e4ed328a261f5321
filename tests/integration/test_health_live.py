"""Health, monitors and the watchdog on real node processes (issue 20).

A thread made to hang (the device node's board I/O thread,
:mod:`tests.integration.health_boards`) is named in telemetry within its
deadline, its monitor's response runs and the node's watchdog (a file standing
in for /dev/watchdog) is no longer stroked, while the control node keeps
stroking systemd's (a datagram socket standing in for $NOTIFY_SOCKET). A CPU
hog beside the nodes and a full disk (a tiny tmpfs mounted for the test) each
raise their monitor.
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.tmpfs import mounted_tmpfs
from zplatform.config.codes import Thread
from zplatform.core.auth import load_keys
from zplatform.core.events import Event, EventReader

from .harness import ROOT, Cluster

pytestmark = pytest.mark.timeout(240)

HEALTH_HZ = 5
BOARD_DEADLINE_MS = 500


def _mission(tmp: Path, *, monitors: list[dict[str, Any]], **health: Any) -> Path:
    """cn + dn0 (a HangBoard), health at 5 Hz, states RUN -> HOT / FAULTED."""
    raw: dict[str, Any] = {
        "mission": "health_live",
        "pythonpath": [str(ROOT)],
        "nodes": {
            "cn": {"listen": ["tcp/127.0.0.1:0"]},
            "dn0": {
                "board": {
                    "driver": "tests.integration.health_boards:HangBoard",
                    "hang_file": str(tmp / "hang"),
                },
            },
        },
        "regions": {
            "cn": [{"name": "beat", "type": "u32"}],
            "dn0_to_cn": [{"name": "dn0_x", "type": "f32"}],
        },
        "health": {"rate_hz": HEALTH_HZ, "deadlines_ms": {"board": BOARD_DEADLINE_MS}, **health},
        "state_machine": {
            "initial": "RUN",
            "states": {
                "RUN": {
                    "transitions": [
                        {"element": "cn_fault", "op": "!=", "value": "NONE", "to": "FAULTED"}
                    ]
                },
                "HOT": {},
                "FAULTED": {},
            },
        },
        "monitors": monitors,
    }
    path = tmp / "health_live.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


class _Events:
    """Every event of the mission's nodes from now on (a subscription of the
    test's session), kept in arrival order; each record's tag is checked
    with the tool's keys (a record that does not verify fails the test).

    Events go out with congestion control DROP (a stalled subscriber never
    blocks a node's loop), so on a starved host one may never arrive; every
    event is also in its node's own log, which :meth:`wait` reads too."""

    def __init__(self, c: Cluster) -> None:
        self._c = c
        self._q: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
        self._reader = EventReader(c.mission, load_keys(c.mission, "tool"))
        self.seen: list[Event] = []
        self._sub = c.session.declare_subscriber(
            f"{c.mission.vehicle}/*/events",
            lambda s: self._q.put((str(s.key_expr), s.payload.to_bytes())),
        )

    def wait(self, node: str, id_: str, timeout_s: float = 30) -> str:
        """The text of the first event ``id_`` of ``node`` (already seen, or
        the next to come), received or in the node's log."""
        deadline = time.monotonic() + timeout_s
        logged = re.compile(rf" {re.escape(node)} {re.escape(id_)}: (.*)$", re.M)
        while True:
            for e in self.seen:
                if e.node == node and e.id == id_:
                    return e.text
            m = logged.search(self._c.log(node))
            if m:
                return m[1]
            try:
                key, raw = self._q.get(timeout=min(0.2, max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                if time.monotonic() < deadline:
                    continue
                texts = [f"{e.node} {e.id}: {e.text}" for e in self.seen]
                raise AssertionError(f"no {id_} event from {node}; saw {texts}") from None
            e, verified = self._reader.read(key, raw)
            assert verified, f"an event on {key} that the tool's keys cannot verify"
            self.seen.append(e)

    def close(self) -> None:
        self._sub.undeclare()


def _healthy(c: Cluster) -> None:
    c.wait_for(
        lambda dv: int(dv.get("dn0_health_seq")) >= 2 and int(dv.get("cn_health_seq")) >= 2,
        60,
        "health samples from both nodes",
    )
    assert int(c.tm.get("dn0_threads_stalled")) == 0
    assert int(c.tm.get("cn_threads_stalled")) == 0
    assert c.tm.get_name("cn_state") == "RUN"


def test_a_hung_thread_is_named_its_monitor_responds_and_its_watchdog_stops(
    tmp_path: Path,
) -> None:
    wd_file = tmp_path / "dn0.watchdog"
    wd_file.touch()
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify.sock"))
    notify.settimeout(30)
    path = _mission(
        tmp_path,
        monitors=[
            {
                "name": "dn0_threads",
                "element": "dn0_threads_stalled",
                "kind": "limit",
                "hi": 0,
                "response": "fault",
                "fault": "THREAD_STALLED",
            },
        ],
    )
    raw = yaml.safe_load(path.read_text())
    raw["nodes"]["dn0"]["watchdog"] = {"kind": "device", "device": str(wd_file), "interval_ms": 50}
    raw["nodes"]["cn"]["watchdog"] = {"kind": "systemd", "interval_ms": 50}
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with notify, Cluster(path, tmp_path) as c:
        c.spawn("dn0")
        c.spawn("cn", env={"NOTIFY_SOCKET": str(tmp_path / "notify.sock")})
        assert notify.recv(64) == b"READY=1"  # the CN's loop started
        _healthy(c)
        assert notify.recv(64) == b"WATCHDOG=1"
        size = wd_file.stat().st_size
        c.advance(30)
        assert wd_file.stat().st_size > size > 0  # dn0 strokes its watchdog
        q = _Events(c)
        try:
            (tmp_path / "hang").touch()
            board = 1 << Thread.BOARD
            # Named within its deadline is the unit tests' (a fake clock:
            # tests/unit/test_health.py); a live test on a loaded box asserts
            # that it is named, and by which thread, not how fast.
            c.wait_for(
                lambda dv: int(dv.get("dn0_threads_stalled")) & board != 0,
                30,
                "dn0's board thread named stalled",
            )
            text = q.wait("dn0", "thread_stalled")
            assert text == (
                f"dn0: thread board has not checked in within its deadline ({BOARD_DEADLINE_MS} ms)"
            )
            # The monitor's response: THREAD_STALLED latched, the state machine answers.
            c.wait_for(lambda dv: dv.get_name("cn_state") == "FAULTED", 30, "FAULTED")
            assert c.tm.get_name("cn_fault") == "THREAD_STALLED"
            text = q.wait("dn0", "watchdog_withheld")
            assert "thread(s) board stalled" in text
        finally:
            q.close()
        # No stroke since: the hardware would reset dn0's host.
        size = wd_file.stat().st_size
        c.advance(50)  # 0.5 s: ten stroke intervals
        assert wd_file.stat().st_size == size
        # The CN's threads are fine: it strokes on (a DN's stall does not reset the CN).
        notify.settimeout(0)
        with contextlib.suppress(BlockingIOError):
            while notify.recv(64):
                pass
        notify.settimeout(30)
        assert notify.recv(64) == b"WATCHDOG=1"


def _hogs(n: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def test_a_cpu_hog_beside_the_nodes_raises_its_monitor(tmp_path: Path) -> None:
    path = _mission(
        tmp_path,
        monitors=[
            {
                "name": "hog",
                "element": "dn0_sys_cpu_pct",
                "kind": "limit",
                "hi": 90,
                "persistence": 2,
                "response": "transition",
                "to": "HOT",
                "states": ["RUN"],
            },
        ],
    )
    hogs: list[subprocess.Popen[bytes]] = []
    with Cluster(path, tmp_path) as c:
        try:
            c.spawn("dn0")
            c.spawn("cn")
            c.wait_for(lambda dv: int(dv.get("dn0_health_seq")) >= 2, 60, "health samples")
            q = _Events(c)
            hogs = _hogs(os.cpu_count() or 2)  # every core busy
            c.wait_for(lambda dv: dv.get_name("cn_state") == "HOT", 60, "the hog monitor")
            text = q.wait("cn", "monitor_tripped")
            q.close()
            assert text.startswith("monitor hog: dn0_sys_cpu_pct = ")
            assert text.endswith("for 2 loops; transition to HOT requested")
            # The value it tripped on, in the event: the telemetry read now
            # may be a later sample, when the hogs shared the box with the
            # test's neighbours (a quiet run saw 56 % there after the trip).
            tripped = float(text.removeprefix("monitor hog: dn0_sys_cpu_pct = ").split()[0])
            assert tripped > 90, text
        finally:
            for h in hogs:
                h.kill()
                h.wait()


def test_a_full_disk_raises_its_monitor(tmp_path: Path) -> None:
    with mounted_tmpfs(tmp_path / "disk", "8m") as disk:
        path = _mission(
            tmp_path,
            disk_path=str(disk),
            limits={"disk_free_mb": {"yellow": [4, None], "red": [1, None]}},
            monitors=[
                {
                    "name": "disk",
                    "element": "dn0_disk_free_mb",
                    "kind": "limit",
                    "band": "red",
                    "response": "fault",
                },
            ],
        )
        with Cluster(path, tmp_path) as c:
            c.spawn("dn0")
            c.spawn("cn")
            _healthy(c)
            assert 7 < float(c.tm.get("dn0_disk_free_mb")) <= 8
            with open(disk / "fill", "wb") as f, contextlib.suppress(OSError):
                for _ in range(16):  # until the disk is full (ENOSPC)
                    f.write(b"\0" * (1 << 20))
                    f.flush()
            c.wait_for(lambda dv: dv.get_name("cn_state") == "FAULTED", 30, "the disk monitor")
            assert c.tm.get_name("cn_fault") == "MONITOR"
            assert float(c.tm.get("dn0_disk_free_mb")) < 1
