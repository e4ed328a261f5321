#!/usr/bin/env python3
"""Regenerate the golden frames in ``codecs/vectors/`` (run by hand only).

    python codecs/generate_vectors.py          # from the repository root

Each vector is two files: ``<name>.bin``, the exact frame bytes, and
``<name>.json``, what a decoder must get out of them (format: FORMAT.md §8).
The frames come from ``vectors/mission.yaml`` through the platform's own
``RegionCodec``; the JSON values are read back from the frame bytes here,
element by element, with ``struct``, not from the Data Vector.

``vectors/auth/`` holds the tags (FORMAT.md §6.1, §6.3, §8.1): a region
frame, a clock query (a hello naming no run, and one naming the run) and
its reply, an event record, and a ground's run hello and its answer,
each tagged under both MACs with keys derived from a published master key
(never a real key: the platform refuses it), in the control node's run
``RUN`` (the hellos in run 0).
Each ``<mac>_<what>.bin`` is the message with its tag; its ``.json``
gives every key and context string on the way.

``tests/unit/test_golden_vectors.py`` decodes and re-encodes every vector and
never regenerates them. Regenerating changes pinned bytes: do it only for a
deliberate wire-format change, and say so where the change is recorded.

This is a script, not a package: there is no ``codecs/__init__.py`` (a
package named ``codecs`` would shadow the standard library's).
"""

from __future__ import annotations

import json
import math
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
VECTORS = HERE / "vectors"
MISSION = VECTORS / "mission.yaml"
sys.path.insert(0, str(HERE.parent))  # run from a checkout without installing

from zplatform import DataVector, ElementSpec, Layout, RegionCodec, load_mission  # noqa: E402
from zplatform.core.auth import (  # noqa: E402
    HEADER_LEN,
    HTAG_LEN,
    MACS,
    NO_RUN,
    RUN_LEN,
    Channel,
    KeySet,
    Run,
    channel_key,
    header_key,
    link_of,
    run_key,
)
from zplatform.core.datavector import _region_descriptor  # noqa: E402
from zplatform.core.events import Event, Severity, encode_event  # noqa: E402

T0 = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z in ns


@dataclass(frozen=True)
class Bits:
    """A float given by its IEEE-754 bit pattern (NaN payloads, signed zero, inf)."""

    bits: int


@dataclass
class Vector:
    name: str
    region: str
    seq: int
    t_ns: int
    description: str
    values: dict[str, Any] = field(default_factory=dict)  # unnamed elements stay 0


U_MAX = {"u8": 255, "u16": 65535, "u32": 2**32 - 1, "u64": 2**64 - 1}
I_MIN = {"i8": -128, "i16": -32768, "i32": -(2**31), "i64": -(2**63)}
I_MAX = {k: -v - 1 for k, v in I_MIN.items()}
F32_MAX = 3.4028234663852886e38
F64_MAX = 1.7976931348623157e308

VECTOR_LIST = [
    # -- cn_to_dn0: every scalar type ------------------------------------------
    Vector("scalars_zero", "cn_to_dn0", 0, 0, "every scalar 0 / false / first enum name"),
    Vector(
        "scalars_typical",
        "cn_to_dn0",
        1,
        T0,
        "ordinary values of every scalar type",
        {
            "s_u8": 200,
            "s_u16": 0x1234,
            "s_u32": 0xDEADBEEF,
            "s_u64": 0x0123456789ABCDEF,
            "s_i8": -5,
            "s_i16": -1234,
            "s_i32": -123456789,
            "s_i64": -1234567890123456789,
            "s_f32": 1.5,
            "s_f64": -0.1,
            "s_bool": True,
            "s_valve": "OPEN",
        },
    ),
    Vector(
        "scalars_max",
        "cn_to_dn0",
        2**64 - 1,
        2**63 - 1,
        "every integer at its maximum, largest finite floats, largest seq and t_ns",
        {
            **{f"s_{t}": v for t, v in U_MAX.items()},
            **{f"s_{t}": v for t, v in I_MAX.items()},
            "s_f32": F32_MAX,
            "s_f64": F64_MAX,
            "s_bool": True,
            "s_valve": "FAULT",
        },
    ),
    Vector(
        "scalars_min",
        "cn_to_dn0",
        2**32,
        -(2**63),
        "every integer at its minimum, most negative finite floats, smallest t_ns",
        {
            **{f"s_{t}": 0 for t in U_MAX},
            **{f"s_{t}": v for t, v in I_MIN.items()},
            "s_f32": -F32_MAX,
            "s_f64": -F64_MAX,
            "s_bool": False,
            "s_valve": "CLOSED",
        },
    ),
    Vector(
        "scalars_minus_one",
        "cn_to_dn0",
        3,
        T0 + 10_000_000,
        "signed -1 (all bits set), negative zero floats",
        {
            **{f"s_{t}": -1 for t in I_MIN},
            "s_f32": Bits(0x8000_0000),
            "s_f64": Bits(0x8000_0000_0000_0000),
        },
    ),
    Vector(
        "scalars_nan_quiet",
        "cn_to_dn0",
        4,
        T0 + 20_000_000,
        "quiet NaNs with non-default payloads (f32 positive, f64 negative)",
        {"s_f32": Bits(0x7FC1_2345), "s_f64": Bits(0xFFF8_0000_00AB_CDEF)},
    ),
    Vector(
        "scalars_nan_signalling",
        "cn_to_dn0",
        5,
        T0 + 30_000_000,
        "signalling NaNs (quiet bit clear): must pass unchanged, not be quieted",
        {"s_f32": Bits(0xFF80_0001), "s_f64": Bits(0x7FF0_0000_0000_0001)},
    ),
    Vector(
        "scalars_inf",
        "cn_to_dn0",
        6,
        T0 + 40_000_000,
        "+inf f32, -inf f64",
        {"s_f32": Bits(0x7F80_0000), "s_f64": Bits(0xFFF0_0000_0000_0000)},
    ),
    Vector(
        "scalars_subnormal",
        "cn_to_dn0",
        7,
        T0 + 50_000_000,
        "smallest positive subnormals",
        {"s_f32": 1e-45, "s_f64": 5e-324},
    ),
    # -- cn_to_dn1: arrays --------------------------------------------------
    Vector(
        "arrays_typical",
        "cn_to_dn1",
        100,
        T0 + 1_000_000_000,
        "arrays of every type in layout order; a u16 enum (value 256)",
        {
            "a_u8": [1, 2, 255],
            "a_u16": [0x0102, 0xFFFE],
            "a_u32": [1, 0x80000000],
            "a_u64": [2**32, 2**63],
            "a_i8": [-1, 127],
            "a_i16": [-300, 0, 300],
            "a_i32": [-(2**31), 7],
            "a_i64": [-2, 2**40],
            "a_f32": [0.5, -1.25, Bits(0x7FC0_0000), Bits(0x8000_0000)],
            "a_f64": [Bits(0x7FF0_0000_0000_0000), Bits(0xFFF0_0000_0000_0000), 1e-300],
            "a_bool": [True, False, True],
            "a_mode": "M256",
        },
    ),
    Vector(
        "arrays_limits",
        "cn_to_dn1",
        101,
        T0 + 1_010_000_000,
        "integer arrays holding their type's minimum then maximum",
        {
            "a_u8": [0, 255, 128],
            "a_u16": [0, 65535],
            "a_u32": [0, 2**32 - 1],
            "a_u64": [0, 2**64 - 1],
            "a_i8": [-128, 127],
            "a_i16": [-32768, 32767, -1],
            "a_i32": [-(2**31), 2**31 - 1],
            "a_i64": [-(2**63), 2**63 - 1],
            "a_f32": [F32_MAX, -F32_MAX, 1e-45, Bits(0x7F80_0001)],
            "a_f64": [F64_MAX, -F64_MAX, Bits(0x7FF8_0000_0000_0001)],
            "a_bool": [False, True, False],
            "a_mode": "M0",
        },
    ),
    # -- bin header boundaries -------------------------------------------------
    Vector(
        "bin8_max_255",
        "cn_to_dn2",
        1000,
        T0 + 2_000_000_000,
        "255 data bytes: the largest frame with a bin8 header (c4 ff)",
        {"dn2_final": True, "b8_bytes": list(range(253)), "b8_flag": True},
    ),
    Vector(
        "bin16_min_256",
        "cn_to_dn3",
        1001,
        T0 + 2_010_000_000,
        "256 data bytes: the smallest frame with a bin16 header (c5 01 00)",
        {
            "b16_count": 2**40 + 5,
            "b16_samples": [i * 0.25 - 7.0 for i in range(61)],
            "b16_tail": [1, 2, 3],
        },
    ),
    Vector(
        "bin16_max_65535",
        "cn_to_dn4",
        1002,
        T0 + 2_020_000_000,
        "65535 data bytes: the largest frame with a bin16 header (c5 ff ff)",
        {"b16max_bytes": [1, 2, 3] + [0] * 65530 + [255]},
    ),
    Vector(
        "bin32_min_65536",
        "cn_to_dn5",
        1003,
        T0 + 2_030_000_000,
        "65536 data bytes: the smallest frame with a bin32 header (c6 00 01 00 00)",
        {"b32_words": list(range(16)) + [0] * 32750 + [65535], "b32_tail": 7},
    ),
    Vector(
        "tiny_1",
        "cn_to_dn6",
        1004,
        T0 + 2_040_000_000,
        "one data byte: a region of the platform's final-loop flag alone",
        {"dn6_final": True},
    ),
]


# -- writing values into a Data Vector -------------------------------------------------


def write_value(dv: DataVector, spec: ElementSpec, value: Any) -> None:
    """Pack ``value`` into ``spec``'s bytes (floats given as Bits go in raw)."""
    items = value if spec.count else [value]
    if len(items) != max(spec.count, 1):
        raise SystemExit(f"{spec.name}: expected {spec.count} values, got {len(items)}")
    st = spec.scalar
    fmt = struct.Struct("<" + st.struct)
    raw = struct.Struct("<I" if st.size == 4 else "<Q")
    for i, v in enumerate(items):
        off = spec.offset + i * st.size
        if isinstance(v, Bits):
            raw.pack_into(dv.buf, off, v.bits)
            continue
        if spec.enum is not None:
            v = spec.enum.index(v) if isinstance(v, str) else v
            if not 0 <= v < len(spec.enum):
                raise SystemExit(f"{spec.name}: {v} is not an enum index")
        elif not st.fits(v):
            raise SystemExit(f"{spec.name}: {v!r} does not fit {st.name}")
        fmt.pack_into(dv.buf, off, v)


# -- reading values back from the frame's data bytes --------------------------------------


def float_json(size: int, bits: int) -> Any:
    """A float as a JSON number when that is exact and unambiguous, else its bits."""
    x = struct.unpack("<f" if size == 4 else "<d", bits.to_bytes(size, "little"))[0]
    if math.isfinite(x) and not (x == 0.0 and math.copysign(1.0, x) < 0):
        return x
    return {"f32_bits" if size == 4 else "f64_bits": f"0x{bits:0{2 * size}x}"}


def json_value(spec: ElementSpec, data: bytes, region_offset: int) -> Any:
    st = spec.scalar
    base = spec.offset - region_offset
    out: list[Any] = []
    for i in range(max(spec.count, 1)):
        chunk = data[base + i * st.size : base + (i + 1) * st.size]
        if st.kind == "float":
            out.append(float_json(st.size, int.from_bytes(chunk, "little")))
        elif st.kind == "bool":
            if chunk not in (b"\x00", b"\x01"):
                raise SystemExit(f"{spec.name}: bool byte {chunk!r} is not 0 or 1")
            out.append(chunk == b"\x01")
        else:
            v = struct.unpack("<" + st.struct, chunk)[0]
            out.append({"name": spec.enum[v], "value": v} if spec.enum is not None else v)
    return out if spec.count else out[0]


def to_json(v: Vector, layout: Layout, frame: bytes, data: bytes) -> str:
    r = layout.region(v.region)
    head = {
        "name": v.name,
        "description": v.description,
        "region": v.region,
        "descriptor": _region_descriptor(r.name, r.elements),
        "layout_id": r.layout_id,
        "layout_id_hex": f"0x{r.layout_id:08x}",
        "seq": v.seq,
        "t_ns": v.t_ns,
        "data_size": r.size,
        "frame_size": len(frame),
        "frame_head_hex": frame[: min(len(frame), 64)].hex(),
    }
    lines = [f"  {json.dumps(k)}: {json.dumps(x)}," for k, x in head.items()]
    vals = [
        f"    {json.dumps(e.name)}: "
        f"{json.dumps(json_value(e, data, r.offset), separators=(',', ':'), allow_nan=False)}"
        for e in r.elements
    ]
    return "{\n" + "\n".join(lines) + '\n  "values": {\n' + ",\n".join(vals) + "\n  }\n}\n"


# -- tags (vectors/auth/) ----------------------------------------------------------------

AUTH = VECTORS / "auth"
MASTER = bytes.fromhex("5a9c4e1f0b7d3a6e82c5f19d4b07e3a8c6d2f5910e8b4a7c3d6f1e0b9a5c8d27")
NONCE = bytes(range(0xA0, 0xB0))
CLOCK_QUERY = struct.Struct("<2sBB16sq")
CLOCK_REPLY = struct.Struct("<2sBB16sqqq")
RUN_HELLO = struct.Struct("<2sB16s")
RUN_ANSWER = struct.Struct("<2sB16sQ")
RUN = T0 - 0x5A5A5A  # the CN's run (a cn_epoch: a clock reading, its low 24 bits random)


def bulk_sample(mission: object) -> bytes:
    """The vectors mission's bulk channel ``frame`` (``u8[16]``, dn1's) as its
    owner publishes it untagged (zplatform/runtime/bulk.py): the 32-byte
    header (layout_id, flags 0, seq 7, loop 70, t_ns T0), then bytes 0..15."""
    (ch,) = mission.bulk  # type: ignore[attr-defined]
    return struct.pack("<IIQQq", ch.layout_id, 0, 7, 70, T0) + bytes(range(ch.nbytes))


def bulk_summary(sample: bytes) -> bytes:
    """What a bulk sample's tag for one reader covers (FORMAT.md §6.1): its
    32-byte header, its length (u32) and a u32 0, then BLAKE3-256 of its
    array."""
    import blake3

    return sample[:32] + struct.pack("<II", len(sample), 0) + blake3.blake3(sample[32:]).digest()


def auth_messages(frame: bytes, bulk: bytes = b"") -> list[tuple[str, str, str, int, bytes]]:
    """``(what, channel, description, run, message)`` of every tagged vector."""
    event = Event("cn", 0, T0, int(Severity.COMMAND), "cmd_accepted", "command LAUNCH #2 accepted")
    query = CLOCK_QUERY.pack(b"ZQ", 1, 0, NONCE, T0)
    return [
        ("cn_to_dn0", "cn_to_dn0", "vector scalars_typical as a trigger to dn0", RUN, frame),
        (
            "clock_hello_dn0",
            "clock_dn0_to_cn",
            "dn0's first clock query, naming no run (a hello): nonce a0..af, t1 = T0",
            NO_RUN,
            query,
        ),
        (
            "clock_query_dn0",
            "clock_dn0_to_cn",
            "the same query naming the run dn0 knows",
            RUN,
            query,
        ),
        (
            "clock_reply_dn0",
            "clock_cn_to_dn0",
            "the CN's reply to either: t2 = T0 + 1.5 ms, t3 = T0 + 1.52 ms, in its run",
            RUN,
            CLOCK_REPLY.pack(b"ZR", 1, 0, NONCE, T0, T0 + 1_500_000, T0 + 1_520_000),
        ),
        ("events_cn", "events_cn", "an event record of the CN", RUN, encode_event(event)),
        (
            "run_hello",
            "run_hello",
            "a ground's run hello (§6.3), in no run: nonce a0..af",
            NO_RUN,
            RUN_HELLO.pack(b"ZH", 1, NONCE),
        ),
        (
            "run_answer",
            "run_answer",
            "the commander's answer to it: the nonce echoed, its run, tagged in that run",
            RUN,
            RUN_ANSWER.pack(b"ZA", 1, NONCE, RUN),
        ),
        (
            "bulk_frame",
            "bulk_frame/dn2",
            "the summary of a sample of bulk channel frame (u8[16], dn1's; header seq 7, "
            "loop 70, t_ns T0, then bytes 0..15: sample_hex), tagged for its reader dn2 "
            "in the run dn1 follows; on the wire: sample || this tag",
            RUN,
            bulk_summary(bulk) if bulk else b"",
        ),
    ]


def write_auth_vectors(mission: object, frame: bytes) -> None:
    AUTH.mkdir(exist_ok=True)
    vehicle = mission.vehicle  # type: ignore[attr-defined]
    keys = KeySet.from_master(mission, MASTER)  # type: ignore[arg-type]
    written = set()
    for mac in MACS:
        for what, name, description, run, body in auth_messages(frame, bulk_sample(mission)):
            link = link_of(name)
            link_key = keys.link_key(link)
            ch_key = channel_key(link_key, vehicle, mac, name)
            sealed = bytes(Channel(link_key, vehicle, name, mac, Run(run)).seal(body))
            tag = sealed[len(body) :]
            word = run.to_bytes(8, "little")
            vec = f"{mac}_{what}"
            doc = {
                "name": vec,
                "description": description,
                "mac": mac,
                "vehicle": vehicle,
                "master_hex": MASTER.hex(),
                "link": link,
                "link_context": f"zplatform/2/link/{vehicle}/{link}",
                "link_key_hex": link_key.hex(),
                "channel": name,
                "channel_context": f"zplatform/2/{vehicle}/{mac}/{name}",
                "channel_key_hex": ch_key.hex(),
                "run": run,
                "run_word_hex": run.to_bytes(8, "little").hex(),
                "run_key_hex": run_key(ch_key, run).hex(),
                "header_context_hex": (b"zplatform/3/header/" + word).hex(),
                "header_key_hex": header_key(ch_key, run).hex(),
                "header_input_hex": (
                    word + len(body).to_bytes(4, "little") + body[:HEADER_LEN]
                ).hex(),
                "message_size": len(body),
                "message_hex": body.hex(),
                "tag_hex": tag.hex(),
                "htag_hex": tag[RUN_LEN : RUN_LEN + HTAG_LEN].hex(),
                "mac_hex": tag[RUN_LEN + HTAG_LEN :].hex(),
            }
            if what == "bulk_frame":  # the sample the summary is of
                doc["sample_hex"] = bulk_sample(mission).hex()
            (AUTH / f"{vec}.bin").write_bytes(sealed)
            (AUTH / f"{vec}.json").write_text(json.dumps(doc, indent=2) + "\n")
            written.add(vec)
            print(f"auth/{vec:30} {len(sealed):6} bytes  tag {doc['tag_hex']}")
    for old in [*AUTH.glob("*.bin"), *AUTH.glob("*.json")]:
        if old.stem not in written:
            old.unlink()


# -- operator and station tags (vectors/operators/) ---------------------------------------

OPERATORS = VECTORS / "operators"
# (what, operator, station, command, seq, element, ref): a lock request and an approval.
OPERATOR_REQUESTS = (
    ("lock", "alice", "pad", "LOCK", 3, 0, 0),
    ("approve", "rso", "lounge", "APPROVE", 5, 0, 4),
)


def write_operator_vectors() -> None:
    """``<mac>_<what>.bin``: a ``gn_to_cn`` region frame (untagged by the
    uplink: §6.1 covers that) whose operator and station tags (§6.7) are
    made with keys derived from :data:`MASTER`; its ``.json`` every key,
    context and the covered bytes."""
    from zplatform.control.authority import IDENTITY_LINK, identity_key
    from zplatform.control.uplink import Uplink
    from zplatform.security.identities import sim_signer

    written = set()
    for mac in MACS:
        mission = load_mission(OPERATORS / "mission.yaml")
        mission.security.mac = mac
        keys = KeySet.from_master(mission, MASTER)
        base = keys.link_key(IDENTITY_LINK)
        vehicle = mission.vehicle
        for what, op, st, cmd, seq, element, ref in OPERATOR_REQUESTS:
            up = Uplink(mission, signer=sim_signer(keys, mission, op, st))
            frame = bytes(up.frame(cmd, seq, element, 0.0, T0, RUN, ref=ref))
            lay = up.req.layout
            r = lay.region("gn_to_cn")
            data = bytes(up.req.region_view("gn_to_cn"))
            covered = lay.element("gn_cmd_op_tag").offset - r.offset
            st_at = lay.element("gn_cmd_st_tag").offset - r.offset
            vec = f"{mac}_{what}"
            doc = {
                "name": vec,
                "description": f"{cmd} #{seq} by operator {op} at station {st}"
                + (f", approving ARM #{ref}" if ref else ""),
                "mac": mac,
                "vehicle": vehicle,
                "master_hex": MASTER.hex(),
                "operators_context": f"zplatform/2/link/{vehicle}/{IDENTITY_LINK}",
                "operators_key_hex": base.hex(),
                "operator": op,
                "operator_number": [o.name for o in mission.ground.operators].index(op) + 1,
                "operator_context": f"zplatform/2/{vehicle}/operator/{op}/1",
                "operator_key_hex": identity_key(base, vehicle, "operator", op, 1).hex(),
                "station": st,
                "station_number": [s.name for s in mission.ground.stations].index(st) + 1,
                "station_context": f"zplatform/2/{vehicle}/station/{st}/1",
                "station_key_hex": identity_key(base, vehicle, "station", st, 1).hex(),
                "command": cmd,
                "seq": seq,
                "run": RUN,
                "t_ns": T0,
                "ref": ref,
                "data_offset": len(frame) - len(data),
                "covered_size": covered,
                "covered_hex": data[:covered].hex(),
                "operator_tag_hex": data[covered : covered + 16].hex(),
                "station_tag_hex": data[st_at : st_at + 16].hex(),
                "frame_size": len(frame),
            }
            (OPERATORS / f"{vec}.bin").write_bytes(frame)
            (OPERATORS / f"{vec}.json").write_text(json.dumps(doc, indent=2) + "\n")
            written.add(vec)
            print(
                f"operators/{vec:25} {len(frame):6} bytes  operator tag {doc['operator_tag_hex']}"
            )
    for old in [*OPERATORS.glob("*.bin"), *OPERATORS.glob("*.json")]:
        if old.stem not in written:
            old.unlink()


def main() -> None:
    mission = load_mission(MISSION)
    layout = Layout.for_node(mission, "cn")
    names = [v.name for v in VECTOR_LIST]
    assert len(set(names)) == len(names), "vector names repeat"
    for old in [*VECTORS.glob("*.bin"), *VECTORS.glob("*.json")]:
        if old.stem not in names:
            old.unlink()
            print(f"removed {old.name}")
    for v in VECTOR_LIST:
        dv = DataVector(layout)  # all zero: the mission gives no initial values
        region = layout.region(v.region)
        unknown = set(v.values) - {e.name for e in region.elements}
        if unknown:
            raise SystemExit(f"{v.name}: not in region {v.region}: {sorted(unknown)}")
        for name, value in v.values.items():
            write_value(dv, layout.element(name), value)
        frame = bytes(RegionCodec(dv, v.region).encode(v.seq, v.t_ns))
        data = bytes(dv.region_view(v.region))
        (VECTORS / f"{v.name}.bin").write_bytes(frame)
        (VECTORS / f"{v.name}.json").write_text(to_json(v, layout, frame, data))
        print(f"{v.name:24} {v.region:10} {len(frame):6} bytes  layout_id 0x{region.layout_id:08x}")
    write_auth_vectors(mission, (VECTORS / "scalars_typical.bin").read_bytes())
    write_operator_vectors()


if __name__ == "__main__":
    main()
