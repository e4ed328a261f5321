"""The recovery igniter system test (the thesis, ch. 5.1.3.2).

The CN decides when to deploy and commands ignition; redundant safety logic
on each of two device nodes checks the command against its own rules before
it drives its igniter output. The igniter circuit needs both outputs (two
switches in series), so it fires only when both device nodes agree.

CN controllers:

* :class:`ApogeeDetector`: from the device nodes' barometric altitudes
  (the lower of them), detects apogee (``apogee_drop_m`` below the highest
  altitude seen) and then raises ``ready`` once below ``deploy_altitude_m``
  (a number or an element: ``configs/recovery_igniter.yaml`` names its
  mission parameter, read every loop); the state machine goes ARMED -> FIRE
  on it.
* :class:`IgnitionController`: in FIRE, commands ignition to every device
  node with the loop number it was sent in (for freshness) and records
  ``fired`` when every igniter feedback reads on.

Device node controller:

* :class:`IgniterSafetyController`: the rules. The output is on only if
  the command is on *and* the verdict is ok: the node is armed (a flag only
  the CN's state machine sets), the command is fresh (stamped within
  ``max_age_loops`` loops of this node's loop), and the node's own altitude
  is inside ``[min_altitude_m, max_altitude_m]``. Safed: output off, verdict
  false.

The physics of the simulated flight is :func:`nodes.recovery_igniter.physics.flight`.
"""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta

from zplatform.control.controllers import Controller
from zplatform.core.datavector import DataVector
from zplatform.errors import ConfigError

__all__ = ["ApogeeDetector", "IgniterSafetyController", "IgnitionController"]

_BOOL = ("bool",)
_FLOAT = ("float",)
_LOOP = ("int",)


def _same_length(ctl: Controller, a: list[str], b: list[str], field: str) -> None:
    if len(a) != len(b):
        raise ConfigError(
            f"{ctl.name}: {field} lists {len(b)} elements, expected {len(a)} (one per device node)",
            f"{ctl.where}.config.{field}",
        )


class ApogeeDetector(Controller):
    """Raises ``ready`` after apogee, below ``deploy_altitude_m`` (see module doc)."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        altitudes: Annotated[list[str], Meta(min_length=1)]
        ready: str
        estimate: str
        apogee: str
        deploy_altitude_m: float | str
        apogee_drop_m: Annotated[float, Meta(gt=0)] = 10.0

    config: Config

    def bind(self, dv: DataVector) -> None:
        cfg = self.config
        self._alts = tuple(
            self.input(a, f"altitudes[{i}]", kinds=_FLOAT) for i, a in enumerate(cfg.altitudes)
        )
        self._ready = self.output(cfg.ready, "ready", kinds=_BOOL)
        self._estimate = self.output(cfg.estimate, "estimate", kinds=_FLOAT)
        self._apogee = self.output(cfg.apogee, "apogee", kinds=_FLOAT)
        self._deploy = self.tunable(cfg.deploy_altitude_m, "deploy_altitude_m", kinds=_FLOAT)
        self._drop = cfg.apogee_drop_m
        self._max = float("-inf")
        self._passed = False

    def run_enabled(self, t_ns: int) -> None:
        est = float("inf")
        for h in self._alts:
            v = h.get()
            if v < est:
                est = v
        self._estimate.set(est)
        if est > self._max:
            self._max = est
            self._apogee.set(est)
        if not self._passed and est < self._max - self._drop:
            self._passed = True
        if self._passed and est < self._deploy.get():
            self._ready.set(True)

    def run_safed(self, t_ns: int) -> None:
        self._max = float("-inf")
        self._passed = False
        self._ready.set(False)


class IgnitionController(Controller):
    """Commands ignition with a freshness stamp; records ``fired`` (see module doc)."""

    takeover_safe = True  # stateless: every loop it writes from what it reads

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        commands: Annotated[list[str], Meta(min_length=1)]
        command_loops: list[str]
        feedbacks: list[str]
        fired: str

    config: Config

    def bind(self, dv: DataVector) -> None:
        cfg = self.config
        _same_length(self, cfg.commands, cfg.command_loops, "command_loops")
        _same_length(self, cfg.commands, cfg.feedbacks, "feedbacks")
        self._loop = self.input("cn_loop")
        self._cmds = tuple(
            self.output(c, f"commands[{i}]", kinds=_BOOL) for i, c in enumerate(cfg.commands)
        )
        self._stamps = tuple(
            self.output(c, f"command_loops[{i}]", kinds=_LOOP)
            for i, c in enumerate(cfg.command_loops)
        )
        self._fbs = tuple(
            self.input(c, f"feedbacks[{i}]", kinds=_BOOL) for i, c in enumerate(cfg.feedbacks)
        )
        self._fired = self.output(cfg.fired, "fired", kinds=_BOOL)

    def _common(self, command: bool) -> None:
        loop = self._loop.get()
        for cmd, stamp in zip(self._cmds, self._stamps, strict=True):
            cmd.set(command)
            stamp.set(loop)
        for fb in self._fbs:
            if not fb.get():
                return
        self._fired.set(True)

    def run_enabled(self, t_ns: int) -> None:
        self._common(True)

    def run_safed(self, t_ns: int) -> None:
        self._common(False)


class IgniterSafetyController(Controller):
    """A device node's igniter rules: armed, fresh, altitude window (see module doc)."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        command: str
        command_loop: str
        armed: str
        altitude: str
        loop: str
        verdict: str
        output: str
        min_altitude_m: float
        max_altitude_m: float
        max_age_loops: Annotated[int, Meta(ge=0)] = 5

        def __post_init__(self) -> None:
            if self.min_altitude_m > self.max_altitude_m:
                raise ValueError("min_altitude_m must not exceed max_altitude_m")

    config: Config

    def bind(self, dv: DataVector) -> None:
        cfg = self.config
        self._cmd = self.input(cfg.command, "command", kinds=_BOOL)
        self._cmd_loop = self.input(cfg.command_loop, "command_loop", kinds=_LOOP)
        self._armed = self.input(cfg.armed, "armed", kinds=_BOOL)
        self._alt = self.input(cfg.altitude, "altitude", kinds=_FLOAT)
        self._loop = self.input(cfg.loop, "loop", kinds=_LOOP)
        self._verdict = self.output(cfg.verdict, "verdict", kinds=_BOOL)
        self._out = self.output(cfg.output, "output", kinds=_BOOL)
        self._lo, self._hi = cfg.min_altitude_m, cfg.max_altitude_m
        self._max_age = cfg.max_age_loops

    def verdict(self) -> bool:
        """Whether every rule allows firing now (the command itself aside)."""
        age = self._loop.get() - self._cmd_loop.get()
        alt = self._alt.get()
        return (
            bool(self._armed.get())
            and 0 <= age <= self._max_age
            and self._lo <= alt <= self._hi  # False for nan
        )

    def run_enabled(self, t_ns: int) -> None:
        ok = self.verdict()
        self._verdict.set(ok)
        self._out.set(ok and bool(self._cmd.get()))

    def run_safed(self, t_ns: int) -> None:
        self._verdict.set(False)
        self._out.set(False)
