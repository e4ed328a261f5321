"""The golden frames of codecs/vectors/: decode each bit-exactly, re-encode to the same bytes.

The vectors are produced by hand with ``codecs/generate_vectors.py``; this test
never regenerates them. A failure here means the wire format changed: either a
bug, or a deliberate change that needs new vectors and a note in FORMAT.md.
"""

from __future__ import annotations

import json
import math
import struct
from functools import cache
from pathlib import Path
from typing import Any

import msgspec
import pytest

from zplatform import DataVector, ElementSpec, Layout, RegionCodec, decode_frame, load_mission
from zplatform.core.datavector import _region_descriptor

VECTORS = Path(__file__).resolve().parents[2] / "codecs" / "vectors"
NAMES = sorted(p.stem for p in VECTORS.glob("*.json"))


@cache
def layout() -> Layout:
    return Layout.for_node(load_mission(VECTORS / "mission.yaml"), "cn")


def load(name: str) -> tuple[dict[str, Any], bytes]:
    return json.loads((VECTORS / f"{name}.json").read_text()), (
        VECTORS / f"{name}.bin"
    ).read_bytes()


def is_bits(item: Any) -> bool:
    return isinstance(item, dict) and ("f32_bits" in item or "f64_bits" in item)


def item_bytes(spec: ElementSpec, item: Any) -> bytes:
    """The little-endian bytes of one JSON item of ``spec`` (FORMAT.md §8)."""
    st = spec.scalar
    if is_bits(item):
        key = "f32_bits" if st.size == 4 else "f64_bits"
        assert st.kind == "float" and set(item) == {key}, (spec.name, item)
        return int(item[key], 16).to_bytes(st.size, "little")
    if spec.enum is not None:
        assert spec.enum[item["value"]] == item["name"], (spec.name, item)
        item = item["value"]
    if st.kind == "float":
        assert isinstance(item, float) and math.isfinite(item), (spec.name, item)
    elif st.kind == "bool":
        assert isinstance(item, bool), (spec.name, item)
    else:
        assert isinstance(item, int) and not isinstance(item, bool), (spec.name, item)
    return struct.pack("<" + st.struct, item)


def element_bytes(spec: ElementSpec, value: Any) -> bytes:
    if spec.count:
        assert isinstance(value, list) and len(value) == spec.count, spec.name
        return b"".join(item_bytes(spec, x) for x in value)
    return item_bytes(spec, value)


def test_vectors_present() -> None:
    bins = sorted(p.stem for p in VECTORS.glob("*.bin"))
    assert bins == NAMES, "every .bin needs its .json and the other way round"
    assert len(NAMES) >= 16
    regions = {load(n)[0]["region"] for n in NAMES}
    assert regions >= {f"cn_to_dn{i}" for i in range(7)}
    sizes = {load(n)[0]["data_size"] for n in NAMES}
    assert sizes >= {255, 256, 65535, 65536}


@pytest.mark.parametrize("name", NAMES)
def test_header_and_layout(name: str) -> None:
    meta, frame = load(name)
    r = layout().region(meta["region"])
    assert meta["name"] == name
    assert meta["descriptor"] == _region_descriptor(r.name, r.elements)
    assert meta["layout_id"] == r.layout_id == int(meta["layout_id_hex"], 16)
    assert meta["data_size"] == r.size
    assert meta["frame_size"] == len(frame)
    assert frame.hex().startswith(meta["frame_head_hex"])
    assert list(meta["values"]) == [e.name for e in r.elements]
    # Any MessagePack decoder reads the frame as the four items.
    lid, seq, t_ns, data = msgspec.msgpack.decode(frame)
    assert (lid, seq, t_ns, len(data)) == (r.layout_id, meta["seq"], meta["t_ns"], r.size)
    f = decode_frame(frame)
    assert (f.layout_id, f.seq, f.t_ns, bytes(f.data)) == (lid, seq, t_ns, data)
    # The minimal encoding of the same items (another encoder's) reads the same.
    minimal = msgspec.msgpack.encode((lid, seq, t_ns, data))
    assert len(minimal) <= len(frame)
    g = RegionCodec(DataVector(layout()), meta["region"]).check(minimal)
    assert (g.layout_id, g.seq, g.t_ns, bytes(g.data)) == (lid, seq, t_ns, data)


@pytest.mark.parametrize("name", NAMES)
def test_decode_bit_exact(name: str) -> None:
    meta, frame = load(name)
    dv = DataVector(layout())
    f = RegionCodec(dv, meta["region"]).apply(frame)
    assert (f.seq, f.t_ns) == (meta["seq"], meta["t_ns"])
    for element, value in meta["values"].items():
        spec = dv.layout.element(element)
        got = bytes(dv.buf[spec.offset : spec.offset + spec.size])
        assert got == element_bytes(spec, value), element
        # and as Python values, where JSON holds them as numbers
        if spec.enum is not None:
            assert dv.get_name(element) == value["name"]
        elif not spec.count and not is_bits(value):
            assert dv.get(element) == value and type(dv.get(element)) is type(value)
        elif spec.count and not any(is_bits(x) for x in value):
            assert dv.get(element).tolist() == value


def write_json_values(dv: DataVector, values: dict[str, Any]) -> None:
    """Write JSON values the way a node would: checked sets, raw bytes only for
    floats given by their bits (a Python float may not carry an f32 NaN's bits)."""
    for element, value in values.items():
        spec = dv.layout.element(element)
        items = value if spec.count else [value]
        if any(is_bits(x) for x in items):
            dv.buf[spec.offset : spec.offset + spec.size] = element_bytes(spec, value)
        elif spec.enum is not None:
            dv.set(element, value["name"])
        else:
            dv.set(element, value)


@pytest.mark.parametrize("name", NAMES)
def test_reencode_identical(name: str) -> None:
    meta, frame = load(name)
    dv = DataVector(layout())
    write_json_values(dv, meta["values"])
    out = RegionCodec(dv, meta["region"]).encode(meta["seq"], meta["t_ns"])
    assert bytes(out) == frame


def test_worked_example_in_format_md() -> None:
    # FORMAT.md §9 walks through this vector byte by byte.
    _, frame = load("scalars_typical")
    text = (VECTORS.parent / "FORMAT.md").read_text()
    assert frame[:26].hex(" ") in text


# -- the tags of codecs/vectors/auth/ (FORMAT.md §6.1, §6.3, §8.1) --------------------

AUTH = VECTORS / "auth"
AUTH_NAMES = sorted(p.stem for p in AUTH.glob("*.json"))


def test_auth_vectors_present() -> None:
    assert sorted(p.stem for p in AUTH.glob("*.bin")) == AUTH_NAMES
    whats = (
        "cn_to_dn0",
        "clock_hello_dn0",
        "clock_query_dn0",
        "clock_reply_dn0",
        "events_cn",
        "run_hello",
        "run_answer",
        "bulk_frame",
    )
    assert sorted(f"{mac}_{w}" for mac in ("blake3", "hmac-sha256") for w in whats) == AUTH_NAMES


@pytest.mark.parametrize("name", AUTH_NAMES)
def test_auth_vector_by_hand(name: str) -> None:
    """Every key and tag from FORMAT.md's formulas alone (hashlib, hmac, blake3)."""
    import hashlib
    import hmac

    import blake3

    meta = json.loads((AUTH / f"{name}.json").read_text())
    sealed = (AUTH / f"{name}.bin").read_bytes()
    master = bytes.fromhex(meta["master_hex"])
    link_ctx = f"zplatform/2/link/{meta['vehicle']}/{meta['link']}"
    ch_ctx = f"zplatform/2/{meta['vehicle']}/{meta['mac']}/{meta['channel']}"
    assert (meta["link_context"], meta["channel_context"]) == (link_ctx, ch_ctx)
    link_key = hmac.new(master, link_ctx.encode(), hashlib.sha256).digest()
    ch_key = hmac.new(link_key, ch_ctx.encode(), hashlib.sha256).digest()
    assert (link_key.hex(), ch_key.hex()) == (meta["link_key_hex"], meta["channel_key_hex"])
    # The run's key (§6.1): the channel's, bound to the run word.
    word = meta["run"].to_bytes(8, "little")
    run_key = hmac.new(ch_key, b"zplatform/2/run/" + word, hashlib.sha256).digest()
    assert (word.hex(), run_key.hex()) == (meta["run_word_hex"], meta["run_key_hex"])
    body = bytes.fromhex(meta["message_hex"])
    # The header tag (§6.1): its own key, over the run word, the length and
    # the first 40 bytes.
    head_key = hmac.new(ch_key, b"zplatform/3/header/" + word, hashlib.sha256).digest()
    head = word + len(body).to_bytes(4, "little") + body[:40]
    assert (head_key.hex(), head.hex()) == (meta["header_key_hex"], meta["header_input_hex"])
    if meta["mac"] == "blake3":
        htag = blake3.blake3(head, key=head_key).digest(8)
        mac = blake3.blake3(body, key=run_key).digest(16)
    else:
        htag = hmac.new(head_key, head, hashlib.sha256).digest()[:8]
        mac = hmac.new(run_key, body, hashlib.sha256).digest()[:16]
    assert (htag.hex(), mac.hex()) == (meta["htag_hex"], meta["mac_hex"])
    tag = word + htag + mac
    assert tag.hex() == meta["tag_hex"] and sealed == body + tag
    assert len(body) == meta["message_size"]
    if "sample_hex" in meta:  # a bulk sample's summary (§6.1): header, length, digest
        sample = bytes.fromhex(meta["sample_hex"])
        digest = blake3.blake3(sample[32:]).digest()
        assert body == sample[:32] + len(sample).to_bytes(4, "little") + bytes(4) + digest


@pytest.mark.parametrize("name", AUTH_NAMES)
def test_auth_vector_by_the_platform(name: str) -> None:
    """The platform opens each vector and makes it again, byte for byte."""
    from zplatform.core.auth import KeySet, Run, RunError
    from zplatform.core.events import EventReader
    from zplatform.runtime.clocksync import ClockLink, ClockResponder, RunAsker

    meta = json.loads((AUTH / f"{name}.json").read_text())
    sealed = (AUTH / f"{name}.bin").read_bytes()
    mission = load_mission(VECTORS / "mission.yaml")
    mission.security.mac = meta["mac"]
    keys = KeySet.from_master(mission, bytes.fromhex(meta["master_hex"]))
    run = meta["run"]
    ch = keys.channel(meta["channel"], Run(run))
    body = bytes(ch.open(sealed))
    assert bytes(ch.seal(body)) == sealed
    if run:  # bound to another run, the receiver refuses it (§6.1)
        with pytest.raises(RunError):
            keys.channel(meta["channel"], Run(run + 1)).open(sealed)
    what = name.split("_", 1)[1]
    rrun = json.loads((AUTH / f"{meta['mac']}_clock_reply_dn0.json").read_text())["run"]
    if what == "cn_to_dn0":
        assert body == (VECTORS / "scalars_typical.bin").read_bytes()
    elif what in ("clock_query_dn0", "clock_hello_dn0"):
        reply = (AUTH / f"{meta['mac']}_clock_reply_dn0.bin").read_bytes()
        t2, t3 = 1_700_000_000_001_500_000, 1_700_000_000_001_520_000
        cn = keys.for_node("cn")
        assert ClockResponder(mission, cn, Run(rrun)).answer(sealed, t2, t3) == reply
        if run:  # a query naming another run than the server's is refused
            assert ClockResponder(mission, cn, Run(rrun + 1)).answer(sealed, t2, t3) is None
    elif what == "clock_reply_dn0":
        nonce = bytes(range(0xA0, 0xB0))
        link = ClockLink(mission, "dn0", keys.for_node("dn0"))
        link.query(1_700_000_000_000_000_000)
        link._sent = (nonce, 1_700_000_000_000_000_000)  # the vector's query
        assert link.check(sealed, nonce) == (
            1_700_000_000_000_000_000,
            1_700_000_000_001_500_000,
            1_700_000_000_001_520_000,
        )
        assert link.run.epoch == run  # the reply told dn0 the run
    elif what == "run_hello":  # the commander answers it with the answer vector (§6.3)
        answer = (AUTH / f"{meta['mac']}_run_answer.bin").read_bytes()
        cn = keys.for_node("cn")
        assert ClockResponder(mission, cn, Run(rrun)).answer(sealed, 0, 0) == answer
    elif what == "run_answer":
        asker = RunAsker(keys.for_node("tool"))
        asker.hello()
        asker._nonce = bytes(range(0xA0, 0xB0))  # the vector's hello
        assert asker.check(sealed) and asker.run.epoch == run == rrun
    elif what == "bulk_frame":  # dn2's intake takes the sample; header and array read back
        from zplatform.runtime.bulk import decode_sample

        ch = mission.bulk[0]
        dn2 = keys.for_node("dn2").channel("bulk_frame/dn2", Run(run))
        sample = bytes.fromhex(meta["sample_hex"]) + sealed[-32:]  # its one reader's tag
        hdr, arr = decode_sample(sample, ch, dn2)
        assert (hdr.layout_id, hdr.seq, hdr.loop) == (ch.layout_id, 7, 70)
        assert hdr.t_ns == 1_700_000_000_000_000_000
        assert arr.tobytes() == bytes(range(16))
    else:
        e, verified = EventReader(mission, keys).read("rocket/cn/events", sealed)
        assert verified is True and (e.node, e.id) == ("cn", "cmd_accepted")
