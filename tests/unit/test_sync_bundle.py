"""The sync bundle (codecs/FORMAT.md §6.2): one wildcard query carries every
DN's frame; each DN takes its own. Packing, strict parsing, the DN's use of
it, the policy that chooses it (a foreign replier on the CN's side:
tests/unit/test_intake.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from zplatform.control.loop import ControlLogic, DeviceLogic
from zplatform.control.uplink import ScriptCommand
from zplatform.core.codec import BUNDLE_MAGIC, BundleEncoder, bundle_entry, is_bundle
from zplatform.core.messages import WILDCARD_MAX_BUNDLE, sync_bundle_size, wildcard_sync_for
from zplatform.errors import FrameFormatError
from zplatform.mission.load import decode_mission, load_mission
from zplatform.sim.lockstep import LockstepRunner, sim_keys

ROOT = Path(__file__).resolve().parents[2]
LED = ROOT / "configs" / "led_test.yaml"


def test_pack_and_take_every_entry() -> None:
    enc = BundleEncoder()
    frames = [bytearray(b"abc"), bytearray(b""), bytearray(range(200))]
    b = enc.pack(frames)
    assert bytes(b[:3]) == BUNDLE_MAGIC and b[3] == 3 and is_bundle(b)
    assert [bytes(bundle_entry(b, i)) for i in range(3)] == [bytes(f) for f in frames]
    # The buffer is the encoder's own: reused while the sizes stay the same.
    assert enc.pack(frames) is b
    with pytest.raises(ValueError, match="at most 255"):
        enc.pack([bytearray(1)] * 256)


@pytest.mark.parametrize(
    ("payload", "i", "why"),
    [
        (b"", 0, "not a sync bundle"),
        (b"ZB\x02\x01\x00\x00\x00\x00", 0, "not a sync bundle"),  # version 2
        (b"\x94ZB\x01", 0, "not a sync bundle"),
        (b"ZB\x01\x01", 1, "holds 1 frames, none for node number 1"),
        (b"ZB\x01\x02\x03\x00", 0, "ends inside the length of frame 0"),
        (b"ZB\x01\x02\x05\x00\x00\x00abc", 0, "says 5 bytes, 3 are left"),
        (b"ZB\x01\x02\x01\x00\x00\x00a\xff\xff\xff\xff", 1, "says 4294967295 bytes"),
    ],
)
def test_malformed_bundles_are_refused_with_a_reason(payload: bytes, i: int, why: str) -> None:
    with pytest.raises(FrameFormatError, match=why):
        bundle_entry(payload, i)


@given(st.binary(max_size=64), st.integers(0, 300))
def test_any_bytes_give_a_bounded_view_or_a_format_error(payload: bytes, i: int) -> None:
    try:
        v = bundle_entry(b"ZB\x01" + payload, i)
    except FrameFormatError:
        return
    assert len(v) <= len(payload)


def _pair() -> tuple[ControlLogic, list[DeviceLogic]]:
    m = load_mission(LED)
    cn = ControlLogic(m, keys=sim_keys(m))
    return cn, [DeviceLogic(m, dn, keys=sim_keys(m)) for dn in m.device_nodes]


def test_each_dn_takes_its_own_frame_from_the_bundle() -> None:
    cn, dns = _pair()
    frames = cn.begin(1, 10**9)
    bundle = BundleEncoder().pack(frames)
    for i, d in enumerate(dns):
        reply = d.trigger(bundle, 10**9)
        assert reply is not None and d.triggered == 1, d.reject_reason
        assert cn.reply(i, reply)
    assert cn.pending == 0


def test_a_bundle_in_the_wrong_order_is_refused_by_every_dn() -> None:
    cn, dns = _pair()
    frames = cn.begin(1, 10**9)
    swapped = BundleEncoder().pack([frames[1], frames[0], frames[2]])
    for d in dns[:2]:
        assert d.trigger(swapped, 10**9) is None  # another channel's tag
        assert "authentication" in d.reject_reason or "layout" in d.reject_reason
        assert int(d.dv.get(f"{d.node}_bad_frames")) == 1
    short = BundleEncoder().pack(frames[:2])
    assert dns[2].trigger(short, 10**9) is None
    assert "none for node number 2" in dns[2].reject_reason


BASE = """
mission: wild
nodes: {cn: {}, dn0: {}, dn1: {}}
transport: {sync_query: %s}
regions:
  cn_to_dn0:
    - {name: a, type: 'u8[%d]'}
  cn_to_dn1:
    - {name: b, type: u8}
"""


def test_the_policy_chooses_wildcard_for_small_bundles_of_two_or_more() -> None:
    assert not wildcard_sync_for(load_mission(LED))  # per_node unless asked
    doc = yaml.safe_load(LED.read_text())
    doc["transport"] = {"sync_query": "auto"}
    assert wildcard_sync_for(decode_mission(yaml.safe_dump(doc)))  # 3 DNs, a few bytes each
    assert not wildcard_sync_for(load_mission(ROOT / "configs" / "minimal.yaml"))  # 1 DN
    small = decode_mission(BASE % ("auto", 10))
    assert wildcard_sync_for(small)
    big = decode_mission(BASE % ("auto", WILDCARD_MAX_BUNDLE))
    assert sync_bundle_size(big) > WILDCARD_MAX_BUNDLE and not wildcard_sync_for(big)
    assert wildcard_sync_for(decode_mission(BASE % ("wildcard", WILDCARD_MAX_BUNDLE)))
    assert not wildcard_sync_for(decode_mission(BASE % ("per_node", 10)))


def test_sim_runs_the_same_with_either_query_form() -> None:
    script = [ScriptCommand(at_ns=500_000_000, command="LAUNCH")]
    results = []
    for mode in ("wildcard", "per_node"):
        text = LED.read_text() + f"\ntransport: {{sync_query: {mode}}}\n"
        r = LockstepRunner(decode_mission(text), commands=script)
        res = r.run(8.0)
        results.append((res.states, res.rx, res.missed, bytes(r.control.dv.buf)))
    a, b = results
    assert a == b and a[0][:3] == ["A", "B", "C"]
