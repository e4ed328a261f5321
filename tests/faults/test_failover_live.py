"""The standby control node in whole flights on real processes (issue 21), with the soaks.

The flight mission (``configs/flight.yaml``: ``cn``, its hot standby
``cn_b``, device nodes dn0/dn1, the ground node, the vehicle world) flown
from the pad to the ground as configured (``configs/flight.commands``: ARM,
LAUNCH, a NOOP after landing), with one failover fault on the way. The
lockstep twins of these cases are ``tests/system/test_failover_sim.py``; the
short live cases of the default suite are ``tests/system/test_failover_live.py``.

* **Under ``zplatform up``** (the supervisor, as an operator runs it): kill
  -9 of whichever control node commands on the pad (ARMED), in BOOST (~4 s),
  in COAST (~10 s) and under the drogue (~20 s); SIGSTOP of it for a second
  in COAST; kill -9 of the standby. The node's PID comes from ``zplatform ps
  --json``, as an operator would find it.
* **In network namespaces** (:class:`~tests.faults.netns.NetnsLab`, a mesh:
  one host per node, one link per pair of hosts, so one pair can be cut
  apart): the two control nodes cut from each other while both still reach
  the device nodes; the commander's host cut from everyone for 3 s; the
  killed commander started again on its host.

Every case ends in the configured state (LANDED, through every state of the
flight in order, both chutes fired, no fault), with no device node ever
safed (telemetry, events and their logs), the ground's commands all
ACCEPTED, and, from the device nodes' own flight recorders (tests/terms.py),
no loop driven by two terms, each node's term only rising and only after
its old term left it undriven for the lease.

Each fault is aimed at the node that has the role at that moment (whichever
commands, whichever stands by): on a busy host a commander stalled past the
lease is replaced as a dead one would be, legitimately, so the run may
have changed terms before. What the fault must do is asserted exactly over
the stretch it acts on: after a kill one takeover exactly (no other control
node is left to take it back), after a standby's death not one to the end;
one term in command from a cut of the control nodes' link until the standby
follows again, and from a restart until the restarted node follows.

No failure is excused: the zenoh defects these cases used to be gated on
(eclipse-zenoh/zenoh#2806, a session between the control nodes split after a
stop when both dialed each other; #2517, queries between connected peers
lost while another peer's session closes) are designed out (one dialer per
pair, :func:`zplatform.runtime.transport.dial_ranks`) or recovered from (a query
that a live peer's queryable leaves unanswered, :mod:`zplatform.runtime.queries`),
docs/architecture.md#failover.

Waits are on telemetry, events, process exit or a node's log file; a sleep
only makes a fault last (the stop, the cuts). Each flight takes about 70 s.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.faults.flightwatch import FlightWatch, Snap
from tests.faults.missions import mesh_mission
from tests.faults.netns import NetnsHost, NetnsLab
from tests.integration.harness import CONFIGS, ROOT
from tests.terms import driven_terms, two_term_loops
from tests.waits import wait_until
from zplatform.cli import registry
from zplatform.config import Mission
from zplatform.mission.load import load_mission
from zplatform.recorder import RECORDER_DIR_ENV, RecorderReader
from zplatform.recorder.format import FRAME
from zplatform.security.pki import ensure_mission_pki
from zplatform.telemetry.logs import read_csv

FLIGHT = CONFIGS / "flight.yaml"
COMMANDS = CONFIGS / "flight.commands"
STATES = ["SAFE", "ARMED", "BOOST", "COAST", "DROGUE", "MAIN", "LANDED"]
COMMANDED = ["ARM", "LAUNCH", "NOOP"]  # configs/flight.commands
DNS = ("dn0", "dn1")
FLIGHT_S = 150.0  # hang detector for a whole flight (it lands at about 48 s)

pytestmark = [pytest.mark.slow, pytest.mark.timeout(480)]


REJOIN_LOOPS = 200  # a node stopped past its lease opens its zenoh sessions again first
STALE_LOOPS = 50  # a takeover from a mirror this much older than its loop is from a stale one

_TOOK = re.compile(
    r" (\S+) cn_took_command: \S+ took command in term (\d+) at loop (\d+): (\S+) \(term \d+\) "
    r"(?:silent since loop (\d+)|cut off from the device nodes for \d+ loops);"
    r".* continuing from the mirror of loop (\d+)"
)
_STOOD = re.compile(
    r" (\S+) cn_stood_down: \S+ stands down at loop (\d+): term (\d+) commands \((.*)\); it follows"
)


@dataclass(frozen=True)
class Took:
    node: str
    term: int
    loop: int
    was: str
    silent_since: int | None
    mirror: int
    line: str


@dataclass(frozen=True)
class Stood:
    node: str
    loop: int
    term: int
    why: str
    line: str


def took_lines(text: str) -> list[Took]:
    """Every ``cn_took_command`` a node logged, in order."""
    out = []
    for line in text.splitlines():
        m = _TOOK.search(line)
        if m:
            silent = int(m[5]) if m[5] else None
            out.append(Took(m[1], int(m[2]), int(m[3]), m[4], silent, int(m[6]), line))
    return out


def stood_lines(text: str) -> list[Stood]:
    """Every ``cn_stood_down`` a node logged, in order."""
    out = []
    for line in text.splitlines():
        m = _STOOD.search(line)
        if m:
            out.append(Stood(m[1], int(m[2]), int(m[3]), m[4], line))
    return out


def other(cn: str) -> str:
    return "cn_b" if cn == "cn" else "cn"


def states_of(snaps: list[dict[str, Any]]) -> list[str]:
    out: list[str] = []
    for v in snaps:
        if not out or out[-1] != v["cn_state"]:
            out.append(v["cn_state"])
    return out


def reigns(snaps: list[dict[str, Any]]) -> set[tuple[int, str]]:
    return {(v["cn_term"], v["cn_commander"]) for v in snaps}


def after(snaps: list[dict[str, Any]], pred: Callable[[dict[str, Any]], bool]) -> list[Any]:
    """The snapshots from the first for which ``pred`` holds."""
    for k, v in enumerate(snaps):
        if pred(v):
            return snaps[k:]
    return []


# --------------------------------------------------------------------------- checks
def assert_flown_as_configured(w: FlightWatch, logs: str, csv: Path) -> int:
    """From the ground node's log of the run (``csv``: every snapshot from
    loop 1, the control node waits for the ground before it): LANDED through
    every state in order, both chutes, no fault, no device node safed at any
    time (telemetry, events, the nodes' logs). Returns the loop the flight
    landed in."""
    rows = read_csv(csv)
    assert rows, f"the ground logged nothing in {csv}"
    last = rows[-1]
    history = [t.line.strip()[24:200] for t in took_lines(logs)]
    assert states_of(rows) == STATES, (states_of(rows), history)
    assert (last["drogue_fired"], last["main_fired"]) == ("1", "1"), last["cn_loop"]
    assert last["cn_fault"] == "NONE", (last["cn_loop"], last["cn_fault"])
    lines = [x for x in logs.splitlines() for dn in DNS if f" {dn} dn_safed:" in x]
    assert not lines, (lines, history)
    safed = [r["cn_loop"] for r in rows if "1" in (r["dn0_safed"], r["dn1_safed"])]
    assert not safed, (safed[:5], history)
    assert w.events_of("dn_safed") == [], (w.events_of("dn_safed"), history)
    return int(after(rows, lambda v: v["cn_state"] == "LANDED")[0]["cn_loop"])


def wait_state(w: FlightWatch, state: str, at_loop: int) -> Snap:
    """The first snapshot in ``state`` from loop ``at_loop`` on: where a fault
    begins. RuntimeError (not an assertion about the run) when
    the watcher came too late to see it."""
    w.wait_for(lambda v: True, 60, "the watcher's first snapshot")
    now = w.last()
    if STATES.index(now["cn_state"]) > STATES.index(state):
        raise RuntimeError(f"the watcher joined too late for {state}: {now}")
    return w.wait_for(
        lambda v: v["cn_state"] == state and v["cn_loop"] >= at_loop,
        FLIGHT_S,
        f"{state} from loop {at_loop}",
    )


def assert_one_term_per_loop(
    mission: Mission, root: Path, *, last_term: int, landed: int
) -> dict[int, dict[str, int]]:
    """The device nodes' flight recorders: no loop ran under two terms; on
    each node the term only rises, and only after its old term left it
    undriven for the lease (``lease_loops`` periods: the new term's first
    loop is at least ``lease_loops + 1`` after the old one's last); the
    flight recorded through its landing, its end driven by ``last_term``.
    Returns the terms per loop."""
    driven = driven_terms(mission, root)
    assert driven, "the device nodes recorded nothing"
    assert two_term_loops(driven) == [], two_term_loops(driven)[:5]
    lease = mission.takeover.lease_loops
    for dn in DNS:
        loops = sorted(n for n, by in driven.items() if dn in by)
        changes = [
            (a, driven[a][dn], b, driven[b][dn])
            for a, b in itertools.pairwise(loops)
            if driven[a][dn] != driven[b][dn]
        ]
        assert all(t1 > t0 and b - a >= lease + 1 for a, t0, b, t1 in changes), (dn, changes)
        assert loops[-1] >= landed, (dn, loops[-1], landed)
        assert driven[loops[-1]][dn] == last_term, (dn, driven[loops[-1]][dn], changes)
    return driven


def terms_between(driven: dict[int, dict[str, int]], lo: int, hi: int) -> set[int]:
    """The terms that drove the device nodes in loops ``lo`` to ``hi``."""
    return {t for n, by in driven.items() if lo <= n <= hi for t in by.values()}


def assert_follows(mission: Mission, root: Path, node: str, lo: int, hi: int) -> None:
    """``node`` stood down at loop ``lo``: within :data:`REJOIN_LOOPS` (its
    zenoh sessions may have to open again) and from then to ``hi`` its flight
    recorder holds a frame at least every :data:`STALE_LOOPS` loops (a
    standby records the commander's telemetry from each mirror it takes; a
    commander its own): it followed, ready to take over from a fresh state."""
    loops = sorted(
        rec.loop
        for _, rec in RecorderReader(root / mission.mission / node).records()
        if rec.type == FRAME and lo < rec.loop <= hi
    )
    gaps = [(a, b) for a, b in itertools.pairwise([*loops, hi]) if b - a > STALE_LOOPS]
    if not loops or loops[0] - lo > REJOIN_LOOPS:
        gaps.insert(0, (lo, loops[0] if loops else hi))
    if gaps:
        raise AssertionError(f"{node} took no mirror in loops {gaps} (it stood down at {lo})")


def announced_again(w: FlightWatch, since: float, node: str) -> None:
    """``node`` stood down at ``since``: the commander must see it as its
    standby again (``cn_standby_ready``) once it follows."""
    if not any(v["cn_standby_ready"] for v in w.since(since)):
        raise AssertionError(f"{node} stood down and follows; last telemetry {w.last()}")


def wait_log(
    text: Callable[[], str], pred: Callable[[str], bool], timeout_s: float, what: str
) -> str:
    """Wait until ``pred`` holds on a log the nodes write; the log then."""

    def holds() -> str | None:
        t = text()
        return t if pred(t) else None

    try:
        return wait_until(holds, timeout_s, what)
    except AssertionError:
        msg = f"no {what} in the logs within {timeout_s} s:\n{text()[-3000:]}"
        raise AssertionError(msg) from None


def _commands_accepted(s: dict[str, Any]) -> None:
    got = [(c["command"], c["status"]) for c in s["commands"]]
    assert got == [(c, "ACCEPTED") for c in COMMANDED], got


# --------------------------------------------------------------------------- under `up`
class UpFlight:
    """``zplatform up configs/flight.yaml --free-ports --commands
    configs/flight.commands`` and a watcher on the mission it remapped; the
    nodes' PIDs as ``zplatform ps --json`` lists them."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.out = tmp / "up.out"
        self.summary_path = tmp / "up.json"
        self.csv = tmp / "tm.csv"  # the ground node's log of the run
        with open(self.out, "wb") as f:
            self.proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "zplatform",
                    "up",
                    str(FLIGHT),
                    "--free-ports",
                    "--commands",
                    str(COMMANDS),
                    "--summary",
                    str(self.summary_path),
                    "--log",
                    str(self.csv),
                ],
                stdout=f,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=dict(os.environ, PYTHONUNBUFFERED="1"),
                cwd=ROOT,
                start_new_session=True,
            )
        self.watch: FlightWatch | None = None
        self.pids: dict[str, int] = {}
        self.mission_file = ""
        self.rc: int | None = None
        try:
            # The remapped mission, as soon as `up` wrote it (before the nodes run).
            e = self._entry(lambda e: bool(e.endpoints), "the remapped mission")
            self.mission_file = e.mission_file
            self.mission = load_mission(e.mission_file)
            with open(tmp / "watch.log", "ab") as err:
                self.watch = FlightWatch(
                    subprocess.Popen(
                        [sys.executable, "-m", "tests.faults.flightwatch", e.mission_file],
                        stdin=subprocess.PIPE,
                        stdout=subprocess.PIPE,
                        stderr=err,
                        text=True,
                        cwd=ROOT,
                    )
                )
            self._entry(lambda e: {"cn", "cn_b", *DNS, "gn"} <= set(e.nodes), "the nodes")
            r = subprocess.run(
                [sys.executable, "-m", "zplatform", "ps", "--json"],
                capture_output=True,
                text=True,
                cwd=ROOT,
                timeout=60,
            )
            assert r.returncode == 0, r.stderr
            (mine,) = [x for x in json.loads(r.stdout) if x["pid"] == self.proc.pid]
            self.pids = {n: int(p) for n, p in mine["nodes"].items()}
        except BaseException:
            self.close()
            raise

    def _entry(self, ready: Callable[[registry.Entry], bool], what: str) -> registry.Entry:
        def entry() -> registry.Entry | None:
            if self.proc.poll() is not None:
                raise AssertionError(f"`up` ended before registering {what}")
            return next(
                (e for e in registry.running() if e.pid == self.proc.pid and ready(e)), None
            )

        try:
            return wait_until(entry, 60, f"`up` to register {what}", poll_s=0.05)
        except AssertionError:
            msg = f"`up` did not register {what}:\n{self.output()[-3000:]}"
            raise AssertionError(msg) from None

    @property
    def w(self) -> FlightWatch:
        assert self.watch is not None
        return self.watch

    def output(self) -> str:
        """`up`'s output: every node's log lines (each names its node) and its own."""
        return self.out.read_text(errors="replace")

    def _ours(self, pid: int) -> bool:
        """``pid`` is still a node of this run (not a process that reused the number)."""
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            return False
        return self.mission_file.encode() in cmd

    def signal(self, node: str, sig: int) -> None:
        pid = self.pids[node]
        assert self._ours(pid), f"{node} ({pid}) is not running"
        os.kill(pid, sig)

    def finish(self, timeout_s: float = 120) -> tuple[int, dict[str, Any]]:
        """`up` ends by itself 15 s after the script's last verdict: its exit
        code and run summary."""
        self.rc = self.proc.wait(timeout_s)
        return self.rc, json.loads(self.summary_path.read_text())

    def close(self) -> None:
        for pid in self.pids.values():  # a stopped node ignores SIGTERM
            if self._ours(pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGCONT)
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)  # `up` stops its nodes in order
            try:
                self.proc.wait(90)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for pid in self.pids.values():  # a node that outlived its `up`
            if self._ours(pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
        if self.watch is not None:
            self.watch.close()

    def __enter__(self) -> UpFlight:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@pytest.fixture
def rec_root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Where this test's nodes keep their flight recorders."""
    root = tmp_path / "rec"
    monkeypatch.setenv(RECORDER_DIR_ENV, str(root))
    return root


@pytest.mark.parametrize(
    ("state", "at_loop"),
    [("ARMED", 0), ("BOOST", 400), ("COAST", 1000), ("DROGUE", 2000)],
    ids=["pad-armed", "boost-4s", "coast-10s", "drogue-20s"],
)
def test_the_commander_killed_in_flight_is_replaced_and_the_flight_lands(
    state: str, at_loop: int, tmp_path: Path, rec_root: Path
) -> None:
    """kill -9 of whichever control node commands, in ``state`` at loop
    ``at_loop`` or later: the other takes command in the next term, exactly
    once (no other control node is left to take it back), and flies on to
    LANDED as configured; ``up`` carries on without the dead node, ends the
    run after the script and exits 1 (a node died)."""
    f = UpFlight(tmp_path)
    with f:
        w = f.w
        at = wait_state(w, state, at_loop)
        dead, term = at.v["cn_commander"], at.v["cn_term"]
        new = other(dead)
        f.signal(dead, signal.SIGKILL)
        w.wait_for(lambda v: v["cn_term"] > term, 60, "a new term in command")
        w.wait_for(lambda v: v["cn_state"] == "LANDED", FLIGHT_S, "LANDED")
        rc, s = f.finish()
        out = f.output()
        assert rc == 1, out[-3000:]
        # `up` names the role the node had when it noticed: the other may have taken over.
        assert f"zplatform up: control node {dead} ended (exit code -9); the " in out
        assert s["final_state"] == "LANDED", s
        _commands_accepted(s)
        reign = after(w.since(at.t), lambda v: v["cn_term"] > term)
        assert reigns(reign) == {(term + 1, new)}, reigns(reign)
        took = [t for t in took_lines(out) if t.term > term]
        assert [(t.node, t.term) for t in took] == [(new, term + 1)], took
        assert (s["nodes"][new]["term"], s["nodes"][new]["commanding"]) == (term + 1, True)
        landed = assert_flown_as_configured(w, out, f.csv)
        driven = assert_one_term_per_loop(f.mission, rec_root, last_term=term + 1, landed=landed)
        assert terms_between(driven, at.v["cn_loop"], landed) == {term, term + 1}


def test_the_commander_stopped_for_a_second_in_coast_stands_down_and_the_flight_lands(
    tmp_path: Path, rec_root: Path
) -> None:
    """SIGSTOP of whichever control node commands for 1 s in COAST (and until
    the other one commands), then SIGCONT: the other took command in the next
    term; the continued node, with its old state, stands down before it
    drives anything (no loop of two terms) and follows; the flight lands as
    configured, and no node died (``up`` exits 0). The stood-down node is
    then the standby: the commander must report it ready."""
    f = UpFlight(tmp_path)
    with f:
        w = f.w
        at = wait_state(w, "COAST", 1000)
        stopped, term = at.v["cn_commander"], at.v["cn_term"]
        new = other(stopped)
        before = len([x for x in stood_lines(f.output()) if x.node == stopped])
        t0 = time.monotonic()
        f.signal(stopped, signal.SIGSTOP)
        try:
            w.wait_for(lambda v: v["cn_term"] > term, 60, "the other control node in command")
            time.sleep(max(0.0, 1.0 - (time.monotonic() - t0)))  # stimulus: the stop lasts 1 s
        finally:
            f.signal(stopped, signal.SIGCONT)
        # Its stand-down is in its log (its event may be lost: it runs before its
        # zenoh sessions, closed while it was stopped, are open again).
        text = wait_log(
            f.output,
            lambda t: len([x for x in stood_lines(t) if x.node == stopped]) > before,
            60,
            f"{stopped} standing down",
        )
        t_down = time.monotonic()
        down = [x for x in stood_lines(text) if x.node == stopped][before]
        w.wait_for(lambda v: v["cn_state"] == "LANDED", FLIGHT_S, "LANDED")
        rc, s = f.finish()
        out = f.output()
        assert rc == 0, out[-3000:]
        assert down.term == term + 1, down
        assert s["final_state"] == "LANDED", s
        _commands_accepted(s)
        # From the takeover until the stopped node stood down: the new term alone.
        reign = after(w.since(at.t, t_down), lambda v: v["cn_term"] > term)
        assert reigns(reign) == {(term + 1, new)}, reigns(reign)
        took = [t for t in took_lines(out) if t.term == term + 1]
        assert [t.node for t in took] == [new], took
        landed = assert_flown_as_configured(w, out, f.csv)
        driven = assert_one_term_per_loop(
            f.mission, rec_root, last_term=w.last()["cn_term"], landed=landed
        )
        assert {term, term + 1} <= terms_between(driven, at.v["cn_loop"], landed)
        assert_follows(f.mission, rec_root, stopped, down.loop, landed)
        announced_again(w, t_down, stopped)


def test_the_standby_killed_in_flight_changes_nothing(tmp_path: Path, rec_root: Path) -> None:
    """kill -9 of the standby (whichever control node does not command) in
    COAST: the commander notices (its ``cn_standby_ready`` goes false) and
    carries on in its term, which nothing changes to the end; the flight
    lands as configured; ``up`` says so, ends the run after the script and
    exits 1 (a node died)."""
    f = UpFlight(tmp_path)
    with f:
        w = f.w
        at = wait_state(w, "COAST", 800)
        commander, term = at.v["cn_commander"], at.v["cn_term"]
        dead = other(commander)
        changes = len(took_lines(f.output())) + len(stood_lines(f.output()))
        t0 = time.monotonic()
        f.signal(dead, signal.SIGKILL)
        gone = w.wait_for(lambda v: not v["cn_standby_ready"], 30, "no standby")
        w.wait_for(lambda v: v["cn_state"] == "LANDED", FLIGHT_S, "LANDED")
        rc, s = f.finish()
        out = f.output()
        assert rc == 1, out[-3000:]
        assert f"control node {dead} ended (exit code -9); the commander carries on" in out
        assert s["final_state"] == "LANDED", s
        _commands_accepted(s)
        assert reigns(w.since(t0)) == {(term, commander)}, reigns(w.since(t0))
        assert not any(v["cn_standby_ready"] for v in w.since(gone.t))
        assert len(took_lines(out)) + len(stood_lines(out)) == changes, out[-3000:]
        landed = assert_flown_as_configured(w, out, f.csv)
        driven = assert_one_term_per_loop(f.mission, rec_root, last_term=term, landed=landed)
        assert terms_between(driven, at.v["cn_loop"], landed) == {term}


# --------------------------------------------------------------------------- namespaces
NAMES = ("cn", "cn_b", "dn0", "dn1", "gn")
CUT_S = 3.0  # past zenoh's 1 s lease: the sessions across the cut close and must reopen


def _readline(p: subprocess.Popen[Any], timeout_s: float) -> str:
    assert p.stdout is not None
    ready, _, _ = select.select([p.stdout], [], [], timeout_s)
    if not ready:
        raise AssertionError(f"no output from {p.args!r} within {timeout_s} s")
    return str(p.stdout.readline()).strip()


class MeshFlight:
    """The flight mission with each node on a host of its own (a 5-host mesh:
    cn, cn_b, dn0, dn1, gn). The vehicle world runs on dn0's host; dn1's
    board reaches it through :mod:`tests.faults.worldlink` (loopback to
    loopback, never over a veth: a cut never takes a node's physics away).
    The ground node flies the script; a watcher on its host reads telemetry
    and events as the ground receives them."""

    def __init__(self, tmp: Path, hosts: list[NetnsHost]) -> None:
        self.tmp = tmp
        self.lab: NetnsLab = hosts[0].lab
        self.hosts = dict(zip(NAMES, hosts, strict=True))
        self.path = mesh_mission(FLIGHT, tmp / "flight.yaml", self.hosts)
        self.mission = load_mission(self.path)
        if self.mission.mtls:
            ensure_mission_pki(self.mission)
        self.procs: dict[str, subprocess.Popen[Any]] = {}
        self.runs: dict[str, int] = {}
        self.watch: FlightWatch | None = None
        self.relay: subprocess.Popen[Any] | None = None
        self.csv = tmp / "gn.csv"  # the ground node's log of the run

    def index(self, node: str) -> int:
        return self.hosts[node].index

    def log_path(self, node: str) -> Path:
        k = self.runs.get(node, 1)
        return self.tmp / (f"{node}.log" if k == 1 else f"{node}-{k}.log")

    def log(self, node: str) -> str:
        """Every run's log of ``node``."""
        return "".join(
            p.read_text(errors="replace")
            for p in sorted(self.tmp.glob(f"{node}*.log"))
            if p.stem == node or p.stem.startswith(f"{node}-")
        )

    def spawn(self, node: str, *extra: str) -> subprocess.Popen[Any]:
        """Start ``node`` on its host (again: a new log, ``node-2.log``)."""
        self.runs[node] = self.runs.get(node, 0) + 1
        cmd = [sys.executable, "-m", "zplatform", "node", str(self.path), node, *extra]
        p = self.hosts[node].popen(cmd, log=self.log_path(node), cwd=ROOT)
        self.procs[node] = p
        return p

    def start(self) -> None:
        world = self.mission.world
        assert world is not None
        dn0, dn1 = self.hosts["dn0"], self.hosts["dn1"]
        w = dn0.popen(
            [sys.executable, "-m", "zplatform", "world", str(self.path)],
            log=self.tmp / "world.log",
            cwd=ROOT,
        )
        self.procs["world"] = w

        def ready() -> bool:
            assert w.poll() is None, "the world did not start"
            return "READY" in (self.tmp / "world.log").read_text(errors="replace")

        wait_until(ready, 60, "the world's READY", poll_s=0.05)
        port = world.listen.rpartition(":")[2]
        self.relay = dn1.popen(
            [sys.executable, "-m", "tests.faults.worldlink", port, dn0.ns],
            log=self.tmp / "worldlink.log",
            pipe_stdio=True,
            cwd=ROOT,
        )
        assert _readline(self.relay, 30) == "ready"
        for dn in DNS:
            self.spawn(dn, "--summary", str(self.tmp / f"{dn}.json"))
        self.spawn(
            "gn",
            "--commands",
            str(COMMANDS),
            "--log",
            str(self.csv),
            "--summary",
            str(self.tmp / "gn.json"),
        )
        self.watch = FlightWatch(
            self.hosts["gn"].popen(
                [sys.executable, "-m", "tests.faults.flightwatch", str(self.path)],
                log=self.tmp / "watch.log",
                pipe_stdio=True,
                cwd=ROOT,
            )
        )
        self.spawn("cn")  # waits for the device nodes and the ground
        self.spawn("cn_b")

    @property
    def w(self) -> FlightWatch:
        assert self.watch is not None
        return self.watch

    def landed(self) -> None:
        """Wait for LANDED and the verdict of the script's last command."""
        self.w.wait_for(lambda v: v["cn_state"] == "LANDED", FLIGHT_S, "LANDED")
        deadline = time.monotonic() + 60
        while not [t for t in self.w.events_of("cmd_accepted") if "NOOP" in t]:
            assert time.monotonic() < deadline, self.w.events[-10:]
            self.w.wait_for(lambda v: True, 30, "telemetry")

    def stop(self) -> dict[str, Any]:
        """Stop as ``up`` does: the control nodes first (the run's final loop),
        then the device nodes and the ground, the world last; the ground's
        summary."""
        for group in (("cn", "cn_b"), (*DNS, "gn"), ("world",)):
            live = [self.procs[n] for n in group if n in self.procs]
            for p in live:
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            for p in live:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(60)
        return dict(json.loads((self.tmp / "gn.json").read_text()))

    def close(self) -> None:
        if self.watch is not None:
            self.watch.close()
        if self.relay is not None and self.relay.stdin is not None:
            with contextlib.suppress(OSError):
                self.relay.stdin.close()
        # The lab kills whatever is left and removes the namespaces.

    def logs(self) -> str:
        """Every node's logs, each line naming its node."""
        return "".join(self.log(n) for n in NAMES)


@pytest.fixture
def mesh(
    netns_hosts: Callable[..., list[NetnsHost]], tmp_path: Path, rec_root: Path
) -> Iterator[MeshFlight]:
    f = MeshFlight(tmp_path, netns_hosts(len(NAMES), "mesh"))
    try:
        f.start()
        yield f
    finally:
        f.close()


def _in_coast(f: MeshFlight) -> Snap:
    """COAST, 8 s into the flight: where each namespace case begins."""
    return wait_state(f.w, "COAST", 800)


def test_control_nodes_cut_from_each_other_change_nothing(mesh: MeshFlight, rec_root: Path) -> None:
    """The link between the two control nodes' hosts cut for 3 s in COAST,
    both still reaching both device nodes: the standby hears no mirror and
    asks the device nodes, which still run the commander's triggers and
    refuse it (``cn_takeover_held``). No takeover: one term in command from
    the cut until a second after the link is back, and the flight lands as
    configured."""
    f, w = mesh, mesh.w
    at = _in_coast(f)
    commander, term = at.v["cn_commander"], at.v["cn_term"]
    standby = other(commander)
    held0 = f.log(standby).count(f" {standby} cn_takeover_held:")
    changes = len(took_lines(f.logs())) + len(stood_lines(f.logs()))
    t0 = time.monotonic()
    f.lab.set_pair(f.index("cn"), f.index("cn_b"), up=False)
    try:
        wait_log(
            lambda: f.log(standby),
            lambda t: t.count(f" {standby} cn_takeover_held:") > held0,
            30,
            f"{standby} holding its takeover",
        )
        time.sleep(max(0.0, CUT_S - (time.monotonic() - t0)))  # stimulus: the cut lasts CUT_S
    finally:
        f.lab.set_pair(f.index("cn"), f.index("cn_b"), up=True)
    healed = w.last()["cn_loop"]
    end = w.wait_for(lambda v: v["cn_loop"] >= healed + 100, 30, "a second more")
    window = w.since(t0, end.t)
    changed = len(took_lines(f.logs())) + len(stood_lines(f.logs())) - changes
    f.landed()
    gn = f.stop()
    _commands_accepted(gn)
    assert reigns(window) == {(term, commander)}, reigns(window)
    assert changed == 0, took_lines(f.logs())[-3:]
    landed = assert_flown_as_configured(w, f.logs(), f.csv)
    driven = assert_one_term_per_loop(
        f.mission, rec_root, last_term=w.last()["cn_term"], landed=landed
    )
    assert terms_between(driven, window[0]["cn_loop"], window[-1]["cn_loop"]) == {term}


def test_the_commander_cut_from_everyone_is_replaced_and_stands_down_when_it_heals(
    mesh: MeshFlight, rec_root: Path
) -> None:
    """The commander's host cut from every other (its links down) for 3 s in
    COAST: the device nodes and the standby no longer hear it; the standby
    takes command in the next term. The cut-off node flies on alone, driving
    nothing; when its links come back it learns of the new term and stands
    down. The flight lands as configured. The stood-down node is then the
    standby: the commander must report it ready."""
    f, w = mesh, mesh.w
    at = _in_coast(f)
    cut, term = at.v["cn_commander"], at.v["cn_term"]
    new = other(cut)
    before = len([x for x in stood_lines(f.log(cut)) if x.node == cut])
    t0 = time.monotonic()
    f.hosts[cut].link_down()
    try:
        w.wait_for(lambda v: (v["cn_term"], v["cn_commander"]) == (term + 1, new), 30, "a new term")
        time.sleep(max(0.0, CUT_S - (time.monotonic() - t0)))  # stimulus: the cut lasts CUT_S
    finally:
        f.hosts[cut].link_up()
    text = wait_log(
        lambda: f.log(cut),
        lambda t: len([x for x in stood_lines(t) if x.node == cut]) > before,
        60,
        f"{cut} standing down",
    )
    t_down = time.monotonic()
    down = [x for x in stood_lines(text) if x.node == cut][before]
    f.landed()
    gn = f.stop()
    _commands_accepted(gn)
    assert down.term == term + 1, down
    reign = after(w.since(at.t, t_down), lambda v: v["cn_term"] > term)
    assert reigns(reign) == {(term + 1, new)}, reigns(reign)
    took = [t for t in took_lines(f.logs()) if t.term == term + 1]
    assert [t.node for t in took] == [new], took
    landed = assert_flown_as_configured(w, f.logs(), f.csv)
    driven = assert_one_term_per_loop(
        f.mission, rec_root, last_term=w.last()["cn_term"], landed=landed
    )
    assert {term, term + 1} <= terms_between(driven, at.v["cn_loop"], landed)
    assert_follows(f.mission, rec_root, cut, down.loop, landed)
    announced_again(w, t_down, cut)


def test_the_killed_commander_restarted_rejoins_as_the_standby(
    mesh: MeshFlight, rec_root: Path
) -> None:
    """kill -9 of the commander in COAST, the other takes command in the next
    term; the killed node started again on its host finds the run going on
    (its probe: the device nodes run the new term) and follows as the
    standby: the commander reports it ready again, and the term stays until
    a second after it follows; the flight lands as configured."""
    f, w = mesh, mesh.w
    at = _in_coast(f)
    dead, term = at.v["cn_commander"], at.v["cn_term"]
    new = other(dead)
    p = f.procs[dead]
    p.kill()
    p.wait()
    w.wait_for(lambda v: (v["cn_term"], v["cn_commander"]) == (term + 1, new), 30, "a new term")
    gone = w.wait_for(lambda v: not v["cn_standby_ready"], 30, "no standby")
    f.spawn(dead)
    back = w.wait_for(lambda v: bool(v["cn_standby_ready"]), 90, f"{dead} following")
    wait_log(lambda: f.log(dead), lambda t: f"{dead} follows as the standby" in t, 30, "following")
    until = w.wait_for(lambda v: v["cn_loop"] >= back.v["cn_loop"] + 100, 30, "a second more")
    f.landed()
    gn = f.stop()
    _commands_accepted(gn)
    window = w.since(gone.t, until.t)
    assert reigns(window) == {(term + 1, new)}, reigns(window)
    assert all(v["cn_standby_ready"] for v in w.since(back.t, until.t))
    landed = assert_flown_as_configured(w, f.logs(), f.csv)
    driven = assert_one_term_per_loop(
        f.mission, rec_root, last_term=w.last()["cn_term"], landed=landed
    )
    assert terms_between(driven, gone.v["cn_loop"], until.v["cn_loop"]) == {term + 1}


def test_the_standby_stopped_for_a_second_gets_the_mirrors_again(
    mesh: MeshFlight, rec_root: Path
) -> None:
    """SIGSTOP of the standby for a second in COAST (until the commander sees
    it gone: its lease ran out and the session between the two closed), then
    SIGCONT: the case of eclipse-zenoh/zenoh#2806 while both control nodes
    dialed each other. With one dialer per pair
    (:func:`zplatform.runtime.transport.dial_ranks`: cn_b dials cn, never cn cn_b)
    the session opens again one way, and the standby takes the commander's
    mirrors again (its flight recorder, to the landing, with no gap longer
    than :data:`STALE_LOOPS`), the commander reports it ready again, and
    nothing changes who commands."""
    f, w = mesh, mesh.w
    at = _in_coast(f)
    commander, term = at.v["cn_commander"], at.v["cn_term"]
    standby = other(commander)
    changes = len(took_lines(f.logs())) + len(stood_lines(f.logs()))
    p = f.procs[standby]
    t0 = time.monotonic()
    p.send_signal(signal.SIGSTOP)
    try:
        gone = w.wait_for(lambda v: not v["cn_standby_ready"], 30, f"{standby} not ready")
        time.sleep(max(0.0, 1.0 - (time.monotonic() - t0)))  # stimulus: the stop lasts a second
    finally:
        p.send_signal(signal.SIGCONT)
    back = w.wait_for(lambda v: bool(v["cn_standby_ready"]), 60, f"{standby} ready again")
    f.landed()
    gn = f.stop()
    _commands_accepted(gn)
    assert reigns(w.since(t0)) == {(term, commander)}, reigns(w.since(t0))
    changed = len(took_lines(f.logs())) + len(stood_lines(f.logs())) - changes
    assert changed == 0, took_lines(f.logs())[-3:]
    flying = [v for v in w.since(back.t) if v["cn_state"] != "LANDED"]
    assert all(v["cn_standby_ready"] for v in flying), "ready again, then not"
    landed = assert_flown_as_configured(w, f.logs(), f.csv)
    assert_one_term_per_loop(f.mission, rec_root, last_term=term, landed=landed)
    assert_follows(f.mission, rec_root, standby, gone.v["cn_loop"], landed)
