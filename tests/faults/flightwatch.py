"""A flight's telemetry and events, watched from a process of its own.

``python -m tests.faults.flightwatch MISSION`` opens a tool's
:class:`~zplatform.ground.link.GroundLink` (the ground's own checks: it
follows the newest CN run and the newest term, refuses replays) and prints
one JSON line per accepted snapshot, ``{"t": T, "tm": {...}}`` with the
elements of :data:`WATCH`, and one per event, ``{"t": T, "ev": {"node",
"id", "text"}}``; ``T`` is the watcher's ``time.monotonic()`` (one kernel,
one monotonic clock across network namespaces). It ends when its stdin
closes. Run it where the test process cannot open a session (inside a
network namespace: ``NetnsHost.popen(..., pipe_stdio=True)``), or beside an
``up`` run so the test process holds no zenoh session of its own. Where it
may, it runs at the lowest real-time priority (SCHED_FIFO 1): below every
node, above a CPU hog, so it joins before the flight leaves the pad.

:class:`FlightWatch` is the test's side: a reader thread keeps every line;
:meth:`FlightWatch.wait_for` waits on a predicate over the snapshots (a hang
detector with a generous timeout, never a speed limit).
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["WATCH", "FlightWatch", "Snap", "watch_main"]

WATCH = (
    "cn_loop",
    "cn_epoch",
    "cn_state",
    "cn_fault",
    "cn_term",
    "cn_commander",
    "cn_standby_ready",
    "drogue_fired",
    "main_fired",
    "dn0_safed",
    "dn1_safed",
    "dn0_term_seen",
    "dn1_term_seen",
)
_NAMED = ("cn_state", "cn_fault", "cn_commander")
_BOOL = ("cn_standby_ready", "drogue_fired", "main_fired", "dn0_safed", "dn1_safed")


@dataclass(frozen=True)
class Snap:
    t: float
    v: dict[str, Any]


class FlightWatch:
    """The test's side of a watcher process (module doc)."""

    def __init__(self, proc: subprocess.Popen[Any]) -> None:
        self.proc = proc
        self.snaps: list[Snap] = []
        self.events: list[tuple[float, dict[str, str]]] = []
        self._lock = threading.Lock()
        self._new = threading.Condition(self._lock)
        self._th = threading.Thread(target=self._read, daemon=True)
        self._th.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                item = json.loads(line)
            except ValueError:
                continue
            with self._new:
                if "tm" in item:
                    self.snaps.append(Snap(item["t"], item["tm"]))
                elif "ev" in item:
                    self.events.append((item["t"], item["ev"]))
                self._new.notify_all()
        with self._new:
            self._new.notify_all()

    def last(self) -> dict[str, Any]:
        with self._lock:
            return self.snaps[-1].v if self.snaps else {}

    def since(self, t: float = 0.0, until: float = float("inf")) -> list[dict[str, Any]]:
        """The snapshots received from ``t`` to ``until`` (monotonic)."""
        with self._lock:
            return [s.v for s in self.snaps if t <= s.t <= until]

    def events_of(
        self, ev_id: str, node: str | None = None, t: float = 0.0, until: float = float("inf")
    ) -> list[str]:
        """The texts of the events ``ev_id`` (of ``node``) received from ``t``
        to ``until``."""
        with self._lock:
            return [
                e["text"]
                for et, e in self.events
                if e["id"] == ev_id and (node is None or e["node"] == node) and t <= et <= until
            ]

    def wait_for(self, pred: Callable[[dict[str, Any]], bool], timeout_s: float, what: str) -> Snap:
        """The first snapshot from now on for which ``pred`` holds."""
        deadline = time.monotonic() + timeout_s
        with self._new:
            seen = len(self.snaps)
            while True:
                for s in self.snaps[seen:]:
                    if pred(s.v):
                        return s
                seen = len(self.snaps)
                left = deadline - time.monotonic()
                if left <= 0 or self.proc.poll() is not None:
                    last = self.snaps[-1].v if self.snaps else None
                    why = "timed out" if left <= 0 else f"the watcher exited ({self.proc.poll()})"
                    raise AssertionError(f"{why} waiting for {what}; last telemetry: {last}")
                self._new.wait(min(left, 0.5))

    def wait_event(
        self, ev_id: str, node: str, timeout_s: float, since: float = 0.0
    ) -> tuple[float, str]:
        """The first event ``ev_id`` of ``node`` received from ``since`` on
        (already or to come): when it came, and its text."""
        deadline = time.monotonic() + timeout_s
        with self._new:
            while True:
                for t, e in self.events:
                    if t >= since and e["id"] == ev_id and e["node"] == node:
                        return t, e["text"]
                left = deadline - time.monotonic()
                if left <= 0 or self.proc.poll() is not None:
                    raise AssertionError(
                        f"no {ev_id} event from {node}; events: {self.events[-10:]}"
                    )
                self._new.wait(min(left, 0.5))

    def close(self) -> None:
        if self.proc.stdin is not None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._th.join(5)


def watch_main(mission_path: str) -> int:
    """Print the mission's telemetry and events as JSON lines until stdin closes."""
    from zplatform.ground.link import GroundLink
    from zplatform.mission.load import load_mission
    from zplatform.telemetry.records import EventRecord

    # The lowest real-time priority where permitted: below every node (they
    # run at the mission's, 20), above a CPU hog, which would otherwise start
    # the watcher only after the flight left the pad. Set before the session
    # opens, so zenoh's threads have it too.
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    m = load_mission(mission_path)
    done = threading.Event()

    def until_eof() -> None:
        sys.stdin.read()
        done.set()

    def on_event(rec: EventRecord) -> None:
        ev = {"node": rec.node, "id": rec.id, "text": rec.text}
        print(json.dumps({"t": time.monotonic(), "ev": ev}), flush=True)

    threading.Thread(target=until_eof, daemon=True).start()
    link = GroundLink(m, on_event=on_event)
    try:
        while not done.is_set():
            if link.next(0.1) is None:
                continue
            dv = link.dv
            v: dict[str, Any] = {}
            for k in WATCH:
                if k in _NAMED:
                    v[k] = dv.get_name(k)
                elif k in _BOOL:
                    v[k] = bool(dv.get(k))
                else:
                    v[k] = int(dv.get(k))
            print(json.dumps({"t": time.monotonic(), "tm": v}), flush=True)
    finally:
        link.close()
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m tests.faults.flightwatch MISSION")
    raise SystemExit(watch_main(sys.argv[1]))
