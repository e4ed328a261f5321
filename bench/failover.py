"""Failover: loops from a fault of the commanding control node to the new term's first loop.

The flight mission (``configs/flight.yaml``: ``cn``, its hot standby
``cn_b``, ``dn0``, ``dn1`` and the vehicle world, copied onto free loopback
ports as the test harness does, ``tests/integration/harness.py``) runs as
node processes, each as configured (SCHED_FIFO 20 when run as root, else
ordinary); the benchmark faults whichever control node commands and watches
the commander's telemetry (``{vehicle}/cn/telemetry``) and every node's
events with a :class:`~zplatform.ground.link.GroundLink`. Cases (one variant
each, one run of the mission each):

* ``kill9``: the vehicle on the pad in SAFE; kill -9 of the commander, then
  the killed node is started again and rejoins as the standby (the wait ends
  when the new commander's telemetry says ``cn_standby_ready``), then the new
  commander is killed, alternating, 20 times (``--kills``; ``--quick``: 2);
* ``sigstop``: SIGSTOP of the commander for 1 s (``--stop-s``) then SIGCONT:
  the standby takes over while it is stopped; continued, it stands down (the
  wait ends on its ``cn_stood_down`` event or, as events are best effort,
  the line its log gets for it; then on ``cn_standby_ready`` or, when that
  does not come, 100 loops of the new term), 20 times;
* ``kill9_flight`` (not with ``--quick``): one flight (``zplatform cmd
  launch --arm`` on the pad), the commander killed in COAST at a random
  phase, restarted (it rejoins in flight as the standby); the flight's end:
  final state (LANDED expected) and whether both chutes fired
  (``drogue_fired``, ``main_fired``).

Each fault is injected at a uniformly random phase of a loop (``--seed``):
the bench reads the schedule's origin from the latest snapshot,
``cn_time_ns - (cn_loop - 1) * period`` (node clocks are anchored to
CLOCK_REALTIME, ``zplatform/runtime/timebase.py``), and sends the signal at
``origin + (n - 1 + u) * period`` for the loop n two after that snapshot, u
uniform in [0, 1). Per takeover it measures:

* ``loops``: from the fault's loop (the commander's schedule at the
  ``time.time_ns()`` of the signal: ``(t - origin) // period + 1``) to the
  first loop of the new term (``cn_term_loop`` in the new term's telemetry);
  ``ms``: the fault to that loop's scheduled start; ``tm_seen_ms``: the fault
  to the bench's receipt of the new term's first snapshot;
* ``dn_untriggered``: per device node, loops in which it ran no trigger
  between the last loop it ran under the old term and the first it ran under
  the new one, read after the run from the device nodes' flight recorders
  (``tests/terms.py``: each records the reply frame, with ``dnX_term_seen``,
  of every loop it runs); the first loop a device node ran under the new
  term there too (``dn_first_loop``), and ``first_trigger_loops``, from the
  fault's loop to it: the issue's "first trigger of the new term", one loop
  more than ``loops`` when the term's first loop (``cn_term_loop``) never
  ran;
* the device nodes' safings: ``dn_safed`` events (a watchdog or a fault
  safing; not ``dn_safed_run_ended``/``dn_safed_at_exit``) in the device
  nodes' flight recorders, stamped before the bench began to stop the
  nodes; and, as a cross-check, snapshots turning ``dnX_safed`` on;
* two-term loops: loops that the device nodes ran under more than one term
  (``tests/terms.py``), over the whole run.

Per case (``variants[case]``), over the bench's faults: ``faults``;
``takeovers`` (every change of ``cn_term`` the telemetry showed) and
``spurious_takeovers`` (those no fault of the bench caused: a commander the
box starved for ``takeover_loops`` periods, listed in ``spurious`` with
their ``dn_untriggered``; ``spurious_dn_untriggered_max``);
``takeover_loops_p50/max/min``, ``first_trigger_loops_p50/max``,
``term_loop_not_run`` (takeovers whose ``cn_term_loop`` no device node ran),
``takeover_ms_p50/max``, ``tm_seen_ms_p50/max``; ``dn_untriggered_p50/max``; ``dn_safed_events``
(all of the run's, listed in ``dn_safed``), ``dn_safed_after_faults`` (those
between a fault's loop and ``dn_watchdog_loops`` after its new term's first
loop), ``dn_safed_in_telemetry``; ``two_term_loops``; ``rejoin_s_p50/max``
(kill9: the restart to ``cn_standby_ready``; sigstop: SIGCONT to the node
standing down); ``standby_ready_again`` (faults after which the commander's
``cn_standby_ready`` came back); ``stood_down_events_seen`` (sigstop: stand-downs
whose ``cn_stood_down`` event reached the bench); ``tm_lag_min_ms`` (the least
receipt time minus ``cn_time_ns``: the bench's clock against the nodes');
``final_state``/``expected_state``/``final_as_configured`` (the flight also
``drogue_fired``, ``main_fired``); the verdicts ``met_p50`` (p50 at most
``TARGET_P50_LOOPS``), ``met_max`` (max below ``faults.dn_watchdog_loops``),
the same on ``first_trigger_loops`` (``met_p50_first_trigger``,
``met_max_first_trigger``), ``met_no_safings``, ``met_no_two_term_loops``; and ``each``: every
takeover's figures (with ``phase``, where in its loop the fault fell).
``params`` has the provenance (run time, the commit, the command, load
average before, during and after, scheduling) and the targets (issue 21):
takeover within 5 loops (50 ms) at p50 and below the device nodes' watchdog
(10 loops) always; no actuator safing; no loop driven by two terms; the
final state as configured.

Takes about 3 minutes (``--quick``: kill9 and sigstop with 2 faults each,
about 20 s). Run ``python -m bench.failover [--quick] [--case NAME]
[--kills N] [--keep DIR] [--json PATH]``; results go to
``bench/results/failover.json`` (``--keep DIR``: each case's node logs and
flight recorders stay in ``DIR/<case>``). Run it alone (``flock
/tmp/zplatform-bench.lock``): a busy box starves the nodes, and the
spurious takeovers and safings show it.
"""

from __future__ import annotations

import importlib
import os
import random
import secrets
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from bench.common import REPO_ROOT, bench_argparser, write_result
from zplatform.config import Mission
from zplatform.core.datavector import DataVector
from zplatform.core.events import decode_event
from zplatform.errors import FrameFormatError, RecordingError
from zplatform.ground.link import GroundLink
from zplatform.recorder import RECORDER_DIR_ENV, RecorderReader
from zplatform.recorder.format import EVENT
from zplatform.telemetry.records import EventRecord

MISSION = REPO_ROOT / "configs" / "flight.yaml"
NODES = ("world", "dn0", "dn1", "cn", "cn_b")
CASES = ("kill9", "sigstop", "kill9_flight")
TARGET_P50_LOOPS = 5
STOP_S = 1.0
SETTLE_LOOPS = 100
"""After a stand-down, loops of the new term to wait when ``cn_standby_ready``
does not come back (module doc)."""
TIMEOUT_S = 60.0
"""Every wait's hang detector: generous, never a speed limit."""
STOOD_DOWN = " stands down: "
"""What a control node's log says when it stands down (zplatform.node.control)."""
SAFINGS = ("dn_safed",)
"""Event ids that count as an actuator safing (a lost control node or a fault)."""


# ----------------------------------------------------------------------------- set-up


@contextmanager
def bench_environment(tmp: Path) -> Iterator[None]:
    """The node processes' environment, as tests/conftest.py makes it: a mission
    key, and the configuration (the mission's PKI), parameter, runtime and
    flight-recorder directories under ``tmp``; restored on exit."""
    saved = dict(os.environ)
    try:
        os.environ.setdefault("ZPLATFORM_KEY", secrets.token_hex(32))
        for k in ("ZPLATFORM_KEY_FILE", "ZPLATFORM_DEPLOYMENT"):
            os.environ.pop(k, None)
        for env, sub in (
            ("XDG_CONFIG_HOME", "config"),
            ("ZPLATFORM_PARAMS_DIR", "params"),
            ("ZPLATFORM_RUNTIME_DIR", "run"),
            (RECORDER_DIR_ENV, "rec"),
        ):
            (tmp / sub).mkdir(parents=True, exist_ok=True)
            os.environ[env] = str(tmp / sub)
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


def _harness() -> Any:
    # Imported by name, as bench.faults imports its cases: tests/ is not in
    # mypy's packages (its helpers are checked by running them).
    return importlib.import_module("tests.integration.harness")


def _terms() -> Any:
    return importlib.import_module("tests.terms")


class Watch:
    """The bench's ground: the commander's telemetry and every node's events.

    :meth:`until` reads snapshots until a predicate holds (the only way the
    bench waits for the nodes), and notes on the way what every snapshot
    says: term changes, ``dnX_safed`` turning on, the receipt lag."""

    def __init__(self, cluster: Any, mission: Mission) -> None:
        self.cluster = cluster
        self.mission = mission
        self.events: list[EventRecord] = []
        self.link = GroundLink(mission, events=True, on_event=self.events.append)
        self.period = mission.period_ns
        self.expect_dead: set[str] = set()
        self.node_args: tuple[str, ...] = ()
        """Extra arguments of every node process (a restarted one's too)."""
        self.term_changes: list[tuple[int, int, int]] = []
        """(old term, new term, the new term's first loop) as the snapshots showed them."""
        self.safed_on = 0
        """Snapshots in which a device node's ``dnX_safed`` turned on."""
        self._safed = dict.fromkeys(mission.device_nodes, False)
        self._term = 0
        self.lag_min_ns: int | None = None
        """The least (receipt time - ``cn_time_ns``) seen: negative if the
        node clocks ran ahead of this process's CLOCK_REALTIME."""
        self.snapshots = 0

    @property
    def dv(self) -> DataVector:
        return self.link.dv

    def close(self) -> None:
        self.link.close()

    def origin(self) -> int:
        """The commander's schedule: loop 1's start, from the latest snapshot."""
        dv = self.dv
        return int(dv.get("cn_time_ns")) - (int(dv.get("cn_loop")) - 1) * self.period

    def _check_procs(self) -> None:
        for name, p in self.cluster.procs.items():
            if name not in self.expect_dead and p.poll() is not None:
                raise RuntimeError(
                    f"{name} exited ({p.returncode}):\n{self.cluster.log(name)[-3000:]}"
                )

    def _note(self, rx_ns: int) -> None:
        dv = self.dv
        self.snapshots += 1
        lag = rx_ns - int(dv.get("cn_time_ns"))
        if self.lag_min_ns is None or lag < self.lag_min_ns:
            self.lag_min_ns = lag
        term = int(dv.get("cn_term"))
        if self._term and term != self._term:
            self.term_changes.append((self._term, term, int(dv.get("cn_term_loop"))))
        self._term = term
        for dn in self._safed:
            on = bool(dv.get(f"{dn}_safed"))
            if on and not self._safed[dn]:
                self.safed_on += 1
            self._safed[dn] = on

    def until(
        self, pred: Callable[[DataVector], bool], what: str, timeout_s: float = TIMEOUT_S
    ) -> DataVector:
        """Read snapshots until ``pred`` holds for one (returned); RuntimeError
        after ``timeout_s`` or when a node exits that should not."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self._check_procs()
            if self.link.next(0.2) is not None:
                self._note(time.time_ns())
                if pred(self.dv):
                    return self.dv
        raise RuntimeError(
            f"timed out after {timeout_s:g} s waiting for {what}; last telemetry: "
            f"{ {k: v for k, v in self.dv.values().items() if k.startswith('cn_')} }"
        )

    def advance(self, loops: int) -> None:
        """Wait until the commander ran ``loops`` more loops."""
        target = int(self.dv.get("cn_loop")) + loops
        self.until(lambda dv: int(dv.get("cn_loop")) >= target, f"cn_loop >= {target}")

    def event(self, node: str, ev_id: str, since: int) -> EventRecord | None:
        """The first event ``ev_id`` of ``node`` among those after index ``since``."""
        return next((e for e in self.events[since:] if e.node == node and e.id == ev_id), None)

    def ready(self) -> tuple[str, int]:
        """Wait for the standby to follow (``cn_standby_ready``); the commander and its term."""
        dv = self.until(lambda dv: bool(dv.get("cn_standby_ready")), "the standby following")
        return dv.get_name("cn_commander"), int(dv.get("cn_term"))


# ----------------------------------------------------------------------------- faults


@dataclass
class Takeover:
    """One fault and the takeover it caused (module doc)."""

    n: int
    fault: str
    victim: str
    old_term: int
    new_term: int = 0
    commander: str = ""
    phase: float = 0.0
    """Where in its loop the fault fell (0: the loop's scheduled start, 1: the next's)."""
    fault_loop: int = 0
    term_loop: int = 0
    loops: int = 0
    ms: float = 0.0
    tm_seen_ms: float = 0.0
    rejoin_s: float | None = None
    standby_ready: bool | None = None
    """Whether the commander's ``cn_standby_ready`` came back after the rejoin."""
    stood_down_event: bool | None = None
    """sigstop: whether the victim's ``cn_stood_down`` event reached the bench."""
    dn_first_loop: int | None = None
    """The first loop a device node ran under the new term (its flight recorder)."""
    first_trigger_loops: int | None = None
    """From the fault's loop to ``dn_first_loop``: the first trigger of the new
    term that ran (``loops`` + 1 when the term's first loop never ran)."""
    dn_untriggered: dict[str, int | None] = field(default_factory=dict)
    loadavg_1m: float = 0.0


def _inject(
    w: Watch, victim: str, sig: signal.Signals, rng: random.Random, n: int, fault: str
) -> tuple[Takeover, int]:
    """Signal ``victim`` at a random phase of a loop; wait for the new term.
    Returns the takeover and the signal's time (``time.time_ns()``)."""
    dv = w.dv
    term = int(dv.get("cn_term"))
    origin = w.origin()
    u = rng.random()
    at_ns = origin + (int(dv.get("cn_loop")) + 1 + u) * w.period  # loop cn_loop + 2
    delay = (at_ns - time.time_ns()) / 1e9
    if delay > 0:
        time.sleep(delay)  # places the fault in its loop: no peer is waited for
    p = w.cluster.procs[victim]
    w.expect_dead.add(victim)
    t_fault = time.time_ns()
    os.kill(p.pid, sig)
    fault_loop = (t_fault - origin) // w.period + 1
    dv = w.until(lambda dv: int(dv.get("cn_term")) > term, f"a new term after {victim}'s {fault}")
    seen = time.time_ns()
    term_loop = int(dv.get("cn_term_loop"))
    t = Takeover(
        n=n,
        fault=fault,
        victim=victim,
        old_term=term,
        new_term=int(dv.get("cn_term")),
        commander=dv.get_name("cn_commander"),
        phase=round((t_fault - origin) % w.period / w.period, 3),
        fault_loop=fault_loop,
        term_loop=term_loop,
        loops=term_loop - fault_loop,
        ms=round((origin + (term_loop - 1) * w.period - t_fault) / 1e6, 2),
        tm_seen_ms=round((seen - t_fault) / 1e6, 2),
        loadavg_1m=round(os.getloadavg()[0], 2),
    )
    print(
        f"  {fault} {n}: {victim} (term {term}) at loop {fault_loop} -> {t.commander} "
        f"term {t.new_term} from loop {term_loop}: {t.loops} loops, {t.ms} ms",
        flush=True,
    )
    return t, t_fault


def _kill9(w: Watch, count: int, rng: random.Random) -> list[Takeover]:
    out: list[Takeover] = []
    for n in range(1, count + 1):
        victim, _ = w.ready()
        t, _ = _inject(w, victim, signal.SIGKILL, rng, n, "kill9")
        _restart(w, t)
        out.append(t)
    return out


def _restart(w: Watch, t: Takeover) -> None:
    """Reap the killed node, start it again and wait until the commander of
    the new term reports it following (``cn_standby_ready``)."""
    c = w.cluster
    c.kill(t.victim)  # reaps it
    w.expect_dead.discard(t.victim)
    t0 = time.monotonic()
    c.spawn(t.victim, *w.node_args)
    term = t.new_term

    def following(dv: DataVector) -> bool:
        return bool(dv.get("cn_standby_ready")) and int(dv.get("cn_term")) == term

    w.until(following, f"{t.victim} restarted and following")
    t.rejoin_s = round(time.monotonic() - t0, 3)
    t.standby_ready = True


def _sigstop(w: Watch, count: int, rng: random.Random, stop_s: float) -> list[Takeover]:
    c = w.cluster
    out: list[Takeover] = []
    w.ready()
    for n in range(1, count + 1):
        victim = w.dv.get_name("cn_commander")
        p = c.procs[victim]
        since = len(w.events)
        logged = c.log(victim).count(STOOD_DOWN)
        try:
            t, t_fault = _inject(w, victim, signal.SIGSTOP, rng, n, "sigstop")
            left = t_fault / 1e9 + stop_s - time.time()
            if left > 0:
                time.sleep(left)  # the fault lasts stop_s: no peer is waited for
        finally:
            os.kill(p.pid, signal.SIGCONT)
        w.expect_dead.discard(victim)
        t0 = time.monotonic()

        # Its cn_stood_down event, or (events are best effort, and a node
        # continued after its peers' lease ran out may publish before its
        # links are back) the line its log got for it.
        def stood_down(
            dv: DataVector, victim: str = victim, since: int = since, logged: int = logged
        ) -> bool:
            return (
                w.event(victim, "cn_stood_down", since) is not None
                or c.log(victim).count(STOOD_DOWN) > logged
            )

        w.until(stood_down, f"{victim} standing down")
        t.rejoin_s = round(time.monotonic() - t0, 3)
        # A node that stood down should follow as the standby again: the new
        # commander's cn_standby_ready; else SETTLE_LOOPS of the new term.
        target = int(w.dv.get("cn_loop")) + SETTLE_LOOPS

        def settled(dv: DataVector, target: int = target) -> bool:
            return bool(dv.get("cn_standby_ready")) or int(dv.get("cn_loop")) >= target

        dv = w.until(settled, f"{victim} following again")
        t.standby_ready = bool(dv.get("cn_standby_ready"))
        t.stood_down_event = w.event(victim, "cn_stood_down", since) is not None
        out.append(t)
    return out


def _zp(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "zplatform", *args],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        timeout=TIMEOUT_S,
        check=False,
    )


def _flight(w: Watch, rng: random.Random) -> tuple[list[Takeover], dict[str, Any]]:
    c = w.cluster
    w.ready()
    r = _zp("cmd", str(c.path), "launch", "--arm")
    if r.returncode != 0:
        raise RuntimeError(f"launch refused: {r.stdout}{r.stderr}")
    w.until(lambda dv: dv.get_name("cn_state") == "COAST", "COAST")
    victim = w.dv.get_name("cn_commander")
    t, _ = _inject(w, victim, signal.SIGKILL, rng, 1, "kill9")
    _restart(w, t)
    end = ("LANDED", "ABORTED")
    dv = w.until(lambda dv: dv.get_name("cn_state") in end, "the landing", 120.0)
    if dv.get_name("cn_state") == "ABORTED":  # recovery still runs: wait for the landing
        dv = w.until(lambda dv: bool(dv.get("ev_landed")), "the landing (aborted)", 120.0)
    return [t], {
        "drogue_fired": bool(dv.get("drogue_fired")),
        "main_fired": bool(dv.get("main_fired")),
        "state_at_kill": "COAST",
    }


# ----------------------------------------------------------------------------- the record


def dn_safings(mission: Mission, root: Path, until_ns: int) -> list[tuple[int, str]]:
    """``dn_safed`` events the device nodes recorded (their latest run), stamped
    before ``until_ns``: each one's loop and text, in loop order."""
    found: list[tuple[int, str]] = []
    for dn in mission.device_nodes:
        runs: dict[int, list[tuple[int, str]]] = {}
        try:
            records = list(RecorderReader(root / mission.mission / dn).records())
        except RecordingError:
            continue
        for head, rec in records:
            runs.setdefault(head.run, [])
            if rec.type != EVENT:
                continue
            try:
                e = decode_event(rec.payload)
            except FrameFormatError:
                continue
            if e.id in SAFINGS and e.t_ns < until_ns:
                runs[head.run].append((rec.loop, f"{e.node} loop {rec.loop}: {e.text}"))
        if runs:
            found += runs[max(runs)]
    return sorted(found)


def dn_gaps(
    driven: dict[int, dict[str, int]], old: int, new: int
) -> tuple[dict[str, int | None], int | None]:
    """Per device node, the loops it ran no trigger in between its last loop of
    term ``old`` and its first of term ``new``; and the new term's first loop
    any device node ran."""
    last: dict[str, int] = {}
    first: dict[str, int] = {}
    for loop in sorted(driven):
        for dn, term in driven[loop].items():
            if term == old:
                last[dn] = loop
            elif term == new and dn not in first:
                first[dn] = loop
    dns = sorted({*last, *first})
    gaps = {dn: (first[dn] - last[dn] - 1 if dn in first and dn in last else None) for dn in dns}
    return gaps, min(first.values()) if first else None


def _p50(xs: list[float]) -> float | None:
    return round(float(statistics.median(xs)), 3) if xs else None


def figures(
    takeovers: list[Takeover],
    w: Watch,
    driven: dict[int, dict[str, int]],
    two_term: list[Any],
    safings: list[tuple[int, str]],
    final: dict[str, Any],
    watchdog_loops: int,
) -> dict[str, Any]:
    """One case's variant (module doc)."""
    loops = [float(t.loops) for t in takeovers]
    first = [float(t.first_trigger_loops) for t in takeovers if t.first_trigger_loops is not None]
    caused = {t.new_term for t in takeovers}
    spurious: list[dict[str, Any]] = [
        {"old": a, "new": b, "loop": k, "dn_untriggered": dn_gaps(driven, a, b)[0]}
        for a, b, k in w.term_changes
        if b not in caused
    ]
    gaps = [g for t in takeovers for g in t.dn_untriggered.values() if g is not None]
    n_safed = len(safings)
    # A safing in a fault's window: from the fault's loop to the DN watchdog
    # after the new term's first loop.
    windows = [(t.fault_loop, t.term_loop + watchdog_loops) for t in takeovers]
    in_windows = sum(any(a <= k <= b for a, b in windows) for k, _ in safings)
    p50 = _p50(loops)
    mx = max(loops) if loops else None
    rejoin = [t.rejoin_s for t in takeovers if t.rejoin_s is not None]
    fig: dict[str, Any] = {
        "faults": len(takeovers),
        "takeovers": len(w.term_changes),
        "spurious_takeovers": len(spurious),
        "takeover_loops_p50": p50,
        "takeover_loops_max": int(mx) if mx is not None else None,
        "takeover_loops_min": int(min(loops)) if loops else None,
        "first_trigger_loops_p50": _p50(first),
        "first_trigger_loops_max": int(max(first)) if first else None,
        "term_loop_not_run": sum(
            t.dn_first_loop is not None and t.dn_first_loop > t.term_loop for t in takeovers
        ),
        "takeover_ms_p50": _p50([t.ms for t in takeovers]),
        "takeover_ms_max": max((t.ms for t in takeovers), default=None),
        "tm_seen_ms_p50": _p50([t.tm_seen_ms for t in takeovers]),
        "tm_seen_ms_max": max((t.tm_seen_ms for t in takeovers), default=None),
        "dn_untriggered_p50": _p50([float(g) for g in gaps]),
        "dn_untriggered_max": max(gaps, default=None),
        "spurious_dn_untriggered_max": max(
            (g for x in spurious for g in x["dn_untriggered"].values() if g is not None),
            default=None,
        ),
        "dn_safed_events": n_safed,
        "dn_safed_after_faults": in_windows,
        "dn_safed_in_telemetry": w.safed_on,
        "two_term_loops": len(two_term),
        "rejoin_s_p50": _p50(rejoin),
        "rejoin_s_max": max(rejoin, default=None),
        "standby_ready_again": sum(bool(t.standby_ready) for t in takeovers),
        "stood_down_events_seen": (
            sum(bool(t.stood_down_event) for t in takeovers)
            if any(t.stood_down_event is not None for t in takeovers)
            else None
        ),
        "loops_recorded": len(driven),
        "tm_lag_min_ms": round(w.lag_min_ns / 1e6, 3) if w.lag_min_ns is not None else None,
        **final,
    }
    fig["met_p50"] = p50 is not None and p50 <= TARGET_P50_LOOPS
    fig["met_max"] = mx is not None and mx < watchdog_loops
    p50_first = _p50(first)
    fig["met_p50_first_trigger"] = p50_first is not None and p50_first <= TARGET_P50_LOOPS
    fig["met_max_first_trigger"] = bool(first) and max(first) < watchdog_loops
    fig["met_no_safings"] = n_safed == 0 and w.safed_on == 0
    fig["met_no_two_term_loops"] = not two_term
    fig["each"] = [asdict(t) for t in takeovers]
    if spurious:
        fig["spurious"] = spurious
    if safings:
        fig["dn_safed"] = [text for _, text in safings[:20]]
    if two_term:
        fig["two_term"] = [{"loop": n, "terms": by} for n, by in two_term[:20]]
    return fig


# ----------------------------------------------------------------------------- a case


def _stop_nodes(c: Any, w: Watch) -> None:
    """The standby first, then the commander (its final loop tells the device
    nodes the run ended), then the rest (the harness's close)."""
    dv = w.dv
    commander = dv.get_name("cn_commander") if w.snapshots else "cn"
    for name in [n for n in ("cn", "cn_b") if n != commander] + [commander]:
        p = c.procs.get(name)
        if p is not None and p.poll() is None:
            p.send_signal(signal.SIGCONT)  # a stopped one could not end
            p.terminate()
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def run_case(
    case: str, kills: int, stop_s: float, seed: int, realtime: bool, keep: Path | None = None
) -> dict[str, Any]:
    """One case on a fresh run of the mission (module doc); its variant. ``keep``:
    run in ``keep/<case>`` (node logs, flight recorders), kept afterwards."""
    harness = _harness()
    rng = random.Random(f"{seed}-{case}")
    with tempfile.TemporaryDirectory(prefix=f"zp-failover-{case}-") as td:
        tmp = Path(td) if keep is None else keep / case
        tmp.mkdir(parents=True, exist_ok=True)
        if any(tmp.iterdir()):
            raise FileExistsError(f"{tmp} is not empty: a new run needs an empty directory")
        with bench_environment(tmp):
            c = harness.Cluster(MISSION, tmp)
            m: Mission = c.mission
            w: Watch | None = None
            extra = () if realtime else ("--no-realtime",)
            try:
                for n in NODES:
                    c.spawn(n, *(extra if n != "world" else ()))
                w = Watch(c, m)
                w.node_args = extra
                final: dict[str, Any] = {}
                if case == "kill9":
                    takeovers = _kill9(w, kills, rng)
                    expected = "SAFE"
                elif case == "sigstop":
                    takeovers = _sigstop(w, kills, rng, stop_s)
                    expected = "SAFE"
                else:
                    takeovers, final = _flight(w, rng)
                    expected = "LANDED"
                w.advance(20)
                dv = w.dv
                final.update(
                    final_state=dv.get_name("cn_state"),
                    final_fault=dv.get_name("cn_fault"),
                    expected_state=expected,
                    final_as_configured=dv.get_name("cn_state") == expected,
                    final_commander=dv.get_name("cn_commander"),
                    final_term=int(dv.get("cn_term")),
                )
                end_ns = time.time_ns()
                _stop_nodes(c, w)
            finally:
                if w is not None:
                    w.close()
                c.close()
            root = tmp / "rec"
            terms = _terms()
            driven: dict[int, dict[str, int]] = terms.driven_terms(m, root)
            two_term = terms.two_term_loops(driven)
            for t in takeovers:
                t.dn_untriggered, t.dn_first_loop = dn_gaps(driven, t.old_term, t.new_term)
                if t.dn_first_loop is not None:
                    t.first_trigger_loops = t.dn_first_loop - t.fault_loop
            safings = dn_safings(m, root, end_ns)
    assert w is not None
    return figures(takeovers, w, driven, two_term, safings, final, m.faults.dn_watchdog_loops)


# ----------------------------------------------------------------------------- main


def _commit() -> str | None:
    try:
        r = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=REPO_ROOT,
            check=True,
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "zplatform", "nodes", "configs"],
            capture_output=True,
            text=True,
            cwd=REPO_ROOT,
            check=True,
        ).stdout.strip()
        return r.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return None


def targets(variants: dict[str, dict[str, Any]], watchdog_loops: int) -> list[dict[str, Any]]:
    """The issue's targets, per case."""
    out: list[dict[str, Any]] = []
    for case, v in variants.items():
        if "error" in v:
            out.append({"name": f"{case}: ran", "value": v["error"][:80], "limit": "-",
                        "unit": "", "met": False})  # fmt: skip
            continue
        out += [
            {
                "name": f"{case}: takeover (to cn_term_loop), p50",
                "value": v.get("takeover_loops_p50"),
                "limit": TARGET_P50_LOOPS,
                "unit": "loops",
                "met": v.get("met_p50"),
            },
            {
                "name": f"{case}: takeover (to cn_term_loop), max (below the DN watchdog)",
                "value": v.get("takeover_loops_max"),
                "limit": watchdog_loops,
                "unit": "loops",
                "met": v.get("met_max"),
            },
            {
                "name": f"{case}: first trigger of the new term that ran (DN recorders), p50",
                "value": v.get("first_trigger_loops_p50"),
                "limit": TARGET_P50_LOOPS,
                "unit": "loops",
                "met": v.get("met_p50_first_trigger"),
            },
            {
                "name": f"{case}: first trigger of the new term that ran, max (below the watchdog)",
                "value": v.get("first_trigger_loops_max"),
                "limit": watchdog_loops,
                "unit": "loops",
                "met": v.get("met_max_first_trigger"),
            },
            {
                "name": f"{case}: actuator safings",
                "value": v.get("dn_safed_events"),
                "limit": 0,
                "unit": "",
                "met": v.get("met_no_safings"),
            },
            {
                "name": f"{case}: loops driven by two terms",
                "value": v.get("two_term_loops"),
                "limit": 0,
                "unit": "",
                "met": v.get("met_no_two_term_loops"),
            },
            {
                "name": f"{case}: final state",
                "value": v.get("final_state"),
                "limit": v.get("expected_state"),
                "unit": "",
                "met": v.get("final_as_configured"),
            },
        ]
    return out


def main(argv: list[str] | None = None) -> None:
    p = bench_argparser(__doc__.splitlines()[0] if __doc__ else "failover")
    p.add_argument("--case", action="append", choices=CASES, help="run only this case (repeatable)")
    p.add_argument(
        "--kills", type=int, default=None, help="faults per case (default 20; --quick 2)"
    )
    p.add_argument("--stop-s", type=float, default=STOP_S, help="sigstop: seconds stopped")
    p.add_argument("--seed", type=int, default=1, help="the faults' phases")
    p.add_argument("--no-realtime", action="store_true", help="nodes without SCHED_FIFO")
    p.add_argument(
        "--keep", type=Path, metavar="DIR", help="keep each case's node logs and recorders here"
    )
    args = p.parse_args(argv)
    kills = args.kills if args.kills is not None else (2 if args.quick else 20)
    cases = args.case or [c for c in CASES if not (args.quick and c == "kill9_flight")]
    from zplatform.mission.load import load_mission

    m = load_mission(MISSION, code=False)
    watchdog = m.faults.dn_watchdog_loops
    load_before = [round(x, 2) for x in os.getloadavg()]
    run_utc = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    t0 = time.monotonic()
    variants: dict[str, dict[str, Any]] = {}
    for case in cases:
        print(f"{case} ...", flush=True)
        c0 = time.monotonic()
        try:
            fig = run_case(case, 1 if case == "kill9_flight" else kills, args.stop_s,
                           args.seed, not args.no_realtime, args.keep)  # fmt: skip
        except Exception as exc:  # one case failing must not hide the others
            traceback.print_exc()
            fig = {"error": f"{type(exc).__name__}: {exc}"[:2000]}
        fig["case_s"] = round(time.monotonic() - c0, 1)
        variants[case] = fig
    loads = [t["loadavg_1m"] for v in variants.values() for t in v.get("each", [])]
    scheduling = (
        "nodes without real-time priority (--no-realtime)"
        if args.no_realtime
        else "nodes as configured: SCHED_FIFO 20 (root)"
        if os.geteuid() == 0
        else "nodes as configured, but not root: no SCHED_FIFO"
    )
    params: dict[str, Any] = {
        "quick": bool(args.quick),
        "mission": f"configs/flight.yaml ({m.loop_hz:g} Hz, takeover_loops "
        f"{m.takeover.takeover_loops}, lease_loops {m.takeover.lease_loops}, "
        f"dn_watchdog_loops {watchdog}) on free loopback ports",
        "faults_per_case": kills,
        "stop_s": args.stop_s,
        "seed": args.seed,
        "scheduling": scheduling,
        "run_utc": run_utc,
        "run_s": round(time.monotonic() - t0, 1),
        "commit": _commit(),
        "loadavg_before": load_before,
        "loadavg_1m_during": [min(loads), max(loads)] if loads else None,
        "loadavg_after": [round(x, 2) for x in os.getloadavg()],
        "command": " ".join(
            ["python -m bench.failover", *(argv if argv is not None else sys.argv[1:])]
        ),
        "loops": "fault loop = (time.time_ns() at the signal - origin) // period + 1, origin = "
        "cn_time_ns - (cn_loop - 1) * period; new term's first loop = cn_term_loop",
        "targets": targets(variants, watchdog),
    }
    write_result("failover", params, variants, args.json)
    print()
    print(markdown(variants))
    for t in params["targets"]:
        print(f"target {t['name']}: {t['value']} (limit {t['limit']} {t['unit']}): "
              f"{'met' if t['met'] else 'NOT met'}")  # fmt: skip


def markdown(variants: dict[str, dict[str, Any]]) -> str:
    """One row per case (bench/report.py has the same table, and more)."""
    rows = [
        "| case | faults | takeover loops p50 / max | first trigger loops p50 / max | "
        "ms p50 / max | DN untriggered max | safings | two-term loops | spurious | final | "
        "configured |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for case, v in variants.items():
        if "error" in v:
            rows.append(f"| {case} | error: {v['error'][:100]} | | | | | | | | | |")
            continue
        rows.append(
            f"| {case} | {v['faults']} | {v['takeover_loops_p50']} / {v['takeover_loops_max']} "
            f"| {v['first_trigger_loops_p50']} / {v['first_trigger_loops_max']} "
            f"| {v['takeover_ms_p50']} / {v['takeover_ms_max']} | {v['dn_untriggered_max']} "
            f"| {v['dn_safed_events']} | {v['two_term_loops']} | {v['spurious_takeovers']} "
            f"| {v['final_state']} | {v['expected_state']} |"
        )
    return "\n".join(rows)


if __name__ == "__main__":
    main()
