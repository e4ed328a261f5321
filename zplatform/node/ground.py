"""Ground Node Main (thesis 4.15): the ground node's runtime, and ``zplatform log``.

A thin driver: a :class:`~zplatform.ground.link.GroundLink` (one session,
the telemetry subscriber, the event intake, the command publisher when a
script is played) feeds the ground's sans-IO
:class:`~zplatform.ground.logic.GroundLogic`, which checks every snapshot,
keeps the CN-layout Data Vector (thesis 4.15), counts gaps and refusals,
and plays the command script. This module only logs what the logic
accepted (:class:`~zplatform.ground.logger.TelemetryLog`; the ground node
also into its :class:`~zplatform.archive.ArchiveWriter`, handed off, unless
the mission's ``archive`` is off) until it is told to stop, and reports.

When the mission's CN has a flight recorder, the log goes through a
:class:`~zplatform.ground.gapfill.GapFill`: a gap a link loss leaves is
asked of the CN's recorder (``{vehicle}/cn/recorder``) as soon as the link
is back, and the rows it brings are written in loop order, before the
snapshots that arrived meanwhile. At the end, fills still open get up to
:data:`FILL_GRACE_S` to finish.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from ..config import Mission
from ..control.authority import Signer
from ..control.handoff import Mailbox
from ..control.uplink import ScriptCommand
from ..core.datavector import DataVector, Layout
from ..errors import ZPlatformError
from ..ground.gapfill import GapFill
from ..ground.link import GroundLink
from ..ground.logger import TelemetryLog
from ..runtime.process import StopFlag
from ..telemetry.records import EventRecord
from ..telemetry.summary import GnSummary

if TYPE_CHECKING:
    from ..archive import ArchiveWriter
    from ..archive.server import ArchiveServer

__all__ = ["run_ground_logger", "run_station", "station_dir"]

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
    signer: Signer | None = None,
    station: str | None = None,
    archive: str | Path | None = None,
    append: bool = False,
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
    --commands``). ``signer``: the operator and station the script's
    requests name (a mission with ``ground:``), who keeps the command lock
    while they hold it (:class:`~zplatform.ground.logic.GroundLogic`).
    ``station`` (with ``as_node`` False): run as that station of
    ``ground.stations`` (:func:`run_station`): through its router, keeping
    the signer's lock with the uplink's publisher (host role ``gn``), and
    archiving into ``archive`` (its own directory, not served).
    ``append``: keep what ``out_csv`` and ``events_out`` hold and log after
    it (:class:`~zplatform.ground.logger.TelemetryLog`), as a station does;
    otherwise they are written anew, as every ``--log`` file is.
    """
    stop = stop or StopFlag()
    node = "gn" if as_node and mission.has_ground else None
    keep_lock = station is not None and signer is not None and node is None
    link = GroundLink(
        mission,
        node=node,
        key_file=key_file,
        script=script or (),
        signer=signer,
        station=station,
        commands=keep_lock,
    )
    logic = link.logic
    try:
        tlog = TelemetryLog(logic.layout, out_csv, events_out, append=append)
    except BaseException:
        link.close()
        raise
    if node == "gn":
        arch = _open_archive(mission, logic.layout)
    elif archive is not None:
        arch = _open_archive(mission, logic.layout, Path(archive))
    else:
        arch = None
    if station is not None:
        # What `up` waits for (its supervisor): the station's session is open.
        print("READY", flush=True)
    # A station's archive is its own (a tool's certificate may declare no
    # queryable): the ground node's alone answers archive queries.
    serve = _serve_archive(link, arch) if arch is not None and node == "gn" else None
    sink: _Sink = tlog if arch is None else _Tee(tlog, arch)
    link.on_event = sink.event  # events are handed over in this thread, by link.next
    fill = _Filler(link, sink) if "cn" in mission.recording_nodes else None
    start = time.monotonic()
    last_rx = start
    try:
        while not stop.is_set():
            if duration_s is not None and time.monotonic() - start >= duration_s:
                break
            t = link.next(0.2 if fill is None or not fill.busy else 0.02)
            tlog.tick(link.clock.now_ns(), logic.events)
            if arch is not None:
                arch.tick(link.clock.now_ns(), logic.events)
            if fill is not None:
                fill.pump()
            if t is None:
                if (
                    idle_exit_s is not None
                    and logic.received
                    and time.monotonic() - last_rx > idle_exit_s
                    and (fill is None or not fill.busy)
                ):
                    break
                continue
            last_rx = time.monotonic()
            if fill is not None:
                fill.fill.snapshot(logic, t)
            else:
                sink.snapshot(t, logic.dv)
        # Take what is already queued, so nothing received is dropped.
        while (t := link.next(0.0)) is not None:
            if fill is not None:
                fill.fill.snapshot(logic, t)
            else:
                sink.snapshot(t, logic.dv)
        if fill is not None:
            fill.drain(FILL_GRACE_S)
        logic.finish(link.clock.now_ns())
        link.next(0.0)  # the ground's last events (fills, verdicts) into the log
    finally:
        if serve is not None:
            serve.close()
        link.close()
        tlog.close()
        if arch is not None:
            arch.close()
            log.info("archive: %s -> %s", arch.stats(), arch.root)
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
        telemetry_filled=fill.fill.filled if fill is not None else 0,
        telemetry_unfilled=fill.fill.unfilled if fill is not None else 0,
        telemetry_not_run=fill.fill.not_run if fill is not None else 0,
        events_missed=c.events_missed,
        events_filled=fill.fill.events_filled if fill is not None else 0,
        events_unfilled=fill.fill.events_unfilled if fill is not None else 0,
        telemetry_iox=c.iox,
        telemetry_duplicates=c.duplicates,
        telemetry_fallbacks=c.path_fallbacks,
        telemetry_unchecked=c.unchecked,
    )


def station_dir(mission: Mission, station: str) -> Path:
    """The directory of a station ``up`` starts (``ground.stations[].start``):
    ``<the mission's archive directory>.stations/<station>`` (its events,
    its telemetry log with ``up --log``, its archive under ``archive/``),
    beside the ground node's archive, never inside it. Reads nothing."""
    from ..archive import archive_dir

    root = archive_dir(mission)
    return root.with_name(root.name + ".stations") / station


def run_station(
    mission: Mission,
    station: str,
    directory: str | Path,
    *,
    signer: Signer | None = None,
    log_csv: bool = False,
    duration_s: float | None = None,
    stop: StopFlag | None = None,
) -> GnSummary:
    """Run as ``station`` of ``mission``'s ``ground.stations`` until stopped
    or ``duration_s`` (``zplatform station``; what ``up`` starts for a
    station with ``start: true``): a ground tool (the tool's certificate)
    connected through the station's router (``connect``) or to every node,
    receiving the CN's telemetry and every node's events, which it writes
    into ``directory`` (made, 0700): ``events.jsonl``, ``telemetry.csv``
    with ``log_csv``, and its archive under ``archive/`` when the mission
    archives. The directory is the station's record across its runs and
    restarts: both logs are appended to, never truncated (a CSV of another
    layout is left alone: the rows go to ``telemetry.N.csv``), and the
    archive keeps each run apart, each loop once. With ``signer`` (its
    operator at this station) it keeps their command lock while they hold
    it; it sends nothing else. Prints ``READY`` once its session is open.
    Blocks; returns its summary. Raises KeyError_ for a missing key,
    TransportError when the session cannot open, CommandError for a
    station the mission does not list."""
    from ..errors import CommandError

    g = mission.ground
    if g is None or not any(s.name == station for s in g.stations):
        listed = ", ".join(s.name for s in g.stations) if g is not None else "none"
        raise CommandError(
            f"mission {mission.mission!r} lists no station {station!r} (stations: {listed})"
        )
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True, mode=0o700)
    return run_ground_logger(
        mission,
        d / "telemetry.csv" if log_csv else None,
        as_node=False,
        duration_s=duration_s,
        stop=stop,
        events_out=d / "events.jsonl",
        signer=signer,
        station=station,
        archive=d / "archive",
        append=True,
    )


class _Sink(Protocol):
    def snapshot(self, rx_ns: int, dv: DataVector) -> None: ...
    def event(self, rec: EventRecord) -> None: ...


class _Tee:
    """The log and the archive, fed the same snapshots and events."""

    def __init__(self, tlog: TelemetryLog, arch: ArchiveWriter) -> None:
        self.tlog, self.arch = tlog, arch

    def snapshot(self, rx_ns: int, dv: DataVector) -> None:
        self.tlog.snapshot(rx_ns, dv)
        self.arch.snapshot(rx_ns, dv)

    def event(self, rec: EventRecord) -> None:
        self.tlog.event(rec)
        self.arch.event(rec)


def _open_archive(
    mission: Mission, layout: Layout, root: Path | None = None
) -> ArchiveWriter | None:
    """The ground node's archive (a station's: in ``root``), or None when the
    mission turns it off or it cannot open (said in the log: the ground logs
    and commands without it)."""
    if not mission.archive.enabled:
        return None
    try:
        from ..archive import ArchiveWriter, archive_dir

        return ArchiveWriter(mission, layout, root if root is not None else archive_dir(mission))
    except ZPlatformError as exc:
        log.warning("no archive: %s", exc)
        return None


def _serve_archive(link: GroundLink, arch: ArchiveWriter) -> ArchiveServer | None:
    """Answer archive queries on ``{vehicle}/archive/query`` (None: it cannot
    be declared; said in the log)."""
    from ..archive import Archive
    from ..archive.server import ArchiveServer
    from ..core.auth import channel

    m = link.mission
    try:
        return ArchiveServer(
            link.ns.session,
            link.keys.archive,
            lambda: Archive(m, arch.root, recover=False),
            channel(link.link_keys, "telemetry"),
            max_age_ns=ARCHIVE_ASK_WINDOW_NS,
            serve_bps=m.archive.serve_bps,
            max_bytes=m.archive.serve_max_bytes,
            per_asker=m.archive.serve_per_asker,
            asker_bps=m.archive.serve_asker_bps,
        )
    except Exception as exc:  # zenoh's errors are not ours: the ground goes on without
        log.warning("the archive is not served over zenoh: %s", exc)
        return None


ARCHIVE_ASK_WINDOW_NS = 60 * 10**9
"""How long after its hello an archive ask is still taken (zplatform.archive.server):
room for the asks a long answer in hand keeps waiting."""
FILL_GRACE_S = 10.0
"""How long a log that ends waits for gap fills still in flight."""
FILL_BACKLOG = 1024
"""Gap-fill replies (chunks of frames) waiting for the ground's thread, at most."""


class _Filler:
    """Drives a :class:`GapFill` over the link: sends its requests as zenoh
    gets, hands it their replies (queued by zenoh's callbacks)."""

    def __init__(self, link: GroundLink, tlog: _Sink) -> None:
        self.link = link
        self.fill = GapFill(
            link.mission,
            link.link_keys,
            link.logic.events,
            tlog.snapshot,
            run=link.logic.run,
            logic=link.logic,  # the CN's missing events too, handed to the log
            on_event=tlog.event,
        )
        # Bounded like every hand-off from zenoh: a peer flooding replies
        # lets the oldest go, and the loops they held are asked for again
        # or told unfilled by the gap fill, never lost silently.
        self._q: Mailbox[tuple[int, bytes | None]] = Mailbox(FILL_BACKLOG)

    @property
    def busy(self) -> bool:
        return self.fill.busy

    def pump(self) -> None:
        """Replies in, requests out, time on; never blocks."""
        fill, now = self.fill, self.link.clock.now_ns
        while (item := self._q.pop()) is not None:
            rid, payload = item
            if payload is None:
                fill.on_done(rid, now())
            else:
                fill.on_reply(rid, payload)
        req = fill.take_request(now())
        if req is not None:
            rid, payload, timeout_s = req
            self.link.query(self.link.keys.recorder, payload, timeout_s, self._q, rid, fill.screen)
        fill.tick(now())

    def drain(self, grace_s: float) -> None:
        """The log ends: let open fills finish (at most ``grace_s``), then
        write everything held."""
        deadline = time.monotonic() + grace_s
        while self.fill.busy and time.monotonic() < deadline:
            self.pump()
            self.link.next(0.02)  # the ground's own events meanwhile
        self.fill.finish(self.link.clock.now_ns())
