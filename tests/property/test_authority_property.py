"""Hypothesis over interleavings of lock requests, releases, handovers,
takeovers, approvals, commands and waits (lease expiries) from every
operator at every station (zplatform.control.authority through the CN's
command handler), against a model of the lock kept from the verdicts:
never two holders (a lock is taken from a holder only by a flight
director's takeover), only the holder's commands are accepted, never an
unapproved two-person command, range safety's ABORT always accepted,
viewers and revoked operators never, and telemetry shows the model's holder."""

from __future__ import annotations

from dataclasses import dataclass, field

from hypothesis import given, settings
from hypothesis import strategies as st

from tests.unit.test_authority import Rig, mission
from zplatform.config.codes import Command, CommandStatus
from zplatform.console import ConsoleModel
from zplatform.control.authority import Identity, LockState
from zplatform.control.commands import ARM_WINDOW_NS

S = 1_000_000_000
M = mission()
OPS = ["fd", "alice", "bob", "rso", "vic", "mallory"]
STATIONS = ["pad", "room", "lounge"]
LEASE_NS = 5 * S
CMDS = ["LOCK", "RELEASE", "HANDOVER", "TAKEOVER", "ARM", "LAUNCH", "APPROVE", "ABORT", "NOOP"]
VEHICLE = {"ARM", "LAUNCH", "ABORT", "NOOP"}
APPROVERS = {"fd", "rso"}

# Weighted by repetition: the holders' and approvers' requests come often
# (so locks, ARMs, approvals and launches are accepted in most examples),
# viewers, revoked operators and wrong stations sometimes.
WHO = [
    *["HOLDER"] * 6,
    *["fd@room"] * 3,
    "fd@pad",
    *["alice@pad"] * 3,
    "alice@room",
    "bob@room",
    *["rso@lounge"] * 2,
    "rso@pad",
    "vic@lounge",
    "mallory@pad",
    "alice@lounge",
]
WHAT = [
    *["LOCK"] * 2,
    "RELEASE",
    "HANDOVER",
    "TAKEOVER",
    *["ARM"] * 3,
    *["LAUNCH"] * 3,
    *["APPROVE"] * 3,
    "ABORT",
    "NOOP",
]
send = st.tuples(
    st.just("send"),
    st.sampled_from(WHO),
    st.sampled_from(WHAT),
    st.integers(0, 7),  # HANDOVER's operator number
    st.sampled_from(["current", "current", "current", "earlier", "junk"]),  # APPROVE's ARM
)
round_ = st.tuples(
    st.just("round"), st.sampled_from(WHO[6:]), st.sampled_from(["current", "earlier", "junk"])
)
wait = st.tuples(st.just("wait"), st.sampled_from([0.5, 2.0, 4.0, 6.0, 11.0]))


@dataclass
class Model:
    holder: str | None = None
    until: int = 0
    arms: list[tuple[int, str, int]] = field(default_factory=list)
    """Accepted ARMs: (number, operator, time)."""
    approvals: dict[int, set[str]] = field(default_factory=dict)
    chain: int = -1
    """The number a hazardous command must follow (the ARM's or its last approval's)."""


@settings(max_examples=300)
@given(st.data())
def test_interleavings_keep_every_authority_rule(data: st.DataObject) -> None:
    r = Rig(M)
    m = Model()
    for _ in range(data.draw(st.integers(5, 60), label="steps")):
        a = data.draw(st.one_of(send, send, send, send, wait, round_))
        if a[0] == "wait":
            r.wait(a[1])
        elif a[0] == "round":  # the two-person round, its approver drawn from everyone
            _, approver, which = a
            step(r, m, "HOLDER", "ARM", 0, which)
            step(r, m, approver, "APPROVE", 0, which)
            step(r, m, "HOLDER", "LAUNCH", 0, which)
        else:
            step(r, m, *a[1:])


def step(r: Rig, m: Model, who: str, cmd: str, target: int, which: str) -> None:
    """One request, its verdict checked against the model, the model updated."""
    if who == "HOLDER":  # the holder's next request (often a valid one)
        st_name = r.dv.get_name("cn_lock_station")
        who = (
            f"{m.holder}@{st_name if st_name != 'NONE' else 'room'}"
            if m.holder is not None
            else "alice@pad"
        )
    op, stn = who.split("@")
    if m.holder is not None and r.t > m.until:
        m.holder = None  # the lease ran out before this loop
    ref = 0
    if cmd == "APPROVE":
        ref = {
            "current": m.arms[-1][0] if m.arms else 0,
            "earlier": m.arms[-2][0] if len(m.arms) > 1 else 1,
            "junk": 99_999,
        }[which]
    t = r.t
    seq = max(r.ch.last_seq, int(r.dv.get("cn_cmd_reject_seq"))) + 1  # as a ground numbers
    verdict = r.send(f"{op}@{stn}", cmd, element=target, ref=ref, seq=seq)
    consumed = r.ch.last_seq == seq
    ok = verdict == "ACCEPTED"
    holder_before = m.holder
    if op in ("vic", "mallory"):
        assert not ok
    if stn == "lounge" and ok:
        assert (op, cmd) in {("rso", "ABORT")} or cmd == "APPROVE"
    if op == "rso" and cmd == "ABORT":
        assert ok, "range safety's ABORT is always accepted"
    if ok and cmd == "LOCK":
        assert holder_before in (None, op), "a lock taken from its holder"
        m.holder, m.until = op, t + LEASE_NS
    elif ok and cmd == "TAKEOVER":
        assert op == "fd"
        m.holder, m.until = op, t + LEASE_NS
    elif ok and cmd == "RELEASE":
        assert holder_before == op
        m.holder = None
    elif ok and cmd == "HANDOVER":
        assert holder_before == op
        m.holder, m.until = OPS[target - 1], t + LEASE_NS
    elif ok and cmd == "APPROVE":
        assert op in APPROVERS and m.arms and ref == m.arms[-1][0]
        assert op != m.arms[-1][1] and op not in m.approvals[ref]
        assert t - m.arms[-1][2] <= ARM_WINDOW_NS
        m.approvals[ref].add(op)
        if m.chain == seq - 1:
            m.chain = seq
    elif ok and cmd in VEHICLE and not (op == "rso" and cmd == "ABORT" and holder_before != op):
        assert holder_before == op, f"{op}'s {cmd} accepted while {holder_before} holds"
        m.until = t + LEASE_NS
    if ok and cmd == "LAUNCH":
        arm_seq, arm_op, arm_t = m.arms[-1]
        assert arm_op == op and m.chain == seq - 1 and t - arm_t <= ARM_WINDOW_NS
        assert m.approvals[arm_seq] - {op}, "an unapproved two-person LAUNCH"
    if ok and cmd == "ARM":
        m.arms.append((seq, op, t))
        m.approvals[seq] = set()
        m.chain = seq
    elif consumed and cmd != "APPROVE" and not (ok and cmd == "ARM"):
        m.chain = -1
    if cmd == "LAUNCH" and consumed:
        m.chain = -1
    if not consumed and m.chain >= 0 and seq == m.chain + 1:
        m.chain = seq  # refused without a verdict: its number is spent, the chain goes on
    assert r.dv.get_name("cn_lock_holder") == (m.holder or "NONE")


@settings(max_examples=300)
@given(st.lists(st.binary(min_size=0, max_size=120), min_size=1, max_size=20))
def test_any_request_bytes_get_a_verdict_and_never_raise(frames: list[bytes]) -> None:
    """Whatever a key holder puts in a request's fields (operator, station,
    reference, tags), the authority refuses or judges it: never an exception,
    never an accepted request without an operator's valid tag."""
    r = Rig(M)
    region = r.dv.region_view("gn_to_cn")
    n = len(region)
    for f in frames:
        data = (f * (n // max(len(f), 1) + 1))[:n] if f else bytes(n)
        region[:] = data
        r.dv.set("gn_cmd_epoch", r.dv.get("cn_epoch"))
        r.dv.set("gn_cmd_seq", r.ch.last_seq + 1)
        assert r.loop(new=True) != "ACCEPTED"
        assert r.dv.get_name("cn_lock_holder") == "NONE"


def _state(draw: st.DrawFn, t: int) -> LockState:
    """A state the CN can publish: no station without a holder, no ARM's
    operator, time or approvers without an ARM."""
    n_ops, n_st = len(OPS), len(STATIONS)
    near = st.integers(t - 12 * S, t + 12 * S)
    holder = draw(st.integers(-1, n_ops - 1))
    station = draw(st.integers(-1, n_st - 1)) if holder >= 0 else -1
    until = draw(near) if holder >= 0 else 0
    arm = draw(st.sampled_from([-1, 1, 5, 6, 40]))
    if arm < 0:
        return LockState(holder, station, until)
    return LockState(
        holder,
        station,
        until,
        arm,
        draw(st.integers(0, n_ops - 1)),
        draw(near),
        draw(st.integers(0, (1 << n_ops) - 1)),
    )


@settings(max_examples=400)
@given(st.data())
def test_the_console_and_the_cn_give_the_same_verdict(data: st.DataObject) -> None:
    """Any published state, any request: the console's refusal (from the
    snapshot) is the CN's (its authority after the loop's expiry), word for
    word; the state the console reads is the one the CN adopts from the
    same vector (a standby's takeover)."""
    r = Rig(M)
    t = r.t
    s = _state(data.draw, t)
    dv = r.dv
    dv.set("cn_time_ns", t)
    dv.set("cn_lock_holder", s.holder + 1)
    dv.set("cn_lock_station", s.station + 1)
    dv.set("cn_lock_until_ns", s.until_ns)
    dv.set("cn_arm_open", max(s.arm_seq, 0))
    dv.set("cn_arm_operator", s.arm_operator + 1)
    dv.set("cn_arm_open_ns", s.arm_t_ns)
    dv.set("cn_arm_approvers", s.approvers)
    r.ch.adopt()
    auth = r.ch.authority
    assert auth is not None
    got = (auth.holder, auth.station, auth.until_ns, auth.arm_seq, auth.arm_operator)
    assert got == (s.holder, s.station, s.until_ns, s.arm_seq, s.arm_operator)
    assert (auth.arm_t_ns, auth.approvers) == (s.arm_t_ns, s.approvers)
    op = data.draw(st.sampled_from(OPS))
    stn = data.draw(st.sampled_from(STATIONS))
    cmd = data.draw(st.sampled_from([c.name for c in Command if c != Command.NONE]))
    target = data.draw(st.integers(0, len(OPS) + 1))
    ref = data.draw(st.sampled_from([0, 1, 5, 6, 40, max(s.arm_seq, 0)]))
    model = ConsoleModel(M)
    model.operator = f"{op}@{stn}"
    model.on_snapshot(dv, t)
    auth.expire(t)
    ident = Identity(OPS.index(op), STATIONS.index(stn))
    cn = auth.check(ident, Command[cmd], t, target=target, ref=ref)
    said = None if cn is None else f"{CommandStatus(cn[0]).name}: {cn[1]}"
    assert model.refusal(cmd, target=target, ref=ref) == said
