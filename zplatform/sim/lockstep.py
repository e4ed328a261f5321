"""The lockstep runner: every node of a mission in one process, in virtual time.

:class:`LockstepRunner` is the second driver of the sans-IO loop
(:mod:`zplatform.control.loop`): it moves the same region frames, encoded and
decoded, between :class:`~zplatform.control.loop.ControlLogic`, every
:class:`~zplatform.control.loop.DeviceLogic` and the same
:class:`~zplatform.ground.logic.GroundLogic` as the live ground node, with no
protocol order of its own. Loop ``n`` (from 1, as live) runs at virtual time
``start_ns + (n - 1) * period_ns``. :func:`replay` feeds a live run's
recorded inputs through a fresh control loop and checks its telemetry bit for bit.
Device nodes are bound to the commander's run as live (:class:`SimDevice`).

Contract: deterministic: nothing reads the wall clock (but
:class:`SimResult`'s speed figure) and nothing iterates a set or hashes into
the output, so the same mission and command script give a byte-identical CSV.
No frame is lost or late unless a test says so (:attr:`LockstepRunner.lost`,
``kill``, ``stop``, ``partition``, ``restart``); no loop is flagged final, so
a runner may be run on. Everything runs on the calling thread. The order of
a loop and why no loop is final: docs/architecture.md#drivers.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from ..boards import Board
from ..config import BulkChannelConfig, Mission
from ..control.authority import Signer
from ..control.failover import Standby
from ..control.intake import INBOX, CnRefusals, RequestIntake, TriggerIntake
from ..control.loop import ControlLogic, DeviceLogic
from ..control.params import MemorySaver
from ..control.role import Command, ControlRole, Probe, Release, Resume, Take, check_recorded
from ..control.uplink import ScriptCommand
from ..core.auth import TAG_LEN, KeySet, Run, channel
from ..core.codec import BundleEncoder, RegionCodec
from ..core.datavector import DataVector, Layout
from ..core.events import Event
from ..core.health import BLOCK_SIZE, HealthPort
from ..core.messages import wildcard_sync_for
from ..errors import NodeError, RecordingError, ZPlatformError
from ..ground.logic import GroundLogic
from ..runtime.clocksync import RELEARN_S, ClockLink, ClockResponder, RunAsker
from ..runtime.timebase import VirtualClock
from ..security.identities import sim_signer
from ..telemetry.logs import CsvLogger
from ..telemetry.records import CommandOutcome, EventRecord
from ..world.model import World
from .replay_recording import RecordReader

__all__ = [
    "DEFAULT_START_NS",
    "SIM_KEY",
    "Difference",
    "LockstepRunner",
    "ReplayResult",
    "SimResult",
    "replay",
    "sim_keys",
]

DEFAULT_START_NS = 1_700_000_000_000_000_000
"""Virtual time of loop 1 (2023-11-14T22:13:20Z): fixed, so runs repeat exactly."""

SIM_KEY = bytes(32)
"""The master key a lockstep run derives its link keys from (every node is
in this process, so the keys protect nothing; they keep the frames and the
code paths those of a live run). Deliberately trivial: no key loader takes
it (:func:`zplatform.core.auth.check_key`)."""


def sim_keys(mission: Mission) -> KeySet | None:
    """Every link key of ``mission`` derived from :data:`SIM_KEY`, or None
    when the mission does not authenticate."""
    return KeySet.from_master(mission, SIM_KEY, source="SIM_KEY") if mission.security.auth else None


class SimResult(msgspec.Struct):
    """The outcome of :meth:`LockstepRunner.run` (cumulative over runs).

    ``states`` lists the states visited in order (the initial state first,
    consecutive repeats merged); ``events`` every node's events in the order
    they were drained (per loop: cn, then dn0, dn1, ...). ``errors`` is
    ``cn_errors`` plus every ``dnX_errors``. ``wall_s`` / ``loops_per_s``
    are the only figures that depend on the machine.
    """

    mission: str
    loops: int
    duration_s: float
    rate_hz: float
    final_state: str
    states: list[str]
    events: list[Event]
    commands: list[CommandOutcome]
    pending_commands: list[str]
    errors: int
    errors_by_node: dict[str, int]
    rx: dict[str, int]
    missed: dict[str, int]
    late: dict[str, int]
    loop_overruns: int
    sync_overruns: int
    telemetry_received: int
    fault: str
    wall_s: float
    loops_per_s: float

    @property
    def clean(self) -> bool:
        """No errors, no fault, every scripted command sent and accepted."""
        return (
            self.errors == 0
            and self.fault == "NONE"
            and not self.pending_commands
            and all(c.status == "ACCEPTED" for c in self.commands)
        )

    def summary(self) -> dict[str, Any]:
        """The ``--summary`` JSON (the fields of ``zplatform up``'s, and more)."""
        return {
            "mission": self.mission,
            "mode": "lockstep",
            "loops": self.loops,
            "duration_s": self.duration_s,
            "rate_hz": self.rate_hz,
            "loop_overruns": self.loop_overruns,
            "sync_overruns": self.sync_overruns,
            "missed": self.missed,
            "late": self.late,
            "rx": self.rx,
            "telemetry_received": self.telemetry_received,
            "errors": self.errors,
            "errors_by_node": self.errors_by_node,
            "fault": self.fault,
            "final_state": self.final_state,
            "states": self.states,
            "commands": [msgspec.to_builtins(c) for c in self.commands],
            "pending_commands": self.pending_commands,
            # As the events file has them; received at the event's own loop time.
            "events": [msgspec.to_builtins(EventRecord.of(e, e.t_ns)) for e in self.events],
            "wall_s": self.wall_s,
            "loops_per_s": self.loops_per_s,
        }


# ---------------------------------------------------------------------------
# bulk channels in memory


class _SimChannel:
    """One bulk channel moved in memory, as the network would: a sample the
    owner publishes in loop n is delivered at the start of loop n+1 and taken
    by each reader's :meth:`_SimBulkPort.receive` in that loop (live, readers
    take the newest sample before their loop's logic, and a sample of loop n
    cannot reach a loop that started before it was published)."""

    def __init__(self, ch: BulkChannelConfig) -> None:
        self.ch = ch
        self._sent = np.zeros(ch.shape, ch.dtype)
        self.delivered = np.zeros(ch.shape, ch.dtype)
        self._pending = False
        self.fresh: dict[str, bool] = dict.fromkeys(ch.readers, False)

    def send(self, loop: int, own: np.ndarray[Any, Any]) -> None:
        if loop % self.ch.rate_divisor == self.ch.rate_phase:
            np.copyto(self._sent, own)
            self._pending = True

    def deliver(self) -> None:
        if self._pending:
            self._sent, self.delivered = self.delivered, self._sent
            self._pending = False
            for r in self.fresh:
                self.fresh[r] = True


class _SimBulkPort:
    """A node's :class:`~zplatform.control.loop.BulkPort` in the lockstep runner.

    Moves samples through :class:`_SimChannel`; counts nothing (the bulk
    counters describe zenoh's transport, shared memory or copied, which a
    run in one process does not have: they stay 0 in sim)."""

    def __init__(self, node: str, channels: list[_SimChannel]) -> None:
        self.node = node
        self.arrays: dict[str, Any] = {}
        self._own: list[tuple[_SimChannel, np.ndarray[Any, Any]]] = []
        self._read: list[tuple[_SimChannel, np.ndarray[Any, Any]]] = []
        for c in channels:
            if c.ch.node == node:
                self.arrays[c.ch.name] = a = np.zeros(c.ch.shape, c.ch.dtype)
                self._own.append((c, a))
            elif node in c.fresh:
                self.arrays[c.ch.name] = a = np.zeros(c.ch.shape, c.ch.dtype)
                self._read.append((c, a))

    def receive(self, loop: int) -> None:
        for c, a in self._read:
            if c.fresh[self.node]:
                np.copyto(a, c.delivered)
                c.fresh[self.node] = False

    def publish(self, loop: int, t_ns: int) -> None:
        for c, a in self._own:
            c.send(loop, a)

    def write_counters(self, dv: DataVector) -> None:
        pass


# ---------------------------------------------------------------------------
# the runner


class _Query:
    """A sync query as an intake reads it (:class:`~zplatform.control.intake.Payload`)."""

    __slots__ = ("data",)

    def __init__(self, data: bytes | bytearray | memoryview) -> None:
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        return bytes(self.data)


class _SimTriggerIntake(TriggerIntake[None]):
    """A device node's live trigger intake (size, tag, run), but for
    freshness: lockstep delivers each trigger once, in order, and nothing
    replays, but two commanders of a failover stamp one virtual instant (as
    a restart's warm-up and its next loop do), which live clocks never do,
    so the newest-stamp rule would refuse the genuine second one. Whether a
    trigger runs is the logic's (:meth:`DeviceLogic.trigger`: loop, term)."""

    def _fresh_header(self, body: memoryview, handle: None) -> bool:
        return True

    def _fresh(self, body: memoryview, handle: None) -> bool:
        return True


class SimDevice:
    """What a lockstep device node has around its logic, as live
    (zplatform.node.device): the run it learned (shared by its logic, its
    trigger intake and its clock link), its trigger intake, and its end of the
    clock exchange, which it asks again on a genuine trigger of another run
    (the intake's cue), at most once a :data:`~zplatform.runtime.clocksync.RELEARN_S`
    of virtual time."""

    def __init__(
        self, logic: DeviceLogic, run: Run, keys: KeySet | None, now_ns: Callable[[], int]
    ) -> None:
        self.logic = logic
        self.run = run
        self.link = ClockLink(logic.mission, logic.node, keys, run=run)
        self.intake = _SimTriggerIntake(
            logic.mission, logic.node, channel(keys, f"cn_to_{logic.node}", run), now_ns
        )
        self.cued = False
        self.intake.on_other_run = self._cue
        self.asked_ns: int | None = None
        """Virtual time of its last hello on a cue (None: none yet)."""
        self.hellos = 0
        """Clock exchanges it asked (its start's included)."""

    def _cue(self) -> None:
        self.cued = True


class SimControlNode:
    """One control node of a lockstep run: its logic and its
    :class:`~zplatform.control.role.ControlRole`; the faults a test put on it
    (:meth:`LockstepRunner.kill`, :meth:`LockstepRunner.stop`,
    :meth:`LockstepRunner.restart`); and what its flight recorder holds (the
    newest telemetry frame it made, when the mission records it)."""

    def __init__(
        self, name: str, logic: ControlLogic, keys: KeySet | None, *, follows: bool = False
    ) -> None:
        self.name = name
        self.logic = logic
        self.keys = keys
        self.role = ControlRole(logic.mission, logic, keys)
        self.clock = ClockResponder(logic.mission, keys, logic.auth_run)
        """Its clock server's sans-IO end, in its run (it answers while it commands)."""
        if follows:
            self.role.follow_from_start()
        self.state_h = logic.dv.handle("cn_state")
        self.saver = MemorySaver()
        self.dead = False
        self.stopped_until = 0
        self._held: tuple[bytes, int] | None = None
        self.records = name in logic.mission.recording_nodes
        self.recorded: bytes | None = None
        """The newest telemetry frame its flight recorder holds (None: none)."""
        self.requests: RequestIntake | None = None
        """Its command inbox while it commands (the live CN's intake, opened
        at its first loop in command: :meth:`take_requests`)."""
        self.refused = CnRefusals()
        self._taken: list[tuple[None, bytes]] = []
        self._dropped = 0

    @property
    def standby(self) -> Standby | None:
        """Its standby while it does not command (None: it commands)."""
        return self.role.standby

    def runs(self, loop: int) -> bool:
        """Whether it runs in ``loop`` (neither dead nor stopped)."""
        return not self.dead and self.stopped_until < loop

    def take_mirror(self, frame: bytes, t: int, loop: int) -> None:
        """A mirror from the commander: applied now, or held while stopped
        (the newest one, as a socket buffer would keep it for a stopped process)."""
        if not self.runs(loop):
            self._held = (frame, t)
            return
        self.role.mirror(frame, t)

    def take_requests(self, frames: tuple[bytes | bytearray, ...]) -> tuple[list[bytes], int]:
        """The request ``frames`` that reached it since its last loop, through
        the live CN's intake (:class:`~zplatform.control.intake.RequestIntake`,
        as :class:`zplatform.node.control.ControlNode` opens it: bound to its
        run, its epoch and its handler's last number, a bounded inbox): returns
        the admitted ones, oldest first, and the inbox's drops since the last
        call; what the intake refused is in :attr:`refused` (``finish``'s
        ``refused``), its sync-reply fields zero (the runner moves no bad reply)."""
        logic = self.logic
        req = self.requests
        if req is None:
            if not logic.mission.has_ground:
                return [], 0
            commands = logic.commands
            req = self.requests = RequestIntake(
                logic.mission,
                channel(self.keys, "gn_to_cn", logic.auth_run),
                int(logic.dv.get("cn_epoch")),
                lambda: commands.last_seq,
                INBOX,
            )
            self._dropped = 0
        box = req.box
        assert box is not None
        for frame in frames:
            req.admit(_Query(frame), None)
        taken = self._taken
        taken.clear()
        box.drain(taken)
        req.take_refusals(self.refused)
        dropped, self._dropped = box.dropped - self._dropped, box.dropped
        return [f for _, f in taken], dropped

    def stand_down(self) -> None:
        """It no longer commands: its inbox is the new commander's (as live)."""
        self.requests = None

    def deliver_held(self, t: int) -> None:
        if self._held is not None:
            frame, at = self._held
            self._held = None
            self.role.mirror(frame, at)


class LockstepRunner:
    """Every node of ``mission`` in one process, in virtual time (module doc).

    ``commands`` is the ground's script; ``boards`` replaces the default
    :class:`~zplatform.boards.SimBoard` of some device nodes (tests inject
    faults through them); ``health`` gives some nodes a health port (a
    :class:`~zplatform.core.health.FakeHealth`: deterministic values, an injected
    stall; without one a node's health elements keep their initial values).
    ``signer``: the operator and station the ground's requests name (a
    mission with ``ground:``; :class:`~zplatform.ground.logic.GroundLogic`).
    A mission with a vehicle world gets one
    :class:`~zplatform.world.model.World` in this process (:attr:`world`), and
    every node it spans a port onto it, whatever that node's board driver
    (a hardware-in-the-loop mission's serial board included: the world is
    what that board would reach). Construction builds every node
    (ConfigError for a bad mission) and resolves the script against the
    mission (CommandError naming ``file:line``). Not thread-safe.
    """

    def __init__(
        self,
        mission: Mission,
        *,
        commands: list[ScriptCommand] | None = None,
        start_ns: int = DEFAULT_START_NS,
        boards: dict[str, Board] | None = None,
        health: dict[str, HealthPort] | None = None,
        signer: Signer | None = None,
    ) -> None:
        self.mission = mission
        self.start_ns = start_ns
        self.period_ns = mission.period_ns
        self.clock = VirtualClock(start_ns)
        keys = sim_keys(mission)
        self.control = ControlLogic(mission, keys=keys and keys.for_node("cn"), epoch=start_ns)
        """The control logic of the control node in command (after a takeover,
        the standby's; with two commanders at once, the higher term's)."""
        # Control nodes: cn commands term 1; a standby cn_b follows it
        # (zplatform.control.failover). Their faults come from the tests: kill, stop,
        # partition (module doc).
        self.cns: dict[str, SimControlNode] = {
            "cn": SimControlNode("cn", self.control, keys and keys.for_node("cn"))
        }
        if mission.standby is not None:
            name = mission.standby
            sb_keys = keys and keys.for_node(name)
            sb_logic = ControlLogic(mission, keys=sb_keys, name=name)
            self._learn_run(sb_logic)
            self.cns[name] = SimControlNode(name, sb_logic, sb_keys, follows=True)
        self._cuts: dict[frozenset[str], int | None] = {}
        self.driven: dict[int, dict[str, int]] = {}
        """Redundant missions: per loop, the term that drove each device node
        that ran it (the oracle of "no loop driven by two terms")."""
        self.commanders: list[tuple[int, str, int]] = []
        """Redundant missions: ``(loop, node, term)`` whenever the control
        node in command (the highest term that ran a loop) changed."""
        boards = dict(boards or {})
        unknown = sorted(set(boards) - set(mission.device_nodes))
        if unknown:
            raise ValueError(f"boards given for nodes that are not device nodes: {unknown}")
        self.world: World | None = World(mission) if mission.world is not None else None
        """The vehicle world, if the mission has one (its ``truth`` is the physics' state)."""
        if self.world is not None:
            for n in self.world.nodes:
                boards.setdefault(n, self.world.board(n))
        # Each device node bound to the run it learns by its clock exchange
        # with the commander (a hello, in virtual time), as live.
        self.dns: list[SimDevice] = []
        for dn in mission.device_nodes:
            run = Run()
            dn_keys = keys and keys.for_node(dn)
            dl = DeviceLogic(mission, dn, board=boards.get(dn), keys=dn_keys, run=run)
            self.dns.append(SimDevice(dl, run, dn_keys, self.clock.now_ns))
        self.devices = [d.logic for d in self.dns]
        """Every device node's logic, in the mission's order."""
        # The ground side: the live ground node's logic, in virtual time.
        ground_keys = keys and keys.for_node("gn" if mission.has_ground else "tool")
        # Bound to the commander's run as live, learned by its run hello.
        self._ground_asker = RunAsker(ground_keys) if ground_keys is not None else None
        self.ground = GroundLogic(
            mission,
            keys=ground_keys,
            script=commands or [],
            run=self._ground_asker.run if self._ground_asker is not None else None,
            signer=signer,
            # A script line naming its sender (`as alice@pad: ...`) is signed
            # with that operator's key of the run's own key set.
            signers=(lambda op, st: sim_signer(keys, mission, op, st))
            if keys is not None and mission.ground is not None
            else None,
        )
        # The sync query's form, as the live CN chooses it (transport.sync_query).
        self._bundle = BundleEncoder() if wildcard_sync_for(mission) else None
        self._ground: bytearray | None = None
        self._stations: list[bytes] = []
        self.lost: set[str] = set()
        """Device nodes that are gone (a test kills one mid-run by adding it):
        they are neither triggered nor answer, so the CN counts their misses
        as it would a dead node's (DN_LOST after ``faults.dn_lost_loops``)."""
        self.loop = 0
        """Loops run so far (the number of the last one)."""
        self._state_h = self.control.dv.handle("cn_state")
        self._states: list[str] = []
        self._last_state = -1
        self._events: list[Event] = []
        self._wall_s = 0.0
        # Bulk channels move in memory (each node's loop receives and
        # publishes them in its own order, zplatform.control.loop).
        logics: dict[str, ControlLogic | DeviceLogic] = {"cn": self.control}
        logics.update({d.node: d for d in self.devices})
        self._channels = [_SimChannel(ch) for ch in mission.bulk if ch.node in logics]
        for n, logic in logics.items():
            port = _SimBulkPort(n, self._channels)
            if port.arrays:
                logic.attach_bulk(port)
        self._health = dict(health or {})
        for n, hp in self._health.items():
            if n not in logics:
                raise ValueError(f"health given for {n!r}, which is not a cn or device node")
            logics[n].attach_health(hp)
        for d in self.dns:  # as live, before the first trigger
            self._hello(d, 1)

    @property
    def saver(self) -> MemorySaver:
        """Where the commander's PRM_SAVE goes in a lockstep run (memory;
        answered next loop)."""
        return next(c.saver for c in self.cns.values() if c.logic is self.control)

    # -- faults (redundant missions) --------------------------------------------
    def kill(self, node: str) -> None:
        """``node`` is gone from the next loop on: a control node runs and
        answers nothing more; a device node is :attr:`lost`."""
        if node in self.cns:
            self.cns[node].dead = True
        elif node in self.mission.device_nodes:
            self.lost.add(node)
        else:
            raise ValueError(f"no control or device node {node!r} to kill")

    def _learn_run(self, logic: ControlLogic) -> None:
        """A control node that follows learns the commander's run as live: by
        a clock exchange with it (a hello, zplatform.runtime.clocksync), in virtual
        time. Without authentication there is no run to learn."""
        keys = sim_keys(self.mission)
        if keys is None:
            return
        t = self.clock.now_ns()
        link = ClockLink(self.mission, logic.name, keys.for_node(logic.name), run=logic.auth_run)
        server = ClockResponder(
            self.mission, keys.for_node(self.control.name), self.control.auth_run
        )
        query, nonce = link.query(t)
        reply = server.answer(query, t, t)
        assert reply is not None and link.check(reply, nonce) is not None

    def _hello(self, d: SimDevice, loop: int) -> bool:
        """Device node ``d`` asks the clock for the run with a hello
        (zplatform.runtime.clocksync), as live: asked of every control node
        that serves the clock (those that command, run in ``loop`` and reach
        it), the first valid answer taken. Whether one answered."""
        t = self.clock.now_ns()
        d.link.forget()
        query, nonce = d.link.query(t)
        d.hellos += 1
        for c in self.cns.values():
            if c.standby is not None or not c.runs(loop) or not self.reach(c.name, d.logic.node):
                continue
            reply = c.clock.answer(query, t, t)
            if reply is not None and d.link.check(reply, nonce) is not None:
                return True
        return False

    def _serve(
        self, d: SimDevice, payload: bytes | bytearray | memoryview, t: int, loop: int
    ) -> tuple[bool, bytearray | None]:
        """Sync query ``payload`` reaches device node ``d`` at ``t``, as live
        (zplatform.runtime.sync.DeviceSync): its intake (refused: unanswered,
        counted in the logic, ``dnX_bad_frames``), then its logic. Returns
        ``(answered, reply)`` (an answered None is an error reply). A genuine
        trigger of another run cues a hello, at most once a RELEARN_S."""
        dev = d.logic
        data = d.intake.check(_Query(payload), None)
        reply = None
        if data is not None:
            reply = dev.trigger(data, t, authentic=d.intake.authenticates)
        size, bad, stale = d.intake.take_counts()
        dev.refused(size, bad, stale, t, unchecked=d.intake.took_unchecked)
        if d.cued:
            d.cued = False
            if d.asked_ns is None or t - d.asked_ns >= round(RELEARN_S * 1e9):
                d.asked_ns = t
                self._hello(d, loop)
        return data is not None, reply

    def inject(self, node: str, payload: bytes | bytearray | memoryview) -> bytearray | None:
        """A sync query for device node ``node`` from the network, outside
        the control nodes' loops (a test's replayed or forged frame), at the
        current virtual time: taken as any trigger is (:meth:`_serve`).
        Returns the reply, or None when it was refused (unanswered, or
        answered with an error); a loop it starts is run."""
        d = self.dns[self.mission.device_nodes.index(node)]
        answered, reply = self._serve(d, payload, self.clock.now_ns(), self.loop + 1)
        if answered and d.logic.triggered:
            d.logic.run(self.clock.now_ns())
        return reply

    def _ground_learns_run(self) -> None:
        """The ground learns the commander's run by its run hello (as live,
        zplatform.ground.link), when it does not know it: at the start, and
        after a restart (live: within a RELEARN_S; here at once)."""
        asker = self._ground_asker
        if asker is None or asker.run.epoch == self.control.auth_run.epoch:
            return
        keys = sim_keys(self.mission)
        assert keys is not None
        server = ClockResponder(
            self.mission, keys.for_node(self.control.name), self.control.auth_run
        )
        answer = server.answer(asker.hello(), 0, 0)
        assert answer is not None and asker.check(answer)

    def stop(self, node: str, loops: int) -> None:
        """Control node ``node`` is frozen for the next ``loops`` loops (as
        SIGSTOP): it runs nothing, then resumes with the state it had, in the
        loop its schedule is at (the loops in between skipped)."""
        self.cns[node].stopped_until = self.loop + loops

    def restart(self, node: str = "cn", *, record: bytes | bool | None = True) -> str:
        """Control node ``node`` starts again as a new process before the next
        loop (after :meth:`kill`, or in place of a live one): a fresh logic
        with a new epoch, whose role decides from what it is fed, as live: a
        STATUS probe of the device nodes (a redundant mission), the warm-up's
        loops of the device nodes, and what its flight recorder holds
        (``record``: True, the newest telemetry frame it made, if the mission
        records it; False, no recorder; None, an empty one; or bytes, a frame
        given). Returns what it did: ``command``, ``follow``, ``resume`` or
        ``start_over``. NodeError as live (no device node answers its probe,
        or no next term); ValueError for a mission with bulk channels (not
        re-attached; a health port given for it is)."""
        old = self.cns[node]
        if self.mission.bulk:
            raise ValueError("restart does not re-attach bulk channels")
        t = self.clock.now_ns()
        keys = old.keys
        logic = ControlLogic(self.mission, keys=keys, epoch=t, name=node)
        c = SimControlNode(node, logic, keys)
        c.records = old.records
        held = old.recorded if record is True else record if isinstance(record, bytes) else None
        self.cns[node] = c
        role = c.role
        reached = [
            i
            for i, d in enumerate(self.devices)
            if d.node not in self.lost and self.reach(node, d.node)
        ]
        if self._health.get(node) is not None:
            logic.attach_health(self._health[node])
        if role.redundant:
            asks = role.status_probe(t)
            answered = 0
            for i in reached:
                reply = self.devices[i].probe(asks[i], t)
                answered += reply is not None and role.answer(i, reply)
            if not answered:  # as live: it cannot start
                raise NodeError(f"{node} cannot start: no device node answers its probe")
            if not isinstance(role.start(), Command):
                self._learn_run(logic)  # as live: its clock exchange with the commander
                return "follow"
        frames = logic.begin(0, t)  # the warm-up: answered, never run
        for i in reached:
            answered, warm = self._serve(self.dns[i], frames[i], t, self.loop + 1)
            if answered:
                logic.reply(i, warm)
        logic.reset_sync_counters()
        logic.events.drain()
        recorded = check_recorded(logic, keys, held) if held is not None else None
        done = role.resume(record is not False and c.records, recorded, t)
        if done is None:
            return "command"
        return "resume" if isinstance(done, Resume) else "start_over"

    def partition(self, a: str, b: str, loops: int | None = None) -> None:
        """Nothing passes between nodes ``a`` and ``b`` (either way) for the
        next ``loops`` loops (None: until :meth:`heal`)."""
        self._cuts[frozenset((a, b))] = None if loops is None else self.loop + loops

    def heal(self) -> None:
        """End every partition."""
        self._cuts.clear()

    def reach(self, a: str, b: str) -> bool:
        """Whether frames pass between ``a`` and ``b`` in the current loop."""
        until = self._cuts.get(frozenset((a, b)), 0)
        return until is not None and until <= self.loop

    # -- running -----------------------------------------------------------
    def step(self, log: CsvLogger | None = None) -> None:
        """Run one loop (module doc order) and advance the virtual clock."""
        loop = self.loop + 1
        t = self.clock.now_ns()
        for ch in self._channels:  # what was published last loop arrives
            ch.deliver()
        running = [c for c in self.cns.values() if c.runs(loop)]
        for c in running:  # a mirror held while a node was stopped arrives first
            c.deliver_held(t)
        commanders = [c for c in running if c.standby is None]
        ground, self._ground = self._ground, None
        # The ground's request, then the other stations' (uplink()), as the
        # CN's inbox would hold them: it refuses or picks among them.
        grounds = ((ground,) if ground is not None else ()) + tuple(self._stations)
        self._stations.clear()
        tms: list[bytearray] = []
        for c in commanders:
            tm = self._command(c, loop, t, grounds)
            if tm is not None:
                tms.append(bytearray(tm))
        if commanders:
            self._mirror(commanders, t)
        for c in running:
            if c.standby is not None:
                c.stand_down()
                self._follow(c, loop, t)
        top = max(
            (c for c in self.cns.values() if c.standby is None and not c.dead),
            key=lambda c: c.logic.term,
            default=None,
        )
        if top is not None:
            self.control = top.logic
            term = top.logic.term
            new = not self.commanders or self.commanders[-1][1:] != (top.name, term)
            if term and top.logic.loop == loop and new:
                self.commanders.append((loop, top.name, term))
        gl = self.ground
        if tms:
            self._ground_learns_run()
        for tm in tms:
            if gl.on_telemetry(tm, t):
                if log is not None:
                    log.write(t, gl.dv)
                requests = gl.take_requests()
                if requests:  # the script player sends at most one per snapshot
                    self._ground = bytearray(requests[-1])
        state = (top.state_h if top is not None else self.cns["cn"].state_h).get()
        if state != self._last_state:
            self._last_state = state
            self._states.append(self._state_h.spec.name_of(state))
        for c in self.cns.values():
            if c.logic.events.pending:
                drained = c.logic.events.drain()
                self._events.extend(drained)
                for e in drained:  # the reasons of verdicts, as live from the event intake
                    gl.on_event(e, t)
        for d in self.devices:
            if d.events.pending:
                self._events.extend(d.events.drain())
        if gl.events.pending:  # what the ground believes: nothing new in virtual time
            gl.events.drain()
        self.loop = loop
        self.clock.advance(self.period_ns)

    def uplink(self, frame: bytes | bytearray) -> None:
        """Deliver a request ``frame`` of another ground station (one built
        by its own :class:`~zplatform.control.uplink.Uplink`) to the control
        nodes in the next loop, beside the ground's (a mission with
        ``ground:`` stations; a partition from ``gn`` cuts it too)."""
        self._stations.append(bytes(frame))

    def _command(
        self, c: SimControlNode, loop: int, t: int, ground: tuple[bytes | bytearray, ...]
    ) -> bytearray | None:
        """Control node ``c`` runs ``loop`` as a commander; returns its telemetry."""
        cn = c.logic
        skipped = max(loop - 1 - cn.loop, 0) if cn.loop else 0
        frames = cn.begin(loop, t)
        lost = self.lost
        reach = self.reach
        term = cn.term
        if self._bundle is not None:  # as live: one wildcard query, every DN takes its frame
            bundle = self._bundle.pack(frames)
        for i, d in enumerate(self.dns):
            dev = d.logic
            if dev.node in lost or not reach(c.name, dev.node):
                continue
            answered, reply = self._serve(
                d, bundle if self._bundle is not None else frames[i], t, loop
            )
            if not answered:  # refused at its intake: the query goes unanswered
                continue
            if dev.triggered:
                dev.run(t)
                if term:
                    self.driven.setdefault(loop, {})[dev.node] = term
            cn.reply(i, reply)
        # As live: every request passes the CN's intake as it arrives (size,
        # tag, run, a number above every one seen or admitted) before the loop.
        grounds, dropped = c.take_requests(ground if reach(c.name, "gn") else ())
        saved = c.saver.poll()
        tm = cn.finish(
            grounds,
            loop_overruns=skipped,
            inbox_dropped=dropped,
            refused=c.refused,
            saves=(saved,) if saved is not None else (),
        )
        save = cn.params.take_save()
        if save is not None:
            c.saver.submit(*save)
        if c.role.finished() is not None:  # a newer term drives the device nodes
            return None
        if tm is not None and c.records:  # its flight recorder's newest frame
            c.recorded = bytes(tm)
        if tm is not None and not reach(c.name, "gn"):
            return None
        return tm

    def _mirror(self, commanders: list[SimControlNode], t: int) -> None:
        """Each commander's mirror to the other control node (held while it is
        stopped, dropped when it is dead or cut off)."""
        for c in commanders:
            if c.standby is not None or c.logic.mirror is None:
                continue
            for other in self.cns.values():
                if other is c or other.dead or not self.reach(c.name, other.name):
                    continue
                other.take_mirror(bytes(c.logic.mirror), t, self.loop + 1)

    def _follow(self, c: SimControlNode, loop: int, t: int) -> None:
        """A standby's turn in ``loop``, half a period in: its role's probe
        rounds, maybe a takeover from the next loop (:mod:`zplatform.control.role`)."""
        role = c.role
        sb = role.standby
        assert sb is not None
        save = sb.take_save()
        if save is not None:
            c.saver.submit(*save)
        now = t + self.period_ns // 2
        action: Probe | Take | Release | None = role.tick(loop, now)
        while isinstance(action, Probe):
            self._probe_round(c, action.asks, now)
            action = role.round_over(loop, now)
        if isinstance(action, Take):
            role.take(action.loop)
        elif isinstance(action, Release):
            for i, release in enumerate(action.releases):
                dev = self.devices[i]
                if (
                    release is not None
                    and dev.node not in self.lost
                    and self.reach(c.name, dev.node)
                ):
                    dev.probe(release, now)

    def _probe_round(self, c: SimControlNode, asks: list[bytes], now: int) -> None:
        """Control node ``c``'s questions to every device node it reaches,
        each answer handed to its role."""
        for i, dev in enumerate(self.devices):
            if dev.node in self.lost or not self.reach(c.name, dev.node):
                continue
            reply = dev.probe(asks[i], now)
            if reply is not None:
                c.role.answer(i, reply)

    def run(self, duration_s: float, *, log: CsvLogger | None = None) -> SimResult:
        """Run ``round(duration_s * loop_hz)`` loops (continuing from any
        earlier run) and return the cumulative result."""
        if duration_s < 0:
            raise ValueError(f"duration must be >= 0, got {duration_s}")
        n = round(duration_s * self.mission.loop_hz)
        step = self.step
        w0 = time.perf_counter()
        for _ in range(n):
            step(log)
        self._wall_s += time.perf_counter() - w0
        if log is not None:
            log.flush()
        return self.result()

    def result(self) -> SimResult:
        """The cumulative :class:`SimResult` so far."""
        dv = self.control.dv
        dns = self.mission.device_nodes
        errors_by_node = {"cn": int(dv.get("cn_errors"))}
        for d in self.devices:  # the DN's own count (the CN's copy is a loop old)
            errors_by_node[d.node] = int(d.dv.get(f"{d.node}_errors"))
        loops = self.loop
        gl = self.ground
        gl.finish(self.clock.now_ns())
        player = gl.player
        return SimResult(
            mission=self.mission.mission,
            loops=loops,
            duration_s=loops * self.period_ns / 1e9,
            rate_hz=self.mission.loop_hz,
            final_state=dv.get_name("cn_state"),
            states=list(self._states),
            events=list(self._events),
            commands=player.results(gl) if player is not None else [],
            pending_commands=player.pending if player is not None else [],
            errors=sum(errors_by_node.values()),
            errors_by_node=errors_by_node,
            rx={dn: int(dv.get(f"cn_rx_{dn}")) for dn in dns},
            missed={dn: int(dv.get(f"cn_missed_{dn}")) for dn in dns},
            late={dn: int(dv.get(f"cn_late_{dn}")) for dn in dns},
            loop_overruns=int(dv.get("cn_loop_overruns")),
            sync_overruns=int(dv.get("cn_sync_overruns")),
            telemetry_received=gl.received,
            fault=dv.get_name("cn_fault"),
            wall_s=self._wall_s,
            loops_per_s=loops / self._wall_s if self._wall_s > 0 else 0.0,
        )


# ---------------------------------------------------------------------------
# replay


class Difference(msgspec.Struct, frozen=True):
    """The first telemetry value a replay did not reproduce."""

    loop: int
    element: str
    recorded: str
    replayed: str


class ReplayResult(msgspec.Struct, frozen=True):
    """The outcome of :func:`replay`.

    ``identical``: every recorded telemetry frame was reproduced byte for
    byte; otherwise ``first_difference`` names the loop and element.
    ``complete`` is False when the recorder had to drop loops (its ring was
    full) or the record ends mid-loop; the replay then stops at the gap.
    """

    mission: str
    loops: int
    first_loop: int
    last_loop: int
    telemetry_frames: int
    identical: bool
    complete: bool
    dropped_loops: int
    first_difference: Difference | None
    final_state: str


def _first_difference(
    layout: Layout, loop: int, recorded: bytes, replayed: bytes | bytearray, tag_len: int
) -> Difference:
    a, b = DataVector(layout), DataVector(layout)
    ca, cb = RegionCodec(a), RegionCodec(b)
    try:
        ca.apply(recorded[: len(recorded) - tag_len])
    except Exception as exc:  # a damaged record: say so rather than crash
        return Difference(loop, "<frame>", f"undecodable ({exc})", "")
    cb.apply(replayed[: len(replayed) - tag_len])
    for name, spec in layout.elements.items():
        va, vb = a.get(name), b.get(name)
        if np.asarray(va).tobytes() != np.asarray(vb).tobytes():
            if spec.enum is not None:
                return Difference(loop, name, a.get_name(name), b.get_name(name))
            return Difference(loop, name, repr(va), repr(vb))
    return Difference(loop, "<frame header>", recorded[:24].hex(), bytes(replayed[:24]).hex())


class _RecordedHealth:
    """The health port of a replay: the loop's recorded block. A health loop
    without one (a damaged record) gets zeros, and the telemetry then says
    where the replay departs from the recording."""

    def __init__(self) -> None:
        self.block: bytes | None = None
        self._zeros = bytes(BLOCK_SIZE)

    def take(self, t_ns: int) -> bytes:
        return self.block if self.block is not None else self._zeros


def replay(
    directory: str | Path,
    mission_file: str | Path,
    *,
    log: CsvLogger | None = None,
    key_file: str | Path | None = None,
) -> ReplayResult:
    """Replay a recording made by ``zplatform up --record DIR`` (or ``node
    --record``) through a fresh control loop; compare the telemetry.

    The loop runs the mission loaded from ``mission_file``, the operator's
    (its code imported as for ``sim``), never code the recording names: the
    recording must be of that mission (the same layout and
    :func:`~zplatform.sim.replay_recording.mission_digest`), else RecordingError naming
    the first difference. The mission key is needed when the mission
    authenticates (the recorded frames carry their tags and are checked
    again). Raises :class:`~zplatform.errors.RecordingError` for a missing
    or malformed recording (:class:`~zplatform.sim.replay_recording.RecordReader`),
    ConfigError for a mission file that does not load, KeyError_ for a
    missing key; a difference is a result, not an error.
    """
    from ..core.auth import load_keys
    from ..mission.load import load_mission

    mission = load_mission(mission_file)
    if mission.bulk:
        raise RecordingError(
            f"mission {mission.mission!r} has bulk channels: their samples (megabytes per "
            "loop) are not recorded, so its loop cannot be replayed bit for bit"
        )
    with RecordReader(directory, mission) as reader:
        return _replay(reader, mission, load_keys(mission, "cn", key_file), log)


def _replay(
    reader: RecordReader, mission: Mission, keys: KeySet | None, log: CsvLogger | None
) -> ReplayResult:
    cn = ControlLogic(mission, keys=keys)
    refused = CnRefusals()
    cn.dv.write_all(reader.initial)  # epoch included
    # A recording that starts mid-run (a standby that took command, a control
    # node that resumed after a restart): every component takes up its state
    # from that vector, as the recording node did. The recording is not
    # trusted (a damaged file, a crafted one): a vector no control node of
    # this mission could have written is its error, never a crash.
    try:
        cn.adopt()
    except (ZPlatformError, IndexError, ValueError, OverflowError) as exc:
        raise RecordingError(
            f"the recording's first vector cannot be taken up by this mission's control node: {exc}"
        ) from exc
    # The recorded blocks, on the recorded loops, from the first block on: a
    # control node that ran without a health port (the lockstep runner, a
    # loop driven by hand) recorded none, and its replay takes none either.
    recorded = _RecordedHealth()
    attached = False
    state_dv = cn.dv
    frames = 0
    loops = 0
    first = last = 0
    diff: Difference | None = None
    for rec in reader.loops():
        recorded.block = rec.health
        if rec.health is not None and not attached:
            cn.attach_health(recorded)
            attached = True
        cn.begin(rec.loop, rec.t_ns, final=rec.final, standby=rec.standby if cn.redundant else None)
        for i, payload in rec.replies:
            cn.reply(i, payload)
        tm = cn.finish(
            rec.grounds,
            sync_overrun=rec.sync_overrun,
            loop_overruns=rec.loop_overruns,
            inbox_dropped=rec.inbox_dropped,
            refused=refused.set_fields(rec.refused),
            saves=rec.saves,
        )
        loops += 1
        first = first or rec.loop
        last = rec.loop
        if log is not None and tm is not None:
            log.write(rec.t_ns, cn.dv)
        if (tm is None) != (rec.telemetry is None):
            diff = Difference(
                rec.loop,
                "<telemetry>",
                "sent" if rec.telemetry is not None else "not sent",
                "sent" if tm is not None else "not sent",
            )
            break
        if tm is not None and rec.telemetry is not None:
            frames += 1
            if bytes(tm) != rec.telemetry:
                tag = TAG_LEN if mission.security.auth else 0
                diff = _first_difference(cn.layout, rec.loop, rec.telemetry, tm, tag)
                break
        if cn.events.pending:
            cn.events.drain()
    if log is not None:
        log.flush()
    return ReplayResult(
        mission=mission.mission,
        loops=loops,
        first_loop=first,
        last_loop=last,
        telemetry_frames=frames,
        identical=diff is None and loops > 0,
        complete=reader.complete,
        dropped_loops=reader.dropped_loops,
        first_difference=diff,
        final_state=state_dv.get_name("cn_state"),
    )
