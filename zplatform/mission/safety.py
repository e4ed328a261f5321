"""Safety smells: a mission that loads fine but leaves a door open.

:func:`safety_warnings` looks at a mission that passed
:func:`zplatform.mission.load.load_mission` for what the loader cannot refuse (each
is legal, and sometimes meant) but an operator should know before flight:
``unprotected_mode``, ``no_safe_value``, ``pyrotechnic_without_hazardous``,
``plain_transport_with_hazardous``, ``control_node_cannot_resume``,
``fault_never_cleared``, each a
:class:`SafetyWarning` naming its YAML path. :func:`doors` lists what
``zplatform check`` prints besides: every element a WRITE may set and every
hazardous output, each with its states.

Contract: pure functions of the mission; they never raise for a smell
(``check --strict`` turns them into errors). The command smells apply only to
a mission with a ground node; the device smells import the devices' classes,
so :func:`safety_warnings` needs a mission loaded with its code.

Each smell, where and why: docs/missions.md#your-own-code (the table of smells).
"""

from __future__ import annotations

from typing import Literal

import msgspec

from ..config import CMD_NAMES, Mission
from ..control.commands import (
    protected_elements,
    refused_while_faulted,
    writable_elements,
    write_states,
)
from ..control.devices import Actuator
from ..control.interlocks import safe_value
from ..core.components import decode_component_config, load_component_class, mission_code_path

__all__ = ["HazardousOutput", "SafetyWarning", "WritableElement", "doors", "safety_warnings"]

WarningKind = Literal[
    "unprotected_mode",
    "no_safe_value",
    "pyrotechnic_without_hazardous",
    "plain_transport_with_hazardous",
    "control_node_cannot_resume",
    "fault_never_cleared",
]


class SafetyWarning(msgspec.Struct, frozen=True):
    """One safety smell: what (``kind``), where (``path``, the YAML path),
    and ``message`` (what it means and how to close it)."""

    kind: WarningKind
    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.message} - at `{self.path}`"


class WritableElement(msgspec.Struct, frozen=True):
    """An element a ground WRITE may set (``commands.writable``), the states
    it may be set in (:func:`zplatform.control.commands.write_states`), whether it
    needs ARM n, WRITE n+1 (``protected``), and the YAML path naming it."""

    element: str
    states: list[str]
    protected: bool
    path: str


class HazardousOutput(msgspec.Struct, frozen=True):
    """A hazardous output (``hazardous_outputs``): its element, the device
    node holding it, the states it may be driven in, its safe value and the
    YAML path naming it."""

    element: str
    node: str
    states: list[str]
    safe: int | float | bool
    path: str


def doors(mission: Mission) -> tuple[list[WritableElement], list[HazardousOutput]]:
    """What ``zplatform check`` lists: every element a WRITE may set, and
    every hazardous output, each with its states. Pure; raises nothing for a
    mission that loaded."""
    protected = set(protected_elements(mission))
    index = {name: i for i, name in enumerate(mission.commands.writable)}
    writable = [
        WritableElement(name, states, name in protected, f"$.commands.writable[{index[name]}]")
        for name, states in write_states(mission).items()
    ]
    table = {e.name: (r, e) for r, es in mission.regions.items() for e in es}
    outputs = []
    for i, h in enumerate(mission.hazardous_outputs):
        region, e = table[h.element]
        node = region.removeprefix("cn_to_").removesuffix("_to_cn")
        outputs.append(
            HazardousOutput(
                h.element, node, list(h.states), safe_value(e, h), f"$.hazardous_outputs[{i}]"
            )
        )
    return writable, outputs


def _write_allowed_somewhere(mission: Mission) -> bool:
    """Whether some state's whitelist lets WRITE through (an unlisted state
    allows every command)."""
    states = list(mission.state_machine.states) if mission.state_machine else ["IDLE"]
    wl = mission.commands.whitelist
    return any(s not in wl or "WRITE" in wl[s] for s in states)


def safety_warnings(mission: Mission) -> list[SafetyWarning]:
    """Every safety smell of ``mission`` (module doc), in YAML order:
    controllers, then devices, then the commands section, then security.

    ``mission`` must have loaded with its code (``load_mission(code=True)``):
    the actuators' classes are imported again here (already in
    ``sys.modules``) and their configs decoded. Raises nothing for a mission
    that loaded.
    """
    out: list[SafetyWarning] = []
    has_commands = mission.has_ground
    if has_commands and _write_allowed_somewhere(mission):
        writable = set(writable_elements(mission))
        protected = set(protected_elements(mission))
        for i, c in enumerate(mission.controllers):
            mode = f"{c.name}_mode"
            if mode in writable and mode not in protected:
                out.append(
                    SafetyWarning(
                        "unprotected_mode",
                        f"$.controllers[{i}]",
                        f"controller {c.name!r}: a plain WRITE of {mode} can enable or safe it "
                        "without confirmation; list it in commands.protected (or give the "
                        "mission a hazardous command: controller modes are then protected)",
                    )
                )
    code = mission_code_path(mission)
    pyros: list[str] = []
    for i, d in enumerate(mission.devices):
        where = f"$.devices[{i}]"
        cls = load_component_class(d.cls, object, f"{where}.class", pythonpath=code)
        if not issubclass(cls, Actuator):
            continue
        if cls.safe is Actuator.safe:
            out.append(
                SafetyWarning(
                    "no_safe_value",
                    where,
                    f"actuator {d.name!r} ({d.cls}) declares no safe value (its class does not "
                    "override Actuator.safe): a device node that loses its control node leaves "
                    "this output to the board's safe state",
                )
            )
        cfg = decode_component_config(cls.Config, d.config, f"{where}.config")
        if cls.pyrotechnic or getattr(cfg, "pyrotechnic", False) is True:
            pyros.append(d.name)
    if has_commands and pyros and not mission.commands.hazardous:
        commands = ", ".join(c for c in CMD_NAMES if c not in ("NONE", "ARM"))
        out.append(
            SafetyWarning(
                "pyrotechnic_without_hazardous",
                "$.commands.hazardous",
                f"the mission drives pyrotechnic outputs ({', '.join(pyros)}) but no command "
                f"is hazardous: none needs an ARM first; list the ones that can fire them "
                f"(of {commands})",
            )
        )
    if pyros and mission.standby is None and "cn" not in mission.recording_nodes:
        out.append(
            SafetyWarning(
                "control_node_cannot_resume",
                "$.nodes",
                f"the mission drives pyrotechnic outputs ({', '.join(pyros)}) with one control "
                "node and no flight recorder for it: a control node lost in flight ends the "
                "flight, and one restarted mid-run starts over; add a standby control node "
                "(cn_b) or a `recorder:` section (the control node resumes from it)",
            )
        )
    if has_commands:
        out.extend(_faults_never_cleared(mission))
    if mission.commands.hazardous and mission.security.transport == "plain":
        out.append(
            SafetyWarning(
                "plain_transport_with_hazardous",
                "$.security.transport",
                f"the mission has hazardous commands ({', '.join(mission.commands.hazardous)}) "
                "but its links are plain: any host on its network can open a session with its "
                "nodes (watch, flood, pose as a tool); leave security.transport at auto (mutual "
                "TLS with access control) unless the network is closed",
            )
        )
    return out


def _faults_never_cleared(mission: Mission) -> list[SafetyWarning]:
    """``fault_never_cleared``: a command refused while a fault is latched
    (``commands.refused_while_faulted``) in a state where no WRITE may clear
    ``cn_fault``: one fault latched there refuses it until the control node
    restarts."""
    sm = mission.state_machine
    wl = mission.commands.whitelist
    clear = set(write_states(mission).get("cn_fault", ()))
    out = []
    for c in refused_while_faulted(mission):
        stuck = [
            s
            for s in (sm.states if sm is not None else {})
            if (s not in wl or c in wl[s]) and s not in clear
        ]
        if stuck:
            out.append(
                SafetyWarning(
                    "fault_never_cleared",
                    "$.commands.writable",
                    f"a fault latched in {', '.join(stuck)} refuses {c} until the control node "
                    "restarts: no WRITE may clear cn_fault there; list cn_fault in "
                    f"commands.writable (write_states: {{cn_fault: [{stuck[0]}]}})",
                )
            )
    return out
