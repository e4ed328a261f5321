"""A control node's role, sans-IO: who commands, follows or takes over.

:class:`ControlRole` holds every protocol decision a control node makes about
*whether* it commands: at start-up (one STATUS probe round: ``Command`` or
``Follow``; after the warm-up: ``Resume`` from the flight recorder or
``StartOver``), as a commander (``StandDown`` on a newer term in a mirror or
in most device nodes' replies) and as a standby (per slot of the commander's
schedule: ``Probe`` STATUS, then ASK only if the commander is silent to the
device nodes too, then ``Take`` or ``Release``, through its
:class:`~zplatform.control.failover.Standby`).

Contract: its two drivers, the zenoh runtime (:mod:`zplatform.node.control`)
and the lockstep runner (:mod:`zplatform.sim.lockstep`), only deliver its inputs
and carry out the actions it returns. It reads no clock (every input comes
with its time), opens nothing and starts no thread; it writes only the
node's own :class:`~zplatform.control.loop.ControlLogic` (its vector and events) and
its Standby. Not thread-safe: the node's loop thread.

The inputs, the actions and their order: docs/architecture.md#failover.
"""

from __future__ import annotations

from typing import NamedTuple

from ..config import Mission
from ..config.codes import SafedWhy
from ..core.auth import KeySet, channel
from ..core.codec import Frame, RegionCodec
from ..core.events import EV
from ..errors import CodecError, NodeError
from .failover import Decision, MirrorReader, Standby
from .fencing import ASK, STATUS, next_term
from .loop import ControlLogic

__all__ = [
    "RESUME_MAX_AGE_NS",
    "Command",
    "ControlRole",
    "Follow",
    "Probe",
    "Release",
    "Resume",
    "StandDown",
    "StartOver",
    "Take",
    "check_recorded",
]

RESUME_MAX_AGE_NS = 60_000_000_000
"""A restarted control node resumes from a recorded frame at most this old."""


class Command(NamedTuple):
    """Command from the start: ``term`` 0 for the first term of a fresh run
    (or a mission without terms), else the term to resume a driverless run in."""

    term: int


class Follow(NamedTuple):
    """Follow as the standby; ``term``: the newest the device nodes run (0: none yet)."""

    term: int
    ran: bool


class Resume(NamedTuple):
    """Resume the run from the recorder's frame (already written and adopted
    into the logic): ``origin`` is the time of the schedule's loop 1, ``loop``
    the recorded frame's loop."""

    origin: int
    loop: int


class StartOver(NamedTuple):
    """Restarted in flight without a usable record: start over (evented)."""

    why: str


class StandDown(NamedTuple):
    """A newer term commands: this node stood down and follows (``why``);
    ``followed``: the newer term's mirror that told it was applied (its
    first as the standby)."""

    why: str
    followed: bool = False


class Probe(NamedTuple):
    """Send ``asks`` (one per device node, ``kind`` STATUS or ASK); hand each
    answer to :meth:`ControlRole.answer`, then call :meth:`ControlRole.round_over`."""

    kind: int
    asks: list[bytes]


class Take(NamedTuple):
    """Take command from ``loop`` on (or the first loop of the schedule not yet begun)."""

    loop: int


class Release(NamedTuple):
    """Send the RELEASE questions (None: nothing to release for that device node)."""

    releases: list[bytes | None]


class ControlRole:
    """One control node's role (module doc). ``logic``: the node's control
    logic; ``keys``: its keys. A redundant mission's node starts as neither
    (``standby`` None, :attr:`commanding` False until :meth:`start`); a
    mission without a standby's node commands."""

    def __init__(self, mission: Mission, logic: ControlLogic, keys: KeySet | None) -> None:
        self.mission = mission
        self.logic = logic
        self.keys = keys
        self.name = logic.name
        self.redundant = mission.standby is not None
        self.standby: Standby | None = None
        """The standby while this node does not command (None: it commands)."""
        self.reader = MirrorReader(logic, keys) if self.redundant else None
        self.resume_term = 0
        """A run going on with no one driving it: the term to resume it in."""
        self._probe: Standby | None = None  # the start-up STATUS round's asker
        self._round = 0  # the kind of the standby's round under way (0: none)

    @property
    def commanding(self) -> bool:
        return self.standby is None

    # -- start-up ---------------------------------------------------------------
    def follow_from_start(self) -> Standby:
        """A redundant mission's standby from the start (the lockstep runner's
        ``cn_b``: it knows the run has not begun)."""
        self.standby = Standby(self.mission, self.logic, self.keys)
        return self.standby

    def status_probe(self, now_ns: int) -> list[bytes]:
        """The start-up question to every device node (STATUS: changes nothing)."""
        if self._probe is None:
            self._probe = Standby(self.mission, self.logic, self.keys)
        return self._probe.ask(0, now_ns, kind=STATUS)

    def answer(self, i: int, payload: bytes | bytearray | memoryview) -> bool:
        """Device node ``i``'s reply to the probe round under way."""
        sb = self.standby if self.standby is not None else self._probe
        return sb is not None and sb.answer(i, payload)

    def start(self) -> Command | Follow:
        """The start-up decision from the STATUS round's answers: none of the
        device nodes ever ran a loop and this is ``cn``: Command(0), the first
        term; the run goes on and no one drives it (both control nodes were
        lost): Command(next term), resumed (:meth:`resume`); else Follow.
        NodeError when the device nodes ran the last term there is."""
        sb = self._probe
        assert sb is not None, "status_probe first"
        m = self.mission
        ran = [a for a in sb.answers if a is not None and (a.last_loop or a.term)]
        lease = m.takeover.lease_loops * m.period_ns
        driven = [a for a in ran if 0 <= a.quiet_ns < lease]
        self._probe = None
        if (not ran and self.name == "cn") or (ran and not driven):
            if ran:
                newest = max(max(a.term, a.promised) for a in ran)
                self.resume_term = next_term(newest)
                if not self.resume_term:  # answers range-checked: newest is TERM_MAX
                    raise NodeError(
                        f"{self.name} cannot resume the run: the device nodes ran term "
                        f"{newest}, the last a node can run (there is no next term)"
                    )
            return Command(self.resume_term)
        sb.term = max((a.term for a in sb.answers if a is not None), default=0)
        self.standby = sb
        return Follow(sb.term, bool(ran))

    def mid_run(self) -> list[int]:
        """After the warm-up sync (its replies in the vector): the loops of the
        device nodes that ran loops and were not told the run ended (a run
        going on without this node)."""
        dv = self.logic.dv
        loops = [int(dv.get(f"{dn}_loop")) for dn in self.mission.device_nodes]
        return [
            n
            for n, dn in zip(loops, self.mission.device_nodes, strict=True)
            if n and dv.get(f"{dn}_safed_why") != SafedWhy.RUN_ENDED
        ]

    def resume(
        self, has_recorder: bool, recorded: Frame | None, now_ns: int
    ) -> Resume | StartOver | None:
        """A commander after the warm-up sync: the device nodes' loops
        (:meth:`mid_run`, from the vector); ``recorded``, the newest frame this
        node's flight recorder holds (``has_recorder``: it has one). None: a
        fresh run. Otherwise restarted in flight: Resume
        (the frame written into the vector and adopted, a new term entered
        in a redundant mission, ``cn_resumed``), or StartOver when the record
        is unusable (``cn_restarted_in_flight`` says why)."""
        mid_run = self.mid_run()
        if not mid_run and not self.resume_term:
            return None
        m, logic = self.mission, self.logic
        dn_loop = max(mid_run, default=0)
        why = _unusable_record(has_recorder, recorded, dn_loop, now_ns)
        if why:
            logic.events.emit(
                EV.CN_RESTARTED_IN_FLIGHT, now_ns, node=self.name, loop=dn_loop, why=why
            )
            return StartOver(why)
        assert recorded is not None
        RegionCodec(logic.dv).write(recorded)
        logic.adopt()
        origin = recorded.t_ns - (recorded.seq - 1) * m.period_ns
        if self.resume_term:
            logic.take_command(self.resume_term, (now_ns - origin) // m.period_ns + 2)
        dv = logic.dv
        logic.events.emit(
            EV.CN_RESUMED,
            now_ns,
            node=self.name,
            epoch=int(dv.get("cn_epoch")),
            loop=recorded.seq,
            state=dv.get_name("cn_state"),
            source=f"its flight recorder's frame of loop {recorded.seq} "
            f"({(now_ns - recorded.t_ns) / 1e9:.1f} s old)",
        )
        return Resume(origin, recorded.seq)

    # -- a commander, and a standby's mirrors ------------------------------------
    def mirror(self, payload: bytes | bytearray | memoryview, now_ns: int) -> StandDown | bool:
        """A mirror frame from the other control node. A commander: a newer
        term's stands it down (StandDown; the mirror is then the standby's
        first), anything else changes nothing (False). A standby: True when
        it applied the mirror (it follows)."""
        if self.standby is None:
            assert self.reader is not None
            term, who = self.reader.newer_term(payload)
            if not term:
                return False
            self.logic.superseded = term
            why = f"a mirror of term {term} came from {self.mission.control_nodes[who]}"
            self._stand_down(why)
            assert self.standby is not None
            return StandDown(why, self.standby.mirror(payload, now_ns))
        return self.standby.mirror(payload, now_ns)

    def finished(self) -> StandDown | None:
        """A commander's loop is finished: when most device nodes' replies
        follow a newer term (:attr:`ControlLogic.superseded`), it stands down."""
        logic = self.logic
        if self.standby is not None or not logic.superseded:
            return None
        fenced = sum(logic._fenced)  # the replies that named the newer term
        return self._stand_down(f"{fenced} device node(s) follow term {logic.superseded}")

    def _stand_down(self, why: str) -> StandDown:
        self.standby = Standby.stand_down(self.mission, self.logic, self.keys, why)
        self._round = 0
        return StandDown(why)

    # -- a standby's slot ------------------------------------------------------------
    def tick(self, slot: int, now_ns: int) -> Probe | None:
        """A standby's beat in ``slot`` (half a period into the commander's
        loop): a STATUS round when the commander has fallen silent
        (:meth:`Standby.tick`), else nothing."""
        sb = self.standby
        assert sb is not None, "a commander does not tick"
        if not sb.tick(slot):
            return None
        # First a question that changes nothing: a term is asked for only when
        # the device nodes' answers show the commander silent too.
        self._round = STATUS
        return Probe(STATUS, sb.ask(slot, now_ns, kind=STATUS))

    def round_over(self, slot: int, now_ns: int) -> Probe | Take | Release | None:
        """The round under way is over (its answers given). After STATUS: a
        Probe(ASK) when the commander is silent to the device nodes too, else
        None (held). After ASK: Take the next slot, or Release the promises."""
        sb = self.standby
        assert sb is not None and self._round, "no round under way"
        kind, self._round = self._round, 0
        if kind == STATUS:
            if not sb.silent(slot, now_ns):
                return None
            self._round = ASK
            return Probe(ASK, sb.ask(slot, now_ns))
        if sb.decide(slot, now_ns) == Decision.TAKE:
            return Take(slot + 1)
        return Release(list(sb.releases))

    def take(self, loop: int) -> ControlLogic:
        """Carry out a Take: command from ``loop`` (:meth:`Standby.take`)."""
        sb = self.standby
        assert sb is not None
        logic = sb.take(loop)
        self.standby = None
        self._round = 0
        return logic


def check_recorded(
    logic: ControlLogic, keys: KeySet | None, payload: bytes | bytearray | memoryview
) -> Frame | None:
    """A telemetry frame a flight recorder held, checked (its tag with the
    node's telemetry key, this mission's layout); None when it does not check."""
    ch = channel(keys, "telemetry")
    try:
        return RegionCodec(logic.dv).check(ch.open(payload) if ch is not None else payload)
    except CodecError:
        return None


def _unusable_record(has_recorder: bool, frame: Frame | None, dn_loop: int, now: int) -> str:
    """Why a restarted node cannot resume from ``frame`` ("" when it can)."""
    if not has_recorder:
        return "the mission has no flight recorder for it (`recorder:`) and no standby"
    if frame is None:
        return "its flight recorder holds no frame"
    if frame.seq > dn_loop + 1 or now - frame.t_ns > RESUME_MAX_AGE_NS:
        return (
            f"its flight recorder's last frame (loop {frame.seq}, "
            f"{(now - frame.t_ns) / 1e9:.0f} s old) is not of the device nodes' run "
            f"(loop {dn_loop})"
        )
    return ""
