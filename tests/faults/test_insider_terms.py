"""A device node's insider and the integers of its own frames (issue 25: the
term + 1 overflow class), in process on the flight mission (a standby, two
device nodes). The insider holds dn0's key, so its probe answers and sync
replies are tagged right; only their ranges can refuse them.

* Out of range (a term or promise above TERM_MAX, u32 max, a loop above
  LOOP_MAX, a quiet time below -1, a grant of no term) a probe answer is
  refused and counted once (``Standby.bad_replies``), and dn0's honest answer
  to the same round is still taken; a sync reply naming a term above
  TERM_MAX is refused and counted once in ``cn_bad_frames``.
* In range, high (up to TERM_MAX): one device node's term is not learned
  (``Standby.term`` takes only what more than half attest); the next round
  asks at most ``TERM_JUMP`` past the known term, the round after forgets
  it: the insider burns at most that many terms, and once gone the standby
  takes command (it used to learn the term whole: no next term for as long
  as it ran). It does not stop the standby applying the commander's
  mirrors. Only a majority at TERM_MAX makes it ask for nothing past it.
* Honest device nodes restarted (term 0) or fenced above the others (a
  term run, a promise) still let the standby take command within a bounded
  number of rounds.
* A commander fenced by a majority with the insider among them stands down
  knowing the term the majority attests, not the insider's TERM_MAX.
"""

from __future__ import annotations

import os
import struct

import pytest

from tests.faults.insider import ROOT
from zplatform.control.failover import Decision, Standby
from zplatform.control.fencing import (
    ASK,
    LOOP_MAX,
    NONCE_LEN,
    STATUS,
    TERM_JUMP,
    TERM_MAX,
    VERSION,
)
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.core.auth import KEY_ENV, TAG_LEN, Channel, KeySet, Run
from zplatform.core.codec import decode_frame, encode_frame
from zplatform.core.datavector import Layout
from zplatform.mission.load import load_mission

M = load_mission(ROOT / "configs" / "flight.yaml")
KEYS = KeySet.from_master(M, bytes.fromhex(os.environ[KEY_ENV]))
INSIDER = KEYS.for_node("dn0")
T0 = 1_700_000_000_000_000_000
U32_MAX, U64_MAX = (1 << 32) - 1, (1 << 64) - 1
_ASK = struct.Struct(f"<2sBBBBI{NONCE_LEN}sq")  # codecs/FORMAT.md §6.5
_REPLY = struct.Struct(f"<2sBB{NONCE_LEN}sIIBBqQq")


def _standby() -> Standby:
    return Standby(M, ControlLogic(M, keys=KEYS, epoch=T0, name="cn_b"), KEYS)


def _forged(
    ask: bytes, term: int, promised: int, granted: int, quiet: int, loop: int, dn: int = 0
) -> bytes:
    """Device node ``dn``'s answer to ``ask`` as its insider writes it (dn0's
    key; another's only to make a majority say it): the run the question
    names, the integers it likes."""
    nonce = _ASK.unpack(ask[: _ASK.size])[6]
    body = _REPLY.pack(b"ZA", VERSION, dn, nonce, term, promised, granted, 0, quiet, loop, T0)
    name = M.device_nodes[dn]
    ch = KEYS.for_node(name).channel(f"probe_{name}_to_cn", Run(Channel.run_of(ask)))
    return bytes(ch.seal(body))


@pytest.mark.parametrize(
    ("term", "promised", "granted", "quiet", "loop"),
    [
        (TERM_MAX + 1, 0, 0, 10**9, 5),
        (U32_MAX, 0, 0, 10**9, 5),
        (1, TERM_MAX + 1, 0, 10**9, 5),
        (1, U32_MAX, 1, 10**9, 5),
        (1, 0, 1, 10**9, 5),  # a grant of no term
        (1, 2, 2, 10**9, 5),  # a grant that is no boolean
        (1, 0, 0, -2, 5),
        (1, 0, 0, -(1 << 63), 5),
        (1, 0, 0, 10**9, LOOP_MAX + 1),
        (1, 0, 0, 10**9, U64_MAX),
    ],
)
def test_a_probe_answer_out_of_range_is_refused_and_counted_once(
    term: int, promised: int, granted: int, quiet: int, loop: int
) -> None:
    sb = _standby()
    dn0 = DeviceLogic(M, "dn0", keys=KEYS)
    asks = sb.ask(1, T0)
    assert not sb.answer(0, _forged(asks[0], term, promised, granted, quiet, loop))
    assert sb.bad_replies == 1 and sb.answers[0] is None
    honest = dn0.probe(asks[0], T0 + 1)
    assert honest is not None and sb.answer(0, honest)
    assert sb.bad_replies == 1


@pytest.mark.parametrize("seen", [TERM_MAX + 1, U32_MAX])
def test_a_sync_reply_naming_a_term_past_the_last_is_refused_and_counted_once(seen: int) -> None:
    cn = ControlLogic(M, keys=KEYS, epoch=T0)
    dn0 = DeviceLogic(M, "dn0", keys=KEYS)
    t = T0 + M.period_ns
    frames = cn.begin(1, t)
    reply = dn0.trigger(bytes(frames[0]), t)
    assert reply is not None
    f = decode_frame(bytes(reply)[:-TAG_LEN])
    lay = Layout.for_node(M, "cn")
    off = lay.element("dn0_term_seen").offset - lay.region("dn0_to_cn").offset
    data = bytearray(f.data)
    struct.pack_into("<I", data, off, seen)
    ch = INSIDER.channel("dn0_to_cn", Run(Channel.run_of(bytes(reply))))
    forged = bytes(ch.seal(encode_frame(f.layout_id, f.seq, f.t_ns, data)))
    before = cn.dv.get("cn_bad_frames")
    assert not cn.reply(0, forged)
    assert cn.dv.get("cn_bad_frames") == before + 1
    assert cn.reply(0, bytes(reply))  # the genuine one is still taken


def _round(
    sb: Standby, dns: list[DeviceLogic], slot: int, t: int, lie: int | None, liars: int = 1
) -> Decision:
    """One probe round: dn0 (its insider answering ``lie`` as its term, when
    given; the first ``liars`` device nodes so) and dn1 answer; the standby
    decides."""
    asks = sb.ask(slot, t)
    for i, d in enumerate(dns):
        if i < liars and lie is not None:
            reply = _forged(asks[i], lie, 0, 0, 10**9, 5, dn=i)
        else:
            reply = d.probe(asks[i], t)
        assert reply is not None and sb.answer(i, reply)
    return sb.decide(slot, t)


def _asked(asks: list[bytes]) -> list[tuple[int, int]]:
    """``(kind, term)`` of each question of a round."""
    return [(_ASK.unpack(a[: _ASK.size])[2], _ASK.unpack(a[: _ASK.size])[5]) for a in asks]


def test_a_majority_at_term_max_asks_nothing_past_it() -> None:
    """Were every device node to say TERM_MAX (more insiders than the
    threat model's one), the standby learns it and asks for no term past
    it (no ``TERM_MAX + 1`` on the wire, a STATUS instead)."""
    sb = _standby()
    dns = [DeviceLogic(M, dn, keys=KEYS) for dn in M.device_nodes]
    assert _round(sb, dns, 1, T0, TERM_MAX, liars=2) is Decision.WAIT
    assert sb.term == TERM_MAX
    asks = sb.ask(2, T0 + M.period_ns)
    assert _asked(asks) == [(STATUS, 0)] * 2, "a question past TERM_MAX"
    for i, d in enumerate(dns):
        reply = d.probe(asks[i], T0 + M.period_ns)
        assert reply is not None and sb.answer(i, reply)
    assert sb.decide(2, T0 + M.period_ns) is Decision.WAIT
    assert ASK != STATUS


@pytest.mark.parametrize("lie", [TERM_MAX, TERM_MAX - TERM_JUMP, 1 << 31, TERM_JUMP + 1])
def test_one_insiders_high_term_is_taken_only_a_bounded_jump_for_one_round(lie: int) -> None:
    """One device node's term, however high, is not learned (the other does
    not attest it): the next round asks at most TERM_JUMP past the term
    known (the term space burns that much, not to its end), and the round
    after, the insider gone, asks past the known term again."""
    sb = _standby()
    dns = [DeviceLogic(M, dn, keys=KEYS) for dn in M.device_nodes]
    assert _round(sb, dns, 1, T0, lie) is Decision.WAIT
    assert sb.term == 0 and sb.reach == TERM_JUMP
    t = T0 + 100 * M.period_ns
    assert _asked(sb.ask(2, t)) == [(ASK, TERM_JUMP + 1)] * 2
    assert _round(sb, dns, 3, t, None) is Decision.TAKE  # forgotten: asks past term 0
    assert sb.reach == 0


def test_one_insiders_term_max_does_not_disable_failover_for_good() -> None:
    sb = _standby()
    dns = [DeviceLogic(M, dn, keys=KEYS) for dn in M.device_nodes]
    assert _round(sb, dns, 1, T0, TERM_MAX) is Decision.WAIT
    # The insider is gone: dn0 answers honestly (it never ran a term).
    t = T0 + 100 * M.period_ns
    assert _round(sb, dns, 2, t, None) is Decision.TAKE
    assert sb._asked <= TERM_JUMP + 1


def _commander(term: int) -> ControlLogic:
    cn = ControlLogic(M, keys=KEYS, epoch=T0)
    cn.dv.handle("cn_term").set(term)
    return cn


def _mirror(cn: ControlLogic, loop: int) -> bytes:
    cn.begin(loop, T0 + (loop - 1) * M.period_ns)
    cn.finish()
    assert cn.mirror is not None
    return bytes(cn.mirror)


def test_one_insiders_term_max_does_not_stop_the_standby_following_the_commander() -> None:
    """The term a lone device node names is not the standby's: the commander's
    next mirror, of its lower term, is still applied."""
    sb = _standby()
    cn = _commander(1)
    dns = [DeviceLogic(M, dn, keys=KEYS) for dn in M.device_nodes]
    assert sb.mirror(_mirror(cn, 1), T0)
    assert _round(sb, dns, 5, T0 + 4 * M.period_ns, TERM_MAX) is Decision.WAIT
    assert sb.mirror(_mirror(cn, 6), T0 + 5 * M.period_ns)
    assert sb.term == 1 and sb.mirrored == 6


def _fly_standby(sb: Standby, dns: list[DeviceLogic], first: int, slots: int) -> int:
    """Drive ``sb`` as :class:`~zplatform.control.role.ControlRole` does
    (docs/architecture.md#failover) from slot ``first`` for up to ``slots``
    slots, the device nodes answering honestly; the rounds (ticks that
    probed) until it took command, or 0 if it did not."""
    assert sb.origin is not None
    rounds = 0
    for slot in range(first, first + slots):
        t = sb.origin + (slot - 1) * M.period_ns + M.period_ns // 2
        if not sb.tick(slot):
            continue
        rounds += 1
        for kind in (STATUS, ASK):
            asks = sb.ask(slot, t, kind=kind)
            for i, d in enumerate(dns):
                reply = d.probe(asks[i], t)
                assert reply is not None and sb.answer(i, reply)
            if kind == STATUS and not sb.silent(slot, t):
                break
            if kind == ASK:
                if sb.decide(slot, t) is Decision.TAKE:
                    return rounds
                for i, rel in enumerate(sb.releases):
                    if rel is not None:
                        dns[i].probe(rel, t)
    return 0


@pytest.mark.parametrize(
    ("ran", "takes"),
    [
        ((0, 0), 6),  # both restarted: they report term 0, the mirror says 5
        ((5, 0), 6),  # one restarted
        ((6, 0), 7),  # dn0 fenced one term above the mirror, dn1 restarted
        ((5 + TERM_JUMP, 5), 6 + TERM_JUMP),  # dn0 fenced as far above as a lone node is heard
        ((7, 5), 8),
    ],
)
def test_honest_device_nodes_restarted_or_fenced_above_the_others_let_the_standby_take_command(
    ran: tuple[int, int], takes: int
) -> None:
    """Honest terms the majority does not attest (restarted device nodes
    report 0; one fenced above the others, by a commander that drove it
    alone) hold no takeover back: the standby following a term-5 commander
    takes command in the first round, past every term a device node ran."""
    sb = _standby()
    cn = _commander(5)
    assert sb.mirror(_mirror(cn, 1), T0)
    dns = [DeviceLogic(M, dn, keys=KEYS) for dn in M.device_nodes]
    for d, term in zip(dns, ran, strict=True):
        assert d.guard is not None
        d.guard.term = term
    assert _fly_standby(sb, dns, 2, 10) == 1
    assert sb._asked == takes


def test_an_honest_promise_above_the_others_holds_the_standby_back_a_lease_at_most() -> None:
    """dn0 promised the other control node a term above everything (its
    asker then died): the standby waits for the promise to lapse (a lease)
    and takes command within a bounded number of rounds."""
    sb = _standby()
    assert sb.mirror(_mirror(_commander(5), 1), T0)
    dns = [DeviceLogic(M, dn, keys=KEYS) for dn in M.device_nodes]
    assert dns[0].guard is not None
    t = T0 + M.period_ns  # the promise is given as the commander falls silent
    assert dns[0].guard.answer(ASK, 0, 5 + TERM_JUMP + 3, t, None)
    rounds = _fly_standby(sb, dns, 2, 20)
    assert 1 <= rounds <= 3
    assert sb._asked == 6  # the promise lapsed: nothing above the mirror's term 5 is left


def test_a_stood_down_commander_takes_the_term_a_majority_fenced_it_with_not_an_insiders() -> None:
    """A commander fenced by both device nodes, dn0's insider saying TERM_MAX
    and dn1 following cn_b's term 2: it stands down knowing term 2 (the
    term both attest), so it follows cn_b's mirrors and has a next term to
    ask for (before: the highest, TERM_MAX, passed on: no failover ever)."""
    cn = _commander(1)
    cnb = ControlLogic(M, keys=KEYS, epoch=T0, name="cn_b")
    dns = [DeviceLogic(M, dn, keys=KEYS) for dn in M.device_nodes]
    for d, term in zip(dns, (TERM_MAX, 2), strict=True):
        assert d.guard is not None
        d.guard.term = term
    cnb.take_command(2, 1)
    n = 1
    while not cn.superseded and n < 20:
        frames = cn.begin(n, T0 + (n - 1) * M.period_ns)
        for i, d in enumerate(dns):
            reply = d.step(frames[i], T0 + (n - 1) * M.period_ns)
            assert reply is not None
            cn.reply(i, reply)
        cn.finish()
        n += 1
    assert cn.superseded == 2
    sb = Standby.stand_down(M, cn, KEYS, "fenced")
    assert sb.term == 2
    assert sb.mirror(_mirror(cnb, n), T0 + (n - 1) * M.period_ns)
    assert sb.following and sb.term == 2
