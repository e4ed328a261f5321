"""Keys per link, each host holding only its own (zplatform.core.auth), with real
frames: whatever a host's keys can make, the links it does not hold refuse.

Before per-link keys, the ground's key was the mission key: it signed
triggers that fired both igniters with the vehicle in SAFE.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path

import pytest

from zplatform.boards import SimBoard
from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.control.uplink import Uplink
from zplatform.core.auth import MACS, AuthError, Channel, KeyError_, KeySet
from zplatform.core.codec import RegionCodec
from zplatform.core.datavector import DataVector, Layout
from zplatform.core.events import EV, EventLog, EventReader, encode_event
from zplatform.mission.load import load_mission

ROOT = Path(__file__).resolve().parents[2]
IGN = load_mission(ROOT / "configs" / "recovery_igniter.yaml")
PERIOD = IGN.period_ns
T0 = 1_700_000_000_000_000_000
EPOCH = 5
KEYS = KeySet.generate(IGN)  # what `zplatform keygen` writes: independent random keys
CN, DN0, DN1, GN, TOOL = (KEYS.for_node(r) for r in ("cn", "dn0", "dn1", "gn", "tool"))
CHANNELS = [
    "cn_to_dn0",
    "dn0_to_cn",
    "cn_to_dn1",
    "dn1_to_cn",
    "gn_to_cn",
    "telemetry",
    "clock_dn0_to_cn",
    "clock_cn_to_dn0",
    "events_cn",
    "events_dn0",
]


def forgeries(held: KeySet, frame: bytes) -> Iterator[bytes]:
    """``frame`` tagged every way a holder of ``held`` can: each key it holds
    used as any channel's link key under either MAC, or as a master key
    deriving a whole set; and untagged, and with a made-up tag."""
    yield frame
    yield frame + bytes(16)
    for link, mac, name in itertools.product(held.links, MACS, CHANNELS):
        yield bytes(Channel(held.link_key(link), IGN.vehicle, name, mac).seal(frame))
    for link in held.links:
        as_master = KeySet.from_master(IGN, held.link_key(link))
        for name in CHANNELS:
            yield bytes(as_master.channel(name).seal(frame))


def fire_trigger(dn: str, seq: int, t_ns: int) -> bytes:
    """A ``cn_to_dnX`` frame that would fire dnX's igniter: armed, commanded
    in this very loop, its safety controller enabled, and stamped with the
    state the igniter may fire in (``dnX_state``, which the DN's interlock
    reads)."""
    dv = DataVector(Layout.for_node(IGN, "cn"))
    dv.set(f"{dn}_state", "FIRE")
    dv.set(f"{dn}_ign_armed", True)
    dv.set(f"{dn}_ign_cmd", True)
    dv.set(f"{dn}_ign_cmd_loop", seq)
    dv.set(f"safety{dn[2:]}_mode", "enabled")
    return bytes(RegionCodec(dv, f"cn_to_{dn}").encode(seq, t_ns))


def test_a_ground_key_set_cannot_fire_an_igniter() -> None:
    """Both DNs run the real CN's SAFE triggers with their barometers reading
    an altitude in the igniter's window (150 m, injected on their boards:
    the vehicle sits in SAFE, as in the attack); then every trigger the
    ground's keys can make is refused, and neither igniter fires. The cn's
    key, used the same way, fires them (the forgery is real)."""
    cn = ControlLogic(IGN, keys=CN, epoch=EPOCH)
    boards = {dn: SimBoard({"digital_pins": 2, "analog_pins": 2}) for dn in ("dn0", "dn1")}
    for b in boards.values():
        b.inject_analog(0, 150.0 / 200.0)  # the barometer's pin: 200 m per volt
    dns = [DeviceLogic(IGN, dn, keys=k, board=boards[dn]) for dn, k in (("dn0", DN0), ("dn1", DN1))]
    loop = 0

    def real_loop() -> None:
        nonlocal loop
        loop += 1
        t = T0 + (loop - 1) * PERIOD
        frames = cn.begin(loop, t)
        for i, d in enumerate(dns):
            cn.reply(i, d.step(bytes(frames[i]), t))
        cn.finish()

    for _ in range(20):
        real_loop()
    assert cn.dv.get_name("cn_state") == "SAFE" and cn.dv.get("dn0_alt_m") > 100
    with pytest.raises(KeyError_, match="no key for link cn-dn0"):
        GN.channel("cn_to_dn0")
    for d in dns:
        seq, t = loop + 1, T0 + loop * PERIOD
        tried = 0
        for forged in forgeries(GN, fire_trigger(d.node, seq, t)):
            tried += 1
            assert d.trigger(forged, t) is None and not d.triggered
        assert d.dv.get(f"{d.node}_ign_armed") is False
        assert int(d.dv.get(f"{d.node}_bad_frames")) == tried > 100
    for _ in range(5):
        real_loop()
    assert cn.dv.get("igniter_fired") is False and cn.dv.get_name("cn_state") == "SAFE"
    assert not any(d.dv.get(f"{d.node}_ign_out") for d in dns)
    # The control: the same trigger under the cn's key of each link fires both.
    seq, t = loop + 1, T0 + loop * PERIOD
    for d in dns:
        d.step(bytes(CN.channel(f"cn_to_{d.node}").seal(fire_trigger(d.node, seq, t))), t)
        assert d.dv.get(f"{d.node}_ign_out") is True
    real_loop()
    real_loop()
    assert cn.dv.get("igniter_fired") is True  # with the vehicle in SAFE: what keys prevent


def test_a_dn_key_cannot_forge_another_dns_replies_or_telemetry() -> None:
    cn = ControlLogic(IGN, keys=CN, epoch=EPOCH)
    cn.begin(1, T0)
    rogue = DataVector(Layout.for_node(IGN, "dn1"))
    rogue.set("dn1_alt_m", 250.0)
    rogue.set("dn1_ign_fb", True)
    reply = bytes(RegionCodec(rogue, "dn1_to_cn").encode(1, T0))
    tm_dv = DataVector(Layout.for_node(IGN, "cn"))
    tm_dv.set("cn_loop", 10**6)
    tm_dv.set("igniter_fired", True)
    tm = bytes(RegionCodec(tm_dv).encode(10**6, T0))
    ground = GN.channel("telemetry")
    for forged in forgeries(DN0, reply):
        assert cn.reply(1, forged) is False
    for forged in forgeries(DN0, tm):
        with pytest.raises(AuthError):
            ground.open(forged)
    cn.finish()
    assert cn.dv.get("cn_rx_dn1") == 0 and cn.dv.get("dn1_ign_fb") is False
    for name in ("dn1_to_cn", "cn_to_dn1", "telemetry", "gn_to_cn", "events_cn"):
        with pytest.raises(KeyError_):
            DN0.channel(name)


def test_a_tool_key_cannot_command() -> None:
    cn = ControlLogic(IGN, keys=CN, epoch=EPOCH)
    plain = Uplink(IGN, None)  # the request's bytes, to be tagged every way a tool can
    frames = [
        bytes(plain.frame("ARM", 1, 0, 0.0, T0, EPOCH)),
        bytes(plain.frame("LAUNCH", 2, 0, 0.0, T0, EPOCH)),
    ]
    loop = 0
    for frame in frames:
        for forged in forgeries(TOOL, frame):
            loop += 1
            cn.begin(loop, T0 + loop * PERIOD)
            cn.finish([forged])
    assert cn.dv.get("cn_cmd_seq") == 0 and cn.dv.get_name("cn_state") == "SAFE"
    with pytest.raises(KeyError_, match="no key for link uplink"):
        Uplink(IGN, TOOL)
    # The ground's own keys do command, through the CN's checks.
    up = Uplink(IGN, GN)
    for seq, cmd in ((1, "ARM"), (2, "LAUNCH")):
        loop += 1
        cn.begin(loop, T0 + loop * PERIOD)
        cn.finish([bytes(up.frame(cmd, seq, 0, 0.0, T0, EPOCH))])
    # Judged by the CN: its device nodes never answered here, so DN_LOST is
    # latched and the LAUNCH is refused for it (commands.refused_while_faulted).
    assert cn.dv.get("cn_cmd_seq") == 2 and cn.dv.get_name("cn_fault") == "DN_LOST"
    assert cn.dv.get_name("cn_cmd_status") == "REJECTED_NOT_ALLOWED"
    assert cn.dv.get_name("cn_state") == "SAFE"


def test_events_are_authenticated_per_node() -> None:
    """A peer without the key cannot put a fake ``cmd_accepted`` on the
    operator's console; a DN cannot speak as the CN; a tool that holds no
    key shows events marked unverified."""
    log = EventLog("cn")
    log.emit(EV.CMD_ACCEPTED, T0, name="LAUNCH", seq=9, detail="")
    record = encode_event(log.drain()[0])
    real = bytes(CN.channel("events_cn").seal(record))
    grounds = EventReader(IGN, GN)
    e, verified = grounds.read("rocket/cn/events", real)
    assert verified is True and e.id == "cmd_accepted"
    for forged in [*forgeries(DN0, record), *forgeries(KeySet.generate(IGN), record)]:
        with pytest.raises(Exception) as ei:
            grounds.read("rocket/cn/events", forged)
        assert "tag" in str(ei.value) or "not an event record" in str(ei.value)
    # A record of the CN's, tagged with dn0's own event key, on dn0's key.
    with pytest.raises(AuthError, match="a record of 'cn' on 'dn0'"):
        grounds.read("rocket/dn0/events", bytes(DN0.channel("events_dn0").seal(record)))
    e, verified = EventReader(IGN, None).read("rocket/cn/events", real)
    assert verified is False and e.text == "command LAUNCH #9 accepted"
    assert TOOL.has("events-cn") and EventReader(IGN, TOOL).read("rocket/cn/events", real)[1]


def test_a_forged_event_record_is_known_by_its_tag_alone() -> None:
    """``EventReader.forged``, which the ground's zenoh callback asks before it
    queues a record: every forgery a keyless peer makes is refused there; a
    genuine record, an insider's (dn0's key, on dn0's key: refused later, by
    ``read``) and a record of a node whose key the reader lacks are not."""
    log = EventLog("cn")
    log.emit(EV.CMD_ACCEPTED, T0, name="LAUNCH", seq=9, detail="")
    record = encode_event(log.drain()[0])
    real = bytes(CN.channel("events_cn").seal(record))
    grounds = EventReader(IGN, GN)
    assert not grounds.forged("rocket/cn/events", real)
    for forged in [*forgeries(KeySet.generate(IGN), record), b"", b"x", record]:
        assert grounds.forged("rocket/cn/events", forged)
    insider = bytes(DN0.channel("events_dn0").seal(record))
    assert not grounds.forged("rocket/dn0/events", insider)
    assert not EventReader(IGN, None).forged("rocket/cn/events", b"junk")  # no key: unchecked
    assert not grounds.forged("rocket/other/events", b"junk")  # no such node's key
