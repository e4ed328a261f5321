"""``zplatform up``: every node of a mission as a process of this host, supervised.

:func:`run_up` registers the run (:mod:`zplatform.cli.registry`), spawns the
device nodes, the ground node and the control node (each ``python -m zplatform
node ...`` in a session of its own, never forked from a process that holds a
zenoh session), watches them (:func:`watch`) through a
:class:`~zplatform.ground.link.GroundLink` of its own, stops them in order
(the CN first, so the ground logs the end) and merges their summaries into
the ``--summary`` JSON (:class:`~zplatform.telemetry.summary.RunSummary`).

Contract: :func:`run_up` blocks until the run ends (its duration, the
script's last verdict plus :data:`~zplatform.ground.script.SETTLE_S` or
``--settle``, a stop, or the CN's death) and returns the exit code. A dead DN,
ground node or station is reported and the rest run on (the run ends
non-zero; a station is restarted, :class:`StationRestarts`); a dead CN ends
the flight. The nodes are signalled before ``up`` closes its own zenoh
session, which closes last, in a thread, for at most :data:`LINK_CLOSE_S`.

What a node's death does and how a run ends: docs/operations.md#running-missions.
"""

from __future__ import annotations

import math
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import STANDBY, Mission, counter_region
from ..core.datavector import DataVector
from ..core.events import EV
from ..errors import DataVectorError, NodeError
from ..ground.link import GroundLink
from ..ground.script import MIN_DURATION_S, SETTLE_S
from ..ground.status import RateMeter, status_line
from ..mission.load import load_mission
from ..node.ground import station_dir
from ..runtime.intrahost import intra_host_mode
from ..runtime.process import LOG_LEVEL_ENV, PARENT_ENV, STATUS_LINE_ENV, STOP_PIPE_ENV
from ..runtime.tmiox import telemetry_path_wanted
from ..runtime.transport import rewrite_endpoints
from ..telemetry.logs import events_path
from ..telemetry.records import EventRecord
from ..telemetry.summary import (
    CnSummary,
    DnSummary,
    GnSummary,
    RunSummary,
    board_line,
    board_trouble,
    cn_summary,
    read_summary,
    write_summary,
)

__all__ = [
    "Children",
    "StationRestarts",
    "Watch",
    "format_board_lines",
    "format_run_summary",
    "merge_summaries",
    "run_up",
    "station_states",
    "watch",
]

STOP_SLOW_S = 10.0
"""A node still running this long after SIGTERM is reported as slow to stop."""

STOP_GRACE_S = 30.0
"""How long ``up`` lets a node stop before SIGKILL. Generous: under mutual
TLS on a busy host a device node was seen to need more than 10 s (zenoh's
TLS link close, eclipse-zenoh/zenoh issue 2675), and a node killed is a
node whose summary is lost."""

LINK_CLOSE_S = 5.0
"""The longest ``up`` waits for its own zenoh session to close, after every
node has stopped; a close still under way then is left to the process's exit."""


class Children:
    """The node processes ``up`` spawned; every one is reaped on exit."""

    def __init__(self, *, quiet: bool = False, status_line: bool = False) -> None:
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self._argv: dict[str, list[str]] = {}
        self._said: dict[str, bytes] = {}  # a respawned child's output before its first line
        # `up --quiet`: the nodes log warnings and errors only (LOG_LEVEL_ENV).
        self._env = {LOG_LEVEL_ENV: "WARNING"} if quiet else {}
        if status_line:
            # `up` redraws a status line in place (\r) on this terminal: each
            # node's log line first clears it, so the two never run together.
            self._env[STATUS_LINE_ENV] = "1"

    def spawn(self, name: str, argv: list[str], *, ready: float | None = None) -> None:
        """Start ``zplatform ARGV``; with ``ready`` (seconds), wait for its
        first output line to be ``READY`` (NodeError if it is not, in time)."""
        self._argv[name] = argv
        proc = self._popen(argv, piped=ready is not None)
        self.procs[name] = proc
        if ready is not None:
            assert proc.stdout is not None
            got = select.select([proc.stdout], [], [], ready)[0]
            line = proc.stdout.readline().decode(errors="replace").strip() if got else ""
            if line != "READY":
                raise NodeError(
                    f"{name} did not start (exit code {proc.poll()}; said {line!r})"
                    if got
                    else f"{name} was not ready within {ready:g} s"
                )

    def _popen(self, argv: list[str], *, piped: bool) -> subprocess.Popen[bytes]:
        env = dict(os.environ, PYTHONUNBUFFERED="1", **self._env)
        env[PARENT_ENV] = str(os.getpid())
        env[STOP_PIPE_ENV] = "1"
        # A new session: a Ctrl-C in the terminal reaches `up` alone, which
        # then stops the nodes in order (CN first, so the ground logs the end).
        # stdin: a pipe `up` closes to stop the node (and the kernel closes if
        # `up` dies), beside SIGTERM.
        return subprocess.Popen(
            [sys.executable, "-m", "zplatform", *argv],
            env=env,
            start_new_session=True,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE if piped else None,
        )

    def respawn(self, name: str) -> None:
        """Start the dead child ``name`` again with the arguments it was
        spawned with, not waiting for it (:meth:`said_ready` tells). The dead
        process's pipes are closed; OSError when it cannot start (the dead
        one is kept). Called while ``up`` holds its zenoh
        session: ``subprocess`` forks and execs at once (vfork on Linux),
        which is safe there; a bare ``os.fork`` is not
        (docs/architecture.md#zenoh)."""
        proc = self._popen(self._argv[name], piped=True)  # OSError: the dead one stays
        old, self.procs[name] = self.procs[name], proc
        for pipe in (old.stdin, old.stdout):
            if pipe is not None:
                pipe.close()
        self._said[name] = b""

    def said_ready(self, name: str) -> bool | None:
        """Whether the respawned child ``name``'s first output line was
        ``READY``: None while no whole line has come, False for another line
        or its output's end. Never blocks (reads what its pipe holds)."""
        out = self.procs[name].stdout
        if out is None or name not in self._said:
            return None
        fd = out.fileno()
        if not select.select([fd], [], [], 0)[0]:
            return None
        chunk = os.read(fd, 256)
        said = self._said[name] + chunk
        if not chunk or len(said) > 256:  # its output ended, or a line no READY is
            return False
        if b"\n" not in said:
            self._said[name] = said
            return None
        del self._said[name]
        return said.split(b"\n", 1)[0].strip() == b"READY"

    def kill(self, name: str) -> bool:
        """SIGKILL the child ``name`` (one that never came up), reaped by
        :meth:`dead`; False when it had ended already."""
        p = self.procs[name]
        if p.poll() is not None:
            return False
        p.kill()
        return True

    def dead(self) -> list[tuple[str, int]]:
        return [(n, p.returncode) for n, p in self.procs.items() if p.poll() is not None]

    def stop(self, names: list[str], timeout_s: float = STOP_GRACE_S) -> dict[str, int]:
        """SIGTERM the children ``names`` (and close their stdin), then wait
        for each (:meth:`_wait`); their exit codes."""
        self._signal(names)
        return self._wait(names, timeout_s)

    def _signal(self, names: list[str]) -> None:
        for n in names:
            p = self.procs.get(n)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
                if p.stdin is not None:
                    p.stdin.close()

    def _wait(self, names: list[str], timeout_s: float = STOP_GRACE_S) -> dict[str, int]:
        """Wait for each signalled child of ``names``: past ``STOP_SLOW_S`` it
        is called slow, past ``timeout_s`` its threads are dumped and it is
        killed."""
        codes: dict[str, int] = {}
        for n in names:
            p = self.procs.get(n)
            if p is None:
                continue
            try:
                codes[n] = p.wait(timeout=STOP_SLOW_S)
                continue
            except subprocess.TimeoutExpired:
                print(f"zplatform up: {n} is slow to stop ({STOP_SLOW_S:g} s)...", file=sys.stderr)
            try:
                codes[n] = p.wait(timeout=max(0.0, timeout_s - STOP_SLOW_S))
            except subprocess.TimeoutExpired:
                # Say where it is stuck before the kill: a node dumps its
                # threads' stacks to its stderr on SIGUSR2 (zplatform node).
                print(
                    f"zplatform up: {n} did not stop within {timeout_s:g} s of SIGTERM; "
                    "its threads follow, then SIGKILL",
                    file=sys.stderr,
                )
                p.send_signal(signal.SIGUSR2)
                try:
                    codes[n] = p.wait(timeout=1.0)  # the dump's time, or a late exit
                except subprocess.TimeoutExpired:
                    p.kill()
                    codes[n] = p.wait()
        return codes

    def stop_all(self) -> dict[str, int]:
        """Stop the CN first and wait for it: its last loop is flagged final
        (``dnX_final``), so the DNs, still running, see the run end rather
        than a lost CN, and the ground logs the end. Then the DNs and the
        ground at once; the vehicle world once the device nodes have
        stopped (they safe their outputs into it as they stop), while the
        ground may still be writing its archive."""
        cns = [n for n in self.procs if n in CONTROL_NODES]  # with a standby, both at once
        codes = self.stop(cns)
        rest = [n for n in self.procs if n not in (*cns, "world")]
        self._signal(rest)
        dns = [n for n in rest if n != "gn" and not n.startswith((ROUTER_PREFIX, STATION_PREFIX))]
        codes.update(self._wait(dns))
        world = [n for n in self.procs if n == "world"]
        self._signal(world)
        codes.update(self._wait([n for n in rest if n not in dns] + world))
        return codes


CONTROL_NODES = ("cn", STANDBY)
ROUTER_PREFIX = "router:"
"""The name ``up`` gives a router's process (``router:pad``)."""
STATION_PREFIX = "station:"
"""The name ``up`` gives a station's process (``station:pad``)."""
STATION_RESTART_S = 1.0
"""How long after a station's death ``up`` restarts it; each rapid death in
a row (:data:`STATION_RAPID_S`) doubles it, up to :data:`STATION_RESTART_MAX_S`."""
STATION_RESTART_MAX_S = 30.0
STATION_RAPID_S = 60.0
"""A station that dies sooner than this after it said ``READY`` (or before
it said it) died rapidly."""
STATION_RAPID_DEATHS = 5
"""Rapid deaths in a row after which ``up`` restarts a station no more (a
crash loop, which restarting does not mend); the status line says so."""


@dataclass
class _Station:
    """One station's restart record (:class:`StationRestarts`)."""

    up_since: float | None
    """When its running process said READY; None while it has not."""
    started: float = 0.0
    """When its running process was (re)started."""
    rapid: int = 0
    """Rapid deaths in a row."""
    restarts: int = 0
    code: int | None = None
    """Its last death's exit code."""
    due: float | None = None
    """When its pending restart is due; None when none is pending."""
    gave_up: bool = False
    killed: bool = False
    """Killed before its READY (its death not seen yet)."""


class StationRestarts:
    """When ``up`` restarts the stations it started, and what their status
    says (sans-IO: the caller gives the time, ``time.monotonic``, and does
    the spawning). A station is not flight-critical: a dead one is restarted
    :data:`STATION_RESTART_S` after its death, twice as late after each
    rapid death in a row (at most :data:`STATION_RESTART_MAX_S`), and no more
    after :data:`STATION_RAPID_DEATHS` of them; one that ran
    :data:`STATION_RAPID_S` since its ``READY`` starts the count again. Not
    thread-safe (the watch loop)."""

    def __init__(self) -> None:
        self._st: dict[str, _Station] = {}

    def ready(self, name: str, now: float) -> None:
        """Station ``name``'s process said ``READY`` at ``now``."""
        st = self._st.setdefault(name, _Station(up_since=now, started=now))
        st.up_since = now

    def died(self, name: str, code: int, now: float) -> float | None:
        """Station ``name`` died (exit ``code``) at ``now``: the seconds until
        its restart, or None when it is restarted no more. One this was
        never told of counts as up long before."""
        st = self._st.setdefault(name, _Station(up_since=-math.inf))
        rapid = st.up_since is None or now - st.up_since < STATION_RAPID_S
        st.rapid = st.rapid + 1 if rapid else 0
        st.code, st.up_since = code, None
        if st.rapid >= STATION_RAPID_DEATHS:
            st.gave_up, st.due = True, None
            return None
        delay = min(STATION_RESTART_MAX_S, STATION_RESTART_S * 2**st.rapid)
        st.due = now + delay
        return delay

    def due(self, now: float) -> list[str]:
        """The stations whose restart is due at ``now``, each once: they
        count as restarted (starting) from now."""
        names = [n for n, st in self._st.items() if st.due is not None and now >= st.due]
        for n in names:
            st = self._st[n]
            st.due, st.started, st.killed = None, now, False
            st.restarts += 1
        return names

    def killed(self, name: str) -> None:
        """Station ``name``, restarted, was killed before its ``READY``: it
        is starting no more (its death, once seen, is a rapid one)."""
        self._st[name].killed = True

    def starting(self) -> list[tuple[str, float]]:
        """The restarted stations not yet ``READY``, with when each started."""
        return [
            (n, st.started)
            for n, st in self._st.items()
            if st.restarts
            and st.up_since is None
            and st.due is None
            and not (st.gave_up or st.killed)
        ]

    def restarts(self, name: str) -> int:
        st = self._st.get(name)
        return st.restarts if st is not None else 0

    def state(self, name: str, code: int | None, now: float) -> str:
        """Station ``name``'s part of the status line (``up``, ``up(2
        restarts)``, ``starting(restart 2)``, ``died(-9; restart 2 in 4
        s)``, ``died(-9; 5 rapid deaths: not restarted)``), its process
        running (``code`` None) or dead with ``code``."""
        st = self._st.get(name)
        if st is not None and st.gave_up:
            return f"died({st.code}; {st.rapid} rapid deaths: not restarted)"
        if st is not None and st.due is not None:
            left = max(0, math.ceil(st.due - now))
            return f"died({st.code}; restart {st.restarts + 1} in {left} s)"
        if code is not None:
            return f"died({code})"
        if st is None or not st.restarts:
            return "up"
        if st.up_since is None:
            return f"starting(restart {st.restarts})"
        return f"up({st.restarts} restart{'s' if st.restarts > 1 else ''})"


class Watch:
    """What :func:`watch` saw: nodes that died, and the CN's last telemetry.
    :meth:`on_event` is the ``on_event`` of the link it watches through."""

    def __init__(self) -> None:
        self.died: dict[str, int] = {}
        self.ok = True
        self.last_cn: CnSummary | None = None
        self.script_done = False
        self.script_done_at: float | None = None
        """When (``time.monotonic``) the ground node said its script was done."""
        self.stations = StationRestarts()
        self.tm_path = "zenoh"
        """The path the ground node's telemetry takes (``iox`` or ``zenoh``),
        by its last ``tm_on_shm`` or ``tm_fallback`` event (zplatform.runtime.tmiox)."""

    def on_event(self, rec: EventRecord) -> None:
        """Note the ground node's ``script_done`` and telemetry path (the
        link's callback: no I/O)."""
        if rec.node != "gn":
            return
        if rec.id == EV.SCRIPT_DONE.name and self.script_done_at is None:
            self.script_done_at = time.monotonic()
        elif rec.id == EV.TM_ON_SHM.name:
            self.tm_path = "iox"
        elif rec.id == EV.TM_FALLBACK.name:
            self.tm_path = "zenoh"


def _cn_from_telemetry(mission: Mission, dv: DataVector, first_t: int) -> CnSummary:
    """The CN's figures as its last telemetry showed them (for a CN that died
    before it could write its summary)."""
    dur = (int(dv.get("cn_time_ns")) - first_t) / 1e9
    return cn_summary(mission, dv, loops=int(dv.get("cn_loop")), duration_s=dur)


def watch(
    mission: Mission,
    children: Children,
    link: GroundLink,
    w: Watch,
    stopping: Callable[[], bool],
    *,
    quiet: bool = False,
    ready_timeout_s: float = 60.0,
    end_after_script: bool = False,
    settle_s: float | None = None,
    on_spawn: Callable[[], None] | None = None,
) -> Watch:
    """Live status until the CN finishes, ``stopping()`` or (with
    ``end_after_script``) the script's end (module doc; ``settle_s``: how
    long after the last verdict, None for the default), through ``link``
    (opened with ``on_event=w.on_event``; the caller closes it, after
    stopping the nodes). Restarts the dead stations
    (:class:`StationRestarts`, ``w.stations``), never waiting for one:
    one not ``READY`` within ``ready_timeout_s`` of its restart is killed,
    a rapid death; ``on_spawn`` is called after each restart. Fills and
    returns ``w``. Blocks."""
    tty = sys.stdout.isatty()
    rate = RateMeter()
    bulk_paths = BulkPaths(mission)
    first_t = 0
    start = time.monotonic()
    try:
        last_print = time.monotonic()
        ready_deadline = time.monotonic() + ready_timeout_s + 30
        while not stopping():
            for n, c in children.dead():
                if n in w.died:
                    continue
                w.died[n] = c
                if (
                    mission.standby is not None
                    and n in mission.control_nodes
                    and not all(cn in w.died for cn in mission.control_nodes)
                ):
                    while link.next(0.0) is not None:
                        pass
                    commander = link.dv.get_name("cn_commander") if link.logic.received else "cn"
                    if n != commander or c != 0:
                        # The standby gone, or the commander lost: the other
                        # control node takes over (zplatform.control.failover).
                        w.ok = w.ok and c == 0
                        what = (
                            "the commander carries on without a standby"
                            if n != commander
                            else "the standby takes over once the device nodes no longer hear it"
                        )
                        print(
                            f"\nzplatform up: control node {n} ended (exit code {c}); {what}",
                            file=sys.stderr,
                        )
                        continue
                if n in mission.control_nodes:
                    # Take what the CN sent before it went: the summary's figures.
                    while link.next(0.0) is not None:
                        pass
                    dv = link.dv
                    if c != 0:
                        w.ok = False
                        state = dv.get_name("cn_state") if link.logic.received else "none"
                        print(
                            f"\nzplatform up: the control node died (exit code {c}): the flight "
                            f"is over; last telemetry: loop {int(dv.get('cn_loop'))}, state "
                            f"{state}",
                            file=sys.stderr,
                        )
                        if link.logic.received:
                            w.last_cn = _cn_from_telemetry(mission, dv, first_t)
                    return w
                w.ok = False
                what = (
                    "the vehicle flies on without the ground link"
                    if n == "gn"
                    else "the simulated vehicle is gone: its boards fail (counted errors)"
                    if n == "world"
                    else "the stations behind it lose the vehicle, which flies on"
                    if n.startswith(ROUTER_PREFIX)
                    else "the vehicle flies on; the station's operator keeps the lock no "
                    "longer than its lease, unless the station is back to renew it"
                    if n.startswith(STATION_PREFIX)
                    else "the control node carries on (DN_LOST and the mission's fault response)"
                )
                if n.startswith(STATION_PREFIX):
                    what += _station_restart(w.stations, n, c, time.monotonic())
                print(f"\nzplatform up: node {n} died (exit code {c}); {what}", file=sys.stderr)
                if n == "gn" and end_after_script and w.script_done_at is None:
                    # The run was to end after the ground node's script, which
                    # now never ends. The vehicle does not depend on the ground:
                    # it flies on (stopping `up` would stop the control node
                    # mid-flight), and the operator is told how the run ends.
                    end_after_script = False
                    print(
                        "zplatform up: the ground node was playing the command script: the "
                        "rest of it is not sent; the vehicle flies on; Ctrl-C ends the run",
                        file=sys.stderr,
                    )
            if not stopping():
                _restart_stations(children, w, ready_timeout_s, on_spawn)
            # Short: the control node's exit (the run's end) is seen this soon.
            got = link.next(0.05)
            if got is not None:
                rate.add_snapshot(link.dv)
                if first_t == 0:
                    first_t = int(link.dv.get("cn_time_ns"))
            elif not link.logic.received and time.monotonic() > ready_deadline:
                print(
                    f"zplatform up: {link.why_no_telemetry(ready_timeout_s + 30)}", file=sys.stderr
                )
                w.ok = False
                return w
            now = time.monotonic()
            done_at = w.script_done_at
            if end_after_script and done_at is not None:
                w.script_done = True
                end = (
                    max(done_at + SETTLE_S, start + MIN_DURATION_S)
                    if settle_s is None
                    else done_at + settle_s
                )
                if now >= end:
                    if not quiet:
                        print(
                            f"\nzplatform up: the script's last verdict came {now - done_at:.0f}"
                            " s ago; stopping",
                            flush=True,
                        )
                    return w
            if not quiet and link.logic.received and now - last_print >= 1.0:
                line = (
                    status_line(mission, link.dv, rate.hz)
                    + sync_paths(mission, link.dv)
                    + bulk_paths.line(link.dv)
                    + telemetry_path(mission, w)
                    + station_states(children, w)
                )
                print(("\r" + line) if tty else line, end="" if tty else "\n", flush=True)
                last_print = now
        return w
    finally:
        if tty and not quiet:
            print()


def _station_restart(restarts: StationRestarts, name: str, code: int, now: float) -> str:
    """Note station ``name``'s death; what ``up`` says of its restart."""
    delay = restarts.died(name, code, now)
    if delay is None:
        return (
            f"; it died {STATION_RAPID_DEATHS} times in a row within {STATION_RAPID_S:g} s of "
            "starting: it is not restarted again"
        )
    return f"; restart {restarts.restarts(name) + 1} in {delay:g} s"


def _restart_stations(
    children: Children, w: Watch, ready_timeout_s: float, on_spawn: Callable[[], None] | None
) -> None:
    """Restart the stations whose time has come, and see whether those
    restarted are ``READY`` (never blocks: a station's start must not hold
    the watch, nor its crash loop the vehicle's nodes, which it never
    touches). One that says something else, or is not ready within
    ``ready_timeout_s``, is killed: its death is a rapid one."""
    now = time.monotonic()
    for n in w.stations.due(now):
        try:
            children.respawn(n)
        except OSError as exc:  # the dead process stays: a death of its own
            what = _station_restart(w.stations, n, w.died.get(n, -1), now)
            print(f"\nzplatform up: {n} could not be restarted ({exc}){what}", file=sys.stderr)
            continue
        w.died.pop(n, None)
        print(f"\nzplatform up: restarting {n} (restart {w.stations.restarts(n)})", file=sys.stderr)
        if on_spawn is not None:
            on_spawn()
    for n, started in w.stations.starting():
        said = children.said_ready(n)
        if said:
            w.stations.ready(n, now)
            print(f"\nzplatform up: {n} is up again", file=sys.stderr)
        elif said is False or now - started > ready_timeout_s:
            w.stations.killed(n)
            if children.kill(n):  # else it ended by itself: its death is reported
                why = "said no READY" if said is False else f"not ready in {ready_timeout_s:g} s"
                print(f"\nzplatform up: {n} {why} after its restart: killed", file=sys.stderr)


def _close_link(link: GroundLink) -> None:
    """Close ``up``'s own session, waiting at most :data:`LINK_CLOSE_S`
    (module doc): the nodes are stopped already, so nothing waits on it."""
    closer = threading.Thread(target=link.close, name="link-close", daemon=True)
    closer.start()
    closer.join(LINK_CLOSE_S)


def merge_summaries(
    mission: Mission,
    paths: dict[str, Path],
    codes: dict[str, int],
    cn_fallback: CnSummary | None = None,
) -> RunSummary:
    """The run's summary from the nodes' summary files (``cn_fallback`` when
    the CN wrote none)."""
    nodes: dict[str, CnSummary | DnSummary | GnSummary | None] = {}
    cns = {n: read_summary(paths[n], CnSummary) for n in mission.control_nodes if n in paths}
    # The run's figures are the last commander's: the highest term, the latest loop.
    last = max(
        (c for c in cns.values() if c is not None and c.commanding),
        key=lambda c: (c.term, c.last_loop),
        default=None,
    )
    cn = last or cns.get("cn") or cn_fallback
    # A takeover: the run is the vehicle's, numbered on across commanders, so
    # its loops are the last commander's last loop, and the account says who
    # commanded when (the last commander alone counted only its own loops).
    took = sorted(
        (c for c in cns.values() if c is not None and c.loops and c.term),
        key=lambda c: (c.term, c.last_loop),
    )
    takeover = None
    if last is not None and any(c.takeovers for c in took):
        takeover = "command changed hands: " + ", then ".join(
            f"{c.node} (term {c.term}, {c.loops} loops)" for c in took
        )
    gn = read_summary(paths["gn"], GnSummary) if "gn" in paths else None
    for name, p in paths.items():
        if name in cns:
            nodes[name] = cns[name]
        elif name == "gn":
            nodes[name] = gn
        else:
            nodes[name] = read_summary(p, DnSummary)
    return RunSummary(
        mission=mission.mission,
        loops=(cn.last_loop if takeover and cn else cn.loops if cn else 0),
        duration_s=cn.duration_s if cn else 0.0,
        rate_hz=cn.rate_hz if cn else 0.0,
        loop_overruns=cn.loop_overruns if cn else None,
        sync_overruns=cn.sync_overruns if cn else None,
        missed=cn.missed if cn else {},
        late=cn.late if cn else {},
        bad_frames=cn.bad_frames if cn else None,
        telemetry_received=gn.telemetry_received if gn else None,
        telemetry_gaps=gn.telemetry_gaps if gn else None,
        events_missed=gn.events_missed if gn else None,
        commands=gn.commands if gn else [],
        errors=cn.errors if cn else None,
        final_state=cn.final_state if cn else None,
        nodes=nodes,
        exit_codes=codes,
        takeover=takeover,
    )


def format_run_summary(s: RunSummary) -> str:
    """The one-line account ``up`` prints at the end."""
    if s.loops == 0:
        return f"{s.mission}: no loop ran (see the messages above)"
    line = (
        f"{s.mission}: {s.loops} loops in {s.duration_s:.2f} s "
        f"({s.rate_hz:.2f} Hz); overruns loop {s.loop_overruns} sync {s.sync_overruns}; "
        f"missed {_per_node(s.missed)}; late {_per_node(s.late)}; telemetry "
        f"{s.telemetry_received} (gaps {s.telemetry_gaps}); errors {s.errors}; final state "
        f"{s.final_state}"
    )
    if s.events_missed:
        line += f"; events missed {s.events_missed} (the ground's events_missed)"
    return f"{line}; {s.takeover}" if s.takeover else line


def sync_paths(mission: Mission, dv: DataVector) -> str:
    """``  sync dn0=shm dn1=zenoh``: the path each DN's last trigger came by
    (``dnX_sync_path``, docs/architecture.md#intra-host); empty for a
    mission whose syncs all go over zenoh (``transport.intra_host``)."""
    if intra_host_mode(mission) == "zenoh":
        return ""
    paths = " ".join(f"{dn}={dv.get_name(f'{dn}_sync_path')}" for dn in mission.device_nodes)
    return f"  sync {paths}"


def telemetry_path(mission: Mission, w: Watch) -> str:
    """``  tm=iox``: the path the ground node's telemetry takes (iceoryx2 on
    the CN's host, else zenoh; :attr:`Watch.tm_path`, from its events);
    empty for a mission whose telemetry stays on zenoh
    (:func:`~zplatform.runtime.tmiox.telemetry_path_wanted`)."""
    if not telemetry_path_wanted(mission):
        return ""
    return f"  tm={w.tm_path}"


def station_states(children: Children, w: Watch) -> str:
    """``  stations pad=up lounge=died(-9; restart 2 in 4 s)``: each station
    process ``up`` started (``ground.stations[].start``), running or dead
    with its exit code, and its restarts (:meth:`StationRestarts.state`);
    empty when it started none."""
    now = time.monotonic()
    states = [
        f"{n[len(STATION_PREFIX) :]}="
        + w.stations.state(n, None if p.poll() is None else p.returncode, now)
        for n, p in children.procs.items()
        if n.startswith(STATION_PREFIX)
    ]
    return f"  stations {' '.join(states)}" if states else ""


#: A bulk reader's counters (``bulk_<ch>_<counter>``, counter_elements) and
#: the path each counts: iceoryx2, zenoh's shared memory, zenoh copied.
BULK_PATHS = (("iox", "iox"), ("shm", "zenoh-shm"), ("copied", "zenoh"))


class BulkPaths:
    """``  bulk frame=iox flat_field=zenoh``: the path each bulk channel's
    samples took to its reader lately (docs/architecture.md#intra-host), from
    the reader's counters in telemetry (``bulk_<ch>_iox``, ``_shm``,
    ``_copied``): the one that grew most between two calls; ``-`` until one
    has grown (no sample yet, or a single snapshot), and the last path seen
    while none grows (a slow channel). Channels whose readers report no
    counters in telemetry (the ground's own) are left out; empty for a
    mission without such a channel. Not thread-safe (the status loop)."""

    def __init__(self, mission: Mission) -> None:
        self._channels = [
            ch.name for ch in mission.bulk if any(counter_region(r) is not None for r in ch.readers)
        ]
        self._last: dict[str, tuple[int, ...]] = {}
        self._path = dict.fromkeys(self._channels, "-")

    def line(self, dv: DataVector) -> str:
        """The status line's part for telemetry snapshot ``dv``."""
        parts = []
        for ch in self._channels:
            try:
                now = tuple(int(dv.get(f"bulk_{ch}_{c}")) for c, _ in BULK_PATHS)
            except DataVectorError:  # a layout without this channel's counters
                continue
            before = self._last.get(ch)
            self._last[ch] = now
            if before is not None:
                # One lower than before: the reader restarted (a u32 at 100 Hz
                # wraps after 497 days), so it counts from zero.
                grew = [a - b if a >= b else a for a, b in zip(now, before, strict=True)]
                if any(grew):
                    self._path[ch] = BULK_PATHS[grew.index(max(grew))][1]
            parts.append(f"{ch}={self._path[ch]}")
        return f"  bulk {' '.join(parts)}" if parts else ""


def _per_node(counts: dict[str, int]) -> str:
    """``dn0 3, dn1 0``: per-node counts in words (``-`` for none)."""
    return ", ".join(f"{n} {c}" for n, c in counts.items()) or "-"


def format_board_lines(s: RunSummary) -> list[str]:
    """One line per device node whose board's link misbehaved over the run
    (timeouts, reconnects, bad frames, late replies, device errors:
    :func:`~zplatform.telemetry.summary.board_trouble`), in node order; ``[]`` when
    every link was clean or no node has one. ``up`` prints them under its
    one-line account."""
    return [
        f"zplatform up: {board_line(name, n.board)}"
        for name, n in s.nodes.items()
        if isinstance(n, DnSummary) and n.board is not None and board_trouble(n.board)
    ]


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def run_up(
    mission: Mission,
    source: str,
    *,
    duration_s: float | None = None,
    log: str | None = None,
    summary: str | None = None,
    free_ports: bool = False,
    commands: str | None = None,
    operator: tuple[str, str] | None = None,
    settle_s: float | None = None,
    realtime: bool = True,
    quiet: bool = False,
    ready_timeout_s: float = 60.0,
    record: str | None = None,
) -> int:
    """Run every node of ``mission`` (loaded from ``source``) until the CN
    finishes (``duration_s``), the script's end (module doc; ``settle_s``
    after its last verdict when given) or Ctrl-C / SIGTERM. Blocks;
    returns the exit code (0: a clean run).

    The caller has refused what a user can get wrong (the mission, the
    script, output paths, busy ports). While it runs the mission is
    registered so ``ps`` lists it and every verb finds it by name; the entry,
    the remapped mission of ``free_ports`` and the scratch folder of the
    nodes' summaries are removed on exit.
    """
    from . import registry

    # Until the nodes run (then _supervise takes SIGTERM over), a SIGTERM ends
    # `up` like Ctrl-C: through the finally below, which unregisters.
    signal.signal(signal.SIGTERM, _interrupt)
    reg = registry.register(mission.mission, source)
    tmp = Path(tempfile.mkdtemp(prefix="zplatform-up-"))
    try:
        path = str(Path(source).resolve())
        if free_ports:
            path = reg.mission_file
            rewrite_endpoints(source, path)
            mission = load_mission(path)
        logs: dict[str, str] = {}
        if log:
            logs["telemetry"] = str(Path(log).resolve())
            logs["events"] = str(events_path(log).resolve())
        reg.update(
            mission_file=path,
            endpoints={n: list(node.listen) for n, node in mission.nodes.items()},
            logs=logs,
        )
        if not quiet:
            where = f" (remapped mission {path})" if free_ports else ""
            print(
                f"zplatform up: running as {reg.name!r}{where}; other verbs take that name "
                f"as MISSION (`zplatform ground {reg.name}`), `zplatform ps` lists it",
                flush=True,
            )
        common = ["--ready-timeout", str(ready_timeout_s)]
        if not realtime:
            common.append("--no-realtime")
        spawn: dict[str, list[str]] = {}
        for dn in mission.device_nodes:
            spawn[dn] = ["node", path, dn, *common]
        if mission.has_ground:
            gn = ["node", path, "gn"]
            if log:
                gn += ["--log", str(Path(log).resolve())]
            if commands:
                gn += ["--commands", str(Path(commands).resolve())]
            if operator is not None:  # who the script commands as (ground:)
                gn += ["--operator", operator[0], "--station", operator[1]]
            spawn["gn"] = gn
        cn = ["node", path, "cn", *common]
        if record:
            cn += ["--record", str(Path(record).resolve())]
        if duration_s is not None:
            cn += ["--duration", str(duration_s)]
        spawn["cn"] = cn
        if mission.standby is not None:  # it follows cn, and takes over if cn dies
            sb = ["node", path, mission.standby, *common]
            if duration_s is not None:
                # The run's end is the vehicle's: after a takeover the standby
                # ends it at the same loop (without it, `up` never ended).
                sb += ["--duration", str(duration_s)]
            if record:  # what it records, once it commands, next to cn's recording
                sb += ["--record", str(Path(record).resolve() / mission.standby)]
            spawn[mission.standby] = sb
        # The vehicle world (zplatform.world.model), when the mission has one: a
        # process of its own that the device nodes' boards reach.
        world = ["world", path, *common[2:]] if mission.world is not None else None
        # The mission's zenoh routers (ground.routers with start: true): before
        # the nodes, each ready once its session is open.
        g = mission.ground
        routers = {
            f"{ROUTER_PREFIX}{r.name}": ["router", path, "--name", r.name]
            for r in (g.routers if g is not None else [])
            if r.start
        }
        # The stations marked `start` (ground.stations): ground processes of
        # their own, after the nodes, each in its own directory.
        stations = {
            f"{STATION_PREFIX}{st.name}": [
                "station",
                path,
                st.name,
                "--dir",
                str(station_dir(mission, st.name)),
                *(["--log"] if log else []),
            ]
            for st in (g.stations if g is not None else [])
            if st.start
        }
        return _supervise(
            mission,
            spawn,
            tmp,
            reg,
            world=world,
            routers=routers,
            stations=stations,
            summary=summary,
            log=log,
            quiet=quiet,
            ready_timeout_s=ready_timeout_s,
            end_after_script=bool(commands) and duration_s is None,
            settle_s=settle_s,
        )
    finally:
        reg.remove()
        shutil.rmtree(tmp, ignore_errors=True)


def _supervise(
    mission: Mission,
    spawn: dict[str, list[str]],
    tmp: Path,
    reg: Any,
    *,
    world: list[str] | None,
    routers: dict[str, list[str]] | None = None,
    stations: dict[str, list[str]] | None = None,
    summary: str | None,
    log: str | None,
    quiet: bool,
    ready_timeout_s: float,
    end_after_script: bool,
    settle_s: float | None = None,
) -> int:
    children = Children(quiet=quiet, status_line=sys.stdout.isatty() and not quiet)
    summaries = {n: tmp / f"{n}.json" for n in spawn}
    stopping = False

    def on_signal(signum: int, frame: Any) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    w = Watch()
    link: GroundLink | None = None
    try:
        # Spawn everything before opening our own zenoh session: never fork
        # a process that holds one. The vehicle world first: the device
        # nodes' boards step it from their first loop.
        if world is not None:
            children.spawn("world", world, ready=ready_timeout_s)
        for name, argv in (routers or {}).items():
            children.spawn(name, argv, ready=ready_timeout_s)
        for name, argv in spawn.items():
            children.spawn(name, [*argv, "--summary", str(summaries[name])])
        for name, argv in (stations or {}).items():
            # Ready once its session is open (it waits for nothing else).
            children.spawn(name, argv, ready=ready_timeout_s)
            w.stations.ready(name, time.monotonic())

        def pids() -> None:  # `ps`'s record of the processes, a restarted station's too
            reg.update(nodes={n: p.pid for n, p in children.procs.items()})

        pids()
        link = GroundLink(mission, keys="mission", on_event=w.on_event)
        watch(
            mission,
            children,
            link,
            w,
            lambda: stopping,
            quiet=quiet,
            ready_timeout_s=ready_timeout_s,
            end_after_script=end_after_script,
            settle_s=settle_s,
            on_spawn=pids,
        )
    finally:
        # The nodes first (CN, DNs and ground, world), then our own session:
        # its close must not eat into a node's time to stop (module doc).
        codes = children.stop_all()
        if link is not None:
            _close_link(link)
    rc = 0 if w.ok else 1
    for name, code in codes.items():
        if code not in (0, -signal.SIGTERM) and name not in w.died:
            print(f"zplatform up: node {name} exited with code {code}", file=sys.stderr)
            rc = 1
    s = merge_summaries(mission, summaries, codes, w.last_cn)
    write_summary(summary, s)
    if not quiet:
        print(format_run_summary(s))
        for line in format_board_lines(s):
            print(line)
        if log:
            print(f"telemetry -> {log}; events -> {events_path(log)}")
    return rc
