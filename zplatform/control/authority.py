"""Stations, operators, the command lock and the two-person rule, sans-IO.

With a ``ground:`` section (not ``single_operator``) every request names its
operator and station and carries a MAC under each one's key
(:func:`request_tag`); both keys derive from the ``operators`` key only the
control nodes hold (:func:`identity_key`), so revoking an operator is a
change of the mission the CN loads, never a re-keying of the vehicle.
:class:`Authority` is the CN's rule book: one holder of the command lock at
most (a lease renewed by its holder's accepted requests; LOCK, RELEASE,
HANDOVER, a flight director's TAKEOVER, expiry), range safety's ABORT from
any station, viewers never, a two-person command's ARM approved by a second
operator. One pure verdict (:meth:`AuthorityRules.verdict`, the CN's and a
console's) over the published state (:func:`read_lock_state`) and the loop's
time. Rules: docs/security.md#stations-and-operators.

Contract: not thread-safe (the CN's loop thread); :meth:`Authority.identify`,
:meth:`Authority.check` and the verdict change nothing (a refusal's text is
its one allocation); :meth:`Authority.apply` and :meth:`Authority.expire`
do, returning what to announce. Nothing in a request can make them raise.
"""

from __future__ import annotations

import hmac
from typing import TYPE_CHECKING, NamedTuple, Protocol

import blake3

from ..config.codes import Command, CommandStatus
from ..core.auth import OPERATORS_LINK
from ..errors import ConfigError

if TYPE_CHECKING:
    from ..config import GroundConfig, Mission
    from ..core.datavector import DataVector

__all__ = [
    "ARM_WINDOW_NS",
    "COMMANDING_ROLES",
    "IDENTITY_LINK",
    "MAX_OPERATORS",
    "STATE_DEPENDENT",
    "TAG_BYTES",
    "Authority",
    "AuthorityRules",
    "Change",
    "Identity",
    "LockState",
    "LockView",
    "Signer",
    "check_config",
    "identity_key",
    "read_lock_state",
    "request_tag",
    "two_person_targets",
]

IDENTITY_LINK = OPERATORS_LINK
"""The link (a key in ``cn.keys`` only) every operator's and station's key
is derived from (:func:`identity_key`)."""
TAG_BYTES = 16
"""Bytes of each identity MAC (``gn_cmd_op_tag``, ``gn_cmd_st_tag``)."""
COMMANDING_ROLES = frozenset({"flight_director", "operator"})
"""Roles that may hold the lock and command with it."""

_NS = 1_000_000_000
ARM_WINDOW_NS = 10 * _NS
"""How long an accepted ARM confirms the next (hazardous) command, and
how long it may be approved: 10 s (:mod:`zplatform.control.commands`)."""
MAX_OPERATORS = 64
"""Most operators a ``ground:`` section lists: an ARM's approvers are
published as a bit mask (``cn_arm_approvers``, one bit per operator)."""
STATE_DEPENDENT = frozenset(
    {
        CommandStatus.REJECTED_NOT_HOLDER,
        CommandStatus.REJECTED_APPROVAL_STALE,
        CommandStatus.REJECTED_APPROVAL_SELF,
    }
)
"""The verdicts of :meth:`AuthorityRules.verdict` that depend on the lock's
state (the others only on the operator's roles and the station)."""


def identity_key(base: bytes, vehicle: str, kind: str, name: str, key_id: int) -> bytes:
    """The key of operator (``kind`` ``"operator"``) or station (``"station"``)
    ``name``, number ``key_id``: HMAC-SHA256(``base``,
    ``"zplatform/2/<vehicle>/<kind>/<name>/<key_id>"``), ``base`` the
    :data:`IDENTITY_LINK` key (codecs/FORMAT.md §6.7). Pure."""
    return hmac.digest(base, f"zplatform/2/{vehicle}/{kind}/{name}/{key_id}".encode(), "sha256")


def request_tag(key: bytes, mac: str, body: bytes | bytearray | memoryview) -> bytes:
    """The :data:`TAG_BYTES`-byte MAC of a request's ``body`` (the
    ``gn_to_cn`` region's bytes before ``gn_cmd_op_tag``: command, number,
    run, argument, operator, station, reference) under ``key`` with the
    mission's ``security.mac``. Pure; allocates the digest."""
    if mac == "blake3":
        return blake3.blake3(body, key=key).digest(TAG_BYTES)
    return hmac.digest(key, body, "sha256")[:TAG_BYTES]


class Identity(NamedTuple):
    """Who a request says sent it, checked: indices into ``ground.operators``
    and ``ground.stations``."""

    operator: int
    station: int


class Signer(NamedTuple):
    """What a ground station signs its requests with
    (:class:`zplatform.control.uplink.Uplink`): the operator's and the
    station's names and keys (:mod:`zplatform.security.identities` reads
    them from their key files)."""

    operator: str
    operator_key: bytes
    station: str
    station_key: bytes


class Change(NamedTuple):
    """What :meth:`Authority.apply` or :meth:`Authority.expire` did to the
    lock, for the caller's event: ``what`` is ``granted``, ``renewed``,
    ``released``, ``handed``, ``taken_over``, ``expired`` or ``approved``;
    ``text`` says it in words (names, not numbers)."""

    what: str
    text: str


def two_person_targets(mission: Mission) -> tuple[frozenset[str], frozenset[str]]:
    """``(commands, elements)`` of ``ground.two_person``: command names, and
    names of elements (a protected WRITE) or parameters (a hazardous PRM_SET)."""
    g = mission.ground
    if g is None:
        return frozenset(), frozenset()
    cmds = frozenset(t for t in g.two_person if t in Command.__members__)
    return cmds, frozenset(g.two_person) - cmds


def check_config(mission: Mission, protected: list[str]) -> None:
    """Check ``ground.two_person`` against the commands (ConfigError naming the
    YAML path): each entry is a hazardous command, a protected element or a
    hazardous parameter: the approval lives inside the ARM window, so only
    what needs an ARM can need one. The rest of ``ground:`` is checked as
    the mission is decoded. ``protected``: the mission's protected elements
    (:func:`zplatform.control.commands.protected_elements`)."""
    g = mission.ground
    if g is None:
        return
    hazardous = set(mission.commands.hazardous)
    if "ABORT" in hazardous and any("range_safety" in o.roles for o in g.operators):
        raise ConfigError(
            "range safety's ABORT is taken from any station, without the lock: it cannot "
            "need an ARM too (drop ABORT from commands.hazardous)",
            "$.commands.hazardous",
        )
    if len(g.operators) > MAX_OPERATORS:
        raise ConfigError(
            f"{len(g.operators)} operators: at most {MAX_OPERATORS} (an ARM's approvers are "
            "published as one bit each, cn_arm_approvers)",
            "$.ground.operators",
        )
    protected_set = set(protected)
    params = {p.name for p in mission.params if p.hazardous}
    for i, t in enumerate(g.two_person):
        where = f"$.ground.two_person[{i}]"
        if t in Command.__members__:
            if t not in hazardous:
                raise ConfigError(
                    f"{t} is not hazardous (commands.hazardous): without an ARM there is no "
                    "window to approve in",
                    where,
                )
        elif t not in protected_set and t not in params:
            raise ConfigError(
                f"{t!r} is neither a hazardous command, a protected element nor a hazardous "
                f"parameter; hazardous: {sorted(hazardous)}, protected: {sorted(protected_set)}, "
                f"hazardous parameters: {sorted(params)}",
                where,
            )
        if t in g.two_person[:i]:
            raise ConfigError(f"{t!r} is listed twice", where)


class LockView(Protocol):
    """The command lock's and the two-person rule's state, as the CN keeps
    it (:class:`Authority`) and publishes it (:func:`read_lock_state`):
    operators and stations are 0-based indices into ``ground.operators`` and
    ``ground.stations``, ``-1`` none. ``holder`` holds the lock from
    ``station`` (``-1`` after a handover until the new holder's first
    request binds it) until ``until_ns``; ``arm_seq`` is the ARM open for
    approvals (``-1``: none), by ``arm_operator``, accepted at ``arm_t_ns``;
    ``approvers`` its approvers, bit ``i`` for operator ``i``."""

    holder: int
    station: int
    until_ns: int
    arm_seq: int
    arm_operator: int
    arm_t_ns: int
    approvers: int


class LockState:
    """A :class:`LockView` as a plain record (what telemetry shows:
    :func:`read_lock_state`; a test's state)."""

    __slots__ = (
        "approvers",
        "arm_operator",
        "arm_seq",
        "arm_t_ns",
        "holder",
        "station",
        "until_ns",
    )

    def __init__(
        self,
        holder: int = -1,
        station: int = -1,
        until_ns: int = 0,
        arm_seq: int = -1,
        arm_operator: int = -1,
        arm_t_ns: int = 0,
        approvers: int = 0,
    ) -> None:
        self.holder = holder
        self.station = station
        self.until_ns = until_ns
        self.arm_seq = arm_seq
        self.arm_operator = arm_operator
        self.arm_t_ns = arm_t_ns
        self.approvers = approvers

    def __repr__(self) -> str:
        return "LockState(" + ", ".join(f"{k}={getattr(self, k)}" for k in self.__slots__) + ")"


def read_lock_state(dv: DataVector) -> LockState:
    """The authority's state a CN-layout vector shows (a mission with
    command authority): ``cn_lock_holder``, ``cn_lock_station``,
    ``cn_lock_until_ns``, ``cn_arm_open``, ``cn_arm_operator``,
    ``cn_arm_open_ns``, ``cn_arm_approvers`` (what
    :class:`~zplatform.control.commands.CommandHandler` publishes). What a
    console judges with, and what a standby's takeover or a restart's resume
    takes up (:meth:`Authority.adopt`). Pure; allocates the record."""
    arm = int(dv.get("cn_arm_open"))
    return LockState(
        int(dv.get("cn_lock_holder")) - 1,
        int(dv.get("cn_lock_station")) - 1,
        int(dv.get("cn_lock_until_ns")),
        arm if arm else -1,
        int(dv.get("cn_arm_operator")) - 1,
        int(dv.get("cn_arm_open_ns")),
        int(dv.get("cn_arm_approvers")),
    )


class AuthorityRules:
    """The rules of ``ground`` (roles, view-only stations, revocations), and
    the one verdict over them (:meth:`verdict`) the CN's :class:`Authority`
    and a console (:class:`zplatform.console.model.ConsoleModel`) both give.
    Immutable after construction; pure."""

    def __init__(self, ground: GroundConfig) -> None:
        self.ground = ground
        self.lease_ns = round(ground.lease_s * _NS)
        self.operators = tuple(o.name for o in ground.operators)
        self.stations = tuple(s.name for s in ground.stations)
        roles = [frozenset(o.roles) for o in ground.operators]
        self._commands = tuple(bool(r & COMMANDING_ROLES) for r in roles)
        self._range_safety = tuple("range_safety" in r for r in roles)
        self._director = tuple("flight_director" in r for r in roles)
        approving = frozenset(ground.approving_roles)
        self._approves = tuple(bool(r & approving) for r in roles)
        self._view_station = tuple(s.may == "view" for s in ground.stations)
        whole = {r for r in ground.revoked if "#" not in r}
        ids = set(ground.revoked) - whole
        self._revoked = tuple(
            o.name in whole or f"{o.name}#{o.key_id}" in ids for o in ground.operators
        )

    # -- names ---------------------------------------------------------------
    def who(self, op: int, st: int = -1) -> str:
        """``alice@pad`` (``alice`` without a station; ``nobody``)."""
        if not 0 <= op < len(self.operators):
            return "nobody"
        return self.operators[op] + (
            f"@{self.stations[st]}" if 0 <= st < len(self.stations) else ""
        )

    def lock_text(self, s: LockView, t_ns: int) -> str:
        """Who holds the lock of state ``s`` at ``t_ns`` and for how long, in words."""
        if s.holder < 0 or t_ns > s.until_ns:
            return "nobody holds the command lock"
        left = (s.until_ns - t_ns) / _NS
        return f"{self.who(s.holder, s.station)} holds the command lock ({left:.1f} s left)"

    # -- the verdict -----------------------------------------------------------
    def verdict(
        self, s: LockView, op: int, st: int, cmd: int, t_ns: int, *, target: int = 0, ref: int = 0
    ) -> tuple[int, str] | None:
        """None when the authority lets operator ``op`` at station ``st``
        (checked indices) send command ``cmd`` on to the command checks at
        loop time ``t_ns`` in state ``s``; else ``(status, detail)``.
        ``target``: HANDOVER's operator number (1-based); ``ref``: APPROVE's
        ARM number. A lease that ran out by ``t_ns`` counts as ended, and
        with it its holder's ARM (:meth:`Authority.expire`). Changes nothing;
        allocates only a refusal's text."""
        if cmd == Command.ABORT and self._range_safety[op]:
            return None  # range safety's ABORT: any station, lock or not
        expired = s.holder >= 0 and t_ns > s.until_ns
        if cmd == Command.APPROVE:
            return self._approve(s, op, ref, t_ns, expired)
        if not self._commands[op]:
            return CommandStatus.REJECTED_VIEW_ONLY, f"{self.who(op)} may not command (roles)"
        if self._view_station[st]:
            return (
                CommandStatus.REJECTED_VIEW_ONLY,
                f"station {self.stations[st]} may only view (ground.stations)",
            )
        holder = -1 if expired else s.holder
        if cmd == Command.TAKEOVER:
            if not self._director[op]:
                return CommandStatus.REJECTED_ROLE, f"{self.who(op)} is no flight director"
            return None
        if cmd == Command.LOCK:
            if holder < 0 or holder == op:  # a holder may move to another station
                return None
            return CommandStatus.REJECTED_NOT_HOLDER, self.lock_text(s, t_ns)
        if holder != op or s.station not in (-1, st):
            return CommandStatus.REJECTED_NOT_HOLDER, self.lock_text(s, t_ns)
        if cmd == Command.HANDOVER:
            to = target - 1
            if not 0 <= to < len(self.operators):
                return CommandStatus.REJECTED_BAD_ARGUMENT, f"no operator number {target}"
            if not self._commands[to] or self._revoked[to]:
                return (
                    CommandStatus.REJECTED_ROLE,
                    f"{self.who(to)} may not hold the lock (roles, or revoked)",
                )
        return None

    def _approve(
        self, s: LockView, op: int, ref: int, t_ns: int, expired: bool
    ) -> tuple[int, str] | None:
        if not self._approves[op]:
            return CommandStatus.REJECTED_ROLE, f"{self.who(op)} has no approving role"
        arm = -1 if expired else s.arm_seq  # an ARM dies with its holder's lock
        if arm < 0 or ref != arm:
            now = f"the current ARM is #{arm}" if arm >= 0 else "no ARM is open"
            return CommandStatus.REJECTED_APPROVAL_STALE, f"approval of ARM #{ref}: {now}"
        if not 0 <= t_ns - s.arm_t_ns <= ARM_WINDOW_NS:
            return (
                CommandStatus.REJECTED_APPROVAL_STALE,
                f"ARM #{ref} is older than {ARM_WINDOW_NS // _NS} s",
            )
        if op == s.arm_operator or s.approvers >> op & 1:
            return (
                CommandStatus.REJECTED_APPROVAL_SELF,
                f"{self.who(op)} armed or approved ARM #{ref} already: a second operator must",
            )
        return None


class Authority(AuthorityRules):
    """The command lock and the two-person rule at the CN (module doc): the
    rules (:class:`AuthorityRules`) and the state (a :class:`LockView`).

    ``ground`` is the mission's section, ``vehicle`` and ``mac`` its
    ``vehicle`` and ``security.mac``, ``base`` the :data:`IDENTITY_LINK`
    key (None: the CN holds none, so every request is refused as
    ``REJECTED_OPERATOR_AUTH``, never taken unauthenticated).
    """

    def __init__(self, ground: GroundConfig, vehicle: str, mac: str, base: bytes | None) -> None:
        super().__init__(ground)
        self.mac = mac
        self._op_keys: tuple[bytes, ...] = ()
        self._st_keys: tuple[bytes, ...] = ()
        if base is not None:
            self._op_keys = tuple(
                identity_key(base, vehicle, "operator", o.name, o.key_id) for o in ground.operators
            )
            self._st_keys = tuple(
                identity_key(base, vehicle, "station", s.name, s.key_id) for s in ground.stations
            )
        self.holder = -1
        self.station = -1
        self.until_ns = 0
        self.arm_seq = -1
        """The current ARM's number (-1: none), its operator, its time and its
        approvers (a bit per operator)."""
        self.arm_operator = -1
        self.arm_t_ns = 0
        self.approvers = 0

    def holder_text(self, t_ns: int) -> str:
        """Who holds the lock and for how long, in words."""
        return self.lock_text(self, t_ns)

    # -- identity --------------------------------------------------------------
    def identify(
        self,
        op_number: int,
        st_number: int,
        body: bytes | bytearray | memoryview,
        op_tag: bytes | bytearray | memoryview,
        st_tag: bytes | bytearray | memoryview,
    ) -> tuple[int, str] | Identity:
        """The request's checked :class:`Identity`, or ``(status, detail)``
        why not: ``REJECTED_OPERATOR_UNKNOWN`` (no operator, or a number the
        mission does not list), ``REJECTED_OPERATOR_REVOKED``,
        ``REJECTED_STATION`` (an unknown station or a bad station tag),
        ``REJECTED_OPERATOR_AUTH`` (a bad operator tag: forged or altered,
        or an old key). ``op_number``/``st_number`` are the request's
        1-based fields; ``body`` the bytes the tags cover. Changes nothing;
        tags compared in constant time."""
        op, st = op_number - 1, st_number - 1
        if not 0 <= op < len(self.operators):
            return (
                CommandStatus.REJECTED_OPERATOR_UNKNOWN,
                "no operator named (ground.operators)"
                if op_number == 0
                else f"operator number {op_number} is not in ground.operators",
            )
        if self._revoked[op]:
            return CommandStatus.REJECTED_OPERATOR_REVOKED, f"operator {self.who(op)} is revoked"
        if not 0 <= st < len(self.stations):
            return CommandStatus.REJECTED_STATION, f"station number {st_number} is not listed"
        if not self._op_keys:
            return (
                CommandStatus.REJECTED_OPERATOR_AUTH,
                "this control node holds no operators key (cn.keys from `zplatform keygen`)",
            )
        if not hmac.compare_digest(request_tag(self._st_keys[st], self.mac, body), st_tag):
            return (
                CommandStatus.REJECTED_STATION,
                f"bad station tag for {self.stations[st]} (forged, or an old station key)",
            )
        if not hmac.compare_digest(request_tag(self._op_keys[op], self.mac, body), op_tag):
            return (
                CommandStatus.REJECTED_OPERATOR_AUTH,
                f"bad operator tag for {self.operators[op]} (forged, altered, or an old key)",
            )
        return Identity(op, st)

    # -- rules -------------------------------------------------------------------
    def expire(self, t_ns: int) -> Change | None:
        """End a lease that ran out by ``t_ns`` (its holder went silent), and
        with it the holder's open ARM."""
        if self.holder >= 0 and t_ns > self.until_ns:
            who = self.who(self.holder, self.station)
            self.holder, self.station, self.until_ns = -1, -1, 0
            self.disarm()  # an ARM dies with its holder's lock
            return Change("expired", f"{who}'s command lock expired (no request in its lease)")
        return None

    def check(
        self, who: Identity, cmd: int, t_ns: int, *, target: int = 0, ref: int = 0
    ) -> tuple[int, str] | None:
        """:meth:`AuthorityRules.verdict` on this CN's own state: None when the
        authority lets ``who``'s command ``cmd`` go on to the command checks
        at ``t_ns`` (after :meth:`expire`), else ``(status, detail)``.
        Changes nothing."""
        return self.verdict(self, who.operator, who.station, cmd, t_ns, target=target, ref=ref)

    def apply(
        self, who: Identity, cmd: int, t_ns: int, *, seq: int = 0, target: int = 0
    ) -> Change | None:
        """Record ``who``'s command ``cmd`` (numbered ``seq``), accepted at
        ``t_ns`` after :meth:`check` let it through: the lock moves or is
        renewed, an ARM opens, an approval is counted. Returns the change
        to announce (None: a plain renewal or nothing)."""
        op, st = who
        lease = t_ns + self.lease_ns
        if cmd == Command.APPROVE:
            self.approvers |= 1 << op
            return Change("approved", f"{self.who(op, st)} approved ARM #{self.arm_seq}")
        if cmd == Command.TAKEOVER:
            was = self.who(self.holder, self.station) if self.holder >= 0 else "nobody"
            self.holder, self.station, self.until_ns = op, st, lease
            return Change("taken_over", f"{self.who(op, st)} took the command lock over from {was}")
        if cmd == Command.ABORT and self.holder != op:
            return None  # range safety's ABORT leaves the lock as it is
        if cmd == Command.RELEASE:
            self.holder, self.station, self.until_ns = -1, -1, 0
            return Change("released", f"{self.who(op, st)} released the command lock")
        if cmd == Command.HANDOVER:
            to = target - 1
            self.holder, self.station, self.until_ns = to, -1, lease
            return Change("handed", f"{self.who(op, st)} handed the command lock to {self.who(to)}")
        granted = self.holder != op
        bound = self.station < 0
        self.holder, self.station, self.until_ns = op, st, lease
        if cmd == Command.ARM:
            self.arm(op, seq, t_ns)
        if granted:
            return Change("granted", f"{self.who(op, st)} holds the command lock")
        if bound:
            return Change("granted", f"{self.who(op, st)} took up the handed-over lock")
        return None

    # -- two-person ------------------------------------------------------------
    def arm(self, op: int, seq: int, t_ns: int) -> None:
        """An ARM numbered ``seq`` by operator ``op`` was accepted at
        ``t_ns``: it opens a new approval round (an earlier ARM's approvals
        no longer count)."""
        self.arm_seq, self.arm_operator, self.arm_t_ns = seq, op, t_ns
        self.approvers = 0

    def approved(self) -> bool:
        """Whether the current ARM has a second operator's approval."""
        return self.approvers != 0

    def approvals(self) -> int:
        """How many operators approved the current ARM."""
        return self.approvers.bit_count()

    def disarm(self) -> None:
        """The current ARM is used up (its command came, accepted or not)."""
        self.arm_seq, self.arm_operator = -1, -1
        self.approvers = 0

    def adopt(self, s: LockView) -> None:
        """Take up the state ``s`` (:func:`read_lock_state` of the vector a
        standby mirrored, or of the frame a restarted CN's flight recorder
        kept): the lock, and an ARM open for approvals with its approvals, so
        the approvals already given count at the new commander. Values out
        of range (a vector from another mission cannot pass the layout check;
        still) are taken as none."""
        n = len(self.operators)
        self.holder = s.holder if 0 <= s.holder < n else -1
        ok_st = self.holder >= 0 and 0 <= s.station < len(self.stations)
        self.station = s.station if ok_st else -1
        self.until_ns = s.until_ns if self.holder >= 0 else 0
        if s.arm_seq >= 0 and 0 <= s.arm_operator < n:
            self.arm_seq, self.arm_operator, self.arm_t_ns = s.arm_seq, s.arm_operator, s.arm_t_ns
            self.approvers = s.approvers & ((1 << n) - 1)
        else:
            self.disarm()
