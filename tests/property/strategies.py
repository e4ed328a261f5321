"""Hypothesis strategies shared by the property tests (one module, as in attrs).

Sections are independent; add new ones at the end.
"""

from __future__ import annotations

import struct
from typing import Any

import msgspec
from hypothesis import strategies as st

from zplatform.config import CMD_NAMES
from zplatform.config.types import SCALAR_TYPES, ScalarType
from zplatform.core.datavector import ElementSpec, RegionSpec

# ---------------------------------------------------------------------------
# State machines and operator commands (statemachine.py, commands.py)

# The mission elements random state machines read and write: name -> (type, enum).
SM_ELEMENTS: dict[str, tuple[str, list[str] | None]] = {
    "x": ("u8", None),
    "z": ("i32", None),
    "w": ("f64", None),
    "y": ("f32", None),
    "flag": ("bool", None),
    "mode": ("enum", ["P", "Q", "R"]),
}
_ORDER_OPS = ["==", "!=", "<", "<=", ">", ">="]
_EQ_OPS = ["==", "!="]
COMMANDS = [c for c in CMD_NAMES if c != "NONE"]
HAZARDOUS_CHOICES = ["LAUNCH", "ABORT", "WRITE", "NOOP"]


def element_values(name: str) -> st.SearchStrategy[Any]:
    """Values that fit SM_ELEMENTS[name] (as a config or ``DataVector.set`` takes them)."""
    typ, enum = SM_ELEMENTS[name]
    if enum is not None:
        return st.sampled_from(enum)
    if typ == "bool":
        return st.booleans()
    if typ == "u8":
        return st.integers(0, 255)
    if typ == "i32":
        return st.integers(-(2**31), 2**31 - 1)
    if typ == "f32":
        return st.floats(-1e6, 1e6, allow_nan=False, width=32)
    return st.floats(-1e9, 1e9, allow_nan=False)


@st.composite
def conditions(draw: st.DrawFn) -> dict[str, Any]:
    """A transition condition on a mission element or on ``cn_cmd``."""
    if draw(st.booleans()):
        return {"element": "cn_cmd", "op": "==", "value": draw(st.sampled_from(COMMANDS))}
    name = draw(st.sampled_from(sorted(SM_ELEMENTS)))
    typ, enum = SM_ELEMENTS[name]
    ops = _EQ_OPS if enum is not None or typ == "bool" else _ORDER_OPS
    return {"element": name, "op": draw(st.sampled_from(ops)), "value": draw(element_values(name))}


@st.composite
def state_machine_missions(draw: st.DrawFn) -> str:
    """YAML text of a valid mission with a random state machine.

    2-6 states ``S0..``; each with 0-3 actions on mission elements (at 0-0.1 s)
    and 0-4 transitions (conditions or ``after_s`` 0-0.1 s) to random states
    (``after_s: 0`` only to a later state: a cycle of those is refused at load);
    a random whitelist (ARM always allowed where a hazardous command is) and
    hazardous set.
    """
    n = draw(st.integers(1, 6))
    names = [f"S{i}" for i in range(n)]
    states: dict[str, Any] = {}
    for s in names:
        actions = []
        for _ in range(draw(st.integers(0, 3))):
            el = draw(st.sampled_from(sorted(SM_ELEMENTS)))
            actions.append(
                {
                    "element": el,
                    "value": draw(element_values(el)),
                    "at_s": draw(st.sampled_from([0, 0, 0.01, 0.025, 0.05, 0.1])),
                }
            )
        transitions = []
        for _ in range(draw(st.integers(0, 4))):
            to = draw(st.sampled_from(names))
            if draw(st.integers(0, 3)) == 0:
                after = draw(st.sampled_from([0, 0.01, 0.05, 0.1]))
                if after == 0 and names.index(to) <= names.index(s):
                    after = 0.01
                transitions.append({"after_s": after, "to": to})
            else:
                transitions.append({**draw(conditions()), "to": to})
        states[s] = {"actions": actions, "transitions": transitions}
    hazardous = draw(st.lists(st.sampled_from(HAZARDOUS_CHOICES), unique=True, max_size=2))
    whitelist: dict[str, list[str]] = {}
    for s in names:
        if draw(st.booleans()):
            allowed = draw(st.lists(st.sampled_from(COMMANDS), unique=True))
            if any(h in allowed for h in hazardous) and "ARM" not in allowed:
                allowed.append("ARM")
            whitelist[s] = allowed
    mission = {
        "mission": "prop",
        "nodes": {"cn": {}, "dn0": {}, "gn": {}},
        "regions": {
            "cn": [
                {"name": k, "type": t, **({"enum": e} if e else {})}
                for k, (t, e) in SM_ELEMENTS.items()
            ],
            "dn0_to_cn": [{"name": "pressure", "type": "f32"}],
        },
        "state_machine": {"initial": draw(st.sampled_from(names)), "states": states},
        "commands": {"whitelist": whitelist, "hazardous": hazardous},
    }
    # PyYAML writes 1e-09 as 1.0e-09: JSON's 1e-09 would read back as a string
    # (YAML 1.1 floats need a dot).
    return msgspec.yaml.encode(mission).decode()


# One loop's inputs: (command or None, seq step, element index, value, element write or None).
LoopInput = tuple[str | None, int, int, float, tuple[str, Any] | None]


@st.composite
def loop_inputs(draw: st.DrawFn) -> LoopInput:
    """What happens in one CN loop: maybe a command request (with a sequence
    step that may replay, an element index that may not exist, any f64), maybe
    a write of a mission element."""
    cmd = draw(st.none() | st.sampled_from(COMMANDS))
    seq_step = draw(st.sampled_from([1, 1, 1, 2, 0, -1]))
    idx = draw(st.integers(0, 40))
    value = draw(st.floats() | st.integers(-3, 300).map(float))
    write = None
    if draw(st.booleans()):
        el = draw(st.sampled_from(sorted(SM_ELEMENTS)))
        write = (el, draw(element_values(el)))
    return cmd, seq_step, idx, value, write


# ---------------------------------------------------------------------------
# Data Vector layouts, region bytes and frame headers (datavector.py, codec.py)

_SCALARS = list(SCALAR_TYPES)
# Float bit patterns worth forcing: zeros, infinities, quiet and signalling
# NaNs with payloads, the smallest subnormal, the largest finite value.
_F32_SPECIAL = [
    0x0,
    0x80000000,
    0x7F800000,
    0xFF800000,
    0x7FC00000,
    0x7FC12345,
    0xFFC00001,
    0x7F800001,
    0xFFBFFFFF,
    0x00000001,
    0x7F7FFFFF,
]
_F64_SPECIAL = [
    0x0,
    0x8000000000000000,
    0x7FF0000000000000,
    0xFFF0000000000000,
    0x7FF8000000000000,
    0x7FF8000000012345,
    0xFFF0000000000001,
    0x7FF0000000000001,
    0x0000000000000001,
    0x7FEFFFFFFFFFFFFF,
]
_IDENT = st.from_regex(r"\A[A-Z][A-Z0-9_]{0,5}\Z")


@st.composite
def element_types(draw: st.DrawFn) -> dict[str, Any]:
    """The type part of one element config: ``{"type": ...}`` or ``{"enum": [...]}``:
    a scalar of any of the 11 types, a fixed array of one, or an enum (rarely
    with more than 256 names, so stored as u16)."""
    kind = draw(st.sampled_from(["scalar", "scalar", "array", "enum"]))
    if kind == "enum":
        if draw(st.integers(0, 9)) == 0:
            return {"enum": [f"V{i}" for i in range(draw(st.integers(257, 300)))]}
        return {"enum": draw(st.lists(_IDENT, min_size=1, max_size=5, unique=True))}
    scalar = draw(st.sampled_from(_SCALARS))
    if kind == "array":
        return {"type": f"{scalar}[{draw(st.integers(1, 9))}]"}
    return {"type": scalar}


@st.composite
def vector_missions(draw: st.DrawFn) -> str:
    """YAML text of a random valid mission for Data Vector and codec tests:
    0-2 device nodes, maybe a ground node, and 1-6 random elements in a random
    subset of the valid regions (``cn`` always)."""
    n_dn = draw(st.integers(0, 2))
    ground = draw(st.booleans())
    nodes: dict[str, Any] = {"cn": {}, **{f"dn{i}": {} for i in range(n_dn)}}
    valid = ["cn"] + [r for i in range(n_dn) for r in (f"cn_to_dn{i}", f"dn{i}_to_cn")]
    if ground:
        nodes["gn"] = {}
        valid.append("gn_to_cn")
    chosen = ["cn"] + [r for r in valid[1:] if draw(st.booleans())]
    regions: dict[str, list[dict[str, Any]]] = {}
    k = 0
    for region in chosen:
        elements = []
        for _ in range(draw(st.integers(1, 6))):
            elements.append({"name": f"e{k}", **draw(element_types())})
            k += 1
        regions[region] = elements
    mission = {"mission": "prop", "nodes": nodes, "regions": regions}
    return msgspec.yaml.encode(mission).decode()


def _pack(fmt: str) -> Any:
    s = struct.Struct("<" + fmt)
    return s.pack


def scalar_item_bytes(scalar: ScalarType, enum: tuple[str, ...] | None) -> st.SearchStrategy[bytes]:
    """The little-endian bytes of one valid item: ints in range, bool 0/1, an
    enum index below its name count, and floats as *any* bit pattern
    (NaN payloads included)."""
    if enum is not None:
        return st.integers(0, len(enum) - 1).map(_pack(scalar.struct))
    if scalar.kind == "bool":
        return st.sampled_from([b"\x00", b"\x01"])
    if scalar.kind == "int":
        assert scalar.lo is not None and scalar.hi is not None
        return st.integers(scalar.lo, scalar.hi).map(_pack(scalar.struct))
    bits = 8 * scalar.size
    special = _F32_SPECIAL if bits == 32 else _F64_SPECIAL
    raw = st.integers(0, (1 << bits) - 1) | st.sampled_from(special)
    return raw.map(_pack("I" if bits == 32 else "Q"))


def element_bytes(spec: ElementSpec) -> st.SearchStrategy[bytes]:
    """The bytes of one element: ``count`` items back to back (1 for a scalar)."""
    n = max(spec.count, 1)
    item = scalar_item_bytes(spec.scalar, spec.enum)
    return st.lists(item, min_size=n, max_size=n).map(b"".join)


def region_bytes(region: RegionSpec) -> st.SearchStrategy[bytes]:
    """A valid value for every element of ``region``, as the region's bytes."""
    return st.tuples(*(element_bytes(e) for e in region.elements)).map(b"".join)


frame_headers = st.tuples(
    st.integers(0, 2**32 - 1), st.integers(0, 2**64 - 1), st.integers(-(2**63), 2**63 - 1)
)
"""``(layout_id, seq, t_ns)`` anywhere in their ranges."""


@st.composite
def mutated(draw: st.DrawFn, frame: bytes) -> bytes:
    """``frame`` with a few random edits: byte flips, cuts, insertions, appends."""
    buf = bytearray(frame)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "flip", "cut", "insert", "append"]))
        if op == "append" or not buf:
            buf += draw(st.binary(min_size=1, max_size=8))
            continue
        i = draw(st.integers(0, len(buf) - 1))
        if op == "flip":
            buf[i] ^= draw(st.integers(1, 255))
        elif op == "cut":
            del buf[i : i + draw(st.integers(1, 16))]
        else:
            buf[i:i] = draw(st.binary(min_size=1, max_size=8))
    return bytes(buf)
