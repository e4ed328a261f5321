"""The on-board flight recorder: each vehicle node keeps its own telemetry and
events on local storage, and the ground fills its telemetry gaps from the
CN's. Not to be confused with :mod:`zplatform.sim.replay_recording`, which
records a CN's loop *inputs* for a bit-exact replay (``up --record``).

A mission turns it on with a ``recorder:`` section
(:class:`~zplatform.config.RecorderConfig`); each node of
``Mission.recording_nodes`` then writes a ring of segment files into its own
directory (:func:`recorder_dir`): the CN every telemetry frame it publishes,
a device node every reply frame it sends for a loop it runs, both every event.
The package: :mod:`.format` (the records, the gap-fill exchange),
:mod:`.writer` (:class:`FlightRecorder`: the loop copies, a thread writes),
:mod:`.reader` (:class:`RecorderReader`), :mod:`.export` (a directory into
the ground's CSV and JSONL) and :mod:`.server` (the CN's gap-fill queryable).

Contract: the loop's side never blocks and drops whole loops, counted, when
its buffer is full; a reader never misreads a damaged record.

The design: docs/architecture.md#flight-recorder; the files: codecs/FORMAT.md (section 12).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from ..config import Mission
from ..core.auth import TAG_LEN
from ..core.codec import RegionCodec
from ..core.datavector import DataVector
from ..errors import RecordingError
from .export import ExportSummary, export, frames_of, reader_role, recorded_node
from .format import HEADER_LEN
from .reader import RecorderReader
from .writer import FlightRecorder

__all__ = [
    "RECORDER_DIR_ENV",
    "ExportSummary",
    "FlightRecorder",
    "RecorderReader",
    "export",
    "open_recorder",
    "reader_role",
    "recorded_node",
    "recorder_dir",
    "summary_line",
]

RECORDER_DIR_ENV = "ZPLATFORM_RECORDER_DIR"
_EVENT_ROOM = 64 * 1024  # buffer room for a burst of events on top of the frames


def recorder_dir(mission: Mission, node: str) -> Path:
    """Where ``node`` of ``mission`` records: ``$ZPLATFORM_RECORDER_DIR/<mission>/<node>``
    when that is set, else ``<recorder.dir>/<node>`` (made absolute when the
    mission loaded), else ``zplatform/recorder/<mission>/<node>`` in the
    state directory (``$XDG_STATE_HOME``, ``~/.local/state``; ``/var/lib``
    for root)."""
    env = os.environ.get(RECORDER_DIR_ENV)
    if env:
        return Path(env) / mission.mission / node
    rec = mission.recorder
    if rec is not None and rec.dir is not None:
        return Path(rec.dir) / node
    if os.geteuid() == 0:
        base = Path("/var/lib")
    else:
        base = Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state")
    return base / "zplatform" / "recorder" / mission.mission / node


def open_recorder(
    mission: Mission, node: str, dv: DataVector, *, run: int, authenticated: bool
) -> FlightRecorder:
    """Start ``node``'s flight recorder (its ``recorder`` section) for the run
    ``run`` (the CN: its epoch; a device node: its start time), reporting
    into ``dv`` (the node's Data Vector; ``<node>_rec_*`` counters) once
    :meth:`~FlightRecorder.attach`-ed. ``authenticated``: the frames carry a
    tag. RecordingError when it cannot start (the directory, its lock)."""
    cfg = mission.recorder
    if cfg is None or node not in mission.recording_nodes:
        raise RecordingError(f"mission {mission.mission!r} does not record node {node!r}")
    layout, region, _ = frames_of(mission, node, None)
    frame_len = RegionCodec(dv, region).max_frame_len + (TAG_LEN if authenticated else 0)
    per_s = mission.loop_hz / (mission.telemetry_divisor if node in mission.control_nodes else 1)
    loops = max(2, math.ceil(cfg.buffer_ms / 1000 * per_s))
    head = {
        "mission": mission.mission,
        "vehicle": mission.vehicle,
        "node": node,
        "run": run,
        "kind": "telemetry" if region is None else region,
        "layout_id": layout.layout_id if region is None else layout.region(region).layout_id,
        "channel": ("telemetry" if region is None else region) if authenticated else None,
        "period_ns": mission.period_ns,
        "telemetry_divisor": mission.telemetry_divisor,
    }
    return FlightRecorder(
        recorder_dir(mission, node),
        head,
        max_bytes=cfg.max_bytes,
        file_bytes=cfg.file_bytes,
        fsync_ms=cfg.fsync_ms,
        buffer_bytes=loops * (HEADER_LEN + frame_len) + _EVENT_ROOM,
        max_record=frame_len,
        interval_s=max(mission.period_ns / 1e9, 0.005),
    )


def summary_line(rec: FlightRecorder) -> str:
    """What a recorder kept, for the node's log at its end: ``12000 loop(s) and
    5 event(s) kept, 0 loop(s) dropped, 3.2 MB written, 0 file(s) removed, 0
    error(s) -> DIR``."""
    s = rec.stats()
    err = f" (last: {s['last_error']})" if s["errors"] else ""
    return (
        f"{s['loops']} loop(s) and {s['events']} event(s) kept, {s['dropped_loops']} loop(s) "
        f"dropped, {int(s['bytes']) / 1e6:.1f} MB written, {s['evicted_files']} file(s) removed, "
        f"{s['errors']} error(s){err} -> {rec.directory}"
    )
