"""The large-frame path (bench.frame_trace): frames tagged in place, the DN's
trigger tag checked once (by its intake), the trigger's data applied after
the reply, telemetry handed to zenoh only for a subscriber; the bytes on the
wire unchanged (codecs/FORMAT.md)."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.zsession import lone_session
from zplatform.control.intake import ReplyCheck, TriggerIntake
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.core.auth import TAG_LEN, AuthError, Channel, channel
from zplatform.core.codec import FrameEncoder, RegionCodec, encode_frame
from zplatform.mission.load import load_mission
from zplatform.runtime.sync import ControlSync, DeviceSync, TapPublisher
from zplatform.runtime.transport import KeySpace
from zplatform.sim.lockstep import sim_keys

MINIMAL = Path(__file__).resolve().parents[2] / "configs" / "minimal.yaml"
M = load_mission(MINIMAL)
KEYS = sim_keys(M)
T0 = 10**9
PERIOD = M.period_ns
KEY = bytes(range(1, 33))


@pytest.mark.parametrize("n", [0, 1, 255, 256, 65535, 65536, 200_000])
def test_an_encoder_with_tail_room_writes_the_same_frame(n: int) -> None:
    data = bytes(i % 251 for i in range(n))
    plain = encode_frame(7, 8, 9, data)
    buf = FrameEncoder(n, TAG_LEN).encode(7, 8, 9, data)
    assert len(buf) == len(plain) + TAG_LEN
    assert bytes(buf[: len(plain)]) == plain


def test_seal_tail_tags_in_place_what_seal_tags_in_a_copy() -> None:
    for mac in ("blake3", "hmac-sha256"):
        ch = Channel(KEY, "v", "cn_to_dn0", mac)
        enc = FrameEncoder(1000, TAG_LEN)
        buf = enc.encode(1, 2, 3, bytes(1000))
        frame = bytes(buf[:-TAG_LEN])
        assert ch.seal_tail(buf) is buf  # the encoder's own buffer, tagged there
        assert bytes(buf) == bytes(Channel(KEY, "v", "cn_to_dn0", mac).seal(frame))
        assert bytes(ch.open(buf)) == frame
    with pytest.raises(ValueError):
        Channel(KEY, "v", "x").seal_tail(bytearray(TAG_LEN))


def test_strip_is_a_view_without_the_tag_and_checks_nothing_else() -> None:
    ch = Channel(KEY, "v", "cn_to_dn0")
    payload = bytes(ch.seal(b"frame"))
    body = ch.strip(payload)
    assert bytes(body) == b"frame" and body.obj is payload  # no copy
    forged = b"frame" + bytes(TAG_LEN)
    assert bytes(ch.strip(forged)) == b"frame"  # the caller vouched for the tag
    with pytest.raises(AuthError):
        ch.open(forged)
    with pytest.raises(AuthError):
        ch.strip(bytes(TAG_LEN))


def test_the_loops_send_the_bytes_a_copy_and_seal_would() -> None:
    """Tagging in place changes no byte on the wire: the CN's query, the DN's
    reply and the telemetry are each the frame followed by its tag."""
    assert KEYS is not None
    cn = ControlLogic(M, keys=KEYS)
    dn = DeviceLogic(M, "dn0", keys=KEYS)
    cn.dv.set("dn0_setpoint", 2.5)
    query = bytes(cn.begin(1, T0 + PERIOD)[0])
    codec = RegionCodec(cn.dv, "cn_to_dn0")
    expect = KEYS.channel("cn_to_dn0").seal(codec.encode(1, T0 + PERIOD))
    assert query == bytes(expect)
    reply = dn.trigger(query, T0 + PERIOD)
    assert reply is not None
    out = RegionCodec(dn.dv, "dn0_to_cn").encode(1, T0 + PERIOD)
    assert bytes(reply) == bytes(KEYS.channel("dn0_to_cn").seal(out))
    assert cn.reply(0, bytes(reply))
    tm = cn.finish()
    assert tm is not None
    whole = RegionCodec(cn.dv).encode(1, T0 + PERIOD)
    assert bytes(tm) == bytes(KEYS.channel("telemetry").seal(whole))


def test_a_trigger_vouched_for_is_not_checked_again() -> None:
    """``authentic=True``: the driver's intake checked the tag; the logic only
    strips it (a bad tag then passes: the contract is the caller's). Without
    it, the tag is checked."""
    assert KEYS is not None
    cn = ControlLogic(M, keys=KEYS)
    query = bytearray(cn.begin(1, T0 + PERIOD)[0])
    query[-1] ^= 1  # a wrong tag
    assert DeviceLogic(M, "dn0", keys=KEYS).trigger(bytes(query), T0 + PERIOD) is None
    dn = DeviceLogic(M, "dn0", keys=KEYS)
    assert dn.trigger(bytes(query), T0 + PERIOD, authentic=True) is not None
    assert dn.triggered == 1


def test_the_trigger_s_data_is_applied_by_run_after_the_reply() -> None:
    assert KEYS is not None
    cn = ControlLogic(M, keys=KEYS)
    dn = DeviceLogic(M, "dn0", keys=KEYS)
    cn.dv.set("dn0_setpoint", 4.0)
    reply = dn.trigger(bytes(cn.begin(1, T0 + PERIOD)[0]), T0 + PERIOD)
    assert reply is not None and dn.triggered == 1
    assert dn.dv.get("dn0_setpoint") == 0.0  # not yet: the reply went first
    dn.run(T0 + PERIOD)
    assert dn.dv.get("dn0_setpoint") == 4.0
    # A trigger that does not run (the same loop again) applies nothing later.
    cn.dv.set("dn0_setpoint", 9.0)
    assert dn.trigger(bytes(cn.begin(1, T0 + PERIOD)[0]), T0 + PERIOD) is not None
    assert dn.triggered == 0
    dn.run(T0 + PERIOD)
    assert dn.dv.get("dn0_setpoint") == 4.0


class _CountingOpen:
    """Stands in for the DN logic's channel: counts tag checks."""

    def __init__(self, ch: Channel) -> None:
        self.ch = ch
        self.opened = 0
        self.stripped = 0

    def open(self, payload: Any) -> memoryview:
        self.opened += 1
        return self.ch.open(payload)

    def strip(self, payload: Any) -> memoryview:
        self.stripped += 1
        return self.ch.strip(payload)


def test_a_live_device_node_checks_each_trigger_s_tag_once() -> None:
    """Through zenoh: the intake checks the tag on zenoh's thread, the loop
    thread strips it; the exchange still completes and applies."""
    assert KEYS is not None
    cn = ControlLogic(M, keys=KEYS)
    dn = DeviceLogic(M, "dn0", keys=KEYS)
    assert dn._open is not None
    spy = _CountingOpen(dn._open)
    dn._open = spy  # type: ignore[assignment]
    session = lone_session()
    try:
        keys = KeySpace(M.vehicle)
        now = iter(range(T0, 2 * T0, PERIOD)).__next__
        intake: TriggerIntake[zenoh.Query] = TriggerIntake(M, "dn0", channel(KEYS, "cn_to_dn0"))
        assert intake.authenticates
        ds = DeviceSync(session, keys, "dn0", now, intake=intake)
        cs = ControlSync(
            session,
            keys,
            ["dn0"],
            2_000_000_000,  # generous: this checks the path, not the timing
            2.0,
            checks=[ReplyCheck(M, "dn0", channel(KEYS, "dn0_to_cn"))],
        )
        try:
            for loop in (1, 2):
                served = threading.Thread(target=ds.wait, args=(dn, 10.0))
                served.start()
                cs.sync(cn.begin(loop, T0 + loop * PERIOD), cn)
                served.join()
                assert cn.pending == 0
                dn.run(T0 + loop * PERIOD)
                cn.finish()
        finally:
            cs.close()
            ds.close()
    finally:
        session.close()
    assert (spy.opened, spy.stripped) == (0, 2)


class _FakePub:
    def __init__(self, matching: bool) -> None:
        self.matching_status = matching
        self.sent: list[bytes] = []

    def put(self, payload: bytes | bytearray) -> None:
        self.sent.append(bytes(payload))


@pytest.mark.parametrize(
    ("exact", "zenoh_says", "sent"), [(False, True, 0), (True, False, 0), (True, True, 1)]
)
def test_a_tap_puts_only_for_a_subscriber(exact: bool, zenoh_says: bool, sent: int) -> None:
    """The listener's flag first; ``exact``: zenoh's own matching state when
    the flag says nobody (a subscriber the listener has not told of yet)."""
    session = lone_session()
    try:
        tap = TapPublisher(session, "large/frames/test", exact=exact)
        real = tap.pub
        assert tap.matching is False
        tap.pub = _FakePub(zenoh_says)  # type: ignore[assignment]
        tap.put(bytearray(b"x" * 100))
        assert len(tap.pub.sent) == sent  # type: ignore[attr-defined]
        tap.matching = True
        tap.put(b"y")
        assert len(tap.pub.sent) == sent + 1  # type: ignore[attr-defined]
        tap.pub = real
        tap.undeclare()
    finally:
        session.close()
