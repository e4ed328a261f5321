"""The failover channels' receiving side (issue "Every door locked by
construction"): the probe (``{vehicle}/dnX/probe``) and the mirror
(``{vehicle}/cn/mirror``) refuse what no genuine peer sends before it can
cost anything, and every integer they carry is range-checked where it is
read (zplatform.control.fencing, zplatform.control.failover, zplatform.control.intake).

Each test names the attack it answers: an insider holding one node's key,
or a peer without any key on plain TCP. Frames are real (the lockstep
runner's keys); clocks are fake; nothing waits on time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.payload import Bytes, FakeQuery
from zplatform import load_mission
from zplatform.control.failover import Decision, MirrorReader, Standby
from zplatform.control.fencing import (
    ASK,
    RELEASE,
    STATUS,
    TERM_MAX,
    ProbeReply,
    ask_frame,
    read_ask,
    read_reply,
    reply_frame,
)
from zplatform.control.handoff import Waker
from zplatform.control.intake import PROBE_BURST, PROBES, MirrorIntake, ProbeIntake
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.core.events import EV
from zplatform.errors import CodecError
from zplatform.sim.lockstep import LockstepRunner, sim_keys

ROOT = Path(__file__).resolve().parents[2]
FLIGHT = load_mission(ROOT / "configs" / "flight.yaml")
P = FLIGHT.period_ns
KEYS = sim_keys(FLIGHT)
assert KEYS is not None
T0 = 1_700_000_000_000_000_000
U32_MAX = 0xFFFF_FFFF


def at(loop: int) -> int:
    return T0 + (loop - 1) * P


def _commander(term: int = 1, who: int = 0) -> ControlLogic:
    """A control node's logic whose mirrors say ``term`` and commander ``who``
    (an insider holding the control nodes' link can write any)."""
    cn = ControlLogic(FLIGHT, keys=KEYS.for_node("cn"), epoch=T0)
    cn.dv.handle("cn_term").set(term)
    cn.dv.handle("cn_commander").set(who)
    return cn


def _mirror(cn: ControlLogic, loop: int) -> bytes:
    cn.begin(loop, at(loop))
    cn.finish()
    assert cn.mirror is not None
    return bytes(cn.mirror)


def _standby() -> Standby:
    cnb = ControlLogic(FLIGHT, keys=KEYS.for_node("cn_b"), name="cn_b", epoch=T0)
    return Standby(FLIGHT, cnb, KEYS.for_node("cn_b"))


def _dn_reply(sb: Standby, i: int, **fields: Any) -> bytes:
    """A probe answer to ``sb``'s current question, made with device node
    ``i``'s key (an insider holding it can put anything in it)."""
    dn = FLIGHT.device_nodes[i]
    r = ProbeReply(i, sb._nonces[i], 1, 0, False, 0, 4 * P, 5, at(5))._replace(**fields)
    # In the run of the question it answers (the standby's: zplatform.core.auth.Run).
    return reply_frame(KEYS.for_node(dn).channel(f"probe_{dn}_to_cn", sb.logic.auth_run), r)


# -- 1. every integer from the wire is range-checked where it is used -------------------


def test_a_probe_answer_of_the_largest_term_is_refused_and_the_standby_asks_on() -> None:
    """Insider with dn0's key: an answer naming term 2^32 - 1 made the standby
    ask for 2^32, which its u32 field cannot hold: struct.error in its loop
    thread, the process dead, nobody to take over. Now the answer is refused
    (counted, evented) and the standby's next round asks as before."""
    sb = _standby()
    assert sb.mirror(_mirror(_commander(), 1), at(1))
    sb.ask(5, at(5))
    for term, promised in ((U32_MAX, 0), (1, U32_MAX)):
        assert not sb.answer(0, _dn_reply(sb, 0, term=term, promised=promised))
    assert sb.bad_replies == 2 and sb.answers[0] is None
    assert sb.decide(5, at(5)) == Decision.WAIT and sb.term == 1
    asks = sb.ask(8, at(8))  # used to raise struct.error here
    ch = KEYS.for_node("dn0").channel("probe_cn_to_dn0")
    assert read_ask(ch, asks[0], 0).term == 2
    # The refusals are evented, once, at the next beat.
    assert sb.tick(9) is False
    bad = [e for e in sb.events.drain() if e.id == EV.BAD_FRAME.name]
    assert len(bad) == 1 and "2 probe answer(s)" in bad[0].text


def test_a_standby_at_the_last_term_asks_for_nothing_and_says_why() -> None:
    """A term at the maximum is never asked +1: the standby holds (one
    event) instead of asking for a term no field can carry."""
    sb = _standby()
    assert sb.mirror(_mirror(_commander(term=TERM_MAX), 1), at(1))
    assert sb.term == TERM_MAX
    assert not sb.tick(5) and not sb.tick(6)
    held = [e for e in sb.events.drain() if e.id == EV.CN_TAKEOVER_HELD.name]
    assert len(held) == 1 and "no next term" in held[0].text
    asks = sb.ask(6, at(6))  # asked anyway: a STATUS, asking for nothing
    ch = KEYS.for_node("dn0").channel("probe_cn_to_dn0")
    assert read_ask(ch, asks[0], 0).kind == STATUS
    assert sb.decide(6, at(6)) == Decision.WAIT


def test_malformed_probe_answers_are_refused() -> None:
    """Insider with dn0's key: a grant of a term not asked for, a flag that
    is neither 0 nor 1, a quiet time below -1, a loop beyond the range."""
    sb = _standby()
    assert sb.mirror(_mirror(_commander(), 1), at(1))
    sb.ask(5, at(5))
    for bad in (
        {"granted": True, "promised": 7},  # not the term asked (2)
        {"granted": True, "promised": 0},
        {"quiet_ns": -2},
        {"last_loop": 1 << 63},
    ):
        assert not sb.answer(0, _dn_reply(sb, 0, **bad)), bad
    assert sb.bad_replies == 4
    # granted=2 on the wire: a flag out of range.
    body = bytearray(_dn_reply(sb, 0, granted=True, promised=2))
    ch = KEYS.for_node("dn0").channel("probe_dn0_to_cn")
    raw = bytearray(ch.open(bytes(body)))
    raw[2 + 1 + 1 + 16 + 8] = 2
    with pytest.raises(CodecError):
        read_reply(ch, bytes(ch.seal(bytes(raw))), 0, sb._nonces[0])
    assert sb.answer(0, _dn_reply(sb, 0, granted=True, promised=2))


def test_probe_questions_out_of_range_are_refused() -> None:
    """Insider with a control node's key: a question from a third control
    node, an ASK of term 0 or above TERM_MAX, a STATUS naming a term."""
    ch = KEYS.for_node("cn").channel("probe_cn_to_dn0")
    n = b"n" * 16
    for kind, asker, term in ((ASK, 2, 2), (ASK, 0, 0), (ASK, 0, U32_MAX), (RELEASE, 1, U32_MAX)):
        with pytest.raises(CodecError):
            read_ask(ch, ask_frame(ch, kind, 0, asker, term, n, 1), 0)
    with pytest.raises(CodecError):
        read_ask(ch, ask_frame(ch, STATUS, 0, 0, 5, n, 1), 0)
    assert read_ask(ch, ask_frame(ch, ASK, 0, 1, TERM_MAX, n, 1), 0).term == TERM_MAX
    dn = DeviceLogic(FLIGHT, "dn0", keys=KEYS.for_node("dn0"))
    assert dn.probe(ask_frame(ch, ASK, 0, 0, U32_MAX, n, 1), at(1)) is None
    assert dn.guard is not None and dn.guard.promised(at(1)) == 0
    assert int(dn.dv.get("dn0_bad_frames")) == 1


def test_a_mirror_naming_no_control_node_or_no_term_is_refused() -> None:
    """Insider with the control nodes' link: a mirror from control node 7
    made the standby index the mission's two control nodes with 7 (IndexError
    in its loop thread), and the commander too; a mirror of term 2^32 - 1
    was adopted. Both are refused, counted."""
    sb = _standby()
    for cn in (_commander(who=7), _commander(term=U32_MAX, who=0), _commander(term=0, who=0)):
        assert not sb.mirror(_mirror(cn, 1), at(1))
    assert sb.bad == 3 and sb.mirrored == 0 and sb.term == 0
    reader = MirrorReader(
        ControlLogic(FLIGHT, keys=KEYS.for_node("cn"), epoch=T0), KEYS.for_node("cn")
    )
    assert reader.newer_term(_mirror(_commander(term=5, who=7), 1)) == (0, -1)
    assert reader.newer_term(_mirror(_commander(term=U32_MAX, who=1), 1)) == (0, -1)
    assert reader.bad == 2
    assert sb.mirror(_mirror(_commander(), 1), at(1)) and sb.term == 1


def test_triggers_and_replies_naming_a_term_above_the_range_are_bad_frames() -> None:
    """Insider with a control node's key: a trigger of term 2^32 - 1 was run
    (and no commander could ever take the node back). Insider with a device
    node's key: a reply naming it counted toward standing the commander down.
    Both are bad frames now, evented once a second however many come."""
    cn = _commander(term=U32_MAX)
    dn = DeviceLogic(FLIGHT, "dn0", keys=KEYS.for_node("dn0"))
    for n in range(1, 51):  # half a second of loops
        assert dn.trigger(cn.begin(n, at(n))[0], at(n)) is None
    assert dn.triggered == 0 and dn.guard is not None and dn.guard.term == 0
    assert int(dn.dv.get("dn0_bad_frames")) == 50
    assert len([e for e in dn.events.drain() if e.id == EV.BAD_FRAME.name]) == 1
    good = _commander()
    assert dn.trigger(good.begin(51, at(51))[0], at(51)) is not None and dn.triggered == 51
    # dn0 (the insider) answers cn's loops saying it follows term 2^32 - 1.
    dn.guard.term = U32_MAX
    bad = int(good.dv.get("cn_bad_frames"))
    for n in range(52, 102):
        reply = dn.trigger(good.begin(n, at(n))[0], at(n))
        assert not good.reply(0, reply)
        good.finish()
    assert int(good.dv.get("cn_bad_frames")) == bad + 50
    assert good.superseded == 0
    out = [e for e in good.events.drain() if e.id == EV.BAD_FRAME.name and "naming term" in e.text]
    assert len(out) == 1


# -- 2. the probe's intake: size, rate, tag, freshness before the loop --------------------


class Clock:
    def __init__(self) -> None:
        self.t = 5 * P

    def __call__(self) -> int:
        return self.t


def _question(asker: int, t_ns: int, dn: int = 0) -> bytes:
    node = FLIGHT.control_nodes[asker]
    ch = KEYS.for_node(node).channel(f"probe_cn_to_{FLIGHT.device_nodes[dn]}")
    return ask_frame(ch, STATUS, dn, asker, 0, b"q" * 16, t_ns)


def _probe_intake(clock: Clock) -> ProbeIntake[str]:
    return ProbeIntake(
        "dn0",
        KEYS.for_node("dn0").channel("probe_cn_to_dn0"),
        Waker(),
        period_ns=P,
        askers=2,
        now_ns=clock,
    )


def test_a_probe_flood_without_the_key_is_refused_by_its_tag_and_spends_no_bound() -> None:
    """Keyless on plain TCP: a flood of probe questions was refused by a
    channel-wide rate bound before any copy, which the flood spent, so the
    standby's genuine question was refused with it (issue 25). Now each is
    copied and refused by its header tag (bad), none beyond a bound, and the
    genuine questions at the same instant are admitted."""
    clock = Clock()
    intake = _probe_intake(clock)
    junk = bytes(len(_question(0, 1)))  # the right size, no valid tag
    copies = Bytes.copies
    for _ in range(1000):
        assert not intake.admit(Bytes(junk), "junk")
    assert not intake.admit(Bytes(b"x" * 500), "long")
    assert Bytes.copies - copies == 1000  # each read (once) for its tag; the long one unread
    assert intake.take_counts() == (1, 1000, 0) and intake.excess == 0
    box = intake.box
    assert box is not None and len(box) == 0
    assert intake.admit(Bytes(_question(1, 10)), "cn_b")
    assert intake.admit(Bytes(_question(0, 10)), "cn")
    assert intake.take_counts() == (0, 0, 0) and intake.excess == 0


def test_one_askers_valid_questions_beyond_its_bound_are_refused_and_replays_cost_nothing() -> None:
    """Insider with a control node's key (or a standby gone wrong): authentic,
    fresh questions beyond one asker's bound are refused in the callback; a
    replay is stale and uses none of the asker's bound."""
    clock = Clock()
    intake = _probe_intake(clock)
    for k in range(PROBE_BURST):
        assert intake.admit(Bytes(_question(1, 100 + k)), f"q{k}")
        assert not intake.admit(Bytes(_question(1, 100 + k)), "replay")
    # The replays used none of cn_b's bound: its burst is spent by its
    # PROBE_BURST fresh questions alone.
    assert not intake.admit(Bytes(_question(1, 150)), "beyond cn_b's bound")
    assert intake.excess == 0 and intake.take_counts() == (0, 0, PROBE_BURST)
    assert intake.excess == 1
    clock.t += P // 2  # half a period: cn_b's own bound still refuses it
    assert not intake.admit(Bytes(_question(1, 200)), "beyond cn_b's bound")
    clock.t += P // 2  # and one more: cn's own bound is untouched by cn_b's questions
    assert intake.admit(Bytes(_question(0, 1)), "cn")
    assert intake.take_counts() == (0, 0, 0) and intake.excess == 1
    box = intake.box
    assert box is not None and box.dropped == PROBE_BURST + 1 - PROBES


def test_a_probe_flood_leaves_the_device_nodes_loop_its_trigger() -> None:
    """The device node's queryable callback (what zenoh's threads run) under
    a flood of junk and of valid-but-excess questions: exact counts, at most
    the bound's questions answered, and the loop's trigger runs as always."""
    from tests.zsession import lone_session
    from zplatform.control.intake import TriggerIntake
    from zplatform.runtime.sync import DeviceSync
    from zplatform.runtime.transport import KeySpace

    clock = Clock()
    dn = DeviceLogic(FLIGHT, "dn0", keys=KEYS.for_node("dn0"))
    triggers: TriggerIntake[Any] = TriggerIntake(
        FLIGHT, "dn0", KEYS.for_node("dn0").channel("cn_to_dn0")
    )
    assert triggers.box is not None
    probes: ProbeIntake[Any] = ProbeIntake(
        "dn0",
        KEYS.for_node("dn0").channel("probe_cn_to_dn0"),
        triggers.box.waker,
        period_ns=P,
        now_ns=clock,
    )
    session = lone_session()
    try:
        sync = DeviceSync(
            session, KeySpace(FLIGHT), "dn0", lambda: at(1), intake=triggers, probes=probes
        )
        try:
            junk = [FakeQuery(bytes(len(_question(0, 1)))) for _ in range(500)]
            valid = [FakeQuery(_question(1, 1000 + k)) for k in range(50)]
            for q in junk:
                sync.on_probe(q)  # type: ignore[arg-type]
            clock.t += 100 * P  # the channel's bound refilled; cn_b's own is PROBE_BURST
            for q in valid:
                sync.on_probe(q)  # type: ignore[arg-type]
            cn = _commander()
            trig = FakeQuery(bytes(cn.begin(1, at(1))[0]))
            triggers.admit(trig.payload, trig)
            assert sync.wait(dn, 1.0) and dn.triggered == 1
            assert len(trig.replies) == 1
            answered = [q for q in valid if q.replies]
            assert len(answered) == PROBES  # the newest two of the bound's eight
            assert not any(q.replies or q.errors for q in junk)
            channel_burst = 2 * PROBE_BURST
            refused = (500 - channel_burst) + channel_burst + (50 - PROBE_BURST)
            assert int(dn.dv.get("dn0_bad_frames")) == refused
            ev = [e for e in dn.events.drain() if e.id == EV.BAD_FRAME.name]
            assert len(ev) == 1 and f"{refused} probe question(s)" in ev[0].text
        finally:
            sync.close()
    finally:
        session.close()


# -- 3, 4. the mirror's intake: size, tag, freshness before the mailbox -------------------


def _mirror_intake(node: str = "cn_b") -> MirrorIntake:
    return MirrorIntake(FLIGHT, node, KEYS.for_node(node).channel("mirror"))


def test_junk_on_the_mirror_key_never_displaces_a_genuine_mirror() -> None:
    """Keyless: junk on {vehicle}/cn/mirror filled the standby's four-slot
    mailbox before any tag check, evicting the genuine mirror (a standby that
    misses mirrors goes blind). Now junk is refused in the callback."""
    intake = _mirror_intake()
    cn = _commander()
    genuine = _mirror(cn, 1)
    assert intake.admit(Bytes(genuine), None)
    copies = Bytes.copies
    for _ in range(100):
        assert not intake.admit(Bytes(b"\x94" + bytes(len(genuine) - 1)), None)  # bad tag
        assert not intake.admit(Bytes(b"x" * (intake.max_len + 1)), None)  # too long: unread
    assert Bytes.copies - copies == 100
    assert intake.take_counts() == (100, 100, 0)
    box = intake.box
    assert box is not None and box.dropped == 0
    (item,) = [box.pop()]
    assert item is not None and item[1] == genuine and box.pop() is None
    sb = _standby()
    assert sb.mirror(item[1], at(1)) and sb.mirrored == 1


def test_a_replayed_mirror_of_this_run_is_refused_and_cannot_make_a_commander_stand_down() -> None:
    """Keyless, replaying mirrors recorded earlier in this run: an older loop
    or an older term is stale at the intake (never displacing the genuine
    one), and a commander hearing an older term's mirror stays in command."""
    intake = _mirror_intake()
    cn = _commander()
    old = [_mirror(cn, n) for n in (1, 2, 3)]
    for m in old:
        assert intake.admit(Bytes(m), None)
    genuine = _mirror(cn, 4)
    assert intake.admit(Bytes(genuine), None)
    for _ in range(50):
        for m in old:
            assert not intake.admit(Bytes(m), None)
    assert intake.take_counts() == (0, 0, 150)
    box = intake.box
    assert box is not None
    out: list[tuple[None, bytes]] = []
    box.drain(out)
    assert out[-1][1] == genuine and len(out) == 4
    # cn_b took command in term 2; cn stood down, then took it back in term 3.
    # cn_b's term-2 mirrors, replayed to cn, are refused at cn's intake ...
    cnb = ControlLogic(FLIGHT, keys=KEYS.for_node("cn_b"), name="cn_b", epoch=T0)
    cnb.take_command(2, 5)
    term2 = [_mirror(cnb, n) for n in (5, 6)]
    at_cn = _mirror_intake("cn")
    assert at_cn.admit(Bytes(term2[1]), None)  # heard while cn_b commanded
    assert not at_cn.admit(Bytes(term2[0]), None) and not at_cn.admit(Bytes(term2[1]), None)
    assert not at_cn.admit(Bytes(_mirror(cn, 9)), None)  # cn's own: never from the other node
    assert at_cn.take_counts() == (0, 0, 3)
    # ... and even one that got past the intake cannot make term 3 stand down.
    cn.dv.handle("cn_term").set(3)
    reader = MirrorReader(cn, KEYS.for_node("cn"))
    assert reader.newer_term(term2[1]) == (0, -1)


# -- 5. a standby never asks for a term while the commander drives the DNs --------------


def test_a_standby_never_asks_for_a_term_while_the_commander_drives_a_device_node() -> None:
    """cn is cut off from cn_b and from dn0 but still drives dn1: the standby,
    hearing no mirror, asked both device nodes for term 2, and dn0 (quiet for
    the lease) promised it, fencing the live commander's triggers to dn0
    until the release came (on a busy host, after cn's next trigger). Now it
    asks a STATUS first and, seeing dn1 driven, asks for nothing; when cn
    really dies it still takes command, in term 2."""
    r = LockstepRunner(FLIGHT)
    asked: list[tuple[int, str, int]] = []
    for dev in r.devices:
        real = dev.probe

        def spy(payload: Any, now: int, real: Any = real, node: str = dev.node) -> Any:
            asked.append((r.loop + 1, node, bytes(payload)[3]))  # the question's kind
            return real(payload, now)

        dev.probe = spy  # type: ignore[method-assign]
    for _ in range(20):
        r.step()
    r.partition("cn", "cn_b")
    r.partition("cn", "dn0")
    for _ in range(30):
        r.step()
    assert [k for k in asked if k[2] != STATUS] == []
    assert asked and all(node == "dn1" or kind == STATUS for _, node, kind in asked)
    assert r.commanders == [(1, "cn", 1)]
    held = [e for e in r.result().events if e.id == EV.CN_TAKEOVER_HELD.name]
    assert held and "dn1 ran loop" in held[0].text
    # The cut heals; cn drives dn0 again, never fenced.
    r.heal()
    for _ in range(10):
        r.step()
    assert r.devices[0].fenced == 0 and r.commanders == [(1, "cn", 1)]
    # cn dies: the device nodes fall silent, the standby asks and takes command.
    r.kill("cn")
    for _ in range(10):
        r.step()
    assert [(node, term) for _, node, term in r.commanders] == [("cn", 1), ("cn_b", 2)]
    assert any(kind == ASK for _, _, kind in asked)


def test_a_mirror_stamped_beyond_the_clock_bound_is_refused_and_counted() -> None:
    """An authentic mirror (the commander's key: an insider's, or a stepped
    clock) stamped further ahead of the standby's clock than the clock
    bound and a period is refused and counted in bad: it would set the
    schedule the standby follows; the next genuine mirror is applied."""
    from zplatform.core.auth import TAG_LEN
    from zplatform.core.codec import decode_frame, encode_frame

    sb = _standby()
    cn = _commander()
    assert sb.mirror(_mirror(cn, 1), at(1))
    genuine = _mirror(cn, 2)
    f = decode_frame(genuine[:-TAG_LEN])
    ch = KEYS.channel("mirror")
    bound = round(FLIGHT.clock.offset_bound_ms * 1e6) + FLIGHT.period_ns
    for t in (at(2) + bound + 1, (1 << 63) - 1):
        assert not sb.mirror(bytes(ch.seal(encode_frame(f.layout_id, 2, t, bytes(f.data)))), at(2))
    assert sb.bad == 2 and sb.mirrored == 1
    assert sb.mirror(genuine, at(2)) and sb.mirrored == 2
    assert sb.origin == at(1)


def test_junk_probe_replies_from_many_peers_never_push_a_device_nodes_reply_out(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Issue 25: a probe round's replies waited in a bounded mailbox (four
    per device node) unchecked but for one reply per replier, so keyless
    peers answering from many sessions (junk, or replies to earlier
    questions) after the device node pushed its reply out, and the round
    found no answer (a takeover delayed). Now zenoh's callback screens each
    reply (header tag, node, the question's nonce) before the mailbox: the
    junk is refused there, counted, and the device node's reply is taken."""
    from types import SimpleNamespace

    from zplatform.runtime import sync
    from zplatform.runtime.transport import KeySpace

    sb = _standby()
    assert sb.mirror(_mirror(_commander(), 1), at(1))
    asks = sb.ask(5, at(5))
    genuine = [_dn_reply(sb, i) for i in range(len(FLIGHT.device_nodes))]
    earlier = [bytes(r) for r in genuine]  # replies to this round: replayed next round
    asks = sb.ask(8, at(8))  # a new round, new nonces
    genuine = [_dn_reply(sb, i) for i in range(len(FLIGHT.device_nodes))]
    peers = iter(range(10**6))

    def reply(data: bytes) -> Any:  # each from a zenoh session of its own
        ok = SimpleNamespace(payload=Bytes(data))
        return SimpleNamespace(ok=ok, replier_id=SimpleNamespace(zid=next(peers)))

    def ask(session: Any, key: str, handler: Any, **kw: Any) -> None:
        i = keys.index(key)
        handler(reply(genuine[i]))  # the device node answers first
        for _ in range(10):
            handler(reply(bytes(len(genuine[i]))))  # junk of the right size
            handler(reply(earlier[i]))  # its reply to the question before

    space = KeySpace(FLIGHT.vehicle)
    keys = [space.probe(dn) for dn in FLIGHT.device_nodes]
    monkeypatch.setattr(sync, "ask", ask)
    cn_b = KEYS.for_node("cn_b")
    screens = [cn_b.channel(f"probe_{dn}_to_cn", sb.logic.auth_run) for dn in FLIGHT.device_nodes]
    probes = sync.ProbeSync(
        None,  # type: ignore[arg-type]
        space,
        FLIGHT.device_nodes,
        50_000_000,
        screens=screens,
    )
    assert probes.round(asks, sb.answer) == len(FLIGHT.device_nodes)
    assert probes.screened == 20 * len(FLIGHT.device_nodes)
    assert all(a is not None for a in sb.answers)


def test_the_mirrors_refused_are_counted_in_the_data_vector() -> None:
    """Issue 25: the mirrors a control node's intake refused were only
    evented; now they go into ``cn_mirror_refused`` with the next loop (an
    input of the loop, as the other refusals), exactly, and a standby's,
    counted while it follows, with its first loop in command. Still one
    event for a flood."""
    from types import SimpleNamespace

    from zplatform.control.intake import CnRefusals, RefusalLog
    from zplatform.node.control import ControlNode

    cn = _commander()
    node: Any = SimpleNamespace(
        mirror_intake=_mirror_intake("cn"),
        _mirror_log=RefusalLog(4),
        _mirror_unfiled=0,
        logic=cn,
        name="cn",
        _refused=CnRefusals(),
        sync=SimpleNamespace(take_refusals=lambda r: None),
        _requests=None,
    )
    genuine = _mirror(_commander(who=1), 1)
    intake = node.mirror_intake
    for _ in range(3):
        assert not intake.admit(Bytes(b"\x94" + bytes(len(genuine) - 1)), None)  # bad tag
        assert not intake.admit(Bytes(b"x" * (intake.max_len + 1)), None)  # too long
    cn.events.drain()
    ControlNode._mirror_refusals(node, at(2))
    cn.begin(2, at(2))
    cn.finish(refused=ControlNode._take_refusals(node))
    assert cn.dv.get("cn_mirror_refused") == 6
    (ev,) = [e for e in cn.events.drain() if e.id == "bad_frame"]
    assert ev.text.startswith("6 mirror frame(s)")
    # Beats without a loop (a standby following): kept, then filed with the next loop.
    for t in (at(3), at(3) + P // 2):
        assert not intake.admit(Bytes(b"\x94" + bytes(len(genuine) - 1)), None)
        ControlNode._mirror_refusals(node, t)
    assert cn.dv.get("cn_mirror_refused") == 6
    cn.begin(3, at(3))
    cn.finish(refused=ControlNode._take_refusals(node))
    assert cn.dv.get("cn_mirror_refused") == 8
    cn.begin(4, at(4))
    cn.finish(refused=ControlNode._take_refusals(node))
    assert cn.dv.get("cn_mirror_refused") == 8  # counted once
