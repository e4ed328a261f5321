"""Terms and fencing (zplatform.control.fencing) on real frames: what a device node runs, and when.

The flight mission has a standby control node, so its triggers carry a
term. Frames are made by real :class:`ControlLogic` instances with the
lockstep runner's keys and judged by a real :class:`DeviceLogic`.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from zplatform import load_mission
from zplatform.control.failover import Decision, MirrorReader, Standby
from zplatform.control.fencing import (
    ASK,
    RELEASE,
    STATUS,
    TERM_MAX,
    TermGuard,
    Verdict,
    ask_frame,
    attested_term,
    read_reply,
)
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.errors import CodecError
from zplatform.sim.lockstep import sim_keys

ROOT = Path(__file__).resolve().parents[2]
FLIGHT = load_mission(ROOT / "configs" / "flight.yaml")
P = FLIGHT.period_ns
LEASE = FLIGHT.takeover.lease_loops * P
KEYS = sim_keys(FLIGHT)
assert KEYS is not None
T0 = 1_700_000_000_000_000_000


def at(loop: int) -> int:
    return T0 + (loop - 1) * P


# -- the term most device nodes attest -------------------------------------------------


def test_the_attested_term_is_what_more_than_half_report_never_one_nodes_alone() -> None:
    assert attested_term([TERM_MAX, 2], 2) == 2  # one liar of two
    assert attested_term([TERM_MAX, 4, 3], 3) == 4  # one liar of three
    assert attested_term([TERM_MAX, TERM_MAX, 3], 3) == TERM_MAX  # a majority
    assert attested_term([0, 0, 7], 3) == 0  # two restarted
    assert attested_term([9], 3) == 0 and attested_term([], 2) == 0  # too few answered
    assert attested_term([5], 1) == 5


# -- the guard alone ---------------------------------------------------------------


def test_a_guard_runs_its_term_fences_lower_ones_and_follows_a_higher_one_after_its_lease() -> None:
    g = TermGuard(LEASE)
    assert g.admit(1, at(1), None) == Verdict.NEW  # the first trigger ever: any term
    assert g.ran(1) and g.term == 1
    assert g.admit(1, at(2), at(1)) == Verdict.SAME
    assert g.admit(0, at(2), at(1)) == Verdict.FENCED
    assert g.admit(2, at(2), at(1)) == Verdict.LEASED  # term 1 ran a period ago
    assert g.admit(2, at(1) + LEASE, at(1)) == Verdict.NEW  # the lease is out
    assert not g.ran(1) and g.ran(2) and g.term == 2
    assert g.admit(1, at(9), at(8)) == Verdict.FENCED


def test_a_promise_fences_the_old_term_lapses_unused_and_is_one_askers() -> None:
    g = TermGuard(LEASE)
    g.ran(1)
    last = at(10)
    assert not g.answer(ASK, 1, 2, last + P, last)  # term 1 ran a period ago: refused
    now = last + LEASE
    assert g.answer(ASK, 1, 2, now, last)  # quiet for the lease: promised to cn_b (1)
    assert g.answer(ASK, 1, 2, now + 1, last)  # the same asker again: still granted
    assert not g.answer(ASK, 0, 2, now + 1, last)  # the other control node: refused
    assert g.seen(now) == 2 and g.promised(now) == 2
    assert g.admit(1, now + 1, last) == Verdict.FENCED  # the old term is fenced at once
    assert g.admit(2, now + 1, last) == Verdict.NEW
    assert g.promised(now + LEASE) == 0 and g.admit(1, now + LEASE, last) == Verdict.SAME
    assert g.answer(ASK, 1, 3, now + LEASE, last)
    assert not g.answer(RELEASE, 0, 3, now + LEASE, last) and g.promised(now + LEASE) == 3
    g.answer(RELEASE, 1, 3, now + LEASE, last)  # its asker lets it go
    assert g.promised(now + LEASE) == 0
    assert not g.answer(STATUS, 1, 9, now + LEASE, last) and g.seen(now + LEASE) == 1


# -- a device node on real frames -----------------------------------------------------


def _pair() -> tuple[ControlLogic, ControlLogic, DeviceLogic]:
    cn = ControlLogic(FLIGHT, keys=KEYS.for_node("cn"), epoch=T0)
    cnb = ControlLogic(FLIGHT, keys=KEYS.for_node("cn_b"), name="cn_b", epoch=T0)
    dn = DeviceLogic(FLIGHT, "dn0", keys=KEYS.for_node("dn0"))
    return cn, cnb, dn


def _seen(cn: ControlLogic, dn: str = "dn0") -> int:
    return int(cn.dv.get(f"{dn}_term_seen"))


def test_a_device_node_never_runs_two_terms_in_one_loop_and_tells_the_old_one() -> None:
    cn, cnb, dn = _pair()
    assert cn.term == 1
    for n in (1, 2, 3):
        assert dn.trigger(cn.begin(n, at(n))[0], at(n)) is not None and dn.triggered == n
    # cn_b in term 2, one period after cn's last trigger: refused (the lease),
    # answered, nothing runs.
    cnb.take_command(2, 4)
    reply = dn.trigger(cnb.begin(4, at(4))[0], at(4))
    assert reply is not None and dn.triggered == 0 and dn.fenced == 1
    assert not cnb.reply(0, reply)  # a reply of term 1: not the new term's
    assert dn.guard is not None and dn.guard.term == 1
    # cn goes on in loop 4 (the same loop): runs.
    dn.trigger(cn.begin(4, at(4))[0], at(4))
    assert dn.triggered == 4
    # Quiet for the lease: term 2's loop 8 runs, and from then on term 1 is fenced.
    dn.trigger(cnb.begin(8, at(8))[0], at(8))
    assert dn.triggered == 8 and dn.guard.term == 2
    reply = dn.trigger(cn.begin(9, at(9))[0], at(9))
    assert reply is not None and dn.triggered == 0
    assert not cn.reply(0, reply)  # fenced: not applied, marked
    # Term 2 cannot run loop 8 again, nor an older one.
    dn.trigger(cnb.begin(8, at(8) + 1)[0], at(9))
    assert dn.triggered == 0


def test_a_majority_of_device_nodes_on_a_newer_term_supersedes_a_commander() -> None:
    cn, cnb, _ = _pair()
    dns = [DeviceLogic(FLIGHT, d, keys=KEYS.for_node(d)) for d in FLIGHT.device_nodes]
    for n in (1, 2):
        frames = cn.begin(n, at(n))
        for i, d in enumerate(dns):
            cn.reply(i, d.step(frames[i], at(n)))
        cn.finish()
    cnb.take_command(2, 6)
    frames = cnb.begin(6, at(6))
    dns[0].step(frames[0], at(6))  # dn0 follows term 2; dn1 did not hear it
    frames = cn.begin(7, at(7))
    for i, d in enumerate(dns):
        cn.reply(i, d.step(frames[i], at(7)))
    assert cn.finish() is not None and cn.superseded == 0  # one of two: not a majority
    # dn1 hears term 2 once cn has left it alone for the lease (cut off from it).
    dns[1].step(cnb.begin(8, at(8))[1], at(8))
    assert dns[1].guard is not None and dns[1].guard.term == 1  # cn drove it at loop 7
    dns[1].step(cnb.begin(11, at(11))[1], at(11))
    assert dns[1].guard.term == 2
    # Fenced by most device nodes for longer than a promise lasts: it stands down.
    for n in range(12, 12 + FLIGHT.takeover.lease_loops + 1):
        assert cn.superseded == 0
        frames = cn.begin(n, at(n))
        for i, d in enumerate(dns):
            cn.reply(i, d.step(frames[i], at(n)))
        tm = cn.finish()
    assert tm is None and cn.superseded == 2


def test_probe_replies_are_bound_to_their_question_and_their_link() -> None:
    cn, cnb, dn = _pair()
    cn.reply(0, dn.trigger(cn.begin(1, at(1))[0], at(1)))
    cn.finish()
    sb = Standby(FLIGHT, cnb, KEYS.for_node("cn_b"))
    assert cn.mirror is not None and sb.mirror(bytes(cn.mirror), at(1))
    asks = sb.ask(5, at(5))
    reply = dn.probe(asks[0], at(5))
    assert reply is not None and sb.answer(0, reply)
    assert sb.answers[0] is not None and sb.answers[0].granted and sb.answers[0].term == 1
    # The same reply, fed to a later question: refused.
    sb.ask(8, at(8))
    assert not sb.answer(0, reply) and sb.bad_replies == 1
    # A question under another link's key (dn1's), or a forged one: refused, counted.
    forged = ask_frame(KEYS.for_node("cn").channel("probe_cn_to_dn1"), ASK, 0, 0, 9, b"n" * 16, 0)
    bad = int(dn.dv.get("dn0_bad_frames"))
    assert dn.probe(forged, at(9)) is None and int(dn.dv.get("dn0_bad_frames")) == bad + 1
    with pytest.raises(CodecError):
        read_reply(None, b"junk", 0, b"n" * 16)


def test_a_standby_takes_command_only_when_every_answer_grants() -> None:
    cn, cnb, _ = _pair()
    dns = [DeviceLogic(FLIGHT, d, keys=KEYS.for_node(d)) for d in FLIGHT.device_nodes]
    sb = Standby(FLIGHT, cnb, KEYS.for_node("cn_b"))
    for n in range(1, 6):
        frames = cn.begin(n, at(n))
        for i, d in enumerate(dns):
            cn.reply(i, d.step(frames[i], at(n)))
        cn.finish()
        assert cn.mirror is not None and sb.mirror(bytes(cn.mirror), at(n))
    assert sb.mirrored == 5 and not sb.tick(6)
    assert sb.tick(8)  # 3 loops without a mirror
    asks = sb.ask(8, at(8))
    sb.answer(0, dns[0].probe(asks[0], at(8) + P // 2) or b"")
    # dn1 is driven by cn right now (it ran loop 8): it refuses.
    dns[1].step(cn.begin(8, at(8))[1], at(8))
    sb.answer(1, dns[1].probe(asks[1], at(8) + P // 2) or b"")
    assert sb.decide(8, at(8) + P // 2) == Decision.WAIT
    # Every device node asked is released (a late answer may carry a promise).
    assert sb.releases[0] is not None and sb.releases[1] is not None
    dns[0].probe(sb.releases[0], at(8) + P // 2)  # the promise is let go
    assert dns[0].guard is not None and dns[0].guard.promised(at(8) + P) == 0
    assert not sb.tick(9) and not sb.tick(10) and sb.tick(11)  # asks again 3 loops later
    asks = sb.ask(11, at(11))
    for i, d in enumerate(dns):
        sb.answer(i, d.probe(asks[i], at(11) + P // 2) or b"")
    assert sb.decide(11, at(11) + P // 2) == Decision.TAKE
    logic = sb.take(12)
    assert logic is cnb and logic.term == 2 and logic.dv.get_name("cn_commander") == "cn_b"


def test_a_commander_reads_a_newer_terms_mirror_and_ignores_its_own() -> None:
    cn, cnb, _ = _pair()
    cn.begin(1, at(1))
    cn.finish()
    assert cn.mirror is not None
    mine = bytes(cn.mirror)
    cnb.take_command(2, 5)
    cnb.begin(5, at(5))
    cnb.finish()
    assert cnb.mirror is not None
    reader = MirrorReader(cn, KEYS.for_node("cn"))
    assert reader.newer_term(mine) == (0, -1)
    assert reader.newer_term(bytes(cnb.mirror)) == (2, 1)
    tampered = bytearray(cnb.mirror)
    tampered[-1] ^= 1
    assert reader.newer_term(bytes(tampered)) == (0, -1) and reader.bad == 1
    # A ground's keys cannot make a mirror: the link is the control nodes' only.
    assert not KEYS.for_node("gn").has("cn-cn_b")


REDUNDANT = """
mission: twin
nodes: {cn: {}, cn_b: {}, dn0: {}}
regions:
  cn: [{name: x, type: u8}]
  cn_to_dn0: [{name: valve, type: bool}]
  dn0_to_cn: [{name: pressure, type: f32}]
controllers:
  - {name: count, class: "stub_components:%s", node: cn, initial_mode: enabled}
"""


def test_a_redundant_mission_holds_its_controllers_to_the_vector() -> None:
    """A control-node controller must declare takeover_safe; one that does and
    still keeps state in an attribute fails in its first loop (safed, an event),
    instead of silently keeping what a takeover would lose."""
    from zplatform.errors import ConfigError
    from zplatform.mission.load import decode_mission

    with pytest.raises(ConfigError) as e:
        decode_mission(REDUNDANT % "Idle")
    assert e.value.path == "$.controllers[0].class" and "takeover_safe" in e.value.reason
    m = decode_mission(REDUNDANT % "Counter")
    cn = ControlLogic(m)
    cn.begin(1, at(1))
    cn.finish()
    failed = [ev for ev in cn.events.drain() if ev.id == "controller_failed"]
    assert len(failed) == 1 and "sets self.n after bind" in failed[0].text
    assert cn.dv.get_name("count_mode") == "safed"
    # Without a standby the same class runs as it likes.
    plain = decode_mission((REDUNDANT % "Counter").replace("cn_b: {}, ", ""))
    cn = ControlLogic(plain)
    cn.begin(1, at(1))
    cn.finish()
    assert cn.dv.get_name("count_mode") == "enabled"


def test_a_fresh_promise_holds_off_the_other_control_nodes_ask() -> None:
    """A node that promised cn_b term 2 a moment ago refuses cn (asking term 3,
    as a node that just stood down and counts silence from its own last loop
    would): the promise is a commander about to drive; the lease runs from it."""
    g = TermGuard(LEASE)
    g.ran(1)
    last = at(10)
    now = last + LEASE
    assert g.answer(ASK, 1, 2, now, last)
    assert not g.answer(ASK, 0, 3, now + P, last)  # within the lease of the promise
    assert g.admit(2, now + P, last) == Verdict.NEW  # cn_b's first trigger still runs
