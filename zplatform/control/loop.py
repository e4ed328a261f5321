"""The sans-IO loop of each node: regions in, frames out.

:class:`ControlLogic` (the CN) and :class:`DeviceLogic` (a DN) own a node's
Data Vector, its codecs, everything that runs on it each loop, *and the
protocol order*. They never touch zenoh, a socket or the wall clock; two
drivers move their frames (the zenoh runtime, :mod:`zplatform.node`, and the
lockstep runner, :mod:`zplatform.sim.lockstep`), neither with an order of its own.

Contract: a CN loop is ``begin(n, t, final=...)`` -> ``reply(i, payload)`` per
DN -> ``finish(ground_frame, ...)`` (the telemetry frame, or None); a DN
trigger is ``trigger(payload, now)`` (the reply, framed from ``dnX_to_cn`` as
it stood before this loop's run) then ``run(t)``. Every input that changes the
Data Vector passes through these calls, so a recorder attached to them
(:attr:`ControlLogic.recorder`) captures what a replay needs, bit for bit.
Nothing blocks; a step allocates nothing; a late reply is counted, a malformed
one counted and evented; neither raises.

The map of the loop (order, last loop, bulk and health ports, interlock):
docs/architecture.md#the-loop.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Any, Protocol, overload

from .. import trace
from ..boards import Board, HealthCounters, safe_board
from ..boards.world import node_board
from ..config import BOARD_LINK_COUNTERS, Mission, interlocked_nodes
from ..config.codes import CommandStatus, SafedWhy
from ..core.auth import (
    NO_RUN,
    RUN_LEN,
    TAG_LEN,
    AuthError,
    Channel,
    KeySet,
    Run,
    RunError,
    channel,
)
from ..core.codec import Frame, RegionCodec, bundle_entry, is_bundle
from ..core.components import Streak
from ..core.datavector import DataVector, Handle, Layout
from ..core.events import EV, EventLog, EventType
from ..core.health import HealthInput, HealthPort
from ..errors import CodecError, ConfigError
from .authority import IDENTITY_LINK
from .commands import CommandHandler, RequestNumber
from .controllers import ControllerSet
from .devices import DeviceSet
from .faults import FaultMonitor
from .fencing import (
    TERM_MAX,
    ProbeReply,
    TermGuard,
    Verdict,
    attested_term,
    read_ask,
    reply_frame,
)
from .intake import CnRefusals, RefusalLog
from .interlocks import OutputInterlock
from .monitors import MonitorSet
from .params import ParamTable, SaveResult
from .statemachine import StateMachine

__all__ = ["BulkPort", "ControlLogic", "DeviceLogic", "LoopRecorder"]

_U32 = struct.Struct("<I")
_U32_MAX = 0xFFFF_FFFF
# A trigger stamped this much later than the last one served, yet with a
# lower loop number, comes from a restarted control node.
_RESTART_NS = 1_000_000_000
_BACKLOG = "skipped in a backlog"


class LoopRecorder(Protocol):
    """What :class:`ControlLogic` tells a recorder, in call order, per loop.

    Implementations must not block or allocate per call
    (:class:`zplatform.sim.replay_recording.Recorder` copies into preallocated chunks).
    """

    def begin(self, loop: int, t_ns: int, final: bool, standby: bool) -> None: ...

    def reply(self, i: int, payload: bytes | bytearray | memoryview | None) -> None: ...

    def health(self, block: bytes | bytearray | memoryview) -> None:
        """The health block the loop copied in (health loops only, before ``finish``)."""

    def finish(
        self,
        grounds: Sequence[bytes | bytearray | memoryview],
        sync_overrun: bool,
        loop_overruns: int,
        inbox_dropped: int,
        refused: CnRefusals | None,
        saves: Sequence[SaveResult],
        telemetry: bytearray | memoryview | None,
    ) -> None: ...


class BulkPort(Protocol):
    """A node's bulk channel ends as its loop uses them (module doc).

    ``arrays``: every channel's array by name, handed to the components (the
    owned ones they fill, the read ones holding the newest sample). The
    methods are called on the loop thread, in the loop's order; none may
    block beyond a channel's ``alloc_timeout_ms`` or raise for a lost
    sample (it is counted).
    """

    arrays: dict[str, Any]

    def receive(self, loop: int) -> None:
        """Take the newest sample of every read channel into its array."""

    def publish(self, loop: int, t_ns: int) -> None:
        """Publish every owned channel due on ``loop``."""

    def write_counters(self, dv: DataVector) -> None:
        """Write the channels' counters into the node's Data Vector."""


class ControlLogic:
    """The control node's loop (module doc).

    Construction builds the CN's Data Vector (every region), its codecs and
    every component, checking the mission (ConfigError naming the YAML
    path). No method raises for a valid mission: bad frames are counted,
    controller exceptions are caught by the
    :class:`~zplatform.control.controllers.ControllerSet`. Not thread-safe: one loop
    thread calls ``begin``, ``reply`` and ``finish`` in that order.
    Buffers returned by ``begin`` and ``finish`` are the codecs' own and are
    overwritten by the next loop: hand them to the transport (which copies)
    first.
    """

    def __init__(
        self,
        mission: Mission,
        *,
        events: EventLog | None = None,
        keys: KeySet | None = None,
        epoch: int = 0,
        name: str = "cn",
    ) -> None:
        if name not in mission.control_nodes:
            raise ConfigError(
                f"{name!r} is not a control node of mission {mission.mission!r}; control "
                f"nodes: {mission.control_nodes}",
                "$.nodes",
            )
        self.mission = mission
        self.name = name
        """This control node's name: ``cn``, or the standby ``cn_b``."""
        self.layout = Layout.for_node(mission, "cn")
        self.dv = dv = DataVector(self.layout)
        # This run's epoch: command requests must carry it (a request made
        # for an earlier run of the CN is refused, not replayed).
        dv.set("cn_epoch", epoch)
        self.auth_run = run = Run(epoch)
        """The run this node's channels are bound to (zplatform.core.auth.Run): its
        ``cn_epoch``, followed by :meth:`adopt` (a resumed or mirrored vector
        brings its run), or learned by a standby's clock exchange with the
        commander. Every frame it sends names it; the replies, probe answers
        and mirrors it takes must be of it."""
        self._h_epoch = dv.handle("cn_epoch")
        self.events = events if events is not None else EventLog(name)
        self.faults = FaultMonitor(mission, dv, self.events)
        self.statemachine = StateMachine(mission, dv, self.events)
        self.params = ParamTable(mission, dv, self.events)
        """The mission's parameters: load the file before loop 1
        (:meth:`~zplatform.control.params.ParamTable.load`), take each PRM_SAVE's bytes
        after a loop (:meth:`~zplatform.control.params.ParamTable.take_save`)."""
        self.commands = CommandHandler(
            mission,
            dv,
            self.events,
            self.statemachine,
            params=self.params,
            # Every operator's and station's key derives from it (authority.py).
            operators_key=keys.link_key(IDENTITY_LINK)
            if keys is not None and keys.has(IDENTITY_LINK)
            else None,
        )
        self.controllers = ControllerSet(mission, "cn", dv, self.events, self.faults)
        self.monitors = MonitorSet(mission, dv, self.events, self.faults, self.statemachine)
        self._health = (
            HealthInput(mission, "cn", dv, self.events) if mission.health is not None else None
        )
        self.dns: tuple[str, ...] = tuple(mission.device_nodes)
        dns = self.dns
        # The CN's links (auth.py): every cn<->dnX, the uplink, the downlink.
        # Bound to this run (auth.Run), the uplink too: the ground learns the
        # run (its run hello, zplatform.runtime.clocksync.RunAsker) and tags
        # its requests in it; a request tagged in another run is refused
        # before any decode. One tagged in none (NO_RUN: a ground bound to no
        # run) is opened under the run-0 key: its data names the run it is
        # for (gn_cmd_epoch), which CommandHandler.admit checks, as before.
        self._seal_to_dn = tuple(channel(keys, f"cn_to_{dn}", run) for dn in dns)
        self._open_from_dn = tuple(channel(keys, f"{dn}_to_cn", run) for dn in dns)
        self._open_ground = channel(keys, "gn_to_cn", run) if mission.has_ground else None
        self._seal_tm = channel(keys, "telemetry", run)
        # What the CN sends is framed with room for its tag, tagged in place
        # (Channel.seal_tail): a frame up to the whole vector is copied once.
        self._to_dn = tuple(
            RegionCodec(dv, f"cn_to_{dn}", tail=TAG_LEN if ch is not None else 0)
            for dn, ch in zip(dns, self._seal_to_dn, strict=True)
        )
        self._from_dn = tuple(RegionCodec(dv, f"{dn}_to_cn") for dn in dns)
        self._ground = RegionCodec(dv, "gn_to_cn") if mission.has_ground else None
        self._tm = RegionCodec(dv, tail=TAG_LEN if self._seal_tm is not None else 0)
        self._frames: list[bytearray | memoryview] = [bytearray() for _ in dns]
        self.trigger_lengths: tuple[int, ...] = tuple(c.frame_len for c in self._to_dn)
        """Bytes of each DN's trigger frame, tag included (``dns`` order): what
        :meth:`begin`'s ``into`` views must hold."""
        self._dropped = dv.handle("cn_cmd_dropped")
        self._number = RequestNumber(self.layout) if self._ground is not None else None
        # Refusals at the driver's intake: one event a second at most.
        self._refusals = RefusalLog(8)  # CN_REFUSALS' seven counts, then those unchecked
        self._out_of_range = RefusalLog(1)  # replies naming a term no node can run
        self._shown = (0, 0)  # the refusal cn_cmd_reject_status/_seq show
        self._rx = tuple(dv.handle(f"cn_rx_{dn}") for dn in dns)
        self._missed = tuple(dv.handle(f"cn_missed_{dn}") for dn in dns)
        self._late = tuple(dv.handle(f"cn_late_{dn}") for dn in dns)
        self._bad = dv.handle("cn_bad_frames")
        self._unchecked = dv.handle("cn_unchecked_frames")
        self._mirror_refused = (
            dv.handle("cn_mirror_refused") if mission.standby is not None else None
        )
        self._recoveries = dv.handle("cn_query_recoveries")
        self._sync_overruns = dv.handle("cn_sync_overruns")
        self._loop_overruns = dv.handle("cn_loop_overruns")
        self._h_loop = dv.handle("cn_loop")
        self._h_time = dv.handle("cn_time_ns")
        self._final = tuple(dv.handle(f"{dn}_final") for dn in dns)
        # The CN's state travels in each trigger to a DN holding a hazardous
        # output (dnX_state): that DN's interlock judges its outputs by it.
        self._h_state = dv.handle("cn_state")
        self._state_dn = tuple(
            dv.handle(f"{dn}_state") for dn in dns if dn in interlocked_nodes(mission)
        )
        self._got = [False] * len(dns)
        self._divisor = mission.telemetry_divisor
        self.loop = 0
        self.t_ns = 0
        self.pending = 0
        """DNs whose reply for the current loop has not been applied yet."""
        self.recorder: LoopRecorder | None = None
        self._bulk: BulkPort | None = None
        # Terms (zplatform.control.fencing), in a mission with a standby control node.
        self.redundant = mission.standby is not None
        self.superseded = 0
        """A higher term that a majority of the device nodes have followed
        for more than ``failover.lease_loops`` loops in a row, seen in the
        replies (0: none): this control node no longer commands; its driver
        stands it down (:mod:`zplatform.control.failover`)."""
        self.mirror: bytearray | None = None
        """The last loop's mirror frame (the whole Data Vector, tagged for the
        standby; redundant missions only): the driver sends it every loop."""
        self._seal_mirror: Channel | None = None
        self._fenced = [False] * len(dns)
        self._fenced_seen = [0] * len(dns)  # the term each fenced reply named
        self._fenced_term = 0
        self._fenced_run = 0  # loops in a row a majority fenced this node
        self._lease_loops = mission.takeover.lease_loops
        if self.redundant:
            self._h_term = dv.handle("cn_term")
            self._h_commander = dv.handle("cn_commander")
            self._h_term_loop = dv.handle("cn_term_loop")
            self._h_ready = dv.handle("cn_standby_ready")
            self._term_dn = tuple(dv.handle(f"{dn}_term") for dn in dns)
            self._seen_at = tuple(
                dv.layout.element(f"{dn}_term_seen").offset - dv.layout.region(f"{dn}_to_cn").offset
                for dn in dns
            )
            self._seal_mirror = channel(keys, "mirror", run)

    @property
    def replied(self) -> Sequence[bool]:
        """Per DN (``dns`` order): its reply for the current loop was applied.
        The logic's own list, valid until the next :meth:`begin`; read it, never
        write it (no copy, so a per-loop reader allocates nothing)."""
        return self._got

    @property
    def term(self) -> int:
        """The term this control node's Data Vector is in (``cn_term``; 0
        in a mission without a standby)."""
        return int(self._h_term.get()) if self.redundant else 0

    # -- the loop ------------------------------------------------------------
    def begin(
        self,
        loop: int,
        t_ns: int,
        *,
        final: bool = False,
        standby: bool | None = None,
        into: Sequence[memoryview | None] | None = None,
    ) -> list[bytearray | memoryview]:
        """Open loop ``loop`` at ``t_ns``; returns the query frame of each DN
        (in ``mission.device_nodes`` order), stamped ``(loop, t_ns)``: the
        logic's own buffers (overwritten by the next call), or, for a DN whose
        ``into`` view is given (exactly its :attr:`trigger_lengths` bytes, e.g.
        a loaned shared-memory sample), that view, encoded and tagged in it
        (the same bytes; no copy of the frame besides the encode's).

        ``final``: this is the run's last loop (module doc): every frame
        carries ``dnX_final`` true. The platform owns that element: it is
        written here every loop, whatever a component wrote into it.
        ``standby``: a redundant mission's other control node is ready (its
        driver watches it; ``cn_standby_ready``, an input like ``final``;
        None: left as it is)."""
        self.loop = loop
        self.t_ns = t_ns
        # The run is the vector's (a resumed or taken-over one's included).
        self.auth_run.set(self._h_epoch.get())
        got = self._got
        frames = self._frames
        tr = trace.tracer
        term = 0
        if self.redundant:
            if standby is not None:
                self._h_ready.set(standby)
            term = self._h_term.get()
            if self._h_term_loop.get() > self._h_loop.get():
                # A term's first loop (take_command named the one planned; this
                # is the one that runs, should the set-up have outlasted it).
                self._h_term_loop.set(loop)
        if self._state_dn:
            state = self._h_state.get()
            for h in self._state_dn:
                h.set(state)
        for i, codec in enumerate(self._to_dn):
            got[i] = False
            self._final[i].set(final)
            if term:  # every trigger says which term sends it (fencing)
                self._term_dn[i].set(term)
                self._fenced[i] = False
            seal = self._seal_to_dn[i]
            if tr is not None:
                tr.mark("cn.encode", i)
            out = into[i] if into is not None else None
            if out is None:
                frame = codec.encode(loop, t_ns)
                if tr is not None:
                    tr.mark("cn.encoded", i)
                frames[i] = seal.seal_tail(frame) if seal is not None else frame
            else:
                view = codec.encode_into(out, loop, t_ns)
                if tr is not None:
                    tr.mark("cn.encoded", i)
                frames[i] = seal.seal_tail(view) if seal is not None else view
            if tr is not None:
                tr.mark("cn.sealed", i)
        self.pending = len(got)
        if self.recorder is not None:
            self.recorder.begin(loop, t_ns, final, bool(standby))
        return frames

    def trigger_frame(self, i: int) -> bytearray:
        """DN ``i``'s trigger of the current loop once more, in the logic's own
        buffer: the very bytes :meth:`begin` wrote (nothing between them
        changes the region, and the tag is a function of the bytes), for a
        driver whose shared-memory loan, which :meth:`begin` wrote into, could
        not go and whose frame zenoh carries instead. One encode and tag."""
        frame = self._to_dn[i].encode(self.loop, self.t_ns)
        seal = self._seal_to_dn[i]
        if seal is not None:
            frame = seal.seal_tail(frame)
        self._frames[i] = frame
        return frame

    def reply(self, i: int, payload: bytes | bytearray | memoryview | None) -> bool:
        """Take one reply from DN ``i`` (``None``: the DN answered with an error).

        Returns True when it is DN ``i``'s reply for the current loop and was
        applied; anything else is counted (late or bad frame) and dropped.
        """
        if self.recorder is not None:
            self.recorder.reply(i, payload)
        if payload is None:
            self._bad_frame(self.dns[i], "the device node answered with an error")
            return False
        codec = self._from_dn[i]
        tr = trace.tracer
        try:
            ch = self._open_from_dn[i]
            body = ch.open(payload) if ch is not None else payload
            if tr is not None:
                tr.mark("cn.opened", i)
            frame = codec.check(body)
            if tr is not None:
                tr.mark("cn.decoded", i)
        except CodecError as exc:
            self._bad_frame(self.dns[i], str(exc))
            return False
        if self.redundant and self.loop:
            seen = _U32.unpack_from(frame.data, self._seen_at[i])[0]
            if seen > TERM_MAX:  # no node can run it (zplatform.control.fencing): malformed
                self._bad.bump()
                ev = self._out_of_range.add(self.t_ns, 1)
                if ev is not None:  # an insider could send one a loop: once a second
                    self.events.emit(
                        EV.BAD_FRAME,
                        self.t_ns,
                        source=f"{ev[0]} repl(ies) from {self.dns[i]}",
                        reason=f"naming term {seen}, above the last a node can run ({TERM_MAX})",
                    )
                return False
            term = self._h_term.get()
            if seen != term:
                # DN i ran nothing of this term's: it follows a newer one (this
                # node is fenced), or still an older one (its lease).
                if seen > term and frame.seq == self.loop:
                    self._fenced[i] = True
                    self._fenced_seen[i] = seen
                return False
        if frame.seq != self.loop or self._got[i]:
            # an answer to an older loop (or a duplicate): counted, dropped
            self._late[i].bump()
            return False
        codec.write(frame)
        if tr is not None:
            tr.mark("cn.applied", i)
        self._got[i] = True
        self._rx[i].bump()
        self.pending -= 1
        return True

    @overload
    def finish(
        self,
        grounds: Sequence[bytes | bytearray | memoryview] = ...,
        *,
        sync_overrun: bool = ...,
        loop_overruns: int = ...,
        inbox_dropped: int = ...,
        refused: CnRefusals | None = ...,
        saves: Sequence[SaveResult] = ...,
        tm_into: None = None,
    ) -> bytearray | None: ...
    @overload
    def finish(
        self,
        grounds: Sequence[bytes | bytearray | memoryview] = ...,
        *,
        sync_overrun: bool = ...,
        loop_overruns: int = ...,
        inbox_dropped: int = ...,
        refused: CnRefusals | None = ...,
        saves: Sequence[SaveResult] = ...,
        tm_into: memoryview | None,
    ) -> bytearray | memoryview | None: ...
    def finish(
        self,
        grounds: Sequence[bytes | bytearray | memoryview] = (),
        *,
        sync_overrun: bool = False,
        loop_overruns: int = 0,
        inbox_dropped: int = 0,
        refused: CnRefusals | None = None,
        saves: Sequence[SaveResult] = (),
        tm_into: memoryview | None = None,
    ) -> bytearray | memoryview | None:
        """Close the loop: count misses, take one command request from
        ``grounds`` (the frames that arrived since the last loop, oldest
        first: each is checked, and refused, before one is chosen; of the
        valid ones the highest number wins, the others are counted in
        ``cn_cmd_dropped``; :meth:`_take_request`), run the logic; returns
        the telemetry frame on telemetry loops (``loop % telemetry_divisor
        == 0``), else None.

        With a bulk port attached, the newest samples of the channels the CN
        reads are taken (and the counters written) before the logic, and the
        owned channels due on this loop are published after it.

        ``sync_overrun``: the driver's sync step ran past its deadline;
        ``loop_overruns``: periods the driver's scheduler skipped since the
        last loop; ``inbox_dropped``: request frames the driver's bounded
        inbox had to drop since the last loop (counted in ``cn_cmd_dropped``);
        ``refused``: what the driver's intake refused as it arrived since the
        last loop (:class:`~zplatform.control.intake.CnRefusals`; module doc);
        ``saves``: parameter saves (PRM_SAVE) its saver finished since the
        last loop. All are inputs, not measured here, so a replay repeats them.
        ``tm_into``: a writable view of exactly :attr:`telemetry_length`
        bytes (a loaned shared-memory sample) that a telemetry frame of
        this loop is encoded and tagged in, and returned as (:meth:`telemetry`);
        unused on other loops.
        """
        loop, t = self.loop, self.t_ns
        for i, got in enumerate(self._got):
            if not got:
                self._missed[i].bump()
        if self.redundant and self._superseded_now():
            # A majority of the device nodes have followed a newer term for
            # longer than any promise lasts: another control node commands. This
            # one runs nothing more (its driver stands it down); one device node
            # alone, or a promise a standby let go, cannot make it stand down.
            self.superseded = self._fenced_term
            if self.recorder is not None:
                self.recorder.finish(
                    grounds, sync_overrun, loop_overruns, inbox_dropped, refused, saves, None
                )
            return None
        if sync_overrun:
            self._sync_overruns.bump()
        if loop_overruns:
            self._loop_overruns.bump(loop_overruns)
        if inbox_dropped:
            self._dropped.bump(inbox_dropped)
            self.events.emit(EV.CMD_DROPPED, t, n=inbox_dropped, why="the command inbox was full")
        self._refused(refused, t)
        for result in saves:
            self.params.saved(result, t)
        bulk = self._bulk
        if bulk is not None:  # the newest samples in, before any logic reads them
            bulk.receive(loop)
            bulk.write_counters(self.dv)
        new_request = False
        if grounds and self._ground is not None:
            new_request = self._take_request(grounds)
        self._h_loop.set(loop)
        self._h_time.set(t)
        health = self._health
        if health is not None and health.port is not None and loop % health.divisor == 0:
            block = health.port.take(t)
            health.apply(block, t)
            if self.recorder is not None:
                self.recorder.health(block)
        self.faults.step(t)
        if self.monitors.monitors:
            self.monitors.step(t)
        self.commands.step(new_request, t)
        self.statemachine.step(t)
        self.controllers.run(loop, t)
        tm: bytearray | memoryview | None = None
        if loop % self._divisor == 0:
            tm = self.telemetry(tm_into)
        if self.redundant:  # the standby mirrors the whole vector every loop
            # The same frame, tagged for the standby (a copy into the mirror
            # channel's buffer: the telemetry's tag sits in the encoder's).
            body: bytearray | memoryview = tm if tm is not None else self._tm.encode(loop, t)
            if self._seal_mirror is None:  # no keys: no tag anywhere
                # (A frame in a loan, which goes before the mirror does, is
                # copied: the CN never lends in a redundant mission.)
                self.mirror = body if type(body) is bytearray else bytearray(body)
            else:
                frame = memoryview(body)[: len(body) - TAG_LEN] if self._seal_tm else body
                self.mirror = self._seal_mirror.seal(frame)
        if bulk is not None:  # what the controllers filled goes out
            bulk.publish(loop, t)
        if self.recorder is not None:
            self.recorder.finish(
                grounds, sync_overrun, loop_overruns, inbox_dropped, refused, saves, tm
            )
        return tm

    def _superseded_now(self) -> bool:
        """This loop's replies: a majority fenced by a newer term, for more
        loops in a row than a device node's promise lasts (``lease_loops``).
        The newer term (:attr:`superseded`) is the one more than half of the
        device nodes attest, not the highest one named: a device node's
        insider among the fenced would pass TERM_MAX on to the standby this
        node becomes, leaving it no next term (issue 25)."""
        fenced = self._fenced
        if sum(fenced) * 2 > len(fenced):
            self._fenced_run += 1
        else:
            self._fenced_run = 0
        if self._fenced_run <= self._lease_loops:
            self._fenced_term = 0
            return False
        seen = [t for t, f in zip(self._fenced_seen, fenced, strict=True) if f]
        self._fenced_term = attested_term(seen, len(fenced))
        return True

    def _refused(self, r: CnRefusals | None, t: int) -> None:
        """Count what the intake refused (module doc): a frame refused for its
        size or its tag, or a sync reply not for the loop asked or from no
        DN, is a bad frame; a request refused for its tag, its run or its
        number is a reject that consumes no number, as the command handler
        counts one (:meth:`CommandHandler.count_refused`: ``cn_cmd_rejects``,
        the highest number in ``cn_cmd_reject_seq``). Evented together, at
        most once a second (a ``bad_frame`` and a ``cmd_rejected`` event).
        Of them, those dropped after their header, their body's MAC not
        checked (the intakes' budget spent: ``reply_unchecked``,
        ``cmd_unchecked``), also go into ``cn_unchecked_frames``, and the
        ``bad_frame`` event says how many. The sync's querier recoveries of
        the loop go into ``cn_query_recoveries`` (the driver events them),
        the mirrors the driver's intake refused into ``cn_mirror_refused``
        (the driver events them too)."""
        if r is not None and r.query_recovered:
            self._recoveries.bump(r.query_recovered)
        if r is not None and r.mirror_refused and self._mirror_refused is not None:
            self._mirror_refused.bump(r.mirror_refused)
        if r is not None and r.total:
            self._bad.bump(r.total - r.cmd_stale)  # a stale request is a reject, not a bad frame
            unchecked = r.reply_unchecked + r.cmd_unchecked
            if unchecked:
                self._unchecked.bump(unchecked)
            if r.cmd_bad or r.cmd_stale:
                self._shown = (r.cmd_status, r.cmd_seq)
                self.commands.count_refused(r.cmd_bad + r.cmd_stale, r.cmd_status, r.cmd_seq)
            ev = self._refusals.add(t, *r.fields()[:7], unchecked)
        else:
            ev = self._refusals.add(t)
        if ev is None:
            return
        rs, rb, rst, rf, cs, cb, cst, un = ev
        if rs + rb + rst + rf + cs + cb:
            self.events.emit(
                EV.BAD_FRAME,
                t,
                source=f"{rs + rb + rst + rf + cs + cb} frame(s)",
                reason=f"refused as they arrived: sync replies: {rs} of a wrong size, {rb} with "
                f"bad tags, {rst} replayed (not for the loop asked), {rf} from no device node; "
                f"command requests: {cs} of a wrong size, {cb} with bad tags" + _unchecked_note(un),
            )
        if cb + cst:
            status, seq = self._shown
            self.events.emit(
                EV.CMD_REJECTED,
                t,
                name="request",
                seq=seq,
                status=CommandStatus(status).name if status else "-",
                detail=f"{cb + cst} request(s) refused as they arrived: {cb} with bad tags, "
                f"{cst} replayed or for another run of the control node (the number and "
                "status shown: the highest number's)",
            )

    def _take_request(self, grounds: Sequence[bytes | bytearray | memoryview]) -> bool:
        """Check every request frame, refuse the ones that cannot be taken
        (a bad tag; a request for another CN run or a number not above the
        last seen: :meth:`CommandHandler.admit`, counted as rejects that
        consume no number) *before* choosing, then apply the valid one with
        the highest number: a replayed frame never displaces a fresh one.
        Returns whether one was applied."""
        assert self._ground is not None and self._number is not None
        best: Frame | None = None
        best_seq = -1
        valid = 0
        for payload in grounds:
            try:
                ch = self._open_ground
                body = (
                    ch.open(payload, any_run=Channel.run_of(payload) == NO_RUN)
                    if ch is not None
                    else payload
                )
                frame = self._ground.check(body)
            except RunError as exc:  # tagged in another run: refused before any decode
                self.commands.reject(CommandStatus.REJECTED_EPOCH, self.t_ns, detail=str(exc))
                continue
            except AuthError as exc:
                self._bad_frame("the ground", str(exc))
                self.commands.reject(CommandStatus.REJECTED_AUTH, self.t_ns, detail=str(exc))
                continue
            except CodecError as exc:
                self._bad_frame("the ground", str(exc))
                continue
            epoch, seq = self._number.read(frame.data)
            if not self.commands.admit(
                epoch, seq, self.t_ns, self._number.command(frame.data), frame.data
            ):
                continue
            valid += 1
            if seq > best_seq:
                best, best_seq = frame, seq
        if valid > 1:
            self._dropped.bump(valid - 1)
            self.events.emit(
                EV.CMD_DROPPED,
                self.t_ns,
                n=valid - 1,
                why="more than one in a loop; the highest number wins",
            )
        if best is None:
            return False
        self._ground.write(best)
        return True

    @property
    def telemetry_length(self) -> int:
        """Bytes of every telemetry frame, its tag included: what
        :meth:`telemetry`'s ``into`` must hold."""
        return self._tm.frame_len

    @overload
    def telemetry(self, into: None = None) -> bytearray: ...
    @overload
    def telemetry(self, into: memoryview) -> memoryview: ...
    def telemetry(self, into: memoryview | None = None) -> bytearray | memoryview:
        """The whole vector framed now, tagged (what :meth:`finish` returns on
        a telemetry loop; a driver's final snapshot off the divisor). One
        copy of the vector, into the telemetry encoder's buffer, which the
        next call overwrites, or into ``into`` (exactly :attr:`telemetry_length`
        bytes, a loaned shared-memory sample: the same bytes, tagged in
        place; ValueError for another length), returned then."""
        tr = trace.tracer
        if tr is not None:
            tr.mark("tm.encode", self.loop)
        seal = self._seal_tm
        if into is not None:
            view = self._tm.encode_into(into, self.loop, self.t_ns)
            if tr is not None:
                tr.mark("tm.encoded", self.loop)
            if seal is not None:
                seal.seal_tail(view)  # the tag in place, in the loan
            if tr is not None:
                tr.mark("tm.sealed", self.loop)
            return view
        tm = self._tm.encode(self.loop, self.t_ns)
        if tr is None:
            return seal.seal_tail(tm) if seal is not None else tm
        tr.mark("tm.encoded", self.loop)
        if seal is not None:
            tm = seal.seal_tail(tm)
        tr.mark("tm.sealed", self.loop)
        return tm

    def attach_bulk(self, port: BulkPort) -> None:
        """Move the CN's bulk channels through ``port`` from the next loop on
        (module doc) and give every controller its arrays (by channel)."""
        self._bulk = port
        for c in self.controllers.controllers:
            c.bulk = port.arrays

    def attach_health(self, port: HealthPort) -> None:
        """Take the CN's health block from ``port`` on health loops from the next
        loop on (module doc); ConfigError when the mission has no ``health:``."""
        _attach_health(self._health, port)

    def adopt(self) -> None:
        """Continue from the Data Vector as it stands (a standby's mirror, a
        resumed control node's recorded frame, a replay's first frame): every
        component takes up its state from it (docs/architecture.md#failover).

        Exact for what a mission keeps in the vector: the state and time in
        it, a hold, the pending command, the last request number and an ARM,
        the latched fault, the controllers' modes and their own state
        elements, the parameters. The persistence counts of the fault
        monitor and of the mission's monitors start over: a symptom must
        persist for its whole count under this control node (a later fault,
        never a spurious one). A parameter save that the node that wrote the
        vector was still writing is written again, by this node
        (:meth:`ParamTable.adopt <zplatform.control.params.ParamTable.adopt>`). Does
        nothing before loop 1 (a fresh vector: every component starts as built).
        The run (:attr:`auth_run`) becomes the vector's ``cn_epoch`` whatever the loop."""
        self.auth_run.set(int(self._h_epoch.get()))
        self.loop = int(self._h_loop.get())
        self.t_ns = t = int(self._h_time.get())
        if self.loop == 0:
            return
        self.statemachine.adopt(t)
        self.commands.adopt()
        self.faults.adopt()
        self.monitors.adopt()
        self.controllers.adopt()
        self.params.adopt(t)
        self.superseded = self._fenced_term = self._fenced_run = 0

    def take_command(self, term: int, loop: int) -> None:
        """Command from ``loop`` on in ``term`` (a takeover: ``cn_term``,
        ``cn_commander`` = this node, ``cn_term_loop``, which the term's first
        :meth:`begin` corrects to the loop that runs); call :meth:`adopt`
        first. ValueError in a mission without a standby."""
        if not self.redundant:
            raise ValueError("a mission without a standby control node has no terms")
        self._h_term.set(term)
        self._h_commander.set(self.mission.control_nodes.index(self.name))
        self._h_term_loop.set(loop)
        self.superseded = self._fenced_term = self._fenced_run = 0

    def reset_sync_counters(self) -> None:
        """Zero rx/missed/late per DN and the sync overruns (after a warm-up)."""
        for hs in (self._rx, self._missed, self._late):
            for h in hs:
                h.set(0)
        self._sync_overruns.set(0)

    def _bad_frame(self, source: str, reason: str) -> None:
        # Not our software failing: counted as a bad frame, not an error.
        # Rare by definition, so an event per frame is affordable and wanted.
        self._bad.bump()
        self.events.emit(EV.BAD_FRAME, self.t_ns, source=f"frame from {source}", reason=reason)


class DeviceLogic:
    """A device node's loop (module doc): trigger check, then board, sensors,
    controllers, actuators.

    ``board`` defaults to the board the node's ``board:`` config names
    (:func:`zplatform.boards.world.node_board`; built, not opened: the runtime
    opens it). ``keys``: the node's keys, its cn<->dnX link (None: the
    mission does not authenticate). ``stale_after_ns``: a trigger stamped (CN time) more than
    this long before ``now_ns`` belongs to a loop the CN has already closed;
    it is answered but does not run (None: never stale).

    A trigger must also be believable (so that no single frame can freeze
    the node): stamped no further ahead of this node's clock than the
    mission's clock-offset bound plus a period, and with a loop number no
    further ahead of the last one than the time between them allows. Such a
    frame is a bad frame, answered with an error.

    Fail safe: :meth:`watchdog` (the driver calls it whenever it waited
    without a trigger) safes the node after ``faults.dn_watchdog_loops``
    periods with no valid trigger: every actuator's safe value, the board's
    safe state, ``dnX_safed`` true, a warning event. The node stays safed
    (its actuators do not run) until the CN is back:
    ``faults.dn_reenable_loops`` valid triggers in a row, whose regions then
    carry what the CN commands now. A final trigger (``dnX_final``, the CN's
    last loop) safes the node the same way after its run, with an activity
    event: the run ended. :meth:`safe` does the same on demand (clean exit).

    A node that answers yet cannot run is safed too: when the CN's
    triggers keep arriving, authentic and each newer than the last, but
    none could run (every one stale, or outside the clock window) over
    ``faults.dn_watchdog_loops`` periods, of the CN's stamps and of this
    node's clock alike, the node safes with a warning naming why, and
    ``dnX_safed_why`` = ``CANNOT_RUN`` in its replies makes the CN latch
    ``DN_SAFED``. Counting only newer triggers over the CN's stamps, a
    replay of captured triggers cannot trip it; over this node's clock too,
    nor can a burst of late triggers served at once after the node stalled
    (a stall is the watchdog's: ``CN_LOST``, no fault). ``dnX_safed_why`` says why the node is safed
    (:class:`~zplatform.config.codes.SafedWhy`).

    Construction raises ConfigError (YAML path) for a bad device or
    controller. No method raises: device and controller exceptions are
    caught by their sets, and an exception of the board's own ``step`` (a
    physics hook bug, a board that cannot latch its inputs) is counted in
    ``dnX_errors`` and reported once per streak.

    The node's hazardous outputs (``hazardous_outputs``) are driven only
    in their states: after the controllers, :attr:`interlock` writes the
    safe value of each whose states do not include the one its trigger
    carries (``dnX_state``), counted in ``dnX_interlocked``.

    A board with a link (a driver of
    :data:`~zplatform.config.BOARD_LINK_DRIVERS`: serial, gpiod) is reported
    every run, right after its step: ``dnX_board_ok`` (that step succeeded)
    and the board's :class:`~zplatform.boards.HealthCounters` (timeouts,
    reconnects, bad frames, ...) in ``dnX_board_*``, which reach the CN with
    the next reply like everything the run writes. :attr:`board_link` says
    whether the node has them.
    """

    def __init__(
        self,
        mission: Mission,
        node: str,
        *,
        board: Board | None = None,
        events: EventLog | None = None,
        stale_after_ns: int | None = None,
        keys: KeySet | None = None,
        run: Run | None = None,
    ) -> None:
        if node not in mission.device_nodes:
            raise ConfigError(
                f"{node!r} is not a device node of mission {mission.mission!r}; device nodes: "
                f"{mission.device_nodes}",
                "$.nodes",
            )
        self.mission = mission
        self.node = node
        self.layout = Layout.for_node(mission, node)
        self.dv = dv = DataVector(self.layout)
        self.events = events if events is not None else EventLog(node)
        self.board: Board = board if board is not None else node_board(mission, node)
        self.devices = DeviceSet(mission, node, dv, self.board, self.events)
        self.controllers = ControllerSet(mission, node, dv, self.events)
        self.interlock = OutputInterlock(mission, node, dv, self.events)
        """The node's interlock on its hazardous outputs (:mod:`zplatform.control.interlocks`)."""
        self._health = (
            HealthInput(mission, node, dv, self.events) if mission.health is not None else None
        )
        self._in = RegionCodec(dv, f"cn_to_{node}")
        # This node's place in a sync bundle (one wildcard query for every DN).
        self._index = mission.device_nodes.index(node)
        # ``run``: the control node's run, learned by this node's clock
        # exchange (zplatform.core.auth.Run): triggers and questions of another run
        # are refused. None: any run's (a test's logic, fed by its own CN).
        # An answer names the run of what it answers (_answering).
        self.auth_run = run
        self._answering = Run()
        self._open: Channel | None = channel(keys, f"cn_to_{node}", run)
        self._seal: Channel | None = channel(keys, f"{node}_to_cn", self._answering)
        # The reply is framed with room for its tag, tagged in place.
        self._out = RegionCodec(dv, f"{node}_to_cn", tail=TAG_LEN if self._seal else 0)
        self.reply_length = self._out.frame_len
        """Bytes of every reply frame, tag included: what :meth:`trigger`'s
        ``into`` view must hold."""
        self._loop = dv.handle(f"{node}_loop")
        self._time = dv.handle(f"{node}_time_ns")
        self._errors = dv.handle(f"{node}_errors")
        self._bad = dv.handle(f"{node}_bad_frames")
        self._unchecked = dv.handle(f"{node}_unchecked_frames")
        self._h_safed = dv.handle(f"{node}_safed")
        self._h_safed_why = dv.handle(f"{node}_safed_why")
        self._h_final = dv.handle(f"{node}_final")
        # Where the flag sits in a trigger's data: read there in a trigger
        # too late to run, whose data is not applied.
        self._final_at = self._h_final.spec.offset - self.layout.region(f"cn_to_{node}").offset
        self._reenable_after = mission.faults.dn_reenable_loops
        self._back = 0  # valid triggers in a row while safed
        self._stale_after = stale_after_ns
        self._period = mission.period_ns
        self._max_ahead = round(mission.clock.offset_bound_ms * 1e6) + mission.period_ns
        self._watchdog_ns = mission.faults.dn_watchdog_loops * mission.period_ns
        self._board_streak = Streak()
        # The board's link (zplatform.config.board_link_elements), for a
        # board that has one: handles bound here, and the board's own
        # mutable HealthCounters read in place each run, because health()
        # builds a new struct per call. A board without HealthCounters (the
        # world's in-process port in lockstep, a test's) leaves the counters
        # at 0, so a lockstep run stays deterministic.
        self.board_link = f"{node}_board_ok" in self.layout.elements
        """Whether this node reports its board's link (``dnX_board_*``)."""
        self._h_board_ok: Handle | None = None
        self._board_counters: HealthCounters | None = None
        self._board_counts: tuple[tuple[Handle, str], ...] = ()
        if self.board_link:
            self._h_board_ok = dv.handle(f"{node}_board_ok")
            counters = getattr(self.board, "counters", None)
            if isinstance(counters, HealthCounters):
                self._board_counters = counters
                self._board_counts = tuple(
                    (dv.handle(f"{node}_board_{suffix}"), attr)
                    for suffix, attr, _ in BOARD_LINK_COUNTERS
                )
        self._bulk: BulkPort | None = None
        self._refusals = RefusalLog(4)  # size, bad, stale, then those unchecked
        # Terms (zplatform.control.fencing), in a mission with a standby control node:
        # where the trigger's term sits in its data, and this node's guard.
        self.guard: TermGuard | None = None
        self._term_at = 0
        self._fenced_log = RefusalLog(2)
        self._probe_log = RefusalLog(5)  # size, bad, stale, excess, then those unchecked
        self._term_log = RefusalLog(1)  # triggers naming a term no node can run
        self._askers = len(mission.control_nodes)
        if mission.standby is not None:
            self.guard = TermGuard(mission.takeover.lease_loops * mission.period_ns)
            self._h_term = dv.handle(f"{node}_term")
            self._term_at = self._h_term.spec.offset - self.layout.region(f"cn_to_{node}").offset
            self._h_term_seen = dv.handle(f"{node}_term_seen")
            self._open_probe = channel(keys, f"probe_cn_to_{node}", run)
            self._seal_probe = channel(keys, f"probe_{node}_to_cn", self._answering)
        self.fenced = 0
        """Triggers answered but not run because of their term (a lower term's,
        or a higher one's while the current commander is alive)."""
        self.last_loop = 0
        self.last_t_ns = 0
        self.last_trigger_ns: int | None = None
        """This node's time at the last valid trigger (None before the first)."""
        # The newest authentic trigger seen, run or not; and, since the last
        # one that ran, the CN stamp of the first newer one that could not.
        self._seen_loop = 0
        self._seen_t = 0
        self._unrun_since: int | None = None
        self._unrun_since_here = 0
        self._unrun = 0
        self.safed = False
        self._safed_by: EventType | None = None
        self.safed_why = ""
        """Why the node was last safed ("" if it never was)."""
        self.stale = 0
        """Triggers answered but not run (older loop, stale, or not newest)."""
        self.triggered = 0
        """The loop the last :meth:`trigger` started, or 0 if it started none."""
        self._pending: Frame | None = None  # that trigger's frame, for run() to apply
        self.reject_reason = ""
        """Why the last :meth:`trigger` returned None."""

    @overload
    def trigger(
        self,
        payload: bytes | bytearray | memoryview,
        now_ns: int,
        *,
        may_run: bool = ...,
        authentic: bool = ...,
        into: None = ...,
    ) -> bytearray | None: ...

    @overload
    def trigger(
        self,
        payload: bytes | bytearray | memoryview,
        now_ns: int,
        *,
        may_run: bool = ...,
        authentic: bool = ...,
        into: memoryview | None,
    ) -> bytearray | memoryview | None: ...

    def trigger(
        self,
        payload: bytes | bytearray | memoryview,
        now_ns: int,
        *,
        may_run: bool = True,
        authentic: bool = False,
        into: memoryview | None = None,
    ) -> bytearray | memoryview | None:
        """Check one CN query frame (or a sync bundle holding it) and frame the reply.

        Returns the reply (``dnX_to_cn`` before this loop's run, stamped with
        the trigger's loop and ``now_ns``), or None for a malformed,
        unauthentic or unbelievable frame (counted in ``dnX_bad_frames``,
        reason in :attr:`reject_reason`; the driver answers with an error).
        Sets :attr:`triggered` to the loop to run, or 0: a query for a loop
        not newer than the last one served, a stale one, or one the driver
        says may not run (``may_run=False``: a backlog the DN skips) is
        answered but not applied. A trigger that starts a loop is applied
        (its data copied into the ``cn_to_dnX`` region) by :meth:`run`, after
        the reply has gone; its frame's data is a view into ``payload``, so
        the caller keeps ``payload`` unchanged until then (the live driver's
        are immutable ``bytes``; :meth:`step` runs at once).

        ``authentic``: the caller checked this very payload's tag with this
        node's ``cn_to_dnX`` key already (the driver's intake,
        :class:`~zplatform.control.intake.TriggerIntake`, on zenoh's thread), so it
        is not computed again here: the tag is only stripped
        (:meth:`~zplatform.core.auth.Channel.strip`). A whole-vector trigger's tag
        costs tens of microseconds to hundreds (HMAC-SHA256), on the sync's
        critical path (``python -m bench.frame_trace``). Without it (the
        default, and every caller but the live driver) the tag is checked.

        ``into``: a writable view of exactly :attr:`reply_length` bytes (a
        loaned shared-memory sample) the reply is framed and tagged in, and
        returned (the same bytes; no copy besides the encode's); None: the
        logic's own buffer, overwritten by the next reply. Left unwritten
        when the trigger is refused.
        """
        self.triggered = 0
        tr = trace.tracer
        last = self.last_trigger_ns
        if last is not None and not self.safed and now_ns - last > self._watchdog_ns:
            # This node was not running (stopped, starved) for longer than
            # the watchdog: whatever it drove meanwhile was unsupervised.
            self.safe(now_ns, f"no valid trigger for {(now_ns - last) / 1e6:.0f} ms")
        newer = False
        guard = self.guard
        verdict = Verdict.SAME
        try:
            if is_bundle(payload):  # a wildcard query: this node's frame from the bundle
                payload = bundle_entry(payload, self._index)
            ch = self._open
            body = (
                payload
                if ch is None
                else ch.strip(payload)
                if authentic
                else ch.open(payload, any_run=True)
            )
            if tr is not None:
                tr.mark("dn.opened")
            frame = self._in.check(body)
            if ch is not None:
                self._run_of_trigger(payload, frame.seq)
            if tr is not None:
                tr.mark("dn.decoded")
            # Authentic from here on.
            if guard is not None and frame.seq > 0:
                term = _U32.unpack_from(frame.data, self._term_at)[0]
                if term > TERM_MAX:  # no commander can run it (zplatform.control.fencing)
                    self._out_of_range(term, now_ns)
                    return None
                verdict = guard.admit(term, now_ns, self.last_trigger_ns)
                if verdict == Verdict.FENCED or verdict == Verdict.LEASED:
                    return self._fence(frame, term, verdict, now_ns, into)
            # Loop 0 is the CN's warm-up, never a loop.
            newer = frame.seq > 0 and (
                frame.seq > self._seen_loop or frame.t_ns > self._seen_t + _RESTART_NS
            )
            if newer:
                self._seen_loop, self._seen_t = frame.seq, frame.t_ns
            self._believable(frame, now_ns)
        except CodecError as exc:
            self._bad.bump()
            self.reject_reason = str(exc)
            self.events.emit(EV.BAD_FRAME, now_ns, source="sync query", reason=exc)
            if newer:  # the CN's, but outside this node's clock window
                self._not_run(frame.t_ns, now_ns, exc)
            return None
        # A lower seq with a later timestamp is a restarted CN, not an old
        # query: follow it rather than stall forever.
        late = self._stale_after is not None and now_ns - frame.t_ns > self._stale_after
        # Loop 0 (the CN's warm-up) is answered, never run: it does not arm
        # the watchdog either (the CN's first loop may come a while later).
        new = (
            may_run
            and frame.seq > 0
            and (frame.seq > self.last_loop or frame.t_ns > self.last_t_ns + _RESTART_NS)
            and not late
        )
        if new:
            # The data goes into the region in run(), not here: the reply
            # (the region before this loop's run) leaves without waiting for
            # the copy, up to a whole region's on the sync's critical path.
            self._pending = frame
            self.last_loop = frame.seq
            self.last_t_ns = frame.t_ns
            self.last_trigger_ns = now_ns
            self.triggered = frame.seq
            self._unrun_since = None
            if guard is not None and verdict == Verdict.NEW:
                self._new_term(frame.seq, now_ns, term)
        else:
            self.stale += 1
            if newer:
                self._not_run(frame.t_ns, now_ns, None if late else _BACKLOG)
            if frame.seq > self.last_loop and frame.data[self._final_at]:
                # The CN's last loop, come too late to run: the run ended all the same.
                self._safe(
                    now_ns,
                    f"the control node's run ended (its last loop, {frame.seq}, came too "
                    "late to run here)",
                    EV.DN_SAFED_RUN_ENDED,
                    SafedWhy.RUN_ENDED,
                )
        if guard is not None:
            self._h_term_seen.set(guard.seen(now_ns))
        if into is not None:
            view = self._out.encode_into(into, frame.seq, now_ns)
            if tr is not None:
                tr.mark("dn.encoded")
            if self._seal is not None:
                self._seal.seal_tail(view)
            if tr is not None:
                tr.mark("dn.sealed")
            return view
        reply = self._out.encode(frame.seq, now_ns)
        if tr is None:
            return self._seal.seal_tail(reply) if self._seal is not None else reply
        tr.mark("dn.encoded")
        if self._seal is not None:
            reply = self._seal.seal_tail(reply)
        tr.mark("dn.sealed")
        return reply

    def _out_of_range(self, term: int, now_ns: int) -> None:
        """An authentic trigger naming a term above
        :data:`~zplatform.control.fencing.TERM_MAX`: a bad frame, never run nor
        followed (the driver answers with an error); evented at most once a
        second (a control node's key could send one a loop)."""
        self._bad.bump()
        self.reject_reason = f"a trigger of term {term}: above {TERM_MAX}"
        ev = self._term_log.add(now_ns, 1)
        if ev is not None:
            self.events.emit(
                EV.BAD_FRAME,
                now_ns,
                source=f"{ev[0]} sync quer(ies)",
                reason=self.reject_reason,
            )

    def _new_term(self, loop: int, now_ns: int, term: int) -> None:
        """The trigger just taken to run carries a higher term: follow it."""
        guard = self.guard
        assert guard is not None
        old = guard.term
        guard.ran(term)
        self.events.emit(
            EV.DN_NEW_TERM,
            now_ns,
            node=self.node,
            term=term,
            old=old,
            loop=loop,
        )

    def _fence(
        self, frame: Frame, term: int, verdict: int, now_ns: int, into: memoryview | None
    ) -> bytearray | memoryview:
        """Answer a trigger whose term this node does not run (zplatform.control.fencing):
        the reply says which term it follows (``dnX_term_seen``); nothing of
        the trigger is applied and nothing runs. Evented once a second at most."""
        guard = self.guard
        assert guard is not None
        self.fenced += 1
        self.stale += 1
        lower = verdict == Verdict.FENCED
        ev = self._fenced_log.add(now_ns, int(lower), int(not lower))
        if ev is not None:
            quiet = (
                f"{(now_ns - self.last_trigger_ns) / 1e6:.0f} ms ago"
                if self.last_trigger_ns is not None
                else "never"
            )
            self.events.emit(
                EV.DN_TERM_FENCED,
                now_ns,
                node=self.node,
                n=sum(ev),
                term=term,
                seen=guard.seen(now_ns),
                why=f"{ev[0]} of a lower term, {ev[1]} of a higher term while its own "
                f"term still drives it (its last trigger ran {quiet})",
            )
        self._h_term_seen.set(guard.seen(now_ns))
        if into is not None:
            view = self._out.encode_into(into, frame.seq, now_ns)
            return self._seal.seal_tail(view) if self._seal is not None else view
        reply = self._out.encode(frame.seq, now_ns)
        return self._seal.seal_tail(reply) if self._seal is not None else reply

    def _run_of_trigger(self, payload: bytes | bytearray | memoryview, loop: int) -> None:
        """Answer in the run of the authentic trigger ``payload``; RunError
        (a CodecError) when it is of another run than this node's and not
        the warm-up (loop 0: answered, never run, changes nothing; a
        restarted control node sends it before it knows whether it resumes
        the run, zplatform.control.role)."""
        self._answer_run_of(payload)
        run = self.auth_run
        if run is not None and loop > 0 and self._answering.epoch != run.epoch:
            raise RunError(
                f"cn_to_{self.node}: a trigger of run {self._answering.epoch}, not of this "
                f"run ({run.epoch})"
            )

    def _answer_run_of(self, payload: bytes | bytearray | memoryview) -> None:
        """Answer in the run of the authentic ``payload`` (its tag's run word;
        re-keys the answering channels only when the run changes)."""
        n = len(payload) - TAG_LEN
        word = memoryview(payload)[n : n + RUN_LEN]
        if word != self._answering.word:
            self._answering.set(int.from_bytes(word, "little"))

    def probe(self, payload: bytes | bytearray | memoryview, now_ns: int) -> bytes | None:
        """Answer a control node's probe question (:mod:`zplatform.control.fencing`):
        the reply frame, or None for a question that is not authentic or
        not one (counted in ``dnX_bad_frames``; the driver answers with an
        error). Only in a mission with a standby control node."""
        guard = self.guard
        if guard is None:
            return None
        try:
            ask = read_ask(self._open_probe, payload, self._index, self._askers)
            if self._open_probe is not None:
                self._answer_run_of(payload)
        except CodecError as exc:
            # Counted and evented with the intake's refusals (at most once a
            # second: without authentication junk gets this far).
            self.reject_reason = str(exc)
            self.probes_refused(0, 1, 0, 0, now_ns, reason=self.reject_reason)
            return None
        last = self.last_trigger_ns
        granted = guard.answer(ask.kind, ask.asker, ask.term, now_ns, last)
        self._h_term_seen.set(guard.seen(now_ns))
        return reply_frame(
            self._seal_probe,
            ProbeReply(
                self._index,
                ask.nonce,
                guard.term,
                guard.promised(now_ns),
                granted,
                int(self._h_safed_why.get()),
                -1 if last is None else now_ns - last,
                self.last_loop,
                self.last_t_ns,
            ),
        )

    def refused(self, size: int, bad: int, stale: int, now_ns: int, *, unchecked: int = 0) -> None:
        """Count the sync queries the driver's intake refused as they arrived
        (:class:`~zplatform.control.intake.TriggerIntake`), unanswered: ``size`` of a
        wrong size, ``bad`` with a bad tag, ``stale`` replayed (not newer
        than the last trigger, or another run's genuine trigger: an earlier
        run's, zplatform.core.auth.Run). Each is a bad frame
        (``dnX_bad_frames``, in the lockstep runner as live); of them,
        ``unchecked`` were dropped after their header, their body's MAC not
        checked (the intake's budget spent,
        :attr:`~zplatform.control.intake.Intake.took_unchecked`), also
        counted in ``dnX_unchecked_frames``. They are evented together, at
        most once a second (:class:`~zplatform.control.intake.RefusalLog`).
        Call it whenever the driver waited, with zeros too: the last counts
        of a burst go out then."""
        if size or bad or stale:
            self._bad.bump(size + bad + stale)
        if unchecked:
            self._unchecked.bump(unchecked)
        ev = self._refusals.add(now_ns, size, bad, stale, unchecked)
        if ev is not None:
            self.events.emit(
                EV.BAD_FRAME,
                now_ns,
                source=f"{sum(ev[:3])} sync quer(ies)",
                reason=f"refused as they arrived, unanswered: {ev[0]} of a wrong size, "
                f"{ev[1]} with bad tags, {ev[2]} replayed (not newer than the last trigger, "
                "or another run's)" + _unchecked_note(ev[3]),
            )

    def probes_refused(
        self,
        size: int,
        bad: int,
        stale: int,
        excess: int,
        now_ns: int,
        *,
        reason: str = "",
        unchecked: int = 0,
    ) -> None:
        """Count the probe questions refused (:class:`~zplatform.control.intake.ProbeIntake`
        as they arrived, unanswered, or :meth:`probe`): ``size`` of a wrong
        size, ``bad`` with a bad tag or out of range, ``stale`` replayed,
        ``excess`` beyond the rate bound. Each is a bad frame
        (``dnX_bad_frames``; ``unchecked`` of them, dropped after their
        header for want of body-MAC budget, also in
        ``dnX_unchecked_frames``), evented together at most once a second
        (``reason``: the last refusal's, if any). Call it whenever the
        driver waited, with zeros too."""
        n = size + bad + stale + excess
        if n:
            self._bad.bump(n)
        if unchecked:
            self._unchecked.bump(unchecked)
        ev = self._probe_log.add(now_ns, size, bad, stale, excess, unchecked)
        if ev is not None:
            self.events.emit(
                EV.BAD_FRAME,
                now_ns,
                source=f"{sum(ev[:4])} probe question(s)",
                reason=f"refused: {ev[0]} of a wrong size, {ev[1]} bad (tag or values), "
                f"{ev[2]} replayed, {ev[3]} beyond the rate bound"
                + _unchecked_note(ev[4])
                + (f"; the last: {reason}" if reason else ""),
            )

    def _not_run(self, stamp_ns: int, now_ns: int, why: object) -> None:
        """An authentic trigger newer than any seen could not run (class doc):
        safe the node once the CN's stamps span the watchdog without a run.
        ``why``: what refused it (None: stale); text is made only to safe."""
        since = self._unrun_since
        if since is None:
            self._unrun_since = stamp_ns
            self._unrun_since_here = now_ns
            self._unrun = 1
            return
        self._unrun += 1
        span = stamp_ns - since
        # Both clocks: the CN's stamps (a replay repeats its stamp) and this
        # node's own (a burst of late triggers served at once after a stall
        # spans no time here: the stall is the watchdog's, CN_LOST).
        if (
            span < self._watchdog_ns
            or now_ns - self._unrun_since_here < self._watchdog_ns
            or self._h_safed_why.get() == SafedWhy.CANNOT_RUN
        ):
            return
        if why is None:
            why = f"stamped {(now_ns - stamp_ns) / 1e6:.1f} ms before this node's clock (stale)"
        self._safe(
            now_ns,
            f"{self._unrun} triggers of the control node over {span / 1e6:.0f} ms and none "
            f"could run, the last {why}: is this node's clock off?",
            EV.DN_SAFED,
            SafedWhy.CANNOT_RUN,
        )

    def _believable(self, frame: Frame, now_ns: int) -> None:
        ahead = frame.t_ns - now_ns
        if ahead > self._max_ahead:
            raise CodecError(
                f"stamped {ahead / 1e6:.3f} ms ahead of this node's clock (at most "
                f"{self._max_ahead / 1e6:.3f} ms is believable)"
            )
        if self.last_loop and frame.seq > self.last_loop:
            # Loop numbers advance with time (skipped periods included).
            allowed = max(frame.t_ns - self.last_t_ns, 0) // self._period + 2
            if frame.seq - self.last_loop > allowed:
                raise CodecError(
                    f"loop {frame.seq} is {frame.seq - self.last_loop} loops past the last one "
                    f"({self.last_loop}) but only {allowed} periods later"
                )

    def run(self, t_ns: int) -> None:
        """Run the loop :meth:`trigger` started, at ``t_ns``: bulk samples in,
        board, sensors, controllers, actuators (not while safed), then the owned
        bulk channels out and their counters; after the CN's last loop (a
        final trigger), the node safes itself (class doc). First, the
        trigger's data goes into its region (:meth:`trigger` leaves that
        copy to here, after the reply)."""
        pending = self._pending
        if pending is not None:
            self._pending = None
            tr = trace.tracer
            if tr is not None:
                tr.mark("dn.apply")
            self._in.write(pending)
            if tr is not None:
                tr.mark("dn.applied")
        loop = self.triggered
        bulk = self._bulk
        if bulk is not None:  # the newest samples in, before the run reads them
            bulk.receive(loop)
        self._loop.set(loop)
        self._time.set(t_ns)
        health = self._health
        if health is not None and health.port is not None and loop % health.divisor == 0:
            health.apply(health.port.take(t_ns), t_ns)
        if self.safed:
            self._back += 1
            if self._back >= self._reenable_after:
                self.safed = False
                self._safed_by = None
                self._h_safed.set(False)
                self._h_safed_why.set(SafedWhy.NONE)
                self.events.emit(EV.DN_REENABLED, t_ns, node=self.node, n=self._back)
        try:
            self.board.step(t_ns)
            self._board_streak.ok()
            board_ok = True
        except Exception as exc:
            self._board_failed(exc, t_ns)
            board_ok = False
        if self._h_board_ok is not None:
            self._write_board_link(board_ok)
        self.devices.run_sensors(loop, t_ns)
        self.controllers.run(loop, t_ns)
        if not self.safed:  # while safed, outputs stay at their safe values
            if self.interlock.active:  # a hazardous output outside its states: safe
                self.interlock.apply(t_ns)
            self.devices.run_actuators(loop, t_ns)
        if bulk is not None:  # after the run: the reply has gone already
            bulk.publish(loop, t_ns)
            bulk.write_counters(self.dv)
        if self._h_final.get():
            self._safe(
                t_ns,
                f"the control node's run ended (its last loop was {loop})",
                EV.DN_SAFED_RUN_ENDED,
                SafedWhy.RUN_ENDED,
            )

    def step(self, payload: bytes | bytearray | memoryview, now_ns: int) -> bytearray | None:
        """:meth:`trigger` then, if it started a loop, :meth:`run` at ``now_ns``;
        returns the reply (the lockstep runner's one call per DN and loop)."""
        reply = self.trigger(payload, now_ns)
        if self.triggered:
            self.run(now_ns)
        return reply

    @property
    def run_ended(self) -> bool:
        """The control node's run ended (its last loop ran here, or came too
        late to): this node is safed and waits for a new run. A plain read,
        safe from another thread (it is a reference compare)."""
        return self._safed_by is EV.DN_SAFED_RUN_ENDED

    def attach_bulk(self, port: BulkPort) -> None:
        """Move the node's bulk channels through ``port`` from the next run on
        (module doc) and give every component its arrays (by channel)."""
        self._bulk = port
        for c in [*self.controllers.controllers, *self.devices.devices]:
            c.bulk = port.arrays

    def attach_health(self, port: HealthPort) -> None:
        """Take the node's health block from ``port`` on health loops from the
        next run on (module doc); ConfigError when the mission has no ``health:``."""
        _attach_health(self._health, port)

    def watchdog(self, now_ns: int) -> bool:
        """Safe the node if it has had no valid trigger for
        ``faults.dn_watchdog_loops`` periods (armed by the first trigger).
        Returns whether the node is safed. Cheap: call it whenever the driver waited in vain."""
        if self.safed:
            return True
        if self.last_trigger_ns is None:
            return False  # armed by the first trigger: nothing was driven before it
        quiet = now_ns - self.last_trigger_ns
        if quiet > self._watchdog_ns:
            self.safe(now_ns, f"no valid trigger from the control node for {quiet / 1e6:.0f} ms")
        return self.safed

    def safe(self, t_ns: int, why: str, *, exiting: bool = False) -> None:
        """Write every actuator's safe value and the board's safe state;
        stay safed until the CN is back (class doc). ``exiting``: a clean
        exit (an activity, not a warning). Never raises."""
        if exiting:
            self._safe(t_ns, why, EV.DN_SAFED_AT_EXIT, SafedWhy.STOPPING)
        else:
            self._safe(t_ns, why, EV.DN_SAFED, SafedWhy.CN_LOST)

    def _safe(self, t_ns: int, why: str, ev: EventType, code: SafedWhy) -> None:
        self.devices.safe_actuators(t_ns)
        safe_board(self.board)
        self._back = 0
        # One event per safing; but a new reason is told even to a node
        # safed already (a stall, then the run's end; a run's end, then
        # triggers that cannot run): from now on it is safed for that one.
        if self.safed and not (
            (ev is EV.DN_SAFED_RUN_ENDED and self._safed_by is not ev)
            or (code is SafedWhy.CANNOT_RUN and self._h_safed_why.get() != code)
        ):
            return
        self.safed = True
        self._safed_by = ev
        self.safed_why = why
        self._h_safed.set(True)
        self._h_safed_why.set(code)
        self.events.emit(ev, t_ns, node=self.node, why=why)

    def _write_board_link(self, ok: bool) -> None:
        """``dnX_board_ok`` and the board's counters into ``dnX_board_*``:
        read in place, set through handles bound at start-up, so nothing is
        built per loop (``health()`` would build a struct)."""
        assert self._h_board_ok is not None
        self._h_board_ok.set(ok)
        c = self._board_counters
        for h, attr in self._board_counts:
            n = getattr(c, attr)
            # The board's counts are unbounded ints; the elements are u32 and
            # saturate like every platform counter (Handle.bump), never wrap.
            h.set(n if n < _U32_MAX else _U32_MAX)

    def _board_failed(self, exc: Exception, t_ns: int) -> None:
        self._errors.bump()
        if self._board_streak.fail() == 1:
            self.events.emit(
                EV.BOARD_FAILED, t_ns, node=self.node, exc_type=type(exc).__name__, exc=exc
            )


def _attach_health(health: HealthInput | None, port: HealthPort) -> None:
    if health is None:
        raise ConfigError("the mission has no `health:` section: no health elements", "$.health")
    health.port = port


def _unchecked_note(n: int) -> str:
    """What a refusal event adds for frames dropped after their header, their
    body's MAC not checked (the intake's budget, MAC_SPARE, spent)."""
    if not n:
        return ""
    return (
        f"; {n} of them dropped after their header, unchecked (the body-MAC budget spent: "
        "genuine headers on other bodies, a man in the middle)"
    )
