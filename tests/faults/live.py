"""Worst-day fault cases on real node processes, shared by the tests
(``test_worst_day_live.py``) and the benchmark (``bench/faults.py``).

Each case is a function ``case(tmp: Path, quick: bool) -> CaseResult``: it
starts the minimal mission's nodes as processes (dn0 behind a
:class:`FrameTap` relay when the case needs the link), injects one fault,
waits on telemetry, liveliness, events or process exit (never a bare sleep
to wait for a peer; a sleep only makes a fault last), and returns what it
measured plus a list of named checks. The tests assert every check; the
bench tabulates the figures.

Figures of every case (``CaseResult.figures``):

* ``detect_ms``: from the fault's injection to the first CN telemetry
  snapshot (received by the test process) that shows it (``cn_fault``, a
  missed counter, ``dn0_safed``), or to the event / process exit that is the
  case's symptom;
* ``loops_missed``: ``cn_missed_dn0`` growth over the case;
* ``final_state``/``expected_state``: what the vehicle ended in and what the
  mission configures for that fault;
* ``forged_applied``: forged or junk inputs that changed the vehicle (must be 0).

What the relay lets a case prove about loss: :class:`FrameTap` finds the
region frames inside every zenoh batch it sees (a frame starts with the
MessagePack header ``94 ce <layout_id> cf <seq>``; frames are authenticated,
not encrypted), so it knows *which loop* each dropped batch carried a query
(``cn_to_dn0``) or a reply (``dn0_to_cn``) for, and what each forwarded reply
contained. With the CN's telemetry at every loop, the set of loops whose
sync the CN missed is known exactly too, so the relation tested is
``loops(dropped frames) ⊆ loops missed`` (every dropped query or reply costs
its loop, exactly one miss each), and the misses not explained by a drop are
counted separately (late replies, the shared box's stalls).

Checks and targets: a *check* is behaviour that holds however busy the
machine is (a state reached, an event sent, a fault latched, counts that
must be exact); the tests assert every check. A *target* is a timing or
rate figure held to a limit (DN_LOST within the 1 s lease, the CN's rate
under a fault, misses a drop does not explain): it depends on how promptly
the box runs the nodes, the relay and the test process itself (all of them
ordinary processes beside whatever else runs), so ``bench.faults`` reports
it and no test asserts it (tests/budget.py). Waits are hang detectors:
generous timeouts on conditions, never a speed limit.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import queue
import random
import signal
import struct
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil
import zenoh

from tests.faults.missions import relay_links
from tests.faults.relay import FaultRelay
from tests.integration.harness import CONFIGS, Cluster
from zplatform.core.auth import load_keys
from zplatform.core.datavector import DataVector, Layout
from zplatform.core.events import EventReader
from zplatform.ground.link import GroundLink
from zplatform.mission.load import load_mission

MISSION = CONFIGS / "minimal.yaml"
PERIOD_S = 0.01
MEASURE_RATES = True
"""Whether a case spends seconds measuring the CN's loop rate beside a fault,
for its rate targets (bench.faults reports them). The tests assert checks
only, never a target (tests/budget.py): they turn this off."""
_SEQ = struct.Struct(">Q")
_U64LE = struct.Struct("<Q")

# What each snapshot keeps (the CN's view; dn0_* come with dn0's replies).
WATCH = (
    "cn_loop",
    "cn_epoch",
    "cn_state",
    "cn_fault",
    "cn_rx_dn0",
    "cn_missed_dn0",
    "cn_late_dn0",
    "cn_bad_frames",
    "cn_loop_overruns",
    "cn_sync_overruns",
    "cn_cmd_rejects",
    "dn0_loop",
    "dn0_safed",
    "dn0_bad_frames",
    "dn0_clock_offset_ns",
)


# --------------------------------------------------------------------------- results
@dataclass
class CaseResult:
    case: str
    figures: dict[str, Any] = field(default_factory=dict)
    checks: list[tuple[str, bool, str]] = field(default_factory=list)
    targets: list[tuple[str, bool, str]] = field(default_factory=list)

    def check(self, name: str, ok: bool, detail: Any = "") -> bool:
        """Behaviour: asserted by the tests."""
        self.checks.append((name, bool(ok), str(detail)))
        return bool(ok)

    def target(self, name: str, met: bool, detail: Any = "") -> bool:
        """A timing or rate figure against its limit: reported by the bench, not asserted."""
        self.targets.append((name, bool(met), str(detail)))
        return bool(met)

    @property
    def ok(self) -> bool:
        return all(ok for _, ok, _ in self.checks)

    def failures(self) -> list[str]:
        return [f"{n}: {d}" for n, ok, d in self.checks if not ok]

    def as_dict(self) -> dict[str, Any]:
        return {
            **self.figures,
            "passed": self.ok,
            "checks": {n: {"ok": ok, "detail": d} for n, ok, d in self.checks},
            "targets": {n: {"met": met, "detail": d} for n, met, d in self.targets},
        }


# --------------------------------------------------------------------------- relay with a frame tap
@dataclass
class Seen:
    t: float
    direction: str
    fate: str  # forwarded | dropped | blocked
    frames: list[tuple[str, int, int]]  # (region, seq, first u64 of data)


class FrameTap(FaultRelay):
    """A :class:`FaultRelay` that also records, while armed or partitioned,
    the region frames found in every batch and what became of the batch.

    ``layouts``: ``{layout_id: region name}`` of the frames to look for."""

    def __init__(self, upstream: str, *, layouts: dict[int, str], **kw: Any) -> None:
        self.layouts = layouts
        self._marks = {
            struct.pack(">BBI", 0x94, 0xCE, lid) + b"\xcf": r for lid, r in layouts.items()
        }
        self.seen: list[Seen] = []
        super().__init__(upstream, **kw)

    def scan(self, msg: bytes) -> list[tuple[str, int, int]]:
        out = []
        for mark, region in self._marks.items():
            i = msg.find(mark)
            while i >= 0:
                seq_at = i + len(mark)
                # header: seq (8) + 0xd3 + t_ns (8), then bin8/16 header
                data_at = seq_at + 8 + 1 + 8
                if len(msg) >= data_at + 2 + 8:
                    (seq,) = _SEQ.unpack_from(msg, seq_at)
                    hdr = msg[data_at]
                    skip = 2 if hdr == 0xC4 else 3 if hdr == 0xC5 else 5
                    first = (
                        _U64LE.unpack_from(msg, data_at + skip)[0]
                        if len(msg) >= data_at + skip + 8
                        else -1
                    )
                    out.append((region, seq, first))
                i = msg.find(mark, i + 1)
        return out

    def _tcp_pump(self, src: Any, dst: Any, pipe: Any) -> None:
        inner = pipe.on_message
        direction = pipe.direction

        def on_message(msg: bytes) -> None:
            if not (self.armed or self.partitioned):
                inner(msg)
                return
            with self.lock:  # re-entrant: the pipe takes it again
                st = self.stats_of(direction)
                d0, b0 = st.dropped, st.blocked
                inner(msg)
                fate = (
                    "dropped" if st.dropped > d0 else "blocked" if st.blocked > b0 else "forwarded"
                )
            frames = self.scan(msg)
            if frames or fate != "forwarded":
                self.seen.append(Seen(time.monotonic(), direction, fate, frames))

        pipe.on_message = on_message
        super()._tcp_pump(src, dst, pipe)

    def lost_loops(self, since: float = 0.0) -> set[int]:
        """Loops whose query or reply frame was in a dropped or blocked batch."""
        return {
            seq
            for s in self.seen
            if s.t >= since and s.fate != "forwarded"
            for region, seq, _ in s.frames
        }

    def replies(self) -> dict[int, int]:
        """Forwarded replies: ``{loop: dn0_loop the reply carried}``."""
        return {
            seq: first
            for s in self.seen
            if s.fate == "forwarded"
            for region, seq, first in s.frames
            if region.endswith("_to_cn")
        }


# --------------------------------------------------------------------------- the live cluster
@dataclass
class Snap:
    t: float  # time.monotonic() at receipt
    v: dict[str, Any]


class Live(Cluster):
    """:class:`Cluster` that keeps every telemetry snapshot it reads
    (:attr:`snaps`) and every event of every node (:attr:`events`)."""

    def __init__(self, tmp: Path, *, relay_dn0: bool = False, mission: Path = MISSION) -> None:
        super().__init__(mission, tmp)
        self.relay: FrameTap | None = None
        self._relays: list[FaultRelay] = []
        if relay_dn0:
            lay = Layout.for_node(self.mission, "cn")
            layouts = {lay.region(r).layout_id: r for r in ("cn_to_dn0", "dn0_to_cn")}

            def make(up: str, **kw: Any) -> FaultRelay:
                r = FrameTap(up, layouts=layouts, **kw)
                self._relays.append(r)
                return r

            self.relay = relay_links(self.path, make, ["dn0"], seed=2024)["dn0"]  # type: ignore[assignment]
            self.mission = load_mission(self.path)
        self.snaps: list[Snap] = []
        self.events: list[tuple[float, dict[str, Any]]] = []
        self._ev_q: queue.SimpleQueue[tuple[float, str, bytes]] = queue.SimpleQueue()
        self._ev_reader = EventReader(self.mission, load_keys(self.mission, "tool"))
        self._ev_sub: Any = None

    # -- processes ---------------------------------------------------------
    def spawn_node(self, name: str, env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
        extra = ["--log", str(self.tmp / "gn.csv")] if name == "gn" else []
        return self.spawn(name, *extra, env=env)

    def signal(self, name: str, sig: int) -> None:
        os.kill(self.procs[name].pid, sig)

    def close(self) -> None:
        for p in self.procs.values():  # a stopped process ignores SIGTERM
            with suppress(ProcessLookupError):
                if p.poll() is None:
                    os.kill(p.pid, signal.SIGCONT)
        if self._ev_sub is not None:
            with suppress(Exception):
                self._ev_sub.undeclare()
        super().close()
        for r in self._relays:
            r.close()

    # -- telemetry and events ----------------------------------------------
    def watch_events(self) -> None:
        if self._ev_sub is None:
            q = self._ev_q
            self._ev_sub = self.session.declare_subscriber(
                f"{self.mission.vehicle}/*/events",
                zenoh.handlers.Callback(
                    lambda s: q.put((time.monotonic(), str(s.key_expr), s.payload.to_bytes())),
                    indirect=False,
                ),
            )

    def drain_events(self) -> list[tuple[float, dict[str, Any]]]:
        while True:
            try:
                t, key, payload = self._ev_q.get_nowait()
            except queue.Empty:
                return self.events
            with suppress(Exception):
                ev, _ = self._ev_reader.read(key, payload)
                self.events.append((t, {"node": ev.node, "id": ev.id, "text": ev.text}))

    def event_since(self, name: str, node: str, since: float) -> float | None:
        for t, e in self.drain_events():
            if t >= since and e["id"] == name and e["node"] == node:
                return t
        return None

    def wait_event(self, name: str, node: str, since: float, timeout_s: float) -> float:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            t = self.event_since(name, node, since)
            if t is not None:
                return t
            self.rx.next(0.05)
            self._record()
        raise AssertionError(
            f"no {name} event from {node} within {timeout_s} s: {self.events[-5:]}"
        )

    def _record(self) -> None:
        dv = self.rx.dv
        received = self.rx.logic.received
        if received and (not self.snaps or self.snaps[-1].v["_n"] != received):
            v = {k: _get(dv, k) for k in WATCH}
            v["_n"] = received
            self.snaps.append(Snap(time.monotonic(), v))

    def wait_for(
        self,
        pred: Callable[[DataVector], bool],
        timeout_s: float = 30.0,
        what: str = "",
        *,
        cn_alive: bool = True,
    ) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            p = self.procs.get("cn")
            if cn_alive and p is not None and p.poll() is not None:
                raise AssertionError(f"cn exited ({p.returncode}):\n{self.log('cn')[-3000:]}")
            got = self.rx.next(0.2)
            if got is not None:
                self._record()
                if pred(self.rx.dv):
                    return
        raise AssertionError(
            f"timed out waiting for {what or pred}; last telemetry: "
            f"{self.snaps[-1].v if self.snaps else None}"
        )

    def pump_for(self, seconds: float) -> None:
        """Keep reading telemetry for ``seconds`` (a fault's duration)."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            if self.rx.next(min(left, 0.05)) is not None:
                self._record()

    def first_snap(self, since: float, pred: Callable[[dict[str, Any]], bool]) -> Snap | None:
        for s in self.snaps:
            if s.t >= since and pred(s.v):
                return s
        return None

    def now(self, k: str) -> Any:
        return _get(self.tm, k)

    def ready(self, rx: int = 20, timeout_s: float = 60) -> None:
        self.wait_for(lambda dv: int(dv.get("cn_rx_dn0")) >= rx, timeout_s, "dn0 in sync")


def _get(dv: DataVector, k: str) -> Any:
    if k in ("cn_state", "cn_fault"):
        return dv.get_name(k)
    v = dv.get(k)
    return bool(v) if k == "dn0_safed" else int(v)


@contextmanager
def live(tmp: Path, *, relay_dn0: bool = False, mission: Path = MISSION) -> Iterator[Live]:
    c = Live(tmp, relay_dn0=relay_dn0, mission=mission)
    try:
        yield c
    finally:
        c.close()


def ms(t0: float, t1: float | None) -> float | None:
    return None if t1 is None else round((t1 - t0) * 1e3, 1)


def per_loop(
    snaps: list[Snap], since: float = 0.0, epoch: int | None = None
) -> list[dict[str, Any]]:
    """Snapshots in loop order (one run of the CN)."""
    out = [s.v for s in snaps if s.t >= since and (epoch is None or s.v["cn_epoch"] == epoch)]
    return out


def missed_loops(vs: list[dict[str, Any]]) -> tuple[set[int], set[int]]:
    """(loops whose dn0 sync the CN missed, loops we cannot tell: telemetry gaps)."""
    missed: set[int] = set()
    unknown: set[int] = set()
    for a, b in itertools.pairwise(vs):
        la, lb = a["cn_loop"], b["cn_loop"]
        grew = b["cn_missed_dn0"] - a["cn_missed_dn0"]
        if lb == la + 1:
            if grew:
                missed.add(lb)
        elif grew:
            unknown.update(range(la + 1, lb + 1))
    return missed, unknown


def miss_run_bounds(vs: list[dict[str, Any]]) -> tuple[int, int]:
    """``(lo, hi)``: the longest run of loops in a row whose dn0 sync the CN
    missed (what DN_LOST counts, ``faults.dn_lost_loops``) is at least ``lo``
    and at most ``hi``. Exact (``lo == hi``) while the snapshots follow the
    CN loop by loop; across a telemetry gap, where the snapshots show some
    of the loops in between missed and some not, in an unknown order, the
    bounds part. Loops are counted as the CN ran them (``rx + missed``), so
    a period the CN skipped is no loop; a CN restart starts over."""
    lo = hi = run_lo = run_hi = 0
    for a, b in itertools.pairwise(vs):
        ran = (b["cn_rx_dn0"] + b["cn_missed_dn0"]) - (a["cn_rx_dn0"] + a["cn_missed_dn0"])
        missed = b["cn_missed_dn0"] - a["cn_missed_dn0"]
        if ran <= 0 or missed < 0:  # a restarted CN: its counters start over
            run_lo = run_hi = 0
            continue
        if missed == ran:  # every loop in between missed: the run goes on
            run_lo += missed
            run_hi += missed
        elif missed == 0:
            run_lo = run_hi = 0
        else:  # the run may go on by up to `missed` first, or end, and a new one end here
            hi = max(hi, run_hi + missed)
            run_lo, run_hi = 0, missed
        lo, hi = max(lo, run_lo), max(hi, run_hi)
    return lo, hi


def max_miss_run(vs: list[dict[str, Any]]) -> int:
    """The longest run of missed loops as far as the snapshots show it (a figure)."""
    return miss_run_bounds(vs)[0]


def expected_fault(c: Live) -> set[str]:
    """The configured outcome of everything the test saw of the CN's current
    run: DN_LOST iff dn0 missed ``dn_lost_loops`` in a row (either, where
    telemetry gaps leave that open)."""
    epoch = c.now("cn_epoch")
    vs = [s.v for s in c.snaps if s.v["cn_epoch"] == epoch]
    return expected_faults_of(vs, c.mission.faults.dn_lost_loops)


def expected_faults_of(vs: list[dict[str, Any]], dn_lost_loops: int) -> set[str]:
    lo, hi = miss_run_bounds(vs)
    if lo >= dn_lost_loops:
        return {"DN_LOST"}
    return {"NONE"} if hi < dn_lost_loops else {"NONE", "DN_LOST"}


# --------------------------------------------------------------------------- cases
def case_loss(tmp: Path, quick: bool, drop: float) -> CaseResult:
    r = CaseResult(f"loss_{round(drop * 100)}pct")
    loops = 200 if quick else 500
    with live(tmp, relay_dn0=True) as c:
        relay = c.relay
        assert relay is not None
        c.spawn_node("dn0")
        c.spawn_node("cn")
        c.ready()
        m0, l0 = c.now("cn_missed_dn0"), c.now("cn_late_dn0")
        o0 = c.now("cn_sync_overruns") + c.now("cn_loop_overruns")
        t0 = time.monotonic()
        relay.arm(drop=drop)
        c.advance(loops)
        relay.disarm()
        counts = relay.counts()  # at once: after disarm every batch is forwarded
        t1 = time.monotonic()
        c.advance(20)  # replies in flight at disarm come in
        for d, st in counts.items():
            r.check(
                f"relay_counts_{d}_match_plan",
                st.decisions() == relay.plan.expected(st.seen, d).decisions(),
                st,
            )
        vs = per_loop(c.snaps, t0 - 0.05)
        missed, unknown = missed_loops(vs)
        lost = relay.lost_loops(t0)
        dropped = counts["up"].dropped + counts["down"].dropped
        lost_q = {
            s
            for x in relay.seen
            if x.fate == "dropped"
            for reg, s, _ in x.frames
            if reg.startswith("cn_to")
        }
        lost_r = {
            s
            for x in relay.seen
            if x.fate == "dropped"
            for reg, s, _ in x.frames
            if reg.endswith("_to_cn")
        }
        missed_total = c.now("cn_missed_dn0") - m0
        late_total = c.now("cn_late_dn0") - l0
        unexplained = missed - lost
        stalls = c.now("cn_sync_overruns") + c.now("cn_loop_overruns") - o0
        r.figures.update(
            drop=drop,
            loops=loops,
            batches_dropped=dropped,
            queries_dropped=len(lost_q),
            replies_dropped=len(lost_r),
            loops_missed=missed_total,
            late=late_total,
            missed_not_dropped=len(unexplained),
            cn_overruns=stalls,
            telemetry_gap_loops=len(unknown),
        )
        t_first = c.first_snap(t0, lambda v: v["cn_missed_dn0"] > m0)
        r.figures["detect_ms"] = ms(t0, t_first.t if t_first else None)
        r.check("some_batches_dropped", dropped > 0, dropped)
        r.check(
            "every_dropped_frame_is_a_missed_loop",
            lost <= missed | unknown,
            sorted(lost - missed - unknown),
        )
        r.check("missed_ge_dropped_frames", missed_total >= len(lost), (missed_total, len(lost)))
        # misses with no dropped frame: a reply that came late (counted late)
        # or the box not scheduling a node, the relay or the test in time.
        r.target(
            "unexplained_misses_bounded",
            len(unexplained) <= late_total + stalls + max(5, loops // 50),
            (len(unexplained), late_total, stalls),
        )
        _check_in_order(r, vs)
        rx = c.now("cn_rx_dn0")
        c.wait_for(lambda dv: int(dv.get("cn_rx_dn0")) >= rx + 50, 60, "dn0 back in sync")
        r.check("one_connection", relay.connections == 1, relay.connections)
        r.figures["max_miss_run"] = max_miss_run(vs)
        _final(r, c, "IDLE")
        r.figures["forged_applied"] = 0
        r.figures["window_s"] = round(t1 - t0, 2)
    return r


def _check_in_order(r: CaseResult, vs: list[dict[str, Any]]) -> None:
    back = [
        (a["cn_loop"], a["dn0_loop"], b["cn_loop"], b["dn0_loop"])
        for a, b in itertools.pairwise(vs)
        if b["dn0_loop"] < a["dn0_loop"]
    ]
    r.check("dn0_loop_never_goes_backwards", not back, back[:5])
    ahead = [(v["cn_loop"], v["dn0_loop"]) for v in vs if v["dn0_loop"] >= v["cn_loop"]]
    r.check("dn0_loop_behind_cn_loop", not ahead, ahead[:5])


def _final(r: CaseResult, c: Live, state: str, fault: str | set[str] | None = None) -> None:
    """The vehicle ended as configured: ``state``, and ``fault`` (by default
    what the misses the test saw call for: :func:`expected_fault`; on a
    loaded box a DN may miss ``dn_lost_loops`` in a row without any fault
    being injected, and then DN_LOST is the configured answer)."""
    faults = expected_fault(c) if fault is None else {fault} if isinstance(fault, str) else fault
    got = (c.now("cn_state"), c.now("cn_fault"))
    r.figures["final_state"] = f"{got[0]}/{got[1]}"
    r.figures["expected_state"] = f"{state}/{'|'.join(sorted(faults))}"
    r.check("final_state_as_configured", got[0] == state and got[1] in faults, got)


def case_delay(tmp: Path, quick: bool) -> CaseResult:
    r = CaseResult("delay_1ms")
    loops = 200 if quick else 500
    with live(tmp, relay_dn0=True) as c:
        relay = c.relay
        assert relay is not None
        c.spawn_node("dn0")
        c.spawn_node("cn")
        c.ready()
        m0, l0 = c.now("cn_missed_dn0"), c.now("cn_late_dn0")
        t0 = time.monotonic()
        relay.arm(delay_s=0.001, jitter_s=0.0005)
        c.advance(loops)
        relay.disarm()
        c.advance(20)
        vs = per_loop(c.snaps, t0 - 0.05)
        r.figures["max_miss_run"] = max_miss_run(vs)
        replies = relay.replies()
        wrong = []
        applied = 0
        for a, b in itertools.pairwise(vs):
            if b["cn_loop"] != a["cn_loop"] + 1:
                continue
            n = b["cn_loop"]
            if b["cn_rx_dn0"] > a["cn_rx_dn0"]:
                applied += 1
                if n in replies and replies[n] != b["dn0_loop"]:
                    wrong.append((n, b["dn0_loop"], replies[n]))
            elif b["dn0_loop"] != a["dn0_loop"]:
                wrong.append((n, b["dn0_loop"], a["dn0_loop"]))
        late = c.now("cn_late_dn0") - l0
        r.figures.update(
            loops=loops,
            applied=applied,
            late=late,
            loops_missed=c.now("cn_missed_dn0") - m0,
            replies_seen=len(replies),
            wrong_loop_applied=len(wrong),
            forged_applied=0,
        )
        t_first = c.first_snap(t0, lambda v: v["cn_late_dn0"] > l0)
        r.figures["detect_ms"] = ms(t0, t_first.t if t_first else None)
        r.check("late_replies_counted", late > 0, late)
        r.check("never_a_wrong_loop", not wrong, wrong[:5])
        r.check("replies_checked", applied > 0 and len(replies) > 0, (applied, len(replies)))
        _check_in_order(r, vs)
        # 1 +- 0.5 ms each way makes the round trip about the 2 ms deadline:
        # most replies come late, and a run of dn_lost_loops late ones is
        # DN_LOST, as configured.
        _final(r, c, "IDLE")
    return r


def case_partition(tmp: Path, quick: bool) -> CaseResult:
    r = CaseResult("partition_5s")
    with live(tmp, relay_dn0=True) as c:
        relay = c.relay
        assert relay is not None
        c.watch_events()
        c.spawn_node("dn0")
        c.spawn_node("cn")
        c.ready()
        m0 = c.now("cn_missed_dn0")
        t0 = time.monotonic()
        relay.partition()
        c.wait_for(lambda dv: int(dv.get("cn_missed_dn0")) > m0, 30, "first miss")
        t_miss = c.snaps[-1].t
        c.wait_for(lambda dv: dv.get_name("cn_fault") == "DN_LOST", 30, "DN_LOST")
        t_lost = c.snaps[-1].t
        run_at_lost = miss_run_bounds([s.v for s in c.snaps])[1]
        c.wait_event("dn_safed", "dn0", t0, 30)
        t_safed = c.event_since("dn_safed", "dn0", t0)
        c.pump_for(max(0.0, 5.0 - (time.monotonic() - t0)))
        latched = all(s.v["cn_fault"] == "DN_LOST" for s in c.snaps if s.t >= t_lost)
        rx = c.now("cn_rx_dn0")
        t_heal = time.monotonic()
        relay.heal()
        c.wait_for(lambda dv: int(dv.get("cn_rx_dn0")) > rx, 60, "dn0 rejoins")
        t_rejoin = c.snaps[-1].t
        c.wait_for(
            lambda dv: int(dv.get("cn_rx_dn0")) >= rx + 30 and not dv.get("dn0_safed"),
            60,
            "dn0 re-enabled",
        )
        t_reen = c.wait_event("dn_reenabled", "dn0", t_heal, 30)
        after = [s.v for s in c.snaps if s.t >= t_heal and s.v["cn_rx_dn0"] > rx]
        r.figures.update(
            detect_ms=ms(t0, t_miss),
            dn_lost_ms=ms(t0, t_lost),
            dn_safed_ms=ms(t0, t_safed),
            rejoin_after_heal_ms=ms(t_heal, t_rejoin),
            reenabled_after_heal_ms=ms(t_heal, t_reen),
            loops_missed=c.now("cn_missed_dn0") - m0,
            reconnections=relay.connections - 1,
            forged_applied=0,
        )
        r.target("dn_lost_within_lease", t_lost - t0 <= 1.0, ms(t0, t_lost))
        r.check(
            "dn_lost_after_dn_lost_loops_misses",
            run_at_lost >= c.mission.faults.dn_lost_loops,
            run_at_lost,
        )
        r.check("dn_lost_latched", latched and c.now("cn_fault") == "DN_LOST")
        r.check("dn_safed_event", t_safed is not None)
        r.check(
            "safed_in_reply_after_heal",
            any(v["dn0_safed"] for v in after),
            [v["dn0_safed"] for v in after[:3]],
        )
        r.check("rejoined", c.now("cn_rx_dn0") >= rx + 30)
        # The state machine has no DN_LOST transition in minimal.yaml: the
        # configured outcome is IDLE with the fault latched.
        _final(r, c, "IDLE", "DN_LOST")
    return r


def _rate(c: Live, seconds: float, *, observe: bool = False) -> float:
    """The CN's loop rate over ``seconds`` of telemetry; NaN at once when
    :data:`MEASURE_RATES` is off, unless the window is also the case's time
    to ``observe`` the fault (then it is read all the same)."""
    if not (MEASURE_RATES or observe):
        return math.nan
    l0, t0 = c.now("cn_loop"), time.monotonic()
    c.pump_for(seconds)
    return (c.now("cn_loop") - l0) / (time.monotonic() - t0)


def case_dn_dies(tmp: Path, quick: bool, sig: int) -> CaseResult:
    name = "kill9" if sig == signal.SIGKILL else "sigstop"
    r = CaseResult(f"dn0_{name}")
    with live(tmp) as c:
        c.watch_events()
        c.spawn_node("dn0")
        c.spawn_node("cn")
        c.ready()
        ref = _rate(c, 1.0)  # this box, now, without the fault
        m0 = c.now("cn_missed_dn0")
        t0 = time.monotonic()
        c.signal("dn0", sig)
        c.wait_for(lambda dv: int(dv.get("cn_missed_dn0")) > m0, 30, "first miss")
        miss = c.snaps[-1]
        c.wait_for(lambda dv: dv.get_name("cn_fault") == "DN_LOST", 30, "DN_LOST")
        lost = c.snaps[-1]
        run_at_lost = miss_run_bounds([s.v for s in c.snaps])[1]
        rate = _rate(c, 1.0)
        loop_after = c.now("cn_loop")
        c.advance(50)  # the CN's loop runs on without dn0
        n_lost = c.mission.faults.dn_lost_loops
        r.figures.update(
            detect_ms=ms(t0, miss.t),
            dn_lost_ms=ms(t0, lost.t),
            dn_lost_loops=lost.v["cn_loop"] - miss.v["cn_loop"] + 1,
            cn_rate_hz=round(rate, 1),
            cn_rate_ref_hz=round(ref, 1),
        )
        # DN_LOST latches after dn_lost_loops missed syncs in a row (500 ms
        # at 100 Hz): never before the snapshots could show such a run (a
        # load miss just before the signal may start it). How soon after the
        # first miss it shows depends on which snapshots the test read: a
        # target.
        r.check("dn_lost_after_dn_lost_loops_misses", run_at_lost >= n_lost, run_at_lost)
        r.target(
            "dn_lost_within_dn_lost_loops",
            lost.v["cn_loop"] - miss.v["cn_loop"] + 1 <= n_lost + 2,
            r.figures["dn_lost_loops"],
        )
        r.check("cn_loop_runs_on", c.now("cn_loop") >= loop_after + 50, c.now("cn_loop"))
        r.target("cn_keeps_rate", rate >= 0.9 * ref, (rate, ref))
        if sig == signal.SIGSTOP:
            rx = c.now("cn_rx_dn0")
            t_cont = time.monotonic()
            c.signal("dn0", signal.SIGCONT)
            c.wait_for(
                lambda dv: int(dv.get("cn_rx_dn0")) >= rx + 30 and not dv.get("dn0_safed"),
                60,
                "dn0 back",
            )
            r.figures["recover_ms"] = ms(t_cont, c.snaps[-1].t)
            # A stopped DN runs nothing, its watchdog included; after SIGCONT
            # its watchdog is only consulted when a wait finds no trigger, and
            # the CN's triggers are already there: it resumes without safing
            # (reported as a finding, not asserted).
            r.figures["dn0_safed_after_cont"] = c.event_since("dn_safed", "dn0", t0) is not None
        r.figures["loops_missed"] = c.now("cn_missed_dn0") - m0
        r.figures["forged_applied"] = 0
        _final(r, c, "IDLE", "DN_LOST")
    return r


def case_gn_dies(tmp: Path, quick: bool, sig: int) -> CaseResult:
    name = "kill9" if sig == signal.SIGKILL else "sigstop"
    r = CaseResult(f"gn_{name}")
    with live(tmp) as c:
        c.spawn_node("dn0")
        c.spawn_node("gn")
        c.spawn_node("cn")
        c.ready()
        ref = _rate(c, 1.0)  # this box, now, without the fault
        state0, m0 = c.now("cn_state"), c.now("cn_missed_dn0")
        n0 = len(c.snaps)
        c.signal("gn", sig)
        rate = _rate(c, 2.0, observe=True)  # the checks below read these 2 s
        loop_after = c.now("cn_loop")
        c.advance(50)  # the CN's loop runs on without its ground
        after = [s.v for s in c.snaps[n0:]]
        r.figures.update(
            detect_ms=None,
            cn_rate_hz=round(rate, 1),
            cn_rate_ref_hz=round(ref, 1),
            loops_missed=c.now("cn_missed_dn0") - m0,
            forged_applied=0,
        )
        r.target("cn_keeps_rate", rate >= 0.9 * ref, (rate, ref))
        r.check("cn_loop_runs_on", c.now("cn_loop") >= loop_after + 50, c.now("cn_loop"))
        r.check("no_fault", all(v["cn_fault"] == "NONE" for v in after))
        r.check("state_unchanged", all(v["cn_state"] == state0 for v in after))
        if sig == signal.SIGSTOP:
            c.signal("gn", signal.SIGCONT)
            c.advance(50)
            r.check("gn_alive_after_cont", c.procs["gn"].poll() is None)
        _final(r, c, "IDLE")
    return r


def case_cn_sigstop(tmp: Path, quick: bool) -> CaseResult:
    r = CaseResult("cn_sigstop")
    with live(tmp) as c:
        c.watch_events()
        c.spawn_node("dn0")
        c.spawn_node("cn")
        c.ready()
        t0 = time.monotonic()
        c.signal("cn", signal.SIGSTOP)
        t_safed = c.wait_event("dn_safed", "dn0", t0, 30)
        # Stopped 0.5 s: well past the 100 ms watchdog, under the 1 s lease.
        time.sleep(max(0.0, 0.5 - (time.monotonic() - t0)))  # stimulus: the stop lasts 0.5 s
        rx = c.now("cn_rx_dn0")
        t_cont = time.monotonic()
        c.signal("cn", signal.SIGCONT)
        c.wait_for(
            lambda dv: int(dv.get("cn_rx_dn0")) >= rx + 30 and not dv.get("dn0_safed"),
            60,
            "dn0 re-enabled",
        )
        t_reen = c.wait_event("dn_reenabled", "dn0", t_cont, 30)
        r.figures.update(
            detect_ms=ms(t0, t_safed),
            reenabled_after_cont_ms=ms(t_cont, t_reen),
            loops_missed=c.now("cn_missed_dn0"),
            loop_overruns=c.now("cn_loop_overruns"),
            forged_applied=0,
        )
        r.target("dn0_safed_within_watchdog_plus_margin", t_safed - t0 <= 0.5, ms(t0, t_safed))
        r.check("dn0_reenabled", t_reen is not None)
        _final(r, c, "IDLE")
    return r


def case_cn_restart(tmp: Path, quick: bool, *, mission: Path = MISSION) -> CaseResult:
    r = CaseResult("cn_kill9_restart")
    with live(tmp, mission=mission) as c:
        c.watch_events()
        c.spawn_node("dn0")
        c.spawn_node("cn")
        c.ready()
        c.advance(100)
        # A loaded box can stall dn0 past its watchdog before the kill: it
        # safes and re-enables 10 loops later. Kill it running, and if it was
        # still safed from such a stall at the kill, that streak is the one
        # the kill prolongs (no second event comes).
        c.wait_for(lambda dv: not dv.get("dn0_safed"), 30, "dn0 running")
        epoch0, loop0 = c.now("cn_epoch"), c.now("cn_loop")
        t0 = time.monotonic()
        c.kill("cn")
        last = {
            e["id"]: t for t, e in c.drain_events() if e["node"] == "dn0" and t < t0
        }  # the last dn_safed / dn_reenabled before the kill, by id
        if last.get("dn_safed", -1.0) > last.get("dn_reenabled", -1.0):
            t_safed = t0
        else:
            t_safed = c.wait_event("dn_safed", "dn0", t0, 30)
        t_restart = time.monotonic()
        c.spawn_node("cn")
        c.wait_for(
            lambda dv: (
                int(dv.get("cn_epoch")) != epoch0
                and int(dv.get("cn_rx_dn0")) >= 30
                and not dv.get("dn0_safed")
            ),
            60,
            "dn0 follows the new CN",
        )
        new = [s.v for s in c.snaps if s.v["cn_epoch"] != epoch0]
        # dn0 runs the new CN's loops: its loop reaches the new run's first
        # snapshot's (read on, not at one instant: the snapshot that met the
        # wait above may predate dn0's first loop of the new run).
        c.wait_for(
            lambda dv: int(dv.get("dn0_loop")) >= new[0]["cn_loop"], 30, "dn0 runs new loops"
        )
        r.figures.update(
            detect_ms=ms(t0, t_safed),
            follow_after_restart_ms=ms(t_restart, c.snaps[-1].t),
            old_last_loop=loop0,
            new_loop=c.now("cn_loop"),
            dn0_loop_new=c.now("dn0_loop"),
            loops_missed=c.now("cn_missed_dn0"),
            forged_applied=0,
        )
        r.check("new_epoch", c.now("cn_epoch") > epoch0, (epoch0, c.now("cn_epoch")))
        # Until the new CN's triggers are stamped 1 s after the old CN's last
        # one (loop.py _RESTART_NS), dn0 answers them without running them
        # (its replies still carry the old run's dn0_loop); then it follows:
        # dn0_loop drops once to the new run's numbers and only grows.
        follow = next((k for k, v in enumerate(new) if v["dn0_loop"] < v["cn_loop"]), len(new))
        r.figures["loops_before_follow"] = new[follow]["cn_loop"] - 1 if follow < len(new) else None
        r.check(
            "lower_loops_followed",
            follow < len(new) and new[-1]["dn0_loop"] < new[-1]["cn_loop"],
            (c.now("dn0_loop"), loop0),
        )
        r.check(
            "stale_answers_only_before_1s",
            all(v["dn0_loop"] >= loop0 - 1 for v in new[:follow]),
            [v["dn0_loop"] for v in new[:follow]][:5],
        )
        r.check(
            "dn0_runs_new_cn_loops",
            c.now("dn0_loop") >= new[0]["cn_loop"],
            (new[0]["cn_loop"], c.now("dn0_loop")),
        )
        _check_in_order(r, new[follow:])
        _final(r, c, "IDLE")
    return r


def case_skew(tmp: Path, quick: bool, skew_ms: int) -> CaseResult:
    r = CaseResult(f"clock_skew_{skew_ms}ms")
    env = {"ZPLATFORM_CLOCK_SKEW_NS": str(skew_ms * 1_000_000)}
    with live(tmp) as c:
        c.spawn_node("dn0", env=env)
        t0 = time.monotonic()
        c.spawn_node("cn")
        # The bound (100 ms) is on the residual after correction (thesis
        # 4.9): every skew is corrected, the residual measured, and it flies.
        c.ready()
        off = c.now("dn0_clock_offset_ns") / 1e6
        res = c.now("dn0_clock_drift_ns") / 1e6
        l0, rx0 = c.now("dn0_loop"), c.now("cn_rx_dn0")
        c.advance(50)
        r.figures.update(
            detect_ms=round((time.monotonic() - t0) * 1e3, 1),
            offset_ms=round(off, 3),
            residual_ms=round(res, 3),
            loops_missed=c.now("cn_missed_dn0"),
            forged_applied=0,
        )
        r.check("offset_corrected", abs(off + skew_ms) <= 5, off)
        r.check("residual_within_bound", abs(res) < 1.0, res)
        r.check(
            "loop_runs",
            c.now("dn0_loop") > l0 and c.now("cn_rx_dn0") > rx0,
            (l0, c.now("dn0_loop"), rx0, c.now("cn_rx_dn0")),
        )
        _final(r, c, "IDLE")
    return r


def _junk(rng: random.Random) -> bytes:
    n = rng.choice((0, 1, 7, 24, 40, 120, 300, 2000))
    return rng.randbytes(n)


def _frame(layout_id: int, seq: int, t_ns: int, data: bytes) -> bytes:
    """A well-formed region frame (codecs/FORMAT.md), unsealed."""
    hdr = struct.pack(">BBIBQBq", 0x94, 0xCE, layout_id, 0xCF, seq, 0xD3, t_ns)
    n = len(data)
    bin_hdr = bytes((0xC4, n)) if n < 256 else b"\xc5" + struct.pack(">H", n)
    return hdr + bin_hdr + data


def _plausible(data_len: int, layout_id: int, seq: int, t_ns: int, rng: random.Random) -> bytes:
    return _frame(layout_id, seq, t_ns, rng.randbytes(data_len))


def case_flood(tmp: Path, quick: bool) -> CaseResult:
    r = CaseResult("junk_flood")
    flood_s = 2.0 if quick else 5.0
    rate_hz = 200  # per key
    with live(tmp) as c:
        c.spawn_node("dn0")
        c.spawn_node("gn")
        cn = c.spawn_node("cn")
        c.ready()
        proc = psutil.Process(cn.pid)
        # Reference window: same length, no flood, same run.
        s0 = {k: c.now(k) for k in WATCH if k not in ("cn_state", "cn_fault")}
        c.pump_for(flood_s)
        s1 = {k: c.now(k) for k in s0}
        dropped1 = c.now("cn_cmd_dropped")
        rss0 = proc.memory_info().rss
        s = c.session
        v = c.mission.vehicle
        # BLOCK: every junk frame reaches the CN (zenoh's default for a put
        # is DROP), so the CN's count of them can be exact.
        pub_cmd = s.declare_publisher(
            f"{v}/gn/to_cn", congestion_control=zenoh.CongestionControl.BLOCK
        )
        pub_tm = s.declare_publisher(f"{v}/cn/telemetry")
        rng = random.Random(7)
        big = rng.randbytes(1 << 20)
        sent = {"to_cn": 0, "to_cn_1mb": 0, "dn0_query": 0, "telemetry": 0}
        stop = threading.Event()

        def flood() -> None:
            period = 1.0 / rate_hz
            nxt = time.monotonic()
            k = 0
            while not stop.is_set():
                k += 1
                pub_cmd.put(big if k % 50 == 0 else _junk(rng))
                sent["to_cn_1mb" if k % 50 == 0 else "to_cn"] += 1
                s.get(f"{v}/dn0/to_cn", lambda _r: None, payload=_junk(rng), timeout=0.05)
                sent["dn0_query"] += 1
                pub_tm.put(_junk(rng))
                sent["telemetry"] += 1
                nxt += period
                stop.wait(max(0.0, nxt - time.monotonic()))

        th = threading.Thread(target=flood, daemon=True)
        rss_samples: list[float] = [round(rss0 / 2**20, 1)]
        bad_rx0 = c.rx.logic.counters.rejected
        t0 = time.monotonic()
        th.start()
        outcome = None
        try:
            sender = GroundLink(c.mission, commands=True)
            try:
                (outcome,) = sender.command("NOOP", timeout_s=10)
            finally:
                sender.close()
            while (left := flood_s - (time.monotonic() - t0)) > 0:
                c.pump_for(min(left, 0.5))
                rss_samples.append(round(proc.memory_info().rss / 2**20, 1))
        finally:
            stop.set()
            th.join(5)
        rss1 = proc.memory_info().rss
        s2 = {k: c.now(k) for k in s0}
        c.advance(30)
        c.procs["gn"].terminate()
        c.procs["gn"].wait(10)
        gn = json.loads((c.tmp / "gn.json").read_text()) if (c.tmp / "gn.json").exists() else {}
        pub_cmd.undeclare()
        pub_tm.undeclare()

        def misses(a: dict[str, int], b: dict[str, int]) -> int:
            return sum(b[k] - a[k] for k in ("cn_missed_dn0", "cn_loop_overruns"))

        ref_loops = max(1, s1["cn_loop"] - s0["cn_loop"])
        fl_loops = max(1, s2["cn_loop"] - s1["cn_loop"])
        ref_rate = misses(s0, s1) / ref_loops
        fl_rate = misses(s1, s2) / fl_loops
        gn_bad = gn.get("telemetry_bad")
        r.figures.update(
            detect_ms=None,
            flood_s=flood_s,
            sent=sum(sent.values()),
            sent_by_key=dict(sent),
            ref_loops=ref_loops,
            ref_missed=misses(s0, s1),
            flood_loops=fl_loops,
            flood_missed=misses(s1, s2),
            miss_rate_ref=ref_rate,
            miss_rate_flood=fl_rate,
            cn_bad_frames=c.now("cn_bad_frames") - s1["cn_bad_frames"],
            dn0_bad_frames=c.now("dn0_bad_frames") - s1["dn0_bad_frames"],
            gn_telemetry_bad=gn_bad,
            test_rx_bad=c.rx.logic.counters.rejected - bad_rx0,
            noop=outcome.status if outcome else None,
            cn_rss_growth_mb=round((rss1 - rss0) / 2**20, 1),
            cn_rss_mb_samples=rss_samples,
            loops_missed=misses(s1, s2),
            forged_applied=0 if c.now("cn_state") == "IDLE" else 1,
        )
        # The target: the flood adds under 1e-4 to the miss rate. One
        # miss in a window of a few hundred loops is already 2e-3 to 5e-3, so
        # a window this short cannot show it: the strict comparison is
        # reported as a figure, and the target is that the loop keeps its
        # rate under the flood (on two shared cores the junk queries the DN
        # must answer cost a few loops: 0 to 4 of 200 seen on a quiet box;
        # beside a CPU hog the box's own misses swamp it, so not asserted).
        r.figures["flood_adds_under_1e-4"] = fl_rate <= ref_rate + 1e-4
        r.target(
            "flood_keeps_the_loop_rate",
            misses(s1, s2) <= misses(s0, s1) + max(2, fl_loops // 20),
            (misses(s1, s2), misses(s0, s1), fl_loops),
        )
        # Every junk frame is a bad frame, or was among the oldest the CN's
        # 16-frame inbox let go when the loop fell behind (counted as
        # dropped); on an idle box none is dropped and the bad count is exact.
        bad = c.now("cn_bad_frames") - s1["cn_bad_frames"]
        junk = sent["to_cn"] + sent["to_cn_1mb"]
        inbox_dropped = c.now("cn_cmd_dropped") - dropped1
        r.check(
            "cn_bad_frames_exact",
            bad <= junk <= bad + inbox_dropped,
            (bad, junk, inbox_dropped),
        )
        r.check("cn_bad_frames_counted", c.now("cn_bad_frames") > s1["cn_bad_frames"])
        r.check("dn0_bad_frames_counted", c.now("dn0_bad_frames") > s1["dn0_bad_frames"])
        r.check("gn_bad_counted", gn_bad is not None and gn_bad > 0, gn_bad)
        r.check("noop_accepted", outcome is not None and outcome.accepted, outcome)
        r.check("cn_rss_bounded", rss1 - rss0 < 50 * 2**20, r.figures["cn_rss_growth_mb"])
        _final(r, c, "IDLE")
    return r


def case_rogue(tmp: Path, quick: bool) -> CaseResult:
    r = CaseResult("rogue_dn0_and_forged_tm")
    with live(tmp) as c:
        c.spawn_node("dn0")
        c.spawn_node("gn")
        c.spawn_node("cn")
        c.ready()
        c.kill("dn0")
        c.wait_for(lambda dv: dv.get_name("cn_fault") == "DN_LOST", 30, "DN_LOST")
        lay = Layout.for_node(c.mission, "cn")
        reg = lay.region("dn0_to_cn")
        rng = random.Random(3)
        answered = [0]

        def rogue(q: zenoh.Query) -> None:
            with q:
                payload = q.payload.to_bytes() if q.payload is not None else b""
                seq = _SEQ.unpack_from(payload, 7)[0] if len(payload) >= 15 else 0
                body = _plausible(reg.size, reg.layout_id, seq, time.time_ns(), rng)
                # alternately unsealed, and sealed with a made-up tag
                tag = b"" if answered[0] % 2 else rng.randbytes(32)
                q.reply(q.key_expr, body + tag)
                answered[0] += 1

        rx0, bad0 = c.now("cn_rx_dn0"), c.now("cn_bad_frames")
        qbl = c.session.declare_queryable(f"{c.mission.vehicle}/dn0/to_cn", rogue)
        t0 = time.monotonic()
        try:
            c.wait_for(
                lambda dv: int(dv.get("cn_bad_frames")) >= bad0 + 50,
                60,
                "rogue replies counted bad",
            )
            t_bad = c.snaps[-1].t
            c.advance(50)
        finally:
            qbl.undeclare()
        rx1 = c.now("cn_rx_dn0")
        # forged telemetry: the CN's layout, a loop number ahead, a made-up tag
        forged_loop = c.now("cn_loop") + 7
        forged = _frame(lay.layout_id, forged_loop, time.time_ns(), rng.randbytes(lay.size))
        forged += rng.randbytes(32)  # a made-up tag
        # BLOCK: each forged frame reaches every subscriber (with zenoh's DROP,
        # a starved host may drop one on the way to the ground node, which
        # then has nothing to count).
        pub = c.session.declare_publisher(
            f"{c.mission.vehicle}/cn/telemetry", congestion_control=zenoh.CongestionControl.BLOCK
        )
        bad_rx0 = c.rx.logic.counters.rejected
        for _ in range(5):
            pub.put(forged)
        pub.undeclare()
        c.wait_for(
            lambda dv: int(dv.get("cn_loop")) >= forged_loop + 20, 60, "past the forged loop"
        )
        c.procs["gn"].terminate()
        c.procs["gn"].wait(10)
        gn = json.loads((c.tmp / "gn.json").read_text())
        rows = (c.tmp / "gn.csv").read_text().splitlines()
        col = rows[0].split(",").index("cn_loop")
        logged = [int(x.split(",")[col]) for x in rows[1:] if x]
        dup = len(logged) - len(set(logged))
        r.figures.update(
            detect_ms=ms(t0, t_bad),
            rogue_replies=answered[0],
            rx_growth=rx1 - rx0,
            cn_bad_frames=c.now("cn_bad_frames") - bad0,
            forged_tm_sent=5,
            gn_telemetry_bad=gn.get("telemetry_bad"),
            test_rx_bad=c.rx.logic.counters.rejected - bad_rx0,
            loops_missed=None,
            forged_applied=(rx1 - rx0) + dup,
        )
        r.check("nothing_applied", rx1 == rx0, (rx0, rx1))
        # Each rogue reply that reached the CN within its query's period is a
        # bad frame; one the test process sent later than that zenoh drops
        # (the query is closed), so at most every reply sent is counted.
        r.check(
            "bad_frames_counted",
            50 <= c.now("cn_bad_frames") - bad0 <= answered[0],
            (c.now("cn_bad_frames") - bad0, answered[0]),
        )
        r.check("gn_counted_forged", gn.get("telemetry_bad", 0) >= 5, gn)
        r.check(
            "forged_loop_row_is_real",
            logged.count(forged_loop) <= 1 and dup == 0,
            (logged.count(forged_loop), dup),
        )
        _final(r, c, "IDLE", "DN_LOST")
    return r


# --------------------------------------------------------------------------- namespaces
class NetWatch:
    """A telemetry watcher running inside a namespace
    (``python -m tests.faults.live watch MISSION``): one JSON line per CN
    snapshot, ``_t`` = the watcher's ``time.monotonic()`` (one kernel, one
    monotonic clock across namespaces)."""

    def __init__(self, proc: subprocess.Popen[Any]) -> None:
        self.proc = proc
        self.snaps: list[Snap] = []
        self._lock = threading.Lock()
        self._new = threading.Condition(self._lock)  # a snapshot came, or the watcher ended
        self._th = threading.Thread(target=self._read, daemon=True)
        self._th.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with suppress(ValueError):
                v = json.loads(line)
                with self._new:
                    self.snaps.append(Snap(v.pop("_t"), v))
                    self._new.notify_all()
        with self._new:
            self._new.notify_all()

    def last(self) -> dict[str, Any]:
        with self._lock:
            return self.snaps[-1].v if self.snaps else {}

    def wait_for(self, pred: Callable[[dict[str, Any]], bool], timeout_s: float, what: str) -> Snap:
        deadline = time.monotonic() + timeout_s
        seen = 0
        with self._new:  # woken by each snapshot the reader thread takes
            while True:
                for sn in self.snaps[seen:]:
                    if pred(sn.v):
                        return sn
                seen = len(self.snaps)
                if self.proc.poll() is not None:
                    raise AssertionError(f"watcher exited ({self.proc.returncode})")
                left = deadline - time.monotonic()
                if left <= 0:
                    last = self.snaps[-1].v if self.snaps else {}
                    raise AssertionError(f"timed out waiting for {what}; last: {last}")
                self._new.wait(min(left, 0.5))


def watch_main(mission_path: str) -> int:
    """Print the CN's telemetry as JSON lines until stdin closes."""
    import sys

    from zplatform.ground.logic import GroundLogic
    from zplatform.runtime.timebase import NodeClock
    from zplatform.runtime.transport import zenoh_config

    m = load_mission(mission_path)
    cfg = zenoh_config(m, None)
    if os.environ.get("ZP_WATCH_ONLY_CN"):
        # connect to the CN only (a tool connects to every node)
        cfg.insert_json5("connect/endpoints", json.dumps(m.nodes["cn"].listen))
    session = zenoh.open(cfg)
    # The ground's own logic on a session of this watcher's (a driver of its own).
    ground = GroundLogic(m, keys=load_keys(m, "tool"))
    clock = NodeClock()
    q: queue.SimpleQueue[tuple[bytes, int]] = queue.SimpleQueue()
    sub = session.declare_subscriber(
        f"{m.vehicle}/cn/telemetry",
        zenoh.handlers.Callback(
            lambda s: q.put((s.payload.to_bytes(), clock.now_ns())), indirect=False
        ),
    )
    done = threading.Event()

    def until_eof() -> None:
        sys.stdin.read()
        done.set()

    threading.Thread(target=until_eof, daemon=True).start()
    try:
        while not done.is_set():
            try:
                payload, rx = q.get(timeout=0.1)
            except queue.Empty:
                continue
            if not ground.on_telemetry(payload, rx):
                continue
            v: dict[str, Any] = {k: _get(ground.dv, k) for k in WATCH}
            v["_t"] = time.monotonic()
            print(json.dumps(v), flush=True)
    finally:
        sub.undeclare()
        session.close()
    return 0


def case_partition_netns(
    tmp: Path, quick: bool, down_s: float = 5.0, cut: str = "dn0"
) -> CaseResult:
    """A cable cut on real kernel links: the CN (and the watcher) on one
    namespace host, dn0 on another; dn0's bridge port is set down for
    ``down_s`` then up again. The CN must keep its rate, see dn0 lost (DN_LOST
    when the cut lasts ``dn_lost_loops``), and dn0 must rejoin and re-enable."""
    from tests.faults.missions import netns_mission
    from tests.faults.netns import NetnsLab, netns_unavailable
    from tests.integration.harness import ROOT

    r = CaseResult(f"cable_cut_{cut}_{down_s:g}s_netns")
    if cut == "gn":
        return _gn_cable_cut(tmp, down_s)
    why = netns_unavailable()
    if why is not None:
        r.figures["skipped"] = why
        return r
    import sys

    with NetnsLab(2) as lab:
        h0, h1 = lab.hosts
        path = netns_mission(MISSION, tmp / "m.yaml", {"cn": h0, "dn0": h1, "gn": h0})
        node = [sys.executable, "-m", "zplatform", "node", str(path)]
        h1.popen([*node, "dn0"], log=tmp / "dn0.log", cwd=ROOT)
        cn_cmd = node
        if os.environ.get("ZP_FAULTS_CN_DROP_PATCH"):
            cn_cmd = [sys.executable, "-m", "tests.faults.cn_drop_patch", "node", str(path)]
            r.figures["cn_drop_patch"] = True
        h0.popen([*cn_cmd, "cn", "--ground-wait", "0"], log=tmp / "cn.log", cwd=ROOT)
        w = NetWatch(
            h0.popen(
                [sys.executable, "-m", "tests.faults.live", "watch", str(path)],
                log=tmp / "watch.log",
                pipe_stdio=True,
                cwd=ROOT,
            )
        )
        r.figures.update(
            forged_applied=0, expected_state="IDLE/DN_LOST" if down_s >= 1 else "IDLE/-"
        )
        try:
            w.wait_for(lambda v: v["cn_rx_dn0"] >= 20, 60, "dn0 in sync")
            m0 = w.last()["cn_missed_dn0"]
            t0 = time.monotonic()
            h1.link_down()
            miss = w.wait_for(lambda v: v["cn_missed_dn0"] > m0, 30, "first miss")
            r.figures["detect_ms"] = ms(t0, miss.t)
            if down_s >= 1:
                lost = w.wait_for(lambda v: v["cn_fault"] == "DN_LOST", 30, "DN_LOST")
                r.figures["dn_lost_ms"] = ms(t0, lost.t)
                r.target("dn_lost_within_lease", lost.t - t0 <= 1.0, ms(t0, lost.t))
            time.sleep(max(0.0, down_s - (time.monotonic() - t0)))  # stimulus: the cut lasts down_s
            rx = w.last()["cn_rx_dn0"]
            loop_at_heal = w.last()["cn_loop"]
            t_heal = time.monotonic()
            h1.link_up()
            r.check(
                "cn_kept_looping_during_cut",
                loop_at_heal > miss.v["cn_loop"],
                (miss.v["cn_loop"], loop_at_heal),
            )
            r.target(
                "cn_kept_its_rate_during_cut",
                loop_at_heal - miss.v["cn_loop"] >= 0.8 * 100 * down_s - 20,
                (miss.v["cn_loop"], loop_at_heal),
            )
            back = w.wait_for(lambda v: v["cn_rx_dn0"] > rx, 60, "dn0 rejoins")
            r.figures["rejoin_after_heal_ms"] = ms(t_heal, back.t)
            w.wait_for(
                lambda v: v["cn_rx_dn0"] >= rx + 30 and not v["dn0_safed"], 60, "dn0 re-enabled"
            )
            with w._lock:
                snaps = list(w.snaps)
            after = [sn.v for sn in snaps if sn.t >= t_heal and sn.v["cn_rx_dn0"] > rx]
            r.check(
                "safed_in_reply_after_heal",
                any(v["dn0_safed"] for v in after),
                [v["dn0_safed"] for v in after[:3]],
            )
            last = w.last()
            r.check("rejoined", last["cn_rx_dn0"] >= rx + 30)
            r.target("rejoined_within_2s", back.t - t_heal <= 2.0, ms(t_heal, back.t))
            gaps = [b.t - a.t for a, b in itertools.pairwise(snaps) if b.t >= t0 - 0.1]
            r.figures["max_tm_gap_ms"] = round(max(gaps, default=0.0) * 1e3, 1)
            # telemetry every loop: a gap is the CN's loop not running (or
            # the watcher, an ordinary process, not being run: a target)
            r.target("cn_never_froze", max(gaps, default=0.0) <= 0.2, r.figures["max_tm_gap_ms"])
            vs = [sn.v for sn in snaps]
            want = expected_faults_of(vs, 50)
            got = (last["cn_state"], last["cn_fault"])
            r.figures["loops_missed"] = last["cn_missed_dn0"] - m0
            r.figures["final_state"] = f"{got[0]}/{got[1]}"
            r.figures["expected_state"] = f"IDLE/{'|'.join(sorted(want))}"
            r.check("final_state_as_configured", got[0] == "IDLE" and got[1] in want, got)
        except AssertionError as exc:
            last = w.last()
            r.figures["final_state"] = f"{last.get('cn_state')}/{last.get('cn_fault')}"
            r.figures["loops_missed"] = last.get("cn_missed_dn0")
            r.check("completed", False, f"{exc}"[:600])
        finally:
            if w.proc.stdin is not None:
                with suppress(OSError):
                    w.proc.stdin.close()
            with suppress(subprocess.TimeoutExpired):
                w.proc.wait(5)
    return r


def _gn_cable_cut(tmp: Path, down_s: float) -> CaseResult:
    """The ground's cable cut for ``down_s``: nothing changes on the vehicle."""
    import sys

    from tests.faults.missions import netns_mission
    from tests.faults.netns import NetnsLab
    from tests.integration.harness import ROOT

    r = CaseResult(f"cable_cut_gn_{down_s:g}s_netns")
    with NetnsLab(2) as lab:
        h0, h1 = lab.hosts
        path = netns_mission(MISSION, tmp / "m.yaml", {"cn": h0, "dn0": h0, "gn": h1})
        node = [sys.executable, "-m", "zplatform", "node", str(path)]
        h0.popen([*node, "dn0"], log=tmp / "dn0.log", cwd=ROOT)
        h1.popen([*node, "gn", "--log", str(tmp / "gn.csv")], log=tmp / "gn.log", cwd=ROOT)
        cn_cmd = node
        if os.environ.get("ZP_FAULTS_CN_DROP_PATCH"):
            cn_cmd = [sys.executable, "-m", "tests.faults.cn_drop_patch", "node", str(path)]
            r.figures["cn_drop_patch"] = True
        h0.popen([*cn_cmd, "cn"], log=tmp / "cn.log", cwd=ROOT)  # waits for the GN
        w = NetWatch(
            h0.popen(
                [sys.executable, "-m", "tests.faults.live", "watch", str(path)],
                log=tmp / "watch.log",
                pipe_stdio=True,
                cwd=ROOT,
            )
        )
        r.figures.update(detect_ms=None, forged_applied=0, expected_state="IDLE/NONE")
        try:
            w.wait_for(lambda v: v["cn_rx_dn0"] >= 20, 60, "dn0 in sync")
            first = w.last()
            t0 = time.monotonic()
            h1.link_down()
            time.sleep(down_s)  # stimulus: the cut lasts down_s
            h1.link_up()
            w.wait_for(lambda v: v["cn_loop"] >= first["cn_loop"] + 100 * down_s + 50, 60, "loops")
            with w._lock:
                snaps = [sn for sn in w.snaps if sn.t >= t0 - 0.1]
            gaps = [b.t - a.t for a, b in itertools.pairwise(snaps)]
            last = w.last()
            r.figures.update(
                max_tm_gap_ms=round(max(gaps, default=0.0) * 1e3, 1),
                loops_missed=last["cn_missed_dn0"] - first["cn_missed_dn0"],
                final_state=f"{last['cn_state']}/{last['cn_fault']}",
            )
            r.target("cn_never_froze", max(gaps, default=0.0) <= 0.2, r.figures["max_tm_gap_ms"])
            r.check("no_fault", all(sn.v["cn_fault"] == "NONE" for sn in snaps))
            r.check("final_state_as_configured", r.figures["final_state"] == "IDLE/NONE")
        except AssertionError as exc:
            r.check("completed", False, f"{exc}"[:600])
        finally:
            if w.proc.stdin is not None:
                with suppress(OSError):
                    w.proc.stdin.close()
            with suppress(subprocess.TimeoutExpired):
                w.proc.wait(5)
    return r


CASES: dict[str, Callable[[Path, bool], CaseResult]] = {
    "loss_1pct": lambda t, q: case_loss(t, q, 0.01),
    "loss_10pct": lambda t, q: case_loss(t, q, 0.10),
    "delay_1ms": case_delay,
    "partition_5s": case_partition,
    "cable_cut_dn0_0.5s_netns": lambda t, q: case_partition_netns(t, q, 0.5),
    "cable_cut_dn0_5s_netns": lambda t, q: case_partition_netns(t, q, 5.0),
    "cable_cut_gn_5s_netns": lambda t, q: case_partition_netns(t, q, 5.0, "gn"),
    "dn0_kill9": lambda t, q: case_dn_dies(t, q, signal.SIGKILL),
    "dn0_sigstop": lambda t, q: case_dn_dies(t, q, signal.SIGSTOP),
    "gn_kill9": lambda t, q: case_gn_dies(t, q, signal.SIGKILL),
    "gn_sigstop": lambda t, q: case_gn_dies(t, q, signal.SIGSTOP),
    "cn_sigstop": case_cn_sigstop,
    "cn_kill9_restart": case_cn_restart,
    "clock_skew_50ms": lambda t, q: case_skew(t, q, 50),
    "clock_skew_500ms": lambda t, q: case_skew(t, q, 500),
    "junk_flood": case_flood,
    "rogue_dn0_and_forged_tm": case_rogue,
}


if __name__ == "__main__":
    import sys

    if len(sys.argv) == 3 and sys.argv[1] == "watch":
        raise SystemExit(watch_main(sys.argv[2]))
    raise SystemExit("usage: python -m tests.faults.live watch MISSION")
