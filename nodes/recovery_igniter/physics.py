"""Simulated flight for the recovery igniter test's barometers.

:func:`flight` is the physics hook of the mission's vehicle world
(:mod:`zplatform.world.model`): both device nodes' boards are ports onto one
flight, which starts when the launch output (``launch_pin``, driven by dn0
when the state machine enters ARMED) first reads on, not when a node starts:
on the pad until then, then a ballistic coast from ``v0_mps`` to apogee,
then a descent under drogue at ``drogue_mps`` to the ground. It writes the
voltage each node's barometric altimeter would give on its ``baro_pins``
pin. ``bias_m`` adds a sensor error per node, and ``stuck_m`` replaces a
node's reading (a failed sensor). Everything is computed from the loop
time: runs repeat exactly.

The parameters are the world's ``params`` (:class:`FlightParams`, checked
at load).
"""

from __future__ import annotations

from typing import Annotated, Any

import msgspec
from msgspec import Meta

__all__ = ["FlightParams", "altitude_m", "check", "flight"]


class FlightParams(msgspec.Struct, forbid_unknown_fields=True):
    launch_pin: tuple[str, int] = ("dn0", 1)
    baro_pins: dict[str, int] = msgspec.field(default_factory=lambda: {"dn0": 0, "dn1": 0})
    v0_mps: Annotated[float, Meta(gt=0)] = 80.0
    g_mps2: Annotated[float, Meta(gt=0)] = 9.81
    drogue_mps: Annotated[float, Meta(gt=0)] = 30.0
    volts_per_m: Annotated[float, Meta(gt=0)] = 0.005
    bias_m: dict[str, float] = msgspec.field(default_factory=dict)
    stuck_m: dict[str, float] = msgspec.field(default_factory=dict)


def altitude_m(tau_s: float, p: FlightParams) -> float:
    """True altitude ``tau_s`` seconds after launch (0 before)."""
    if tau_s <= 0:
        return 0.0
    t_apogee = p.v0_mps / p.g_mps2
    if tau_s <= t_apogee:
        return p.v0_mps * tau_s - 0.5 * p.g_mps2 * tau_s * tau_s
    h_apogee = 0.5 * p.v0_mps * p.v0_mps / p.g_mps2
    return max(0.0, h_apogee - p.drogue_mps * (tau_s - t_apogee))


def flight(world: Any, t_ns: int) -> None:
    """Physics hook: note the launch, inject every barometer's voltage for ``t_ns``."""
    p: FlightParams = world.params
    launch = world.state.get("launch_ns")
    node, pin = p.launch_pin
    if launch is None and world.boards[node].output_digital(pin):
        launch = world.state["launch_ns"] = t_ns
    alt = altitude_m((t_ns - launch) / 1e9, p) if launch is not None else 0.0
    world.truth = alt
    for n, baro in p.baro_pins.items():
        reading = p.stuck_m[n] if n in p.stuck_m else alt + p.bias_m.get(n, 0.0)
        world.boards[n].inject_analog(baro, reading * p.volts_per_m)


def check(world: Any) -> None:
    """Load-time check (:mod:`zplatform.world.model`): every pin named is on its board."""
    p: FlightParams = world.params
    pins = [(p.launch_pin, "digital"), *(((n, pin), "analog") for n, pin in p.baro_pins.items())]
    for (node, pin), kind in pins:
        board = world.boards.get(node)
        if board is None:
            raise ValueError(f"no board {node!r} in the world ({sorted(world.boards)})")
        n = board.digital_pins if kind == "digital" else board.analog_pins
        if not 0 <= pin < n:
            raise ValueError(f"{kind} pin {pin} is not on {node} ({n} {kind} pins)")


flight.Params = FlightParams  # type: ignore[attr-defined]
flight.check = check  # type: ignore[attr-defined]
