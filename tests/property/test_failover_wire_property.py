"""Fuzzing every failover wire decoder: the probe question, the probe
answer, the mirror. Any bytes, tagged or not, get a clean refusal (the
project's CodecError from a reader, False or None from a receiver),
never another exception.

Three kinds of input each: arbitrary bytes; bytes of the exact size with
arbitrary fields (past the length check); and either, *sealed* with the
right channel's key (what an insider holding that key can send: past the
tag, into the range checks).
"""

from __future__ import annotations

import struct
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.payload import Bytes
from zplatform import load_mission
from zplatform.control.failover import MirrorReader, Standby
from zplatform.control.fencing import NONCE_LEN, ask_stamp, read_ask, read_reply
from zplatform.control.handoff import Waker
from zplatform.control.intake import MirrorIntake, ProbeIntake
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.core.codec import frame_overhead
from zplatform.core.datavector import Layout
from zplatform.errors import CodecError
from zplatform.sim.lockstep import sim_keys

ROOT = Path(__file__).resolve().parents[2]
FLIGHT = load_mission(ROOT / "configs" / "flight.yaml")
KEYS = sim_keys(FLIGHT)
assert KEYS is not None
T0 = 1_700_000_000_000_000_000
P = FLIGHT.period_ns

_ASK = struct.Struct(f"<2sBBBBI{NONCE_LEN}sq")
_REPLY = struct.Struct(f"<2sBB{NONCE_LEN}sIIBBqQq")
ASK_CH = KEYS.for_node("cn_b").channel("probe_cn_to_dn0")
REPLY_CH = KEYS.for_node("dn0").channel("probe_dn0_to_cn")
MIRROR_CH = KEYS.for_node("cn").channel("mirror")
NONCE = b"n" * NONCE_LEN

_SETTINGS = settings(
    max_examples=200,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def _edges(bits: int, signed: bool = False) -> st.SearchStrategy[int]:
    """Integers of a field, with its edges (where the range checks bite) often."""
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    edges = sorted(e for e in {lo, lo + 1, -2, -1, 0, 1, 2, hi - 1, hi} if lo <= e <= hi)
    return st.one_of(st.sampled_from(edges), st.integers(lo, hi))


u8, u32, u64, i64 = _edges(8), _edges(32), _edges(64), _edges(64, signed=True)
magic = st.sampled_from([b"ZP", b"ZA", b"ZZ"])

questions = st.one_of(
    st.binary(max_size=2 * _ASK.size),
    # The right magic, version, device node and nonce: the fields are what vary.
    st.builds(_ASK.pack, st.just(b"ZP"), st.just(1), u8, st.just(0), u8, u32, st.just(NONCE), i64),
    st.builds(_ASK.pack, magic, u8, u8, u8, u8, u32, st.binary(min_size=16, max_size=16), i64),
)
answers = st.one_of(
    st.binary(max_size=2 * _REPLY.size),
    st.builds(
        _REPLY.pack,
        st.just(b"ZA"),
        st.just(1),
        st.just(0),
        st.just(NONCE),
        u32,
        u32,
        u8,
        u8,
        i64,
        u64,
        i64,
    ),
    st.builds(
        _REPLY.pack,
        magic,
        u8,
        u8,
        st.binary(min_size=16, max_size=16),
        u32,
        u32,
        u8,
        u8,
        i64,
        u64,
        i64,
    ),
)


def _sealed(ch: object, data: bytes) -> bytes:
    return bytes(ch.seal(data))  # type: ignore[attr-defined]


def _genuine_mirror() -> bytes:
    cn = ControlLogic(FLIGHT, keys=None, epoch=T0)
    cn.begin(1, T0)
    cn.finish()
    assert cn.mirror is not None
    return bytes(cn.mirror)


MIRROR = _genuine_mirror()  # untagged: a mission without keys sends it so


def _edited(edits: list[tuple[int, int]]) -> bytes:
    """The genuine mirror with some bytes replaced (its term, commander, loop...)."""
    out = bytearray(MIRROR)
    for i, b in edits:
        out[i] = b
    return bytes(out)


_LAYOUT = Layout.for_node(FLIGHT, "cn")
_AT = frame_overhead(_LAYOUT.size)
# What the failover reads from a mirror: its loop (seq, header bytes 7-14),
# its term and its commander.
_READ = [
    *range(7, 15),
    *(_AT + _LAYOUT.element("cn_term").offset + k for k in range(4)),
    _AT + _LAYOUT.element("cn_commander").offset,
]
mirrors = st.one_of(
    st.binary(max_size=len(MIRROR) + 40),
    st.lists(st.tuples(st.integers(0, len(MIRROR) - 1), u8), max_size=12).map(_edited),
    st.lists(st.tuples(st.sampled_from(_READ), u8), min_size=1, max_size=6).map(_edited),
)


@_SETTINGS
@given(data=questions, seal=st.booleans())
def test_any_probe_question_is_read_or_refused_as_a_codec_error(data: bytes, seal: bool) -> None:
    payload = _sealed(ASK_CH, data) if seal else data
    for ch in (ASK_CH, None):
        try:
            ask = read_ask(ch, payload, 0)
        except CodecError:
            continue
        assert ask.asker < 2 and 0 <= ask.term <= 0xFFFF_FFFE
    try:
        ask_stamp(memoryview(data))
    except CodecError:
        pass
    dn = DeviceLogic(FLIGHT, "dn0", keys=KEYS.for_node("dn0"))
    reply = dn.probe(payload, T0)
    assert reply is None or isinstance(reply, bytes)
    intake: ProbeIntake[None] = ProbeIntake("dn0", ASK_CH, Waker(), period_ns=P, now_ns=lambda: T0)
    assert intake.check(Bytes(payload), None) in (None, payload)


@_SETTINGS
@given(data=answers, seal=st.booleans())
def test_any_probe_answer_is_read_or_refused_as_a_codec_error(data: bytes, seal: bool) -> None:
    payload = _sealed(REPLY_CH, data) if seal else data
    for ch in (REPLY_CH, None):
        try:
            r = read_reply(ch, payload, 0, NONCE)
        except CodecError:
            continue
        assert r.term <= 0xFFFF_FFFE and r.promised <= 0xFFFF_FFFE and r.quiet_ns >= -1
    cnb = ControlLogic(FLIGHT, keys=KEYS.for_node("cn_b"), name="cn_b", epoch=T0)
    sb = Standby(FLIGHT, cnb, KEYS.for_node("cn_b"))
    sb.ask(5, T0)
    sb._nonces[0] = NONCE  # the fuzzed answer echoes this question's nonce
    assert sb.answer(0, payload) in (True, False)
    sb.decide(5, T0)
    sb.ask(8, T0)  # whatever it learned, the next question can be made
    sb.silent(8, T0)


@settings(_SETTINGS, max_examples=120)  # four control logics an example
@given(data=mirrors, seal=st.booleans())
def test_any_mirror_is_applied_or_refused_never_raises(data: bytes, seal: bool) -> None:
    payload = _sealed(MIRROR_CH, data) if seal else data
    keys = KEYS if seal else None
    for node, name in (("cn", "cn"), ("cn_b", "cn_b")):
        logic = ControlLogic(FLIGHT, keys=keys and keys.for_node(node), name=name, epoch=T0)
        reader = MirrorReader(logic, keys and keys.for_node(node))
        term, who = reader.newer_term(payload)
        assert (term, who) == (0, -1) or (1 <= term <= 0xFFFF_FFFE and who in (0, 1))
        sb = Standby(FLIGHT, logic, keys and keys.for_node(node))
        if sb.mirror(payload, T0):
            sb.tick(sb.slot(T0) + 10)
            sb.ask(sb.slot(T0) + 10, T0)
        intake = MirrorIntake(FLIGHT, node, MIRROR_CH if seal else None)
        assert intake.check(Bytes(payload), None) in (None, payload)
