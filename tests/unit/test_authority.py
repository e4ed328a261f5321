"""Tests of zplatform.control.authority through the CN's command handler:
operator and station identity, the command lock (request, release, hand
over, takeover, lease expiry), range safety's ABORT, viewers, revocation,
the two-person rule; each refusal's own status, counted, evented at most
once a second; the ``ground:`` section's config rules; key derivation."""

from __future__ import annotations

import textwrap

import pytest

from tests.drive import step_request
from tests.keys import AUTH_VEHICLE
from zplatform import DataVector, Layout, decode_mission
from zplatform.config import Mission
from zplatform.control.authority import Signer, identity_key
from zplatform.control.commands import CommandHandler
from zplatform.control.statemachine import StateMachine
from zplatform.control.uplink import Uplink, operator_number, validate_words
from zplatform.core.events import EventLog
from zplatform.errors import CommandError, ConfigError

S = 1_000_000_000
PERIOD = 10_000_000
BASE_KEY = bytes(range(7, 39))

MISSION = (
    "mission: authtest\n"
    + AUTH_VEHICLE
    + """\
state_machine:
  initial: A
  states:
    A:
      transitions:
        - {element: cn_cmd, op: "==", value: LAUNCH, to: B}
    B: {}
commands:
  hazardous: [LAUNCH]
  writable: [x]
"""
)

GROUND = """
ground:
  lease_s: 5
  stations:
    - {name: pad}
    - {name: room}
    - {name: lounge, may: view}
  operators:
    - {name: fd, roles: [flight_director]}
    - {name: alice, roles: [operator]}
    - {name: bob, roles: [operator]}
    - {name: rso, roles: [range_safety]}
    - {name: vic, roles: [viewer]}
    - {name: mallory, roles: [operator]}
  two_person: [LAUNCH]
  revoked: [mallory]
"""


def mission(ground: str = GROUND, base: str = MISSION) -> Mission:
    return decode_mission(base + textwrap.dedent(ground))


def signer(m: Mission, op: str, st: str, key: bytes = BASE_KEY) -> Signer:
    g = m.ground
    assert g is not None
    kid = {o.name: o.key_id for o in g.operators}[op]
    sid = {s.name: s.key_id for s in g.stations}[st]
    return Signer(
        op,
        identity_key(key, m.vehicle, "operator", op, kid),
        st,
        identity_key(key, m.vehicle, "station", st, sid),
    )


class Rig:
    """The CN's Data Vector, command handler and state machine; requests
    framed by a ground's :class:`Uplink` (as each station signs them) and
    applied as the CN's loop applies them (admit, then step)."""

    def __init__(self, m: Mission | None = None, key: bytes | None = BASE_KEY) -> None:
        self.m = m = m if m is not None else mission()
        self.dv = DataVector(Layout.for_node(m, "cn"))
        self.events = EventLog("cn")
        self.sm = StateMachine(m, self.dv, self.events)
        self.ch = CommandHandler(m, self.dv, self.events, self.sm, operators_key=key)
        self.t = 100 * S
        self._ups: dict[tuple[str, str], Uplink] = {}
        self.log: list[str] = []
        self.texts: list[str] = []

    def uplink(self, op: str, st: str) -> Uplink:
        if (op, st) not in self._ups:
            self._ups[(op, st)] = Uplink(self.m, signer=signer(self.m, op, st))
        return self._ups[(op, st)]

    def send(
        self,
        who: str,
        command: str,
        element: int = 0,
        ref: int = 0,
        seq: int | None = None,
        up: Uplink | None = None,
    ) -> str:
        """One loop with ``who`` (``op@station``) sending ``command`` numbered
        ``seq`` (None: as a ground numbers, above every number the CN showed,
        refused ones too: the live CN's intake admits each number once); its
        verdict."""
        op, st = who.split("@")
        up = up if up is not None else self.uplink(op, st)
        if seq is None:
            seq = max(self.ch.last_seq, int(self.dv.get("cn_cmd_reject_seq"))) + 1
        up.frame(command, seq, element, 0.0, self.t, 0, ref=ref)
        self.dv.region_view("gn_to_cn")[:] = up.req.region_view("gn_to_cn")
        return self.loop(new=True)

    def loop(self, new: bool = False, dt: int = PERIOD) -> str:
        rejects = self.dv.get("cn_cmd_rejects")
        step_request(self.ch, self.dv, new, self.t)
        self.sm.step(self.t)
        self.t += dt
        for e in self.events.drain():
            self.log.append(e.id)
            self.texts.append(e.text)
        if self.dv.get("cn_cmd_rejects") != rejects:
            return self.dv.get_name("cn_cmd_reject_status")
        return self.dv.get_name("cn_cmd_status")

    def wait(self, seconds: float) -> None:
        self.loop(dt=round(seconds * S))

    @property
    def holder(self) -> str:
        return f"{self.dv.get_name('cn_lock_holder')}@{self.dv.get_name('cn_lock_station')}"


# ------------------------------------------------------------------ the lock


def test_nobody_holds_the_lock_at_first_and_a_command_names_that() -> None:
    r = Rig()
    assert r.holder == "NONE@NONE"
    assert r.send("alice@pad", "NOOP") == "REJECTED_NOT_HOLDER"
    assert r.dv.get("cn_auth_refused") == 1
    assert r.dv.get("cn_cmd_seq") == 0  # refused without consuming a number


def test_lock_then_command_then_release() -> None:
    r = Rig()
    assert r.send("alice@pad", "LOCK") == "ACCEPTED"
    assert r.holder == "alice@pad"
    assert r.dv.get("cn_lock_until_ns") == r.t - PERIOD + 5 * S
    assert r.dv.get_name("cn_cmd_operator") == "alice"
    assert r.send("alice@pad", "NOOP") == "ACCEPTED"
    assert r.send("bob@room", "NOOP") == "REJECTED_NOT_HOLDER"
    assert r.send("bob@room", "LOCK") == "REJECTED_NOT_HOLDER"
    assert r.send("alice@pad", "RELEASE") == "ACCEPTED"
    assert r.holder == "NONE@NONE"
    assert r.send("bob@room", "LOCK") == "ACCEPTED"
    assert r.holder == "bob@room"


def test_the_refusal_names_the_holder() -> None:
    r = Rig()
    r.send("alice@pad", "LOCK")
    r.texts.clear()
    r.send("bob@room", "NOOP")
    assert len(r.texts) == 1
    assert "REJECTED_NOT_HOLDER" in r.texts[0]
    assert "bob@room" in r.texts[0] and "alice@pad holds the command lock" in r.texts[0]


def test_the_holder_at_another_station_is_not_the_holder() -> None:
    r = Rig()
    r.send("alice@pad", "LOCK")
    assert r.send("alice@room", "NOOP") == "REJECTED_NOT_HOLDER"
    assert r.send("alice@room", "LOCK") == "ACCEPTED"  # moves her own lock
    assert r.holder == "alice@room"


def test_handover_binds_the_new_holders_station_at_their_first_request() -> None:
    r = Rig()
    r.send("alice@pad", "LOCK")
    to = operator_number(r.m, "bob")
    assert r.send("alice@pad", "HANDOVER", element=to) == "ACCEPTED"
    assert r.holder == "bob@NONE"
    assert r.send("alice@pad", "NOOP") == "REJECTED_NOT_HOLDER"
    assert r.send("bob@room", "NOOP") == "ACCEPTED"
    assert r.holder == "bob@room"
    assert "cmd_lock" in r.log


def test_handover_to_a_viewer_or_a_revoked_operator_is_refused() -> None:
    r = Rig()
    r.send("alice@pad", "LOCK")
    assert r.send("alice@pad", "HANDOVER", element=operator_number(r.m, "vic")) == "REJECTED_ROLE"
    assert (
        r.send("alice@pad", "HANDOVER", element=operator_number(r.m, "mallory")) == "REJECTED_ROLE"
    )
    assert r.send("alice@pad", "HANDOVER", element=99) == "REJECTED_BAD_ARGUMENT"
    assert r.holder == "alice@pad"


def test_a_flight_director_takes_the_lock_over_with_an_event() -> None:
    r = Rig()
    r.send("alice@pad", "LOCK")
    assert r.send("bob@room", "TAKEOVER") == "REJECTED_ROLE"
    r.log.clear()
    assert r.send("fd@room", "TAKEOVER") == "ACCEPTED"
    assert r.holder == "fd@room"
    assert "cmd_lock" in r.log
    assert r.send("alice@pad", "NOOP") == "REJECTED_NOT_HOLDER"


def test_the_lease_runs_out_when_the_holders_station_goes_silent() -> None:
    r = Rig()
    r.send("alice@pad", "LOCK")
    r.wait(4.9)
    assert r.send("alice@pad", "NOOP") == "ACCEPTED"  # renews
    r.wait(4.9)
    assert r.holder == "alice@pad"
    r.log.clear()
    r.wait(0.2)
    r.loop()
    assert r.holder == "NONE@NONE"
    assert r.dv.get("cn_lock_until_ns") == 0
    assert r.log.count("cmd_lock") == 1
    assert r.send("bob@room", "LOCK") == "ACCEPTED"


# ------------------------------------------------------------------ who may


def test_range_safety_aborts_from_any_station_lock_or_not() -> None:
    r = Rig()
    r.send("alice@pad", "LOCK")
    assert r.send("rso@lounge", "ABORT") == "ACCEPTED"
    assert r.holder == "alice@pad"  # the lock stays where it was
    assert r.send("rso@lounge", "NOOP") == "REJECTED_VIEW_ONLY"  # only ABORT
    assert r.send("alice@lounge", "ABORT") == "REJECTED_VIEW_ONLY"  # not range safety


def test_a_viewer_never_commands() -> None:
    r = Rig()
    for cmd in ("LOCK", "NOOP", "ABORT", "TAKEOVER"):
        assert r.send("vic@pad", cmd) == "REJECTED_VIEW_ONLY"
    assert r.send("alice@lounge", "LOCK") == "REJECTED_VIEW_ONLY"
    assert r.dv.get("cn_auth_refused") == 5


def test_unknown_revoked_and_forged_operators_each_have_their_status() -> None:
    r = Rig()
    assert r.send("mallory@pad", "LOCK") == "REJECTED_OPERATOR_REVOKED"
    # A request naming nobody (a ground without operator keys).
    plain = Uplink(r.m)
    assert r.send("x@y", "LOCK", up=plain) == "REJECTED_OPERATOR_UNKNOWN"
    # Alice's name, Bob's key: a forged operator field.
    bob = signer(r.m, "bob", "pad")
    forged = Signer("alice", bob.operator_key, "pad", bob.station_key)
    assert r.send("x@y", "LOCK", up=Uplink(r.m, signer=forged)) == "REJECTED_OPERATOR_AUTH"
    # A right operator key with a wrong station key.
    bad_st = Signer("alice", signer(r.m, "alice", "pad").operator_key, "pad", bytes(32))
    assert r.send("x@y", "LOCK", up=Uplink(r.m, signer=bad_st)) == "REJECTED_STATION"
    assert r.holder == "NONE@NONE"
    assert r.dv.get("cn_auth_refused") == 4
    assert r.dv.get("cn_cmd_seq") == 0


def test_an_altered_request_fails_its_operator_tag() -> None:
    r = Rig()
    up = r.uplink("alice", "pad")
    up.frame("LOCK", 1, 0, 0.0, r.t, 0)
    region = r.dv.region_view("gn_to_cn")
    region[:] = up.req.region_view("gn_to_cn")
    r.dv.set("gn_cmd", 2)  # LAUNCH instead of LOCK, tags unchanged
    assert r.loop(new=True) == "REJECTED_STATION"  # the first tag checked fails


def test_revoking_one_key_id_keeps_the_operators_new_key() -> None:
    ground = GROUND.replace(
        "{name: bob, roles: [operator]}", "{name: bob, roles: [operator], key_id: 2}"
    )
    ground = ground.replace("revoked: [mallory]", 'revoked: [mallory, "bob#1"]')
    m = mission(ground)
    r = Rig(m)
    old_key = identity_key(BASE_KEY, m.vehicle, "operator", "bob", 1)
    old = Signer("bob", old_key, "pad", signer(m, "bob", "pad").station_key)
    assert r.send("x@y", "LOCK", up=Uplink(m, signer=old)) == "REJECTED_OPERATOR_AUTH"
    assert r.send("bob@pad", "LOCK") == "ACCEPTED"


def test_a_cn_without_the_operators_key_refuses_every_operator() -> None:
    r = Rig(key=None)
    assert r.send("alice@pad", "LOCK") == "REJECTED_OPERATOR_AUTH"


def test_authority_refusals_are_evented_at_most_once_a_second() -> None:
    r = Rig()
    for _ in range(150):  # 1.5 s of a viewer's requests, one a loop
        assert r.send("vic@lounge", "NOOP") == "REJECTED_VIEW_ONLY"
    assert r.dv.get("cn_auth_refused") == 150
    assert r.dv.get("cn_cmd_rejects") == 150
    assert r.log.count("cmd_rejected") == 2


# ------------------------------------------------------------------ two-person


def launch_with(r: Rig, approvals: list[str], holder: str = "alice@pad") -> str:
    r.send(holder, "LOCK")
    assert r.send(holder, "ARM") == "ACCEPTED"
    arm = r.ch.last_seq
    for who in approvals:
        r.send(who, "APPROVE", ref=arm)
    return r.send(holder, "LAUNCH")


def test_two_person_launch_is_refused_with_one_approval_and_accepted_with_two() -> None:
    r = Rig()
    assert launch_with(r, []) == "REJECTED_NOT_APPROVED"
    assert r.dv.get_name("cn_state") == "A"
    r2 = Rig()
    assert launch_with(r2, ["fd@room"]) == "ACCEPTED"
    assert r2.dv.get_name("cn_state") == "B"
    assert r2.dv.get("cn_arm_approvals") == 0  # used up


def test_the_approver_may_sit_at_a_view_station() -> None:
    r = Rig()
    assert launch_with(r, ["rso@lounge"]) == "ACCEPTED"


def test_same_operator_twice_is_refused() -> None:
    r = Rig()
    r.send("alice@pad", "LOCK")
    r.send("alice@pad", "ARM")
    arm = r.ch.last_seq
    assert r.send("alice@pad", "APPROVE", ref=arm) == "REJECTED_ROLE"  # operators do not approve
    assert r.send("fd@room", "APPROVE", ref=arm) == "ACCEPTED"
    assert r.dv.get("cn_arm_approvals") == 1
    assert r.send("fd@pad", "APPROVE", ref=arm) == "REJECTED_APPROVAL_SELF"


def test_a_refused_request_between_an_arm_and_its_command_breaks_no_chain() -> None:
    """Another station's request refused by the authority between the ARM
    and its approval: the CN's intake admitted its number, so the ground
    numbers above it; the chain goes on through it (numbers n, n+1 refused,
    APPROVE n+2, LAUNCH n+3). A gap no refusal explains still breaks it."""
    r = Rig()
    r.send("alice@pad", "LOCK")
    assert r.send("alice@pad", "ARM") == "ACCEPTED"
    arm = r.ch.last_seq
    assert r.send("bob@room", "NOOP") == "REJECTED_NOT_HOLDER"
    assert r.dv.get("cn_cmd_reject_seq") == arm + 1
    assert r.send("alice@room", "APPROVE", ref=arm) == "REJECTED_ROLE"  # alice: no approver
    assert r.send("fd@room", "APPROVE", ref=arm) == "ACCEPTED"
    assert r.ch.last_seq == arm + 3
    assert r.send("alice@pad", "LAUNCH") == "ACCEPTED"
    assert r.dv.get_name("cn_state") == "B"
    # A refusal opens no chain without an ARM, and a number skipped for no
    # reason the CN saw still leaves the command unarmed.
    r2 = Rig()
    r2.send("alice@pad", "LOCK")
    assert r2.send("bob@room", "NOOP") == "REJECTED_NOT_HOLDER"
    assert r2.send("alice@pad", "LAUNCH") == "REJECTED_NOT_ARMED"
    r2.send("alice@pad", "ARM")
    r2.send("fd@room", "APPROVE", ref=r2.ch.last_seq)
    assert r2.send("alice@pad", "LAUNCH", seq=r2.ch.last_seq + 2) == "REJECTED_NOT_ARMED"


def test_the_arming_director_cannot_approve_their_own_arm() -> None:
    r = Rig()
    r.send("fd@pad", "LOCK")
    r.send("fd@pad", "ARM")
    assert r.send("fd@room", "APPROVE", ref=r.ch.last_seq) == "REJECTED_APPROVAL_SELF"
    assert r.send("fd@pad", "LAUNCH") == "REJECTED_NOT_APPROVED"


def test_an_approval_of_an_earlier_arm_is_refused() -> None:
    r = Rig()
    r.send("alice@pad", "LOCK")
    r.send("alice@pad", "ARM")
    first = r.ch.last_seq
    r.send("alice@pad", "NOOP")
    r.send("alice@pad", "ARM")
    assert r.send("fd@room", "APPROVE", ref=first) == "REJECTED_APPROVAL_STALE"
    assert r.send("alice@pad", "LAUNCH") == "REJECTED_NOT_APPROVED"


def test_an_approval_after_the_arm_window_is_refused() -> None:
    r = Rig()
    r.send("alice@pad", "LOCK")
    r.send("alice@pad", "ARM")
    arm = r.ch.last_seq
    r.send("alice@pad", "LOCK")  # keep the lease
    r.wait(4)
    r.send("alice@pad", "LOCK")
    r.wait(4)
    r.send("alice@pad", "LOCK")
    r.wait(3)
    assert r.send("fd@room", "APPROVE", ref=arm) == "REJECTED_APPROVAL_STALE"


def test_an_arm_by_another_holder_does_not_confirm() -> None:
    """A lock handed over between ARM and command: the new holder cannot
    fire the old holder's ARM."""
    r = Rig(mission(GROUND.replace("two_person: [LAUNCH]", "two_person: []")))
    r.send("alice@pad", "LOCK")
    r.send("alice@pad", "ARM")
    r.send("alice@pad", "HANDOVER", element=operator_number(r.m, "bob"))
    assert r.send("bob@room", "LAUNCH") == "REJECTED_NOT_ARMED"


# ------------------------------------------------------------------ modes


def test_single_operator_keeps_todays_behaviour() -> None:
    m = mission(GROUND + "  single_operator: true\n")
    r = Rig(m)
    plain = Uplink(m)
    assert r.send("x@y", "NOOP", up=plain) == "ACCEPTED"
    assert r.send("x@y", "LOCK", up=plain) == "REJECTED_NOT_ALLOWED"
    assert r.send("x@y", "ARM", up=plain) == "ACCEPTED"
    assert r.send("x@y", "LAUNCH", up=plain) == "ACCEPTED"
    assert r.dv.get("cn_auth_refused") == 0


def test_a_mission_without_ground_has_no_authority_elements() -> None:
    m = decode_mission(MISSION)
    lay = Layout.for_node(m, "cn")
    assert "cn_lock_holder" not in lay.elements and "gn_cmd_operator" not in lay.elements
    dv = DataVector(lay)
    ch = CommandHandler(m, dv, EventLog("cn"), StateMachine(m, dv, EventLog("cn")))
    assert ch.authority is None


# ------------------------------------------------------------------ config


@pytest.mark.parametrize(
    ("ground", "path", "message"),
    [
        ("two_person: [NOOP]", "$.ground.two_person[0]", "not hazardous"),
        ("two_person: [x]", "$.ground.two_person[0]", "neither a hazardous command"),
        ("revoked: [eve]", "$.ground.revoked[0]", "not an operator"),
        ('revoked: ["alice#0"]', "$.ground.revoked[0]", "NAME#KEY_ID"),
    ],
)
def test_ground_rules(ground: str, path: str, message: str) -> None:
    text = GROUND.replace("two_person: [LAUNCH]", "").replace("revoked: [mallory]", ground)
    with pytest.raises(ConfigError) as e:
        mission(text)
    assert e.value.path == path
    assert message in str(e.value)


OPS = "operators: [{name: a, roles: [operator]}]}"


@pytest.mark.parametrize(
    ("ground", "path", "message"),
    [
        (
            "ground: {stations: [{name: pad}], operators: [{name: a, roles: [operator]}], x: 1}",
            "$.ground",
            "x",
        ),
        (
            "ground: {stations: [{name: pad, may: fly}], " + OPS,
            "$.ground.stations[0].may",
            "",
        ),
        (
            "ground: {stations: [{name: pad}], operators: [{name: a, roles: [pilot]}]}",
            "$.ground.operators[0].roles[0]",
            "",
        ),
        (
            "ground: {stations: [{name: pad}, {name: pad}], " + OPS,
            "$.ground.stations[1].name",
            "duplicate",
        ),
        (
            "ground: {stations: [{name: Pad}], " + OPS,
            "$.ground.stations[0].name",
            "must match",
        ),
        (
            "ground: {stations: [{name: pad, may: view}], " + OPS,
            "$.ground.stations",
            "no station may command",
        ),
        (
            "ground: {stations: [{name: pad}], operators: [{name: a, roles: [viewer, operator]}]}",
            "$.ground.operators[0].roles",
            "viewer",
        ),
        (
            "ground: {stations: [{name: pad}], operators: [{name: a, roles: [viewer]}]}",
            "$.ground",
            "no operator may command",
        ),
    ],
)
def test_ground_section_errors_name_their_yaml_path(ground: str, path: str, message: str) -> None:
    with pytest.raises(ConfigError) as e:
        decode_mission(MISSION + ground + "\n")
    assert e.value.path.startswith(path)
    assert message in str(e.value)


def test_range_safetys_abort_cannot_be_hazardous() -> None:
    with pytest.raises(ConfigError) as e:
        mission(base=MISSION.replace("hazardous: [LAUNCH]", "hazardous: [LAUNCH, ABORT]"))
    assert e.value.path == "$.commands.hazardous" and "range safety" in str(e.value)


def test_ground_needs_the_ground_node_and_auth() -> None:
    g = "ground: {stations: [{name: pad}], operators: [{name: a, roles: [operator]}]}\n"
    with pytest.raises(ConfigError) as e:
        decode_mission(MISSION.replace(", gn: {}", "") + g)
    assert e.value.path == "$.ground"
    with pytest.raises(ConfigError) as e:
        decode_mission(MISSION + "security: {auth: false}\n" + g)
    assert "security.auth" in str(e.value)


def test_identity_keys_differ_per_name_kind_and_key_id() -> None:
    keys = {
        identity_key(BASE_KEY, "rocket", k, n, i)
        for k in ("operator", "station")
        for n in ("a", "b")
        for i in (1, 2)
    }
    assert len(keys) == 8


def test_the_ground_checks_lock_commands_before_sending() -> None:
    m = mission()
    assert validate_words(m, "handover", ["bob"]) == ("HANDOVER", 3, 0.0)
    assert validate_words(m, "approve", ["17"]) == ("APPROVE", 0, 17.0)
    assert validate_words(m, "lock", []) == ("LOCK", 0, 0.0)
    for cmd, args, match in (
        ("handover", ["eve"], "no operator named 'eve'"),
        ("handover", [], "needs OPERATOR"),
        ("approve", ["x"], "ARM's number"),
        ("takeover", ["fd"], "no arguments"),
    ):
        with pytest.raises(CommandError, match=match):
            validate_words(m, cmd, args)
    with pytest.raises(CommandError, match="no command lock"):
        validate_words(decode_mission(MISSION), "lock", [])


def test_a_standby_takes_the_lock_over_from_the_mirrored_vector() -> None:
    """A takeover (CommandHandler.adopt): the lock and the ARM open for
    approvals, with its approvals, are in the Data Vector, so the new
    commander keeps its holder, lease, ARM and approvals."""
    r = Rig()
    r.send("alice@pad", "LOCK")
    r.send("alice@pad", "ARM")
    r.send("fd@room", "APPROVE", ref=r.ch.last_seq)
    b = Rig()
    b.dv.write_all(r.dv.view())
    b.t = r.t
    b.ch.adopt()
    auth = b.ch.authority
    assert auth is not None and (auth.holder, auth.station) == (1, 0)
    assert auth.until_ns == r.dv.get("cn_lock_until_ns") and auth.approved()
    a = r.ch.authority
    assert a is not None
    assert (auth.arm_seq, auth.arm_operator, auth.arm_t_ns, auth.approvers) == (
        a.arm_seq,
        a.arm_operator,
        a.arm_t_ns,
        a.approvers,
    )
    assert b.send("fd@pad", "APPROVE", ref=a.arm_seq) == "REJECTED_APPROVAL_SELF"
    assert b.send("bob@room", "NOOP") == "REJECTED_NOT_HOLDER"
    assert b.send("alice@pad", "NOOP") == "ACCEPTED"


# ------------------------------------------- when the CN last heard a station


def test_the_cn_stamps_when_it_last_heard_each_station_by_verified_tags_only() -> None:
    """cn_heard_<station>_ns: the loop time of the last request whose
    operator and station tags verified, accepted or refused by the
    authority; a request whose tags fail stamps nothing."""
    r = Rig()
    assert [r.dv.get(f"cn_heard_{s}_ns") for s in ("pad", "room", "lounge")] == [0, 0, 0]
    t_lock = r.t
    assert r.send("alice@pad", "LOCK") == "ACCEPTED"
    assert r.dv.get("cn_heard_pad_ns") == t_lock
    t_refused = r.t
    assert r.send("bob@room", "NOOP") == "REJECTED_NOT_HOLDER"  # authority-refused
    assert r.dv.get("cn_heard_room_ns") == t_refused
    assert r.dv.get("cn_heard_pad_ns") == t_lock
    # A forged operator tag and a bad station tag "from" the lounge: not heard.
    bob = signer(r.m, "bob", "lounge")
    forged = Signer("alice", bob.operator_key, "lounge", bob.station_key)
    assert r.send("x@y", "NOOP", up=Uplink(r.m, signer=forged)) == "REJECTED_OPERATOR_AUTH"
    bad_st = Signer("alice", signer(r.m, "alice", "lounge").operator_key, "lounge", bytes(32))
    assert r.send("x@y", "NOOP", up=Uplink(r.m, signer=bad_st)) == "REJECTED_STATION"
    assert r.dv.get("cn_heard_lounge_ns") == 0
    # A lease renewal (the holder's LOCK again) is heard too.
    r.wait(2.0)
    t_renew = r.t
    assert r.send("alice@pad", "LOCK") == "ACCEPTED"
    assert r.dv.get("cn_heard_pad_ns") == t_renew
    assert r.dv.get("cn_heard_room_ns") == t_refused


def test_a_mission_without_authority_has_no_heard_elements() -> None:
    single = mission(GROUND.replace("  lease_s: 5\n", "  lease_s: 5\n  single_operator: true\n"))
    names = Layout.for_node(single, "cn").elements
    assert not [n for n in names if n.startswith("cn_heard_")]
    assert "cn_heard_pad_ns" in Layout.for_node(mission(), "cn").elements
