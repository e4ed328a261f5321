"""The ground side of operator commands, sans-IO: scripts, element
resolution and request framing.

Everything that turns an operator's ``launch`` or ``write led_a_cmd true``
into a ``gn_to_cn`` frame lives here (:func:`fill_request`, element and
value resolution). Reading the CN's answer, numbering requests and playing
scripts over time are the ground logic's (:mod:`zplatform.ground.logic`,
:mod:`zplatform.ground.script`), which the zenoh tools and the lockstep
runner share, so a script means the same thing live and in ``sim``.

Command scripts (:func:`parse_commands`, :func:`load_commands`) have one
command per line (``at 1.0 launch``, ``at 2.0 write seq_leds_mode manual``,
``at 3.0 prm_set apogee_target_m 550``); ``#`` starts a comment; times are
seconds (decimal, read exactly) from the start of loop 1. ``as alice@pad:
at 1.0 lock`` names who sends a line, ``as alice@pad`` alone the lines after.

Contract: pure functions (:func:`load_commands` also reads its file); a bad
script or command raises CommandError naming where, before anything is sent
(docs/operations.md#commanding).
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Sequence
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any, NamedTuple

import msgspec

from ..config import CMD_NAMES, Mission
from ..core.auth import KeySet, Run, channel
from ..core.codec import RegionCodec
from ..core.datavector import DataVector, Layout
from ..errors import CommandError, DataVectorError
from .authority import TAG_BYTES, Signer, request_tag

__all__ = [
    "CheckedCommand",
    "ScriptCommand",
    "Uplink",
    "element_index",
    "fill_request",
    "load_commands",
    "operator_number",
    "parse_commands",
    "resolve_param",
    "resolve_write",
    "validate_command",
    "validate_words",
]

_COMMANDS = tuple(c.lower() for c in CMD_NAMES if c != "NONE")
_TWO_ARGS = {"write": "ELEMENT VALUE", "prm_set": "PARAMETER VALUE"}
_ONE_ARG = {"handover": "OPERATOR", "approve": "ARM_NUMBER"}
_LINE_RE = re.compile(r"^at\s+(\S+)\s+(\S+)(?:\s+(.*))?$")
_AS_RE = re.compile(r"^as\s+([^\s@:]+)@([^\s@:]+)\s*(:.*)?$")


class ScriptCommand(msgspec.Struct, frozen=True):
    """One scripted operator command.

    ``at_ns`` is the time from the start of loop 1; ``command`` the upper
    case command name; ``element`` and ``value`` (text as written) for
    WRITE, and for PRM_SET the parameter and its value; ``source`` is
    ``file:line`` for messages; ``operator`` and ``station``: who sends it
    (``as OPERATOR@STATION``, a mission with ``ground:``; None: the ground's
    own ``--operator``/``--station``).
    """

    at_ns: int
    command: str
    element: str | None = None
    value: str | None = None
    source: str = "<script>"
    operator: str | None = None
    station: str | None = None


# ---------------------------------------------------------------------------
# scripts


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
    (parameters and values of PRM_SET) are checked against the mission by the player
    (:class:`~zplatform.ground.script.ScriptPlayer`). The result is in time
    order (stable: file order for equal times).
    """
    out: list[ScriptCommand] = []
    default: tuple[str | None, str | None] = (None, None)
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"{source}:{n}"
        who = default
        if line.startswith("as ") or line == "as":
            a = _AS_RE.match(line)
            if a is None:
                raise CommandError(
                    f"{where}: expected 'as OPERATOR@STATION' or 'as OPERATOR@STATION: at "
                    f"SECONDS COMMAND [ARGS]', got {line!r}"
                )
            if a.group(3) is None:  # a header: the lines after it
                default = (a.group(1), a.group(2))
                continue
            who = (a.group(1), a.group(2))
            line = a.group(3)[1:].strip()
        m = _LINE_RE.match(line)
        if m is None:
            raise CommandError(f"{where}: expected 'at SECONDS COMMAND [ARGS]', got {line!r}")
        at_ns = _seconds_to_ns(m.group(1), where)
        cmd = m.group(2).lower()
        args = (m.group(3) or "").split()
        if cmd not in _COMMANDS:
            hint = did_you_mean(cmd, list(_COMMANDS)) or f"; expected one of {', '.join(_COMMANDS)}"
            raise CommandError(f"{where}: unknown command {m.group(2)!r}{hint}")
        if cmd in _TWO_ARGS:
            if len(args) != 2:
                raise CommandError(f"{where}: {cmd} takes {_TWO_ARGS[cmd]}, got {args}")
            out.append(ScriptCommand(at_ns, cmd.upper(), args[0], args[1], where, *who))
            continue
        if cmd in _ONE_ARG:  # the command lock's: checked against the mission by the player
            if len(args) != 1:
                raise CommandError(f"{where}: {cmd} takes {_ONE_ARG[cmd]}, got {args}")
            out.append(ScriptCommand(at_ns, cmd.upper(), args[0], None, where, *who))
            continue
        if args:
            raise CommandError(f"{where}: {cmd} takes no arguments, got {' '.join(args)!r}")
        out.append(ScriptCommand(at_ns, cmd.upper(), None, None, where, *who))
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


# ---------------------------------------------------------------------------
# requests


def _all_element_names(mission: Mission) -> list[str]:
    """The CN's element list, in ``ElementSpec.index`` order."""
    return [e.name for r in mission.region_names() for e in mission.regions[r]]


def element_index(mission: Mission, name: str) -> int:
    """The ``gn_cmd_element`` value naming element ``name`` (its index in the
    CN's element list). Raises CommandError for an unknown name."""
    names = _all_element_names(mission)
    try:
        return names.index(name)
    except ValueError:
        close = difflib.get_close_matches(name, names, n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise CommandError(f"no element named {name!r}{hint}") from None


def did_you_mean(word: str, choices: Sequence[str]) -> str:
    """``"; did you mean a, b?"`` naming the choices closest to ``word``, or
    ``""``: the hint `check` gives, for every name an operator types."""
    close = difflib.get_close_matches(word.lower(), list(choices), n=3)
    return f"; did you mean {', '.join(close)}?" if close else ""


def resolve_write(layout: Layout, element: str, value: str, where: str) -> tuple[int, float]:
    """``(gn_cmd_element, gn_cmd_value)`` of ``write element value``.

    ``value`` may be a number, an enum name, or true/false/on/off for a
    bool. Raises CommandError naming ``where`` for an unknown element, an
    array, or a value that does not fit (the CN checks again).
    """
    try:
        spec = layout.element(element)
    except DataVectorError as exc:
        hint = did_you_mean(element, list(layout.elements))
        raise CommandError(f"{where}: {exc}{hint}") from None
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


def resolve_param(mission: Mission, name: str, value: str, where: str) -> tuple[int, float]:
    """``(gn_cmd_element, gn_cmd_value)`` of ``prm_set name value``.

    ``value`` is a number, or true/false/on/off for a bool parameter.
    Raises CommandError naming ``where`` for an unknown parameter, a value
    that does not fit its type or lies outside its ``[min, max]`` (the CN
    checks again)."""
    params = {p.name: p for p in mission.params}
    if not params:
        raise CommandError(f"{where}: mission {mission.mission!r} has no parameters")
    p = params.get(name)
    if p is None:
        close = difflib.get_close_matches(name, list(params), n=3)
        listed = ", ".join(close) if close else ""
        hint = f"; did you mean {listed}?" if close else f"; parameters: {', '.join(params)}"
        raise CommandError(f"{where}: no parameter named {name!r}{hint}")
    index, num = resolve_write(Layout.for_node(mission, "cn"), name, value, where)
    if p.min is not None and p.max is not None and not p.min <= num <= p.max:
        units = f" {p.units}" if p.units else ""
        raise CommandError(
            f"{where}: {value} is outside {name}'s bounds [{p.min!r}, {p.max!r}]{units}"
        )
    return index, num


class CheckedCommand(NamedTuple):
    """An operator command :func:`validate_command` let through, as it goes
    into ``gn_to_cn``: the ground takes it as checked
    (:meth:`zplatform.ground.logic.GroundLogic.submit`), never again."""

    command: str
    """The command's name, upper case."""
    element: int
    """``gn_cmd_element``: the element's or parameter's index (0 without one)."""
    value: float
    """``gn_cmd_value`` (0.0 without one)."""


def validate_command(
    mission: Mission,
    command: str,
    element: str | None = None,
    value: str | None = None,
    where: str | None = None,
) -> CheckedCommand:
    """Check an operator command against the mission before anything is sent:
    the ground's one place for it (the tools, the console, the script
    player and the ground logic all call it, each command once).

    Returns ``(COMMAND, element index, value)`` as they go into ``gn_to_cn``.
    Raises CommandError for an unknown command, element or parameter, or a
    value that does not fit the element (enum names and true/false
    accepted) or the parameter's bounds. ``where`` starts the messages
    (default: the command's name).
    """
    cmd = command.upper()
    where = where or cmd.lower()
    if cmd not in CMD_NAMES or cmd == "NONE":
        names = [c.lower() for c in CMD_NAMES[1:]]
        hint = did_you_mean(command, names) or f"; expected one of {', '.join(names)}"
        raise CommandError(f"unknown command {command!r}{hint}")
    if cmd in _LOCK_NAMES:
        return _lock_command(mission, cmd, element, value)
    args = _TWO_ARGS.get(cmd.lower())
    if args is None:
        if element is not None:
            raise CommandError(f"{command} takes no arguments")
        if cmd == "PRM_SAVE" and not mission.params:
            raise CommandError(f"mission {mission.mission!r} has no parameters to save")
        return CheckedCommand(cmd, 0, 0.0)
    if element is None or value is None:
        raise CommandError(f"{cmd.lower()} needs {args}")
    if cmd == "PRM_SET":
        index, num = resolve_param(mission, element, value, where)
    else:
        index, num = resolve_write(Layout.for_node(mission, "cn"), element, value, where)
    return CheckedCommand(cmd, index, num)


_LOCK_NAMES = ("LOCK", "RELEASE", "HANDOVER", "TAKEOVER", "APPROVE")
_F64_EXACT = 1 << 53


def _lock_command(
    mission: Mission, cmd: str, element: str | None, value: str | None
) -> CheckedCommand:
    """The command lock's commands: ``handover OPERATOR`` (``gn_cmd_element``:
    the operator's number), ``approve ARM_NUMBER`` (carried in ``gn_cmd_value``
    to the uplink, which puts it in ``gn_cmd_ref``), the others without an
    argument; only in a mission with command authority."""
    if not mission.authority:
        raise CommandError(
            f"{cmd.lower()}: mission {mission.mission!r} has no command lock (a `ground:` "
            "section without single_operator)"
        )
    if value is not None:
        raise CommandError(f"{cmd.lower()} takes at most one argument")
    if cmd == "HANDOVER":
        if element is None:
            raise CommandError("handover needs OPERATOR")
        return CheckedCommand(cmd, operator_number(mission, element), 0.0)
    if cmd == "APPROVE":
        if element is None or not element.isdigit() or not 1 <= int(element) < _F64_EXACT:
            raise CommandError(f"approve needs the ARM's number (1..2**53-1), got {element!r}")
        return CheckedCommand(cmd, 0, float(int(element)))
    if element is not None:
        raise CommandError(f"{cmd.lower()} takes no arguments")
    return CheckedCommand(cmd, 0, 0.0)


def validate_words(
    mission: Mission, command: str, args: Sequence[str], where: str | None = None
) -> CheckedCommand:
    """:func:`validate_command` for a command as an operator types it: its
    name and at most two words (ELEMENT VALUE, PARAMETER VALUE); more raise
    CommandError."""
    if len(args) > 2:
        raise CommandError(f"{command} takes at most ELEMENT VALUE, got {list(args)}")
    element = args[0] if args else None
    return validate_command(mission, command, element, args[1] if len(args) > 1 else None, where)


def fill_request(
    dv: DataVector,
    command: str,
    seq: int,
    element_index: int = 0,
    value: float = 0.0,
    epoch: int = 0,
) -> None:
    """Write one command request into the ``gn_to_cn`` elements of ``dv``.

    ``command`` is a name of :data:`~zplatform.config.CMD_NAMES` (any case,
    not ``NONE``); ``seq`` must be above every number the CN has seen (read
    ``cn_cmd_seq`` from telemetry and add one); ``epoch`` is the CN's
    ``cn_epoch`` from telemetry (a request for another run is refused).
    Raises CommandError for an unknown command, a ``seq`` outside
    1..2**64-1, an ``element_index``
    outside 0..65535, or a ``dv`` without the ``gn_to_cn`` region. The value
    itself is checked by the CN (a bad one is rejected there).
    """
    name = command.upper()
    if name not in CMD_NAMES or name == "NONE":
        raise CommandError(f"unknown command {command!r}; commands: {', '.join(CMD_NAMES[1:])}")
    if not 1 <= seq < 1 << 64:
        raise CommandError(f"command number {seq} is outside 1..2**64-1")
    if not 0 <= epoch < 1 << 64:
        raise CommandError(f"epoch {epoch} is outside 0..2**64-1")
    if not 0 <= element_index <= 0xFFFF:
        raise CommandError(f"element index {element_index} is outside 0..65535")
    try:
        dv.handle("gn_cmd").set(CMD_NAMES.index(name))
        dv.handle("gn_cmd_seq").set(seq)
        dv.handle("gn_cmd_epoch").set(epoch)
        dv.handle("gn_cmd_element").set(element_index)
        dv.handle("gn_cmd_value").set(float(value))
    except DataVectorError as exc:
        raise CommandError(f"cannot fill a command request: {exc}") from exc


def operator_number(mission: Mission, name: str) -> int:
    """The ``gn_cmd_element`` of ``handover NAME``: the operator's index in
    ``ground.operators`` plus one. CommandError for a name not listed."""
    ops = [o.name for o in mission.ground.operators] if mission.ground is not None else []
    if name not in ops:
        raise CommandError(f"no operator named {name!r}{did_you_mean(name, ops)}")
    return ops.index(name) + 1


class Uplink:
    """Frames command requests: one ``gn_to_cn`` vector, its codec, and the
    uplink's ``gn_to_cn`` channel from ``keys`` (None: the mission does not
    authenticate), its tags in ``run`` (the run the ground learned: a
    control node refuses a request tagged in another run before any decode;
    None: :data:`~zplatform.core.auth.NO_RUN`, and only the run the request
    names in its data is checked).

    ``signer``: in a mission with ``ground:``, the operator and station
    every request names and is tagged by (``gn_cmd_operator``,
    ``gn_cmd_station``, ``gn_cmd_op_tag``, ``gn_cmd_st_tag``; codecs/FORMAT.md
    §6.7); None: the request names nobody (what a ``single_operator``
    mission takes; one with command authority refuses it).

    :meth:`frame` returns a buffer of its own (reused by the next call).
    """

    def __init__(
        self,
        mission: Mission,
        keys: KeySet | None = None,
        run: Run | None = None,
        signer: Signer | None = None,
    ) -> None:
        if not mission.has_ground:
            raise CommandError(f"mission {mission.mission!r} has no ground node 'gn'")
        self.mission = mission
        self.req = DataVector(Layout.for_regions(mission, ["gn_to_cn"]))
        self._codec = RegionCodec(self.req, "gn_to_cn")
        self._seal = channel(keys, "gn_to_cn", run)
        self.signer = signer
        g = mission.ground
        if signer is not None:
            if g is None:
                raise CommandError(f"mission {mission.mission!r} has no `ground:` operators")
            ops = [o.name for o in g.operators]
            sts = [s.name for s in g.stations]
            if signer.operator not in ops or signer.station not in sts:
                raise CommandError(
                    f"{signer.operator}@{signer.station}: the mission lists operators "
                    f"{ops} and stations {sts}"
                )
            self._op_n = ops.index(signer.operator) + 1
            self._st_n = sts.index(signer.station) + 1
            lay = self.req.layout
            base = lay.region("gn_to_cn").offset
            self._op_at = lay.element("gn_cmd_op_tag").offset - base
            self._st_at = lay.element("gn_cmd_st_tag").offset - base
            self._region = self.req.region_view("gn_to_cn")

    def frame(
        self,
        command: str,
        seq: int,
        index: int,
        value: float,
        t_ns: int,
        epoch: int = 0,
        ref: int = 0,
    ) -> bytearray:
        """The request frame, authenticated (CommandError as :func:`fill_request`).
        ``ref``: APPROVE's ARM number (a mission with ``ground:``)."""
        fill_request(self.req, command, seq, index, value, epoch)
        s = self.signer
        if s is not None:
            dv = self.req
            dv.handle("gn_cmd_operator").set(self._op_n)
            dv.handle("gn_cmd_station").set(self._st_n)
            if not 0 <= ref < 1 << 64:
                raise CommandError(f"ARM number {ref} is outside 0..2**64-1")
            dv.handle("gn_cmd_ref").set(ref)
            mv = self._region
            body = mv[: self._op_at]
            mac = self.mission.security.mac
            mv[self._op_at : self._op_at + TAG_BYTES] = request_tag(s.operator_key, mac, body)
            mv[self._st_at : self._st_at + TAG_BYTES] = request_tag(s.station_key, mac, body)
        frame = self._codec.encode(seq, t_ns)
        return self._seal.seal(frame) if self._seal is not None else frame
