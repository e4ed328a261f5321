"""The lockstep runner: every node of a mission in one process, in virtual time.

:class:`LockstepRunner` drives the same sans-IO node logic as the zenoh
runtime (:class:`~zplatform.node.logic.ControlLogic`,
:class:`~zplatform.node.logic.DeviceLogic`) and moves the same region
frames (:class:`~zplatform.codec.RegionCodec`, encoded and decoded, not
copied around the codec), in the protocol's order. Each loop, at virtual time
``t = start_ns + loop * period_ns``:

1. for each device node in order: the CN encodes ``cn_to_dnX``; the DN
   applies it and replies at once with ``dnX_to_cn`` as it stood *before* its
   step; the CN applies the reply (``cn_rx_dnX += 1``); the DN runs its step;
2. the ground node sends at most one scripted command that has come due
   (``gn_to_cn`` filled with :func:`~zplatform.commands.fill_request`, numbers
   1, 2, 3, ...), which the CN applies (``new_request=True``);
3. the CN runs its step;
4. on telemetry loops (``loop % telemetry_divisor == 0``) the CN encodes its
   whole vector, the ground side applies it and, given a
   :class:`~zplatform.telemetry.CsvLogger`, logs it with
   ``rx_time_ns = t``.

No frame is ever lost or late here, so ``cn_missed_dnX`` and ``cn_late_dnX``
stay 0. Nothing reads the wall clock except the speed figure of
:class:`SimResult`, and nothing iterates a set or hashes into the output: the
same mission and the same command script give a byte-identical CSV log.

Command scripts (:func:`parse_commands`, :func:`load_commands`) have one
command per line, ``#`` starts a comment::

    at 0.5 arm
    at 1.0 launch
    at 2.0 write seq_leds_mode manual
    at 9.0 abort

Times are seconds from the start of the run (decimal, read exactly).
Commands run in time order (file order for equal times), at most one per
loop: one due while another is being sent waits for the next loop.
"""

from __future__ import annotations

import re
import time
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any

import msgspec

from .codec import RegionCodec, VectorCodec
from .commands import fill_request
from .config import CMD_NAMES, Mission
from .datavector import DataVector, Handle, Layout
from .devices import Board
from .errors import CommandError, DataVectorError
from .events import Event
from .node.logic import ControlLogic, DeviceLogic
from .telemetry import CsvLogger
from .timebase import VirtualClock

__all__ = [
    "DEFAULT_START_NS",
    "CommandOutcome",
    "LockstepRunner",
    "ScriptCommand",
    "SimResult",
    "load_commands",
    "parse_commands",
]

DEFAULT_START_NS = 1_700_000_000_000_000_000
"""Virtual time of loop 0 (2023-11-14T22:13:20Z): fixed, so runs repeat exactly."""

_COMMANDS = tuple(c.lower() for c in CMD_NAMES if c != "NONE")
_LINE_RE = re.compile(r"^at\s+(\S+)\s+(\S+)(?:\s+(.*))?$")


class ScriptCommand(msgspec.Struct, frozen=True):
    """One scripted operator command.

    ``at_ns`` is the time from the start of the run; ``command`` the upper
    case command name; ``element`` and ``value`` (text as written) for
    WRITE; ``source`` is ``file:line`` for messages.
    """

    at_ns: int
    command: str
    element: str | None = None
    value: str | None = None
    source: str = "<script>"


class CommandOutcome(msgspec.Struct, frozen=True):
    """What became of a scripted command: sent at ``t_ns`` (virtual, since start)
    with number ``seq`` in loop ``loop``; ``status`` is the CN's verdict."""

    source: str
    command: str
    seq: int
    loop: int
    t_ns: int
    status: str


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
            "events": [
                {
                    "node": e.node,
                    "seq": e.seq,
                    "t_ns": e.t_ns,
                    "severity": e.severity_name,
                    "id": e.id,
                    "text": e.text,
                }
                for e in self.events
            ],
            "wall_s": self.wall_s,
            "loops_per_s": self.loops_per_s,
        }


# ---------------------------------------------------------------------------
# command scripts


def _seconds_to_ns(text: str, where: str) -> int:
    try:
        d = Decimal(text)
    except InvalidOperation:
        raise CommandError(f"{where}: time {text!r} is not a number of seconds") from None
    if not d.is_finite() or d < 0:
        raise CommandError(f"{where}: time {text!r} must be a finite number >= 0")
    return int((d * 1_000_000_000).to_integral_value())


def parse_commands(text: str, source: str = "<string>") -> list[ScriptCommand]:
    """Parse a command script (module doc); raises CommandError naming ``source:line``.

    Checks the syntax and command names only; elements and values of WRITE
    are checked against the mission by :class:`LockstepRunner`. The result is
    in time order (stable: file order for equal times).
    """
    out: list[ScriptCommand] = []
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"{source}:{n}"
        m = _LINE_RE.match(line)
        if m is None:
            raise CommandError(f"{where}: expected 'at SECONDS COMMAND [ARGS]', got {line!r}")
        at_ns = _seconds_to_ns(m.group(1), where)
        cmd = m.group(2).lower()
        args = (m.group(3) or "").split()
        if cmd not in _COMMANDS:
            raise CommandError(
                f"{where}: unknown command {m.group(2)!r}; expected one of {', '.join(_COMMANDS)}"
            )
        if cmd == "write":
            if len(args) != 2:
                raise CommandError(f"{where}: write takes ELEMENT VALUE, got {args}")
            out.append(ScriptCommand(at_ns, "WRITE", args[0], args[1], where))
            continue
        if args:
            raise CommandError(f"{where}: {cmd} takes no arguments, got {' '.join(args)!r}")
        out.append(ScriptCommand(at_ns, cmd.upper(), source=where))
    out.sort(key=lambda c: c.at_ns)  # stable
    return out


def load_commands(path: str | Path) -> list[ScriptCommand]:
    """Read and parse a command script file (CommandError on a bad line or file)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise CommandError(f"cannot read command script {str(p)!r}: {exc.strerror}") from exc
    except UnicodeDecodeError as exc:
        raise CommandError(f"{p}: not UTF-8 text: {exc}") from exc
    return parse_commands(text, str(p))


def resolve_write(layout: Layout, element: str, value: str, where: str) -> tuple[int, float]:
    """``(gn_cmd_element, gn_cmd_value)`` of ``write element value``.

    ``value`` may be a number, an enum name, or true/false/on/off for a
    bool. Raises CommandError naming ``where`` for an unknown element, an
    array, or a value that does not fit (the CN checks again).
    """
    try:
        spec = layout.element(element)
    except DataVectorError as exc:
        raise CommandError(f"{where}: {exc}") from None
    if spec.count:
        raise CommandError(f"{where}: {element} is an array; WRITE sets one scalar")
    v: Any = value
    if spec.enum is not None and value in spec.enum:
        v = spec.enum.index(value)
    elif spec.scalar.kind == "bool" and value.lower() in ("true", "on", "false", "off"):
        v = 1 if value.lower() in ("true", "on") else 0
    try:
        num = float(v)
    except ValueError:
        raise CommandError(f"{where}: {value!r} is not a valid value for {element}") from None
    try:
        DataVector.coerce(spec, int(num) if num.is_integer() else num)
    except DataVectorError as exc:
        raise CommandError(f"{where}: {exc}") from None
    return spec.index, num


# ---------------------------------------------------------------------------
# the runner


class _Link:
    """The CN <-> one DN sync path: four codecs and the rx counter."""

    __slots__ = ("cn_rx", "cn_tx", "dev", "dn_rx", "dn_tx", "rx")

    def __init__(self, cn_dv: DataVector, dev: DeviceLogic) -> None:
        dn = dev.node
        self.dev = dev
        self.cn_tx = RegionCodec(cn_dv, f"cn_to_{dn}")
        self.dn_rx = RegionCodec(dev.dv, f"cn_to_{dn}")
        self.dn_tx = RegionCodec(dev.dv, f"{dn}_to_cn")
        self.cn_rx = RegionCodec(cn_dv, f"{dn}_to_cn")
        self.rx: Handle = cn_dv.handle(f"cn_rx_{dn}")


class _Due(msgspec.Struct, frozen=True):
    loop: int
    command: ScriptCommand
    element_index: int
    value: float


class LockstepRunner:
    """Every node of ``mission`` in one process, in virtual time (module doc).

    ``commands`` is the ground's script; ``boards`` replaces the default
    :class:`~zplatform.devices.SimBoard` of some device nodes (tests inject
    faults through them). Construction builds every node (ConfigError for a
    bad mission) and resolves the script against the mission (CommandError
    naming ``file:line``). Not thread-safe.
    """

    def __init__(
        self,
        mission: Mission,
        *,
        commands: list[ScriptCommand] | None = None,
        start_ns: int = DEFAULT_START_NS,
        boards: dict[str, Board] | None = None,
    ) -> None:
        self.mission = mission
        self.start_ns = start_ns
        self.period_ns = mission.period_ns
        self.clock = VirtualClock(start_ns)
        self.control = ControlLogic(mission)
        boards = boards or {}
        unknown = sorted(set(boards) - set(mission.device_nodes))
        if unknown:
            raise ValueError(f"boards given for nodes that are not device nodes: {unknown}")
        self.devices = [
            DeviceLogic(mission, dn, board=boards.get(dn)) for dn in mission.device_nodes
        ]
        cn_dv = self.control.dv
        self._links = tuple(_Link(cn_dv, d) for d in self.devices)
        # The ground side: a command request vector and a telemetry receiver.
        self.ground_dv: DataVector | None = None
        self._gn_tx: RegionCodec | None = None
        self._gn_rx: RegionCodec | None = None
        if mission.has_ground:
            self.ground_dv = DataVector(Layout.for_regions(mission, ["gn_to_cn"]))
            self._gn_tx = RegionCodec(self.ground_dv, "gn_to_cn")
            self._gn_rx = RegionCodec(cn_dv, "gn_to_cn")
        self.telemetry_dv = DataVector(Layout.for_node(mission, "cn"))
        self._tm_tx = VectorCodec(cn_dv)
        self._tm_rx = VectorCodec(self.telemetry_dv)
        self._script = self._resolve(commands or [])
        self._next_cmd = 0
        self._seq = 0
        self.loop = 0
        self.telemetry_received = 0
        self._state_h = cn_dv.handle("cn_state")
        self._status_h = cn_dv.handle("cn_cmd_status")
        self._states: list[str] = []
        self._last_state = -1
        self._events: list[Event] = []
        self._outcomes: list[CommandOutcome] = []
        self._wall_s = 0.0

    def _resolve(self, script: list[ScriptCommand]) -> tuple[_Due, ...]:
        if script and not self.mission.has_ground:
            raise CommandError(
                f"{script[0].source}: mission {self.mission.mission!r} has no ground node 'gn' "
                "to send commands"
            )
        layout = self.control.layout
        out = []
        for c in sorted(script, key=lambda c: c.at_ns):
            index, value = 0, 0.0
            if c.command == "WRITE":
                if c.element is None or c.value is None:
                    raise CommandError(f"{c.source}: write needs ELEMENT VALUE")
                index, value = resolve_write(layout, c.element, c.value, c.source)
            # First loop whose time is at or after the command's time.
            due = -(-c.at_ns // self.period_ns)
            out.append(_Due(due, c, index, value))
        return tuple(out)

    # -- running -----------------------------------------------------------
    def step(self, log: CsvLogger | None = None) -> None:
        """Run one loop (module doc order) and advance the virtual clock."""
        loop = self.loop
        t = self.clock.now_ns()
        for link in self._links:
            link.dn_rx.apply(link.cn_tx.encode(loop, t))
            link.cn_rx.apply(link.dn_tx.encode(loop, t))
            link.rx.bump()
            link.dev.step(loop, t)
        sent: _Due | None = None
        script = self._script
        if self._next_cmd < len(script) and script[self._next_cmd].loop <= loop:
            sent = script[self._next_cmd]
            self._next_cmd += 1
            self._send(sent, t)
        control = self.control
        control.step(loop, t, sent is not None)
        if sent is not None:
            self._outcomes.append(
                CommandOutcome(
                    sent.command.source,
                    sent.command.command,
                    self._seq,
                    loop,
                    t - self.start_ns,
                    self._status_h.spec.name_of(self._status_h.get()),
                )
            )
        if loop % self.mission.telemetry_divisor == 0:
            self._tm_rx.apply(self._tm_tx.encode(loop, t))
            self.telemetry_received += 1
            if log is not None:
                log.write(t, self.telemetry_dv)
        state = self._state_h.get()
        if state != self._last_state:
            self._last_state = state
            self._states.append(self._state_h.spec.name_of(state))
        if control.events.pending:
            self._events.extend(control.events.drain())
        for d in self.devices:
            if d.events.pending:
                self._events.extend(d.events.drain())
        self.loop = loop + 1
        self.clock.advance(self.period_ns)

    def _send(self, due: _Due, t: int) -> None:
        assert self.ground_dv is not None and self._gn_tx is not None
        assert self._gn_rx is not None
        self._seq += 1
        fill_request(self.ground_dv, due.command.command, self._seq, due.element_index, due.value)
        self._gn_rx.apply(self._gn_tx.encode(self._seq, t))

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
        return SimResult(
            mission=self.mission.mission,
            loops=loops,
            duration_s=loops * self.period_ns / 1e9,
            rate_hz=self.mission.loop_hz,
            final_state=dv.get_name("cn_state"),
            states=list(self._states),
            events=list(self._events),
            commands=list(self._outcomes),
            pending_commands=[d.command.source for d in self._script[self._next_cmd :]],
            errors=sum(errors_by_node.values()),
            errors_by_node=errors_by_node,
            rx={dn: int(dv.get(f"cn_rx_{dn}")) for dn in dns},
            missed={dn: int(dv.get(f"cn_missed_{dn}")) for dn in dns},
            late={dn: int(dv.get(f"cn_late_{dn}")) for dn in dns},
            loop_overruns=int(dv.get("cn_loop_overruns")),
            sync_overruns=int(dv.get("cn_sync_overruns")),
            telemetry_received=self.telemetry_received,
            fault=dv.get_name("cn_fault"),
            wall_s=self._wall_s,
            loops_per_s=loops / self._wall_s if self._wall_s > 0 else 0.0,
        )
