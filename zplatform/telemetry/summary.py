"""Run summaries: what each node and ``zplatform up`` report when they stop.

Frozen ``msgspec.Struct``\\ s (snapshots, like trio's statistics objects), so
every field is named, typed and documented once, and the ``--summary`` JSON
of docs/architecture.md#files is their encoding. Node processes write theirs
(:func:`write_summary`); ``up`` reads them back (:func:`read_summary`) and
merges them into a :class:`RunSummary`.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TypeVar

import msgspec

from ..boards.base import BoardHealth
from ..config import Mission
from ..core.datavector import DataVector
from .records import CommandOutcome

__all__ = [
    "CnSummary",
    "DnSummary",
    "GnSummary",
    "LoopWork",
    "RunSummary",
    "board_line",
    "board_trouble",
    "cn_summary",
    "read_summary",
    "write_summary",
]


class LoopWork(msgspec.Struct, frozen=True):
    """CN work time per loop (sync wait and logic, not the sleep), in us."""

    p50: float = 0.0
    p99: float = 0.0
    max: float = 0.0


class CnSummary(msgspec.Struct, frozen=True):
    """The control node's run: counters as its last telemetry showed them."""

    loops: int
    duration_s: float
    rate_hz: float
    loop_overruns: int
    sync_overruns: int
    missed: dict[str, int]
    late: dict[str, int]
    rx: dict[str, int]
    bad_frames: int
    errors: int
    final_state: str
    fault: str = "NONE"
    loop_work_us: LoopWork = LoopWork()
    recorded_loops: int | None = None
    recording_dropped_loops: int | None = None
    node: str = "cn"
    last_loop: int = 0
    """The loop its vector was at when it ended (``cn_loop``)."""
    term: int = 0
    """A redundant mission's: the term its vector was in (0: no terms)."""
    commanding: bool = True
    """Whether it commanded when it ended (False: it ended as the standby)."""
    takeovers: int = 0
    """Times it took command as the standby (zplatform.control.failover)."""


class DnSummary(msgspec.Struct, frozen=True):
    """A device node's run."""

    node: str
    loops: int
    clock_offset_ns: int
    clock_drift_ns: int
    bad_frames: int
    errors: int
    stale_queries: int
    safed_why: str = ""
    """Why the node's actuators were safed when it stopped serving triggers
    ("" when they were not): the control node's run ended (its final loop),
    or no valid trigger came (a lost control node). A clean exit safes them
    after this summary is taken."""
    board: BoardHealth | None = None
    """Its board's health as the node stopped serving triggers (its counters
    over the whole run), for a board with a link (``serial``, ``gpiod``:
    :data:`~zplatform.config.BOARD_LINK_DRIVERS`, the nodes with
    ``dnX_board_*`` elements); None for any other board."""


class GnSummary(msgspec.Struct, frozen=True):
    """The ground node's (or ``zplatform log``'s) run: telemetry and commands.

    ``telemetry_bad`` counts every snapshot not applied (malformed,
    unauthenticated or refused); ``telemetry_refused`` breaks the refusals
    down by reason (:data:`zplatform.telemetry.records.REFUSALS`);
    ``epoch_changes``: control node restarts the ground followed;
    ``events_logged``: event records written to the events file;
    ``telemetry_filled``/``telemetry_unfilled``: gap loops written from the
    CN's flight recorder / given up; ``telemetry_not_run``: gap loops the
    CN never ran (skipped periods: no loss) (:mod:`zplatform.ground.gapfill`);
    ``events_missed``: verified events that did not arrive (numbers
    skipped), ``events_filled``/``events_unfilled``: of those, the CN's
    filled from its recorder / not;
    ``telemetry_iox``, ``_duplicates``, ``_fallbacks``: a ground on the CN's
    host (:class:`~zplatform.telemetry.records.TelemetryCounters`)."""

    telemetry_received: int
    telemetry_gaps: int
    telemetry_bad: int
    first_seq: int
    last_seq: int
    final_state: str | None
    commands: list[CommandOutcome] = []
    pending_commands: list[str] = []
    node: str = "gn"
    telemetry_refused: dict[str, int] = {}
    epoch_changes: int = 0
    events_logged: int = 0
    telemetry_filled: int = 0
    telemetry_unfilled: int = 0
    telemetry_not_run: int = 0
    events_missed: int = 0
    events_filled: int = 0
    events_unfilled: int = 0
    telemetry_iox: int = 0
    """Snapshots that came over iceoryx2 (zplatform.runtime.tmiox)."""
    telemetry_duplicates: int = 0
    """Copies dropped as duplicates (the same snapshot by the other path)."""
    telemetry_fallbacks: int = 0
    """Times the telemetry fell back from iceoryx2 to zenoh."""
    telemetry_unchecked: int = 0
    """Of ``telemetry_bad``, snapshots dropped after their header unchecked
    (the body-MAC budget spent: a flood behind genuine headers)."""


class RunSummary(msgspec.Struct, frozen=True):
    """``zplatform up``'s summary (docs/architecture.md#files): the CN's figures, the
    ground's telemetry and command verdicts, every node's own summary
    (``None`` for a node that wrote none) and exit code."""

    mission: str
    loops: int
    duration_s: float
    rate_hz: float
    loop_overruns: int | None
    sync_overruns: int | None
    missed: dict[str, int]
    late: dict[str, int]
    bad_frames: int | None
    telemetry_received: int | None
    telemetry_gaps: int | None
    commands: list[CommandOutcome]
    errors: int | None
    final_state: str | None
    nodes: dict[str, CnSummary | DnSummary | GnSummary | None]
    exit_codes: dict[str, int]
    takeover: str | None = None
    """A redundant mission whose command changed hands: who commanded, in
    which term, for how many loops (None: one commander throughout)."""
    events_missed: int | None = None
    """Verified events the ground node saw numbered past (None: no ground
    summary); the CN's filled from its recorder count here too."""


S = TypeVar("S", CnSummary, DnSummary, GnSummary)


def board_trouble(h: BoardHealth) -> bool:
    """Whether a board's link misbehaved over the run: any timeout,
    reconnect, bad frame, late reply or device ERROR (what ``up`` and the
    node's exit log call out)."""
    return bool(h.timeouts or h.reconnects or h.bad_frames or h.late_replies or h.device_errors)


def board_line(node: str, h: BoardHealth) -> str:
    """A board's link counters in one line, for a person: ``dn0's board:
    3 timeouts, 1 reconnect, 0 bad frames, 2 late replies, 0 device errors
    (5400 frames sent, 5398 received; ok at the end); last error: ...``
    (the end: when ``h`` was taken; ``last_error`` only when there is one)."""
    counts = (
        (h.timeouts, "timeout", "timeouts"),
        (h.reconnects, "reconnect", "reconnects"),
        (h.bad_frames, "bad frame", "bad frames"),
        (h.late_replies, "late reply", "late replies"),
        (h.device_errors, "device error", "device errors"),
    )
    parts = [f"{c} {one if c == 1 else many}" for c, one, many in counts]
    state = "ok" if h.ok else ("safed" if h.safe_active else "failing")
    if not h.connected:
        state = "link down"
    line = (
        f"{node}'s board: {', '.join(parts)} ({h.frames_sent} frames sent, "
        f"{h.frames_received} received; {state} at the end)"
    )
    if h.last_error:
        line += f"; last error: {h.last_error}"
    return line


def cn_summary(
    mission: Mission,
    dv: DataVector,
    *,
    loops: int,
    duration_s: float,
    loop_work_us: LoopWork | None = None,
    recorded_loops: int | None = None,
    recording_dropped_loops: int | None = None,
    node: str = "cn",
    commanding: bool = True,
    takeovers: int = 0,
) -> CnSummary:
    """The CN's summary from a CN-layout vector: its own, or the last
    telemetry snapshot of a CN that died before it could write one."""
    dns = mission.device_nodes
    return CnSummary(
        loops=loops,
        duration_s=duration_s,
        rate_hz=(loops - 1) / duration_s if duration_s > 0 else 0.0,
        loop_overruns=int(dv.get("cn_loop_overruns")),
        sync_overruns=int(dv.get("cn_sync_overruns")),
        missed={dn: int(dv.get(f"cn_missed_{dn}")) for dn in dns},
        late={dn: int(dv.get(f"cn_late_{dn}")) for dn in dns},
        rx={dn: int(dv.get(f"cn_rx_{dn}")) for dn in dns},
        bad_frames=int(dv.get("cn_bad_frames")),
        errors=int(dv.get("cn_errors")) + sum(int(dv.get(f"{dn}_errors")) for dn in dns),
        final_state=dv.get_name("cn_state"),
        fault=dv.get_name("cn_fault"),
        loop_work_us=loop_work_us or LoopWork(),
        recorded_loops=recorded_loops,
        recording_dropped_loops=recording_dropped_loops,
        node=node,
        last_loop=int(dv.get("cn_loop")),
        term=int(dv.get("cn_term")) if "cn_term" in dv.layout.elements else 0,
        commanding=commanding,
        takeovers=takeovers,
    )


def write_summary(path: str | Path | None, summary: msgspec.Struct) -> None:
    """Write a summary as indented JSON to ``path`` ('-' = stdout); no-op for None."""
    if path is None:
        return
    text = msgspec.json.format(msgspec.json.encode(summary), indent=2).decode()
    if str(path) == "-":
        sys.stdout.write(text + "\n")
    else:
        Path(path).write_text(text + "\n")


def read_summary(path: str | Path, kind: type[S]) -> S | None:
    """A node's summary file, or None when it is missing or unreadable (the
    node died before writing it)."""
    try:
        return msgspec.json.decode(Path(path).read_bytes(), type=kind)
    except (OSError, msgspec.DecodeError, msgspec.ValidationError):
        return None
