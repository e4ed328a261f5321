"""Simulated flight for the recovery igniter test's barometers.

:func:`flight` is a :class:`~zplatform.boards.SimBoard` physics hook. It
writes the voltage a barometric altimeter would give on ``baro_pin`` for a
simple flight: on the pad until ``launch_s`` after the board's first step,
then a ballistic coast from ``v0_mps`` to apogee, then a descent under
drogue at ``drogue_mps`` to the ground. ``bias_m`` adds a sensor error, and
``stuck_m`` (when set) replaces the reading (a failed sensor). Everything is
computed from the loop time: runs repeat exactly.

The parameters are the board's ``params`` (:class:`FlightParams`, checked
at load).
"""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta

from zplatform.boards import SimBoard

__all__ = ["FlightParams", "altitude_m", "flight"]


class FlightParams(msgspec.Struct, forbid_unknown_fields=True):
    launch_s: Annotated[float, Meta(ge=0)] = 1.0
    v0_mps: Annotated[float, Meta(gt=0)] = 80.0
    g_mps2: Annotated[float, Meta(gt=0)] = 9.81
    drogue_mps: Annotated[float, Meta(gt=0)] = 30.0
    volts_per_m: Annotated[float, Meta(gt=0)] = 0.005
    baro_pin: Annotated[int, Meta(ge=0)] = 0
    bias_m: float = 0.0
    stuck_m: float | None = None


def altitude_m(t_s: float, p: FlightParams) -> float:
    """True altitude ``t_s`` seconds after start."""
    tau = t_s - p.launch_s
    if tau <= 0:
        return 0.0
    t_apogee = p.v0_mps / p.g_mps2
    if tau <= t_apogee:
        return p.v0_mps * tau - 0.5 * p.g_mps2 * tau * tau
    h_apogee = 0.5 * p.v0_mps * p.v0_mps / p.g_mps2
    return max(0.0, h_apogee - p.drogue_mps * (tau - t_apogee))


def flight(board: SimBoard, t_ns: int) -> None:
    """Physics hook: inject the barometer voltage for time ``t_ns``."""
    p: FlightParams = board.params
    assert board.start_ns is not None
    if p.stuck_m is not None:
        alt = p.stuck_m
    else:
        alt = altitude_m((t_ns - board.start_ns) / 1e9, p) + p.bias_m
    board.inject_analog(p.baro_pin, alt * p.volts_per_m)


flight.Params = FlightParams  # type: ignore[attr-defined]
