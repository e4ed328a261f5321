"""The on-board flight recorder: each vehicle node keeps its own telemetry and
events on local storage, and the ground fills its telemetry gaps from the
CN's (issue 20). Not to be confused with :mod:`zplatform.replay_recording`, which
records a CN's loop *inputs* for a bit-exact replay (``up --record``).

A mission turns it on with a ``recorder:`` section
(:class:`~zplatform.config.RecorderConfig`); each node of
``Mission.recording_nodes`` then writes a ring of segment files into its own
directory (:func:`recorder_dir`):

* :mod:`.format`: the record on disk (self-delimiting, CRC-32 checked), the
  segment files, the gap-fill request and reply;
* :mod:`.writer`: :class:`FlightRecorder`, the loop's side (copies into a
  preallocated RAM buffer, never blocks, drops whole loops and counts them)
  and the writer thread (segments, the ring bound, the fsync policy);
* :mod:`.reader`: :class:`RecorderReader`, every record that checks and a
  line for every one that does not;
* :mod:`.export`: a directory into the ground log's CSV and events JSONL
  (``zplatform log MISSION --from-recorder DIR``);
* :mod:`.server`: the CN's queryable ``{vehicle}/cn/recorder`` that answers
  the ground's gap-fill requests (:mod:`zplatform.ground.gapfill`).

What each node records: the CN, every telemetry frame it publishes (the
same authenticated frame); a device node, every reply frame it sends for a
loop it runs (its region ``dnX_to_cn`` as it stood before that loop's run:
what the CN received, or would have); both, every event they publish. The
ground node records nothing: its log is the ground's record.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from ..auth import TAG_LEN
from ..codec import RegionCodec
from ..config import Mission
from ..datavector import DataVector
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
