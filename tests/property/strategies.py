"""Hypothesis strategies shared by the property tests (one module, as in attrs).

Sections are independent; add new ones at the end.
"""

from __future__ import annotations

from typing import Any

import msgspec
from hypothesis import strategies as st

from zplatform.config import CMD_NAMES

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
    and 0-4 transitions (conditions or ``after_s`` 0-0.1 s) to random states;
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
                transitions.append(
                    {"after_s": draw(st.sampled_from([0, 0.01, 0.05, 0.1])), "to": to}
                )
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
