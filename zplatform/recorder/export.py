"""A recorder directory into the ground's files: ``zplatform log MISSION
--from-recorder DIR --out CSV``.

:func:`export` reads one node's recorder directory
(:class:`~.reader.RecorderReader`) and writes what it holds in the ground
log's formats: each recorded frame that checks like live telemetry (the
channel's tag, the layout of the mission given) as one row of the telemetry
CSV (:class:`~zplatform.telemetry.logs.CsvLogger`: same header, same rows; a
device node's directory gives its region ``dnX_to_cn``), and each event as
one line of the events JSONL (:class:`~zplatform.telemetry.logs.EventWriter`). A
row's ``rx_time_ns`` is the frame's own stamp, so the same frame gives the
same row whoever reads it (the ground's gap fill writes its rows the same way).

Contract: nothing in the directory stops the export: a damaged or torn
record, a frame whose tag or layout does not check, an event that does not
decode is skipped and counted with one line in
:attr:`ExportSummary.problems`, as are the loops the recorder dropped and
runs without their ``END`` record. Blocks on file I/O. See docs/operations.md#the-flight-recorder.
"""

from __future__ import annotations

from pathlib import Path

import msgspec

from ..config import Mission
from ..core.auth import Channel, KeySet, channel
from ..core.codec import RegionCodec
from ..core.datavector import DataVector, Layout
from ..core.events import decode_event
from ..errors import CodecError, FrameFormatError, RecordingError
from ..telemetry.logs import CsvLogger, EventWriter
from ..telemetry.records import EventRecord
from .format import DROPPED, END, EVENT, FRAME
from .reader import RecorderReader, SegmentHead, counts

__all__ = ["ExportSummary", "export", "frames_of", "reader_role", "recorded_node"]


class ExportSummary(msgspec.Struct, frozen=True):
    """What :func:`export` read and wrote.

    ``node``: whose directory; ``segments``: files read; ``rows``: CSV rows
    written (frames that checked); ``first_loop``/``last_loop``: of those
    rows (0 without any); ``events``: JSONL lines written; ``refused``:
    frames or events that did not check; ``damaged``: damaged records and
    unreadable files; ``not_recorded``: loops the recorder said it dropped;
    ``runs``/``runs_ended``: runs met, and those that ended with their END
    record; ``problems``: one line per refusal, damage and drop, in order;
    ``run_ids``: every run the directory holds; ``picked``: the run read
    (None: all of them).
    """

    node: str
    segments: int
    rows: int
    first_loop: int
    last_loop: int
    events: int
    refused: int
    damaged: int
    not_recorded: int
    runs: int
    runs_ended: int
    problems: list[str]
    run_ids: tuple[int, ...] = ()
    picked: int | None = None


def frames_of(
    mission: Mission, node: str, keys: KeySet | None
) -> tuple[Layout, str | None, Channel | None]:
    """What a node's recorder holds, for ``mission``: the layout of the
    frames (the CN: its whole vector; device node ``dnX``: its region
    ``dnX_to_cn``), the region (None: the whole vector) and the channel
    whose tag they carry (None without authentication). RecordingError for
    a node that does not record frames of this mission; KeyError_ when
    ``keys`` does not hold that channel's link (:func:`reader_role`)."""
    if node in mission.control_nodes:  # either control node records the whole vector
        return Layout.for_node(mission, "cn"), None, channel(keys, "telemetry")
    if node in mission.device_nodes:
        region = f"{node}_to_cn"
        return Layout.for_regions(mission, [region]), region, channel(keys, region)
    raise RecordingError(
        f"the recorder directory is node {node!r}'s, which is not the control node or a device "
        f"node of mission {mission.mission!r}"
    )


def reader_role(mission: Mission, node: str) -> str:
    """The host role whose keys check node ``node``'s recorded frames
    (:func:`zplatform.core.auth.load_keys`): ``tool`` for the CN's (telemetry,
    the downlink's key, which every ground holds), the device node itself
    for a DN's (its replies, tagged with the key of its link to the CN,
    which only the DN and the CN hold), ``tool`` for any other name, which
    :func:`export` refuses."""
    return node if node in mission.device_nodes else "tool"


def recorded_node(directory: str | Path) -> str:
    """The node whose recorder directory ``directory`` is (its first
    readable segment header); RecordingError when no segment has one."""
    return _first_head(RecorderReader(directory), directory).node


def _first_head(reader: RecorderReader, directory: str | Path) -> SegmentHead:
    first = reader.first_head()
    if first is None:
        raise RecordingError(
            f"{str(directory)!r}: no segment has a readable header: nothing to read"
        )
    return first


def export(
    directory: str | Path,
    mission: Mission,
    keys: KeySet | None,
    csv_path: str | Path,
    events_path: str | Path | None,
    *,
    run: int | str | None = None,
) -> ExportSummary:
    """Write the recorder directory ``directory`` as a telemetry CSV and an
    events JSONL (module doc). Blocks on file I/O.

    RecordingError before anything is written when the directory holds no
    readable segment or is of a node (or a layout) that is not
    ``mission``'s, KeyError_ when ``keys`` cannot check its frames
    (:func:`reader_role` says whose keys can); everything else is counted
    in the summary. ``run``: only that run's records (its id, the CN epoch,
    or ``"last"``); None reads every run in the directory, in file order
    (:attr:`ExportSummary.run_ids` names them). RecordingError for a run the
    directory does not hold."""
    reader = RecorderReader(directory)
    first = _first_head(reader, directory)
    run_ids = _run_ids(reader)
    if run == "last":
        run = run_ids[-1] if run_ids else None
    if run is not None and run not in run_ids:
        held = ", ".join(str(r) for r in run_ids) or "none"
        raise RecordingError(f"{str(directory)!r} holds no run {run} (its runs: {held})")
    layout, region, ch = frames_of(mission, first.node, keys)
    dv = DataVector(layout)
    codec = RegionCodec(dv, region)
    if first.layout_id != codec.layout_id:
        raise RecordingError(
            f"{str(directory)!r} was recorded with another Data Vector layout "
            f"({first.layout_id:#010x}) than mission {mission.mission!r}'s "
            f"({codec.layout_id:#010x}): read it with the mission file it flew"
        )
    problems: list[str] = reader.problems  # the reader's own lines, in order with ours
    n = {"rows": 0, "events": 0, "refused": 0, "not_recorded": 0}
    loops = [0, 0]
    runs: set[int] = set()
    ended: set[int] = set()
    skipped: set[int] = set()  # segments refused whole (their header does not fit)

    def refuse(text: str) -> None:
        n["refused"] += 1
        problems.append(text)

    def usable(head: SegmentHead) -> bool:
        if head.segment in skipped:
            return False
        why = ""
        if head.node != first.node:
            why = f"it is node {head.node!r}'s, not {first.node!r}'s"
        elif head.layout_id != codec.layout_id:
            why = f"its layout {head.layout_id:#010x} is not the mission's {codec.layout_id:#010x}"
        if why:
            skipped.add(head.segment)
            problems.append(f"{head.path.name}: {why}: its records are skipped")
            return False
        return True

    csv = CsvLogger(csv_path, layout)
    events = EventWriter(events_path) if events_path is not None else None
    try:
        for head, rec in reader.records():
            if (run is not None and head.run != run) or not usable(head):
                continue
            runs.add(head.run)
            where = f"{head.path.name}: offset {rec.offset}"
            if rec.type == FRAME:
                try:
                    body = ch.open(rec.payload) if ch is not None else rec.payload
                    frame = codec.check(body)
                except CodecError as exc:
                    refuse(f"{where}: frame of loop {rec.loop} refused: {exc}")
                    continue
                codec.write(frame)
                csv.write(frame.t_ns, dv)
                n["rows"] += 1
                loops[0] = loops[0] or frame.seq
                loops[1] = frame.seq
            elif rec.type == EVENT:
                try:
                    e = decode_event(rec.payload)
                except FrameFormatError as exc:
                    refuse(f"{where}: event refused: {exc}")
                    continue
                if events is not None:
                    events.write(EventRecord.of(e, e.t_ns))
                n["events"] += 1
            elif rec.type == DROPPED:
                c = counts(rec.payload)
                if c is None:
                    refuse(f"{where}: malformed DROPPED record")
                    continue
                a, b, k = c
                n["not_recorded"] += k
                problems.append(
                    f"{where}: the recorder dropped {k} loop(s) ({a}..{b}): not recorded"
                )
            elif rec.type == END:
                ended.add(head.run)
            else:
                refuse(f"{where}: unknown record type {rec.type}: skipped")
    finally:
        csv.close()
        if events is not None:
            events.close()
    for run in sorted(runs - ended):
        problems.append(
            f"run {run} has no END record: it is still running, or it ended by a kill, a "
            "crash or a power loss (what was written before is read)"
        )
    return ExportSummary(
        node=first.node,
        segments=len(reader.segments),
        rows=n["rows"],
        first_loop=loops[0],
        last_loop=loops[1],
        events=n["events"],
        refused=n["refused"],
        damaged=reader.damaged,
        not_recorded=n["not_recorded"],
        runs=len(runs),
        runs_ended=len(ended),
        problems=problems,
        run_ids=tuple(run_ids),
        picked=run if isinstance(run, int) else None,
    )


def _run_ids(reader: RecorderReader) -> list[int]:
    """Every run the directory's segments belong to, oldest first (by id:
    a run's id is its CN epoch, which grows from run to run)."""
    ids: set[int] = set()
    for index, path in reader.segments:
        head = reader.head_of(index, path)
        if head is not None:
            ids.add(head.run)
    return sorted(ids)
