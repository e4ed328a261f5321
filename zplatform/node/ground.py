"""Ground Node Main (thesis 4.15): the ground node's runtime, and ``zplatform log``.

A thin driver: a :class:`~zplatform.ground.link.GroundLink` (one session,
the telemetry subscriber, the event intake, the command publisher when a
script is played) feeds the ground's sans-IO
:class:`~zplatform.ground.logic.GroundLogic`, which checks every snapshot,
keeps the CN-layout Data Vector (the GN's first Data Vector, thesis 4.15),
counts gaps and refusals, and plays the command script (the GN's second
Data Vector holds the requests). This module only logs what the logic
accepted (:class:`~zplatform.ground.logger.TelemetryLog`) until it is told
to stop, and reports.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from ..config import Mission
from ..ground.link import GroundLink
from ..ground.logger import TelemetryLog
from ..summary import GnSummary
from ..uplink import ScriptCommand
from .runtime import StopFlag

__all__ = ["run_ground_logger"]

log = logging.getLogger("zplatform.gn")


def run_ground_logger(
    mission: Mission,
    out_csv: str | Path | None,
    *,
    as_node: bool = True,
    duration_s: float | None = None,
    stop: StopFlag | None = None,
    idle_exit_s: float | None = None,
    script: list[ScriptCommand] | None = None,
    key_file: str | None = None,
    events_out: str | Path | None = None,
) -> GnSummary:
    """Log accepted telemetry snapshots to ``out_csv`` until stopped or
    ``duration_s``. Blocks; returns the summary.

    ``events_out``: also write every event of every node (and the ground's
    own: joined, restarted, refused, script done) there, as JSON lines; an
    undecodable event is counted and skipped. ``as_node``: run as the
    mission's ``gn`` node (its endpoints, its liveliness token, its events
    published); otherwise as a tool connected to every node. ``idle_exit_s``:
    stop when no telemetry was accepted for this long *after* some was (the
    CN finished). ``script``: commands to play (the ground node under ``up
    --commands``).
    """
    stop = stop or StopFlag()
    node = "gn" if as_node and mission.has_ground else None
    link = GroundLink(mission, node=node, key_file=key_file, script=script or ())
    logic = link.logic
    try:
        tlog = TelemetryLog(logic.layout, out_csv, events_out)
    except BaseException:
        link.close()
        raise
    link.on_event = tlog.event  # events are handed over in this thread, by link.next
    start = time.monotonic()
    last_rx = start
    try:
        while not stop.is_set():
            if duration_s is not None and time.monotonic() - start >= duration_s:
                break
            t = link.next(0.2)
            if t is None:
                if (
                    idle_exit_s is not None
                    and logic.received
                    and time.monotonic() - last_rx > idle_exit_s
                ):
                    break
                continue
            last_rx = time.monotonic()
            tlog.snapshot(t, logic.dv)
        # Take what is already queued, so nothing received is dropped.
        while (t := link.next(0.0)) is not None:
            tlog.snapshot(t, logic.dv)
        logic.finish(link.clock.now_ns())
    finally:
        link.close()
        tlog.close()
    c = logic.counters
    player = logic.player
    return GnSummary(
        telemetry_received=c.received,
        final_state=logic.dv.get_name("cn_state") if c.received else None,
        telemetry_gaps=c.gaps,
        commands=player.results(logic) if player is not None else [],
        telemetry_bad=c.rejected,
        pending_commands=player.pending if player is not None else [],
        first_seq=c.first_seq,
        telemetry_refused={k: n for k, n in c.refused.items() if n},
        last_seq=c.last_seq,
        epoch_changes=c.epoch_changes,
        events_logged=tlog.event_count,
    )
