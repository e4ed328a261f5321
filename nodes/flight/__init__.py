"""The flight mission: a rocket flown by the platform (``configs/flight.yaml``).

Flight software only: every class here talks to the Data Vector and, for
devices, to board pins. The physics behind the pins is
:mod:`nodes.flight.physics`, reached through the mission's vehicle world
(:mod:`zplatform.world.model`), the serial board simulator in hardware in the
loop, or real hardware; nothing here can tell which.

Device nodes (each reads its sensors at its own rate):

* :class:`ImuFifo`: the IMU samples at 400 Hz into its FIFO; the device
  reads the FIFO's newest samples (one analog channel each) every loop and
  averages them; a FIFO that did not move (a dead IMU) or holds a non-number
  is reported through ``ok``.
* :class:`Barometer`: pressure to ISA pressure altitude.
* :class:`Gps`: altitude and fix at the GPS's rate (a rate group), with a
  sample counter so the CN uses each fix once.

Control node (100 Hz):

* :class:`Ekf`: altitude, vertical velocity and accelerometer bias from the
  IMU, both barometers and the GPS; falls back to barometers alone when the
  IMU is lost (an event says so).
* :class:`FlightEvents`: lift-off, burnout, apogee, main altitude and
  landing, each with a persistence count, so that noise, a Mach transient
  or one bad sample cannot trigger it.
* :class:`Airbrakes`: drives the airbrakes so that the predicted apogee
  (drag-ballistic, closed form) meets ``target_m``.

Settings a ground crew tunes (the apogee target, the main-chute altitude,
the airbrake rate, the EKF's measurement noise) are config fields that take
a number or the name of an element: ``configs/flight.yaml`` names its
mission parameters there (``target_m: apogee_target_m``), which the
controllers read every loop, so a PRM_SET changes the flight without a
rebuild (:mod:`zplatform.control.params`).

Takeover-ready: every piece of state a controller needs from one loop to the
next (EKF state and covariance, ground reference, persistence counts,
event latches and times, the airbrake command) lives in Data Vector
elements of the ``cn`` (or ``cn_to_dnX``) regions, never in Python
attributes, so a standby CN that mirrors the Data Vector can take over in
any loop (the controllers' docstrings name their elements).

The recovery igniters use the two-node agreement of
``configs/recovery_igniter.yaml``: :class:`nodes.recovery_igniter.IgnitionController`
on the CN, :class:`nodes.recovery_igniter.IgniterSafetyController` on each
device node, each chute's two switches in series.
"""

from __future__ import annotations

import math
from typing import Annotated

import msgspec
from msgspec import Meta

from zplatform.control.controllers import Controller
from zplatform.control.devices import Sensor
from zplatform.core.datavector import DataVector
from zplatform.errors import ConfigError

from .physics import atmosphere, pressure_altitude

__all__ = ["Airbrakes", "Barometer", "Ekf", "FlightEvents", "Gps", "ImuFifo"]

_INIT, _ACCEL, _BARO = 0, 1, 2  # Ekf's mode enum
_F = ("float",)
_B = ("bool",)
_I = ("int",)


# ---------------------------------------------------------------------------
# devices (device nodes)


class ImuFifo(Sensor):
    """The IMU's FIFO, burst-read every loop: ``accel`` = mean of the
    ``accel_pins`` samples x ``scale``; ``gyro`` = ``gyro_pin`` x
    ``gyro_scale``; ``ok`` false when a sample is not a number, or when the
    FIFO has not moved for ``stale_loops`` reads in a row (the IMU stopped
    sampling; one empty read is jitter, not a dead sensor)."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        accel_pins: Annotated[list[int], Meta(min_length=1, max_length=16)]
        accel: str
        ok: str
        scale: float = 1.0
        gyro_pin: int | None = None
        gyro: str | None = None
        gyro_scale: float = 1.0
        stale_loops: Annotated[int, Meta(ge=1)] = 3

    config: Config

    def bind(self, dv: DataVector) -> None:
        c = self.config
        self._pins = tuple(
            self.analog_pin(p, f"accel_pins[{i}]") for i, p in enumerate(c.accel_pins)
        )
        self._accel = self.output(c.accel, "accel", kinds=_F)
        self._ok = self.output(c.ok, "ok", kinds=_B)
        self._gpin = self.analog_pin(c.gyro_pin, "gyro_pin") if c.gyro_pin is not None else None
        self._gyro = self.output(c.gyro, "gyro", kinds=_F) if c.gyro is not None else None
        self._last = [math.nan] * len(self._pins)
        self._n = len(self._pins)
        self._still = 0  # reads in a row that found the FIFO unmoved

    def run(self, t_ns: int) -> None:
        get = self.board.get_analog
        last = self._last
        total = 0.0
        moved = False
        for i, pin in enumerate(self._pins):
            v = get(pin)
            total += v
            if v != last[i]:
                moved = True
            last[i] = v
        mean = total / self._n * self.config.scale
        self._still = 0 if moved else self._still + 1
        self._accel.set(mean)
        self._ok.set(self._still < self.config.stale_loops and math.isfinite(mean))
        if self._gpin is not None and self._gyro is not None:
            self._gyro.set(get(self._gpin) * self.config.gyro_scale)


class Barometer(Sensor):
    """Pressure (``pin`` volts x ``pa_per_volt``) to ISA pressure altitude in
    ``element`` (nan stays nan: the CN decides what a lost sensor means)."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        pin: int
        element: str
        pa_per_volt: float = 1.0

    config: Config

    def bind(self, dv: DataVector) -> None:
        self._pin = self.analog_pin(self.config.pin)
        self._out = self.output(self.config.element, "element", kinds=_F)
        self._k = self.config.pa_per_volt

    def run(self, t_ns: int) -> None:
        pa = self.board.get_analog(self._pin) * self._k
        self._out.set(pressure_altitude(pa) if pa > 0.0 else math.nan)


class Gps(Sensor):
    """A GPS fix: when ``fix_pin`` reads on, ``alt`` = ``alt_pin`` x ``scale``
    and ``seq`` counts the fix (the CN uses each fix once); ``fix`` mirrors
    the pin. Run it in a rate group at the receiver's rate."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        alt_pin: int
        fix_pin: int
        alt: str
        fix: str
        seq: str
        scale: float = 1.0

    config: Config

    def bind(self, dv: DataVector) -> None:
        c = self.config
        self._apin = self.analog_pin(c.alt_pin, "alt_pin")
        self._fpin = self.digital_pin(c.fix_pin, "fix_pin")
        self._alt = self.output(c.alt, "alt", kinds=_F)
        self._fix = self.output(c.fix, "fix", kinds=_B)
        self._seq = self.output(c.seq, "seq", kinds=_I)

    def run(self, t_ns: int) -> None:
        fix = self.board.get_digital(self._fpin)
        self._fix.set(fix)
        if fix:
            self._alt.set(self.board.get_analog(self._apin) * self.config.scale)
            self._seq.set((self._seq.get() + 1) & 0xFFFF)


# ---------------------------------------------------------------------------
# control node


class Ekf(Controller):
    """Vertical navigation: an extended Kalman filter on ``[h, v, b]``.

    ``h`` altitude above the pad, ``v`` vertical velocity, ``b`` the
    accelerometer's bias. Prediction integrates the IMU's specific force
    (``v' = a - b - g``); each barometer and each new GPS fix correct
    ``h`` (a fix is up to ``gps_latency_s`` old when read, so its noise
    grows by the distance flown meanwhile, ``v`` times that; innovations
    beyond ``gate_sigma`` are refused, so a Mach dip or a glitch is ignored;
    above ``transonic_mps`` the barometers are not used at all). A loop in
    flight that takes no altitude (transonic, or every measurement refused)
    is blind: the errors of the prediction that a vertical model does not
    know (tilt, scale, the barometers' lag absorbed into the bias) grow in
    the covariance as a velocity random walk of ``blind_walk_mps`` per root
    second, so the gate widens until the barometers are taken again
    (without it, an estimate that drifted past the gate during the
    transonic blackout refused every barometer for the rest of the climb
    and fired the drogue early: the Mach 1.05 flight of
    ``tests/system/test_flight.py``). ``baro_sigma_m`` and ``gps_sigma_m``,
    the measurement noises that set the Kalman gains, are numbers or
    elements (parameters). On the pad (before ``liftoff`` is set) the filter
    also takes ``h = 0, v = 0`` and averages the barometers into the ground
    reference.

    Fallback: when the IMU is lost (``imu_ok`` false, or a sample that is
    not a number, or beyond ``saturation_mps2``) the prediction runs without
    it (constant velocity, ``fallback_sigma_mps2`` of process noise) and
    ``mode`` reads ``BARO``; an event reports each change of mode. ``mode``
    reads ``INIT`` until the IMU has first reported (on the pad).

    State in the Data Vector (takeover): ``h``, ``v``, ``bias`` (f64),
    ``cov`` (f64[6]: P00 P01 P02 P11 P12 P22), ``ground`` (f64), ``mode``,
    ``stamp`` (i64, the last loop's time: the step) and ``gps_used`` (the
    last GPS fix taken).
    """

    takeover_safe = True  # every state it keeps is a Data Vector element

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        accel: str
        imu_ok: str
        baros: list[str]
        gps_alt: str
        gps_seq: str
        liftoff: str
        h: str
        v: str
        bias: str
        cov: str
        ground: str
        mode: str
        stamp: str
        gps_used: str
        g_mps2: float = 9.80665
        accel_sigma_mps2: Annotated[float, Meta(gt=0)] = 0.5
        bias_walk: Annotated[float, Meta(ge=0)] = 0.02
        fallback_sigma_mps2: Annotated[float, Meta(gt=0)] = 20.0
        baro_sigma_m: Annotated[float, Meta(gt=0)] | str = 1.0
        gps_sigma_m: Annotated[float, Meta(gt=0)] | str = 3.0
        gps_latency_s: Annotated[float, Meta(ge=0)] = 0.1
        gate_sigma: Annotated[float, Meta(gt=0)] = 5.0
        saturation_mps2: Annotated[float, Meta(gt=0)] = 150.0
        transonic_mps: Annotated[float, Meta(gt=0)] = 250.0
        blind_walk_mps: Annotated[float, Meta(ge=0)] = 3.0
        ground_tau_s: Annotated[float, Meta(gt=0)] = 2.0

    config: Config

    def bind(self, dv: DataVector) -> None:
        c = self.config
        self._accel = self.input(c.accel, "accel", kinds=_F)
        self._imu_ok = self.input(c.imu_ok, "imu_ok", kinds=_B)
        self._baros = tuple(self.input(b, f"baros[{i}]", kinds=_F) for i, b in enumerate(c.baros))
        self._gps = self.input(c.gps_alt, "gps_alt", kinds=_F)
        self._gps_seq = self.input(c.gps_seq, "gps_seq", kinds=_I)
        self._liftoff = self.input(c.liftoff, "liftoff", kinds=_B)
        self._hh = self.output(c.h, "h", kinds=_F)
        self._hv = self.output(c.v, "v", kinds=_F)
        self._hb = self.output(c.bias, "bias", kinds=_F)
        self._hp = self.output(c.cov, "cov", kinds=_F, array=True)
        if self._hp.spec.count != 6:
            raise ConfigError(f"{c.cov} must be f64[6]", f"{self.where}.config.cov")
        self._hg = self.output(c.ground, "ground", kinds=_F)
        self._hmode = self.output(c.mode, "mode", kinds=("enum",))
        enum: list[str] = list(self._hmode.spec.enum or [])
        if enum[:3] != ["INIT", "ACCEL", "BARO"]:
            raise ConfigError(
                f"{c.mode} must be an enum [INIT, ACCEL, BARO]", f"{self.where}.config.mode"
            )
        self._stamp = self.output(c.stamp, "stamp", kinds=_I)
        self._gps_used = self.output(c.gps_used, "gps_used", kinds=_I)
        self._baro_sigma = self.tunable(c.baro_sigma_m, "baro_sigma_m", kinds=_F)
        self._gps_sigma = self.tunable(c.gps_sigma_m, "gps_sigma_m", kinds=_F)

    def run_safed(self, t_ns: int) -> None:
        """Safed: the estimate is frozen (nothing to drive)."""

    def run_enabled(self, t_ns: int) -> None:
        c = self.config
        last = self._stamp.get()
        self._stamp.set(t_ns)
        dt = min(max((t_ns - last) / 1e9, 0.001), 0.1) if last else 0.01
        h, v, b = self._hh.get(), self._hv.get(), self._hb.get()
        p = self._hp.get()
        p00, p01, p02, p11, p12, p22 = (
            float(p[0]),
            float(p[1]),
            float(p[2]),
            float(p[3]),
            float(p[4]),
            float(p[5]),
        )
        if p00 == 0.0 and p11 == 0.0 and p22 == 0.0:  # first run: an honest prior
            p00, p11, p22 = 100.0, 1.0, 1.0
        a = self._accel.get()
        imu = bool(self._imu_ok.get()) and math.isfinite(a) and abs(a) < c.saturation_mps2
        on_pad = not self._liftoff.get()
        was = self._hmode.get()
        mode = _ACCEL if imu else _INIT if was == _INIT and on_pad else _BARO
        if mode != was:
            self._hmode.set(mode)
            if imu:
                self.report(t_ns, "navigation on the accelerometer, barometers and GPS")
            else:
                self.report(
                    t_ns, "IMU lost: navigation falls back to barometers and GPS", warning=True
                )
        # -- predict: x' = F x + B (a - g); P' = F P F^T + Q -------------------
        if imu:
            acc = a - b - c.g_mps2
            sa = c.accel_sigma_mps2
            f02, f12 = -0.5 * dt * dt, -dt
        else:
            acc = 0.0
            sa = c.fallback_sigma_mps2
            f02 = f12 = 0.0
        h = h + v * dt + 0.5 * acc * dt * dt
        v = v + acc * dt
        # F = [[1, dt, f02], [0, 1, f12], [0, 0, 1]]
        a00 = p00 + dt * p01 + f02 * p02
        a01 = p01 + dt * p11 + f02 * p12
        a02 = p02 + dt * p12 + f02 * p22
        a11 = p11 + f12 * p12
        a12 = p12 + f12 * p22
        n00 = a00 + dt * a01 + f02 * a02
        n01 = a01 + f12 * a02
        n02 = a02
        n11 = a11 + f12 * a12
        n12 = a12
        n22 = p22
        q = sa * sa
        g0, g1 = 0.5 * dt * dt, dt
        p00 = n00 + g0 * g0 * q
        p01 = n01 + g0 * g1 * q
        p02 = n02
        p11 = n11 + g1 * g1 * q
        p12 = n12
        p22 = n22 + c.bias_walk * c.bias_walk * dt
        # -- updates: scalar measurements of h (or v) ------------------------
        ground = self._hg.get()
        state = [h, v, b, p00, p01, p02, p11, p12, p22]
        if on_pad:
            n = 0
            total = 0.0
            for hb in self._baros:
                z = hb.get()
                if math.isfinite(z):
                    total += z
                    n += 1
            if n:
                mean = total / n
                ground = mean if ground == 0.0 else ground + (mean - ground) * dt / c.ground_tau_s
                self._hg.set(ground)
            _update(state, 0, 0.0, 0.05**2, 1e9)
            _update(state, 1, 0.0, 0.01**2, 1e9)
        else:
            took = False
            if abs(state[1]) < c.transonic_mps:
                r = self._baro_sigma.get() ** 2
                for hb in self._baros:
                    z = hb.get()
                    if math.isfinite(z):
                        took = _update(state, 0, z - ground, r, c.gate_sigma) or took
            seq = self._gps_seq.get()
            if seq != self._gps_used.get():
                self._gps_used.set(seq)
                z = self._gps.get()
                if math.isfinite(z):
                    r = self._gps_sigma.get() ** 2 + (state[1] * c.gps_latency_s) ** 2
                    took = _update(state, 0, z - ground, r, c.gate_sigma) or took
            if not took:  # blind this loop: the prediction's own errors grow (class doc)
                w = c.blind_walk_mps * c.blind_walk_mps * dt
                state[3] += w * dt * dt / 3.0
                state[4] += w * dt / 2.0
                state[6] += w
        h, v, b, p00, p01, p02, p11, p12, p22 = state
        self._hh.set(h)
        self._hv.set(v)
        self._hb.set(b)
        p[0], p[1], p[2], p[3], p[4], p[5] = p00, p01, p02, p11, p12, p22


def _update(s: list[float], row: int, z: float, r: float, gate: float) -> bool:
    """One scalar Kalman update of state ``s`` (h, v, b, then P's upper
    triangle) with ``z = x[row] + noise(r)``; refused (False) when the
    innovation is beyond ``gate`` standard deviations."""
    h, v, b, p00, p01, p02, p11, p12, p22 = s
    if row == 0:
        c0, c1, c2 = p00, p01, p02
        y = z - h
    else:
        c0, c1, c2 = p01, p11, p12
        y = z - v
    sv = (c0 if row == 0 else c1) + r
    if y * y > gate * gate * sv:
        return False
    k0, k1, k2 = c0 / sv, c1 / sv, c2 / sv
    s[0] = h + k0 * y
    s[1] = v + k1 * y
    s[2] = b + k2 * y
    s[3] = p00 - k0 * c0
    s[4] = p01 - k0 * c1
    s[5] = p02 - k0 * c2
    s[6] = p11 - k1 * c1
    s[7] = p12 - k1 * c2
    s[8] = p22 - k2 * c2
    return True


class FlightEvents(Controller):
    """Lift-off, burnout, apogee, main altitude and landing, from the estimate.

    Each event needs its condition to hold for ``persist_loops`` loops in a
    row (one noisy sample or a transient does nothing), and latches:

    * ``liftoff``: the measured acceleration above ``liftoff_g`` (or, the IMU
      lost, the altitude above ``liftoff_m``);
    * ``burnout``: after lift-off, the measured acceleration below 0 (drag
      only), or ``max_burn_s`` after lift-off;
    * ``apogee``: after burnout and ``min_coast_s`` after lift-off, the
      vertical velocity below ``-apogee_mps`` (a margin over the estimate's
      noise: never before the true apogee, about ``apogee_mps / g`` after);
    * ``below_main``: after apogee, the altitude below ``main_m`` (a number
      or an element: a parameter, read every loop);
    * ``landed``: after apogee, ``|v|`` below ``landed_mps`` for
      ``landed_s``.

    State in the Data Vector (takeover): the latches, ``liftoff_ns`` and
    ``streaks`` (u16[5], the persistence counts).
    """

    takeover_safe = True  # every state it keeps is a Data Vector element

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        accel: str
        imu_ok: str
        h: str
        v: str
        liftoff: str
        burnout: str
        apogee: str
        below_main: str
        landed: str
        liftoff_ns: str
        streaks: str
        main_m: Annotated[float, Meta(gt=0)] | str
        liftoff_g: float = 2.5
        liftoff_m: float = 30.0
        max_burn_s: float = 6.0
        min_coast_s: float = 4.0
        apogee_mps: Annotated[float, Meta(ge=0)] = 2.0
        landed_mps: Annotated[float, Meta(gt=0)] = 1.0
        landed_s: Annotated[float, Meta(gt=0)] = 2.0
        persist_loops: Annotated[int, Meta(ge=1)] = 5

    config: Config

    def bind(self, dv: DataVector) -> None:
        c = self.config
        self._accel = self.input(c.accel, "accel", kinds=_F)
        self._imu_ok = self.input(c.imu_ok, "imu_ok", kinds=_B)
        self._h = self.input(c.h, "h", kinds=_F)
        self._v = self.input(c.v, "v", kinds=_F)
        self._flags = tuple(
            self.output(getattr(c, n), n, kinds=_B)
            for n in ("liftoff", "burnout", "apogee", "below_main", "landed")
        )
        self._main = self.tunable(c.main_m, "main_m", kinds=_F)
        self._t0 = self.output(c.liftoff_ns, "liftoff_ns", kinds=_I)
        self._streaks = self.output(c.streaks, "streaks", kinds=_I, array=True)
        if self._streaks.spec.count != 5:
            raise ConfigError(f"{c.streaks} must be u16[5]", f"{self.where}.config.streaks")

    def run_safed(self, t_ns: int) -> None:
        """Safed: no detection (the latches keep what they hold)."""

    def _persist(self, i: int, cond: bool) -> bool:
        s = self._streaks.get()
        n = int(s[i]) + 1 if cond else 0
        s[i] = min(n, 0xFFFF)
        return n >= self.config.persist_loops

    def run_enabled(self, t_ns: int) -> None:
        c = self.config
        lift, burn, apo, main, land = self._flags
        a = self._accel.get()
        imu = bool(self._imu_ok.get()) and math.isfinite(a)
        h, v = self._h.get(), self._v.get()
        if not lift.get():
            cond = a > c.liftoff_g * 9.80665 if imu else h > c.liftoff_m
            if self._persist(0, cond):
                lift.set(True)
                self._t0.set(t_ns)
            return
        since = (t_ns - self._t0.get()) / 1e9
        if not burn.get():
            if self._persist(1, imu and a < 0.0) or since > c.max_burn_s:
                burn.set(True)
            return
        if not apo.get():
            if self._persist(2, since > c.min_coast_s and v < -c.apogee_mps):
                apo.set(True)
            return
        if not main.get() and self._persist(3, h < self._main.get() and v < 0.0):
            main.set(True)
        if not land.get():
            need = max(1, round(c.landed_s * 100))
            s = self._streaks.get()
            n = int(s[4]) + 1 if abs(v) < c.landed_mps else 0
            s[4] = min(n, 0xFFFF)
            if n >= need:
                land.set(True)


class Airbrakes(Controller):
    """Airbrakes that aim the apogee at ``target_m`` (an energy-based controller).

    Each loop, from the estimate (``h``, ``v``), the drag-ballistic apogee
    ``h + m/(2k) ln(1 + k v^2/(m g))`` with ``k = rho/2 (cd_area +
    u brake_cda)`` (air density at the mid-point of the remaining climb) is
    solved for the deployment ``u`` in [0, 1] that ends the climb at the
    target: the drag area whose work removes exactly the surplus energy.
    Solved again every loop, it corrects its own model errors as the climb
    goes on. The command is rate-limited to ``rate`` per second (the servo).
    Safed: retracted. ``target_m`` and ``rate`` are numbers or elements
    (parameters), read every loop.

    State in the Data Vector (takeover): only its output ``command`` (a
    ``cn_to_dnX`` element) and ``predicted``.
    """

    takeover_safe = True  # every state it keeps is a Data Vector element

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        h: str
        v: str
        ground: str
        command: str
        predicted: str
        target_m: Annotated[float, Meta(gt=0)] | str
        mass_kg: Annotated[float, Meta(gt=0)]
        cd_area_m2: Annotated[float, Meta(gt=0)]
        brake_cda_m2: Annotated[float, Meta(gt=0)]
        g_mps2: float = 9.80665
        rate: Annotated[float, Meta(gt=0)] | str = 2.0
        period_s: Annotated[float, Meta(gt=0)] = 0.01

    config: Config

    def bind(self, dv: DataVector) -> None:
        c = self.config
        self._h = self.input(c.h, "h", kinds=_F)
        self._v = self.input(c.v, "v", kinds=_F)
        self._ground = self.input(c.ground, "ground", kinds=_F)
        self._cmd = self.output(c.command, "command", kinds=_F)
        self._pred = self.output(c.predicted, "predicted", kinds=_F)
        self._target = self.tunable(c.target_m, "target_m", kinds=_F)
        self._rate = self.tunable(c.rate, "rate", kinds=_F)

    def apogee(self, h: float, v: float, u: float) -> float:
        """Predicted apogee above the pad for deployment ``u`` held to the top."""
        c = self.config
        if v <= 0.0:
            return h
        m, g = c.mass_kg, c.g_mps2
        climb = v * v / (2 * g)
        ground = self._ground.get()
        for _ in range(2):  # density at the middle of the remaining climb
            rho = atmosphere(ground + h + climb / 2)[0]
            k = 0.5 * rho * (c.cd_area_m2 + u * c.brake_cda_m2)
            climb = m / (2 * k) * math.log1p(k * v * v / (m * g))
        return h + climb

    def run_enabled(self, t_ns: int) -> None:
        c = self.config
        h, v = self._h.get(), self._v.get()
        target = self._target.get()
        free = self.apogee(h, v, 0.0)
        self._pred.set(free)
        if v <= 0.0 or free <= target:
            want = 0.0
        elif self.apogee(h, v, 1.0) >= target:
            want = 1.0
        else:
            lo, hi = 0.0, 1.0
            for _ in range(12):
                mid = 0.5 * (lo + hi)
                if self.apogee(h, v, mid) > target:
                    lo = mid
                else:
                    hi = mid
            want = 0.5 * (lo + hi)
        last = self._cmd.get()
        step = self._rate.get() * c.period_s
        self._cmd.set(last + min(max(want - last, -step), step))

    def run_safed(self, t_ns: int) -> None:
        self._cmd.set(0.0)
