"""The flight's physics: a rocket in a 2-D vertical plane, its motor, air, chutes and sensors.

This is simulation, not flight code: it runs behind the board contract, as
the physics hook of the mission's vehicle world (:mod:`zplatform.world.model`),
and the flight software (:mod:`nodes.flight`) sees only what it puts on the
boards' pins. :func:`vehicle` is that hook; :class:`Flight` is the model,
also used alone by ``python -m bench.flight_validation``.

Model (SI units, z up, x downwind):

* **Motor** from a RASP ``.eng`` file (:class:`Motor`): thrust linearly
  interpolated between the points (from 0 N at 0 s); propellant burnt in
  proportion to the impulse delivered (RocketPy's and OpenRocket's model).
* **Gravity** constant (``g_mps2``); **air** the ISA troposphere
  (:func:`atmosphere`): density, pressure, speed of sound.
* **Drag** ``0.5 rho v_air^2 (Cd(M) A + airbrake Cd.A + chutes' Cd.A)``
  against the air-relative velocity; ``Cd(M)`` a piecewise-linear curve.
* **Attitude**: the body axis starts along the rail; off the rail it turns
  toward the air-relative velocity with a time constant (a damped
  weathercock); thrust acts along it. Under a chute it hangs vertical.
* **Chutes** (drogue, main): deploy when *every* pin wired to them is on
  (the igniter circuit's switches in series), then inflate linearly to their
  full Cd.A over ``inflation_s``. Deployment latches.
* **Airbrakes**: a servo driven by an analog pin (0..``airbrake_full_volts``),
  slewing at ``airbrake_rate`` (fraction per second), adding up to
  ``airbrake_cda_m2``.
* **Wind**: ``wind_mps`` plus a seeded gust (a first-order random process).
* **Ground**: on the pad until thrust exceeds weight; after lift-off, at
  ``z <= 0`` the airframe stops at ``crush_mps2`` (the impact the
  accelerometer feels), then it has landed.

The vehicle is integrated with RK4 on a fixed 400 Hz grid (:data:`STEP_NS`)
aligned to the world's first step; every grid point also samples the
sensors (:class:`Sensors`), so each board sees what a real board's ADC and
sample FIFO would hold at that time. Nothing happens before the igniter pin
is on: the flight starts at ignition, whenever the loop is then.
"""

from __future__ import annotations

import itertools
import math
import random
from pathlib import Path
from typing import Annotated, Any

import msgspec
from msgspec import Meta

__all__ = [
    "STEP_NS",
    "Flight",
    "Motor",
    "Sensors",
    "VehicleParams",
    "atmosphere",
    "check",
    "vehicle",
]

STEP_NS = 2_500_000
"""Integration and sensor sampling step: 400 Hz."""

_R = 287.05287  # J/(kg K), dry air
_T0 = 288.15
_P0 = 101_325.0
_LAPSE = 0.0065
_GAMMA = 1.4
_EXP = 9.80665 / (_R * _LAPSE)  # 5.2559 (ISA uses standard gravity here)
HERE = Path(__file__).resolve().parent


def atmosphere(h_m: float) -> tuple[float, float, float]:
    """ISA troposphere at geometric altitude ``h_m`` (clamped to 0..11 km):
    ``(density kg/m^3, pressure Pa, speed of sound m/s)``."""
    h = min(max(h_m, -500.0), 11_000.0)
    t = _T0 - _LAPSE * h
    p = _P0 * (t / _T0) ** _EXP
    return p / (_R * t), p, math.sqrt(_GAMMA * _R * t)


def pressure_altitude(p_pa: float) -> float:
    """Inverse of the ISA pressure: the altitude at which the pressure is ``p_pa``."""
    return (_T0 / _LAPSE) * (1.0 - (max(p_pa, 1.0) / _P0) ** (1.0 / _EXP))


class Motor:
    """A solid motor from a RASP ``.eng`` file (the format of ThrustCurve.org).

    Raises ValueError naming the line for a malformed file. ``thrust(t)``
    is 0 before 0 s and after the last point; ``propellant(t)`` the
    propellant left, burnt in proportion to the impulse delivered.
    """

    def __init__(self, path: str | Path) -> None:
        p = Path(path)
        if not p.is_absolute() and not p.exists():
            p = HERE / p
        self.path = p
        header: list[str] | None = None
        pts: list[tuple[float, float]] = []
        for n, raw in enumerate(p.read_text().splitlines(), 1):
            line = raw.split(";", 1)[0].strip()
            if not line:
                continue
            if header is None:
                header = line.split()
                if len(header) < 7:
                    raise ValueError(f"{p}:{n}: RASP header needs 7 fields, got {len(header)}")
                continue
            try:
                t, f = (float(x) for x in line.split())
            except ValueError:
                raise ValueError(f"{p}:{n}: expected 'time thrust', got {raw!r}") from None
            if pts and t <= pts[-1][0]:
                raise ValueError(f"{p}:{n}: times must increase")
            pts.append((t, f))
        if header is None or not pts:
            raise ValueError(f"{p}: no RASP header or no thrust points")
        self.name = header[0]
        self.diameter_m = float(header[1]) / 1000.0
        self.propellant_kg = float(header[4])
        self.total_kg = float(header[5])
        self.dry_kg = self.total_kg - self.propellant_kg
        if pts[0][0] > 0.0:
            pts.insert(0, (0.0, 0.0))
        self.times = [t for t, _ in pts]
        self.thrusts = [f for _, f in pts]
        imp = [0.0]
        for i in range(1, len(pts)):
            dt = self.times[i] - self.times[i - 1]
            imp.append(imp[-1] + 0.5 * dt * (self.thrusts[i] + self.thrusts[i - 1]))
        self._impulse = imp
        self.total_impulse = imp[-1]
        self.burn_time = self.times[-1]

    def _seg(self, t: float) -> int:
        ts = self.times
        lo, hi = 0, len(ts) - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if ts[mid] <= t:
                lo = mid
            else:
                hi = mid
        return lo

    def thrust(self, t: float) -> float:
        if t <= 0.0 or t >= self.burn_time:
            return 0.0
        i = self._seg(t)
        t0, t1 = self.times[i], self.times[i + 1]
        f0, f1 = self.thrusts[i], self.thrusts[i + 1]
        return f0 + (f1 - f0) * (t - t0) / (t1 - t0)

    def impulse(self, t: float) -> float:
        if t <= 0.0:
            return 0.0
        if t >= self.burn_time:
            return self.total_impulse
        i = self._seg(t)
        f = self.thrust(t)
        return self._impulse[i] + 0.5 * (t - self.times[i]) * (self.thrusts[i] + f)

    def propellant(self, t: float) -> float:
        return self.propellant_kg * (1.0 - self.impulse(t) / self.total_impulse)


Pin = tuple[str, int]


class Wiring(msgspec.Struct, forbid_unknown_fields=True):
    """Which board pins the vehicle's hardware hangs on: ``[board, pin]`` pairs.

    ``drogue`` and ``main`` list every switch of a chute's igniter circuit
    (in series: the chute deploys only when all are on). Sensor pins are
    the boards' analog inputs (digital for the GPS fix).
    """

    ignition: Pin
    drogue: list[Pin]
    main: list[Pin]
    airbrake: Pin | None = None
    accel_fifo: list[Pin] = msgspec.field(default_factory=list)
    gyro: Pin | None = None
    baro: list[Pin] = msgspec.field(default_factory=list)
    gps_alt: Pin | None = None
    gps_fix: Pin | None = None


class SensorParams(msgspec.Struct, forbid_unknown_fields=True):
    """Sensor flaws (1-sigma noise; biases drawn once per flight from the seed).

    Scales: what one volt on the pin means (the devices' ``scale``).
    ``baro_noise_pa`` ~ 0.5 m; ``accel_sat_mps2`` 16 g; GPS at ``gps_hz``
    with ``gps_dropout`` probability per fix and no fix above ``gps_max_g``.
    ``imu_fail_s`` / ``baro_fail_s``: seconds after ignition at which the
    IMU freezes / dn0's barometer reads nan (fault injection; None: never).
    """

    seed: int = 1
    baro_noise_pa: Annotated[float, Meta(ge=0)] = 6.0
    baro_lag_s: Annotated[float, Meta(ge=0)] = 0.03
    baro_quantum_pa: Annotated[float, Meta(ge=0)] = 1.2
    baro_transonic: Annotated[float, Meta(ge=0)] = 0.2
    baro_pa_per_volt: Annotated[float, Meta(gt=0)] = 50_000.0
    accel_noise_mps2: Annotated[float, Meta(ge=0)] = 0.4
    accel_bias_mps2: Annotated[float, Meta(ge=0)] = 0.4
    accel_sat_mps2: Annotated[float, Meta(gt=0)] = 156.9
    accel_quantum_mps2: Annotated[float, Meta(ge=0)] = 0.0048
    accel_mps2_per_volt: Annotated[float, Meta(gt=0)] = 100.0
    gyro_noise_dps: Annotated[float, Meta(ge=0)] = 0.2
    gyro_bias_dps: Annotated[float, Meta(ge=0)] = 0.5
    gyro_sat_dps: Annotated[float, Meta(gt=0)] = 2000.0
    gyro_dps_per_volt: Annotated[float, Meta(gt=0)] = 1000.0
    gps_hz: Annotated[float, Meta(gt=0, le=50)] = 10.0
    gps_noise_m: Annotated[float, Meta(ge=0)] = 2.5
    gps_dropout: Annotated[float, Meta(ge=0, le=1)] = 0.05
    gps_max_g: Annotated[float, Meta(gt=0)] = 4.0
    gps_m_per_volt: Annotated[float, Meta(gt=0)] = 1000.0
    imu_fail_s: float | None = None
    baro_fail_s: float | None = None


class VehicleParams(msgspec.Struct, forbid_unknown_fields=True):
    """The rocket, its motor and its recovery (the world's ``params``)."""

    motor: str
    wiring: Wiring
    dry_mass_kg: Annotated[float, Meta(gt=0)]
    diameter_m: Annotated[float, Meta(gt=0)]
    cd_mach: list[tuple[float, float]] = msgspec.field(
        default_factory=lambda: [(0.0, 0.45), (0.8, 0.47), (1.0, 0.62), (1.2, 0.58), (2.0, 0.45)]
    )
    rail_length_m: Annotated[float, Meta(ge=0)] = 3.0
    launch_angle_deg: Annotated[float, Meta(gt=0, le=90)] = 90.0
    pad_altitude_m: float = 0.0
    g_mps2: Annotated[float, Meta(gt=0)] = 9.80665
    weathercock_s: Annotated[float, Meta(gt=0)] = 0.3
    crush_mps2: Annotated[float, Meta(gt=0)] = 100.0
    drogue_cda_m2: Annotated[float, Meta(ge=0)] = 0.1
    drogue_inflation_s: Annotated[float, Meta(ge=0)] = 0.5
    main_cda_m2: Annotated[float, Meta(ge=0)] = 1.2
    main_inflation_s: Annotated[float, Meta(ge=0)] = 1.0
    airbrake_cda_m2: Annotated[float, Meta(ge=0)] = 0.01
    airbrake_rate: Annotated[float, Meta(gt=0)] = 2.0
    airbrake_full_volts: Annotated[float, Meta(gt=0)] = 5.0
    wind_mps: float = 0.0
    gust_mps: Annotated[float, Meta(ge=0)] = 0.0
    gust_tau_s: Annotated[float, Meta(gt=0)] = 2.0
    sensors: SensorParams = msgspec.field(default_factory=SensorParams)

    def __post_init__(self) -> None:
        if len(self.cd_mach) < 1 or any(
            b[0] <= a[0] for a, b in zip(self.cd_mach, self.cd_mach[1:], strict=False)
        ):
            raise ValueError("cd_mach needs [mach, cd] points with increasing mach")


def _interp(points: list[tuple[float, float]], x: float) -> float:
    if x <= points[0][0]:
        return points[0][1]
    for (x0, y0), (x1, y1) in itertools.pairwise(points):
        if x <= x1:
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return points[-1][1]


class Flight:
    """The vehicle's state and its integration (module doc).

    :meth:`step` advances one :data:`STEP_NS` with the given actuator
    states. Everything is deterministic given ``params`` (the gust draws
    come from ``params.sensors.seed``).
    """

    def __init__(self, params: VehicleParams) -> None:
        self.p = params
        self.motor = Motor(params.motor)
        self.area = math.pi * (params.diameter_m / 2) ** 2
        a = math.radians(params.launch_angle_deg)
        self.rail = (math.cos(a), math.sin(a))
        self.t = 0.0  # s since ignition
        self.x = self.z = self.vx = self.vz = 0.0
        self.axis = self.rail
        self.pitch_rate = 0.0  # rad/s, the axis turning (the gyro's quantity)
        self.ignited = False
        self.lifted = False
        self.off_rail = False
        self.landed = False
        self.drogue_at: float | None = None
        self.main_at: float | None = None
        self.brake = 0.0  # airbrake deployment 0..1
        self.specific_force = 0.0  # along the body axis, m/s^2 (the accelerometer's)
        self.mach = 0.0
        self.gust = 0.0
        self._rng = random.Random(params.sensors.seed * 7919 + 17)
        # records
        self.apogee_m = 0.0
        self.apogee_t: float | None = None
        self.max_speed = 0.0

    @property
    def mass(self) -> float:
        return self.p.dry_mass_kg + self.motor.dry_kg + self.motor.propellant(self.t)

    def chute_cda(self, t: float) -> float:
        p = self.p
        cda = 0.0
        for at, full, infl in (
            (self.drogue_at, p.drogue_cda_m2, p.drogue_inflation_s),
            (self.main_at, p.main_cda_m2, p.main_inflation_s),
        ):
            if at is not None and t >= at:
                cda += full if infl <= 0 or t - at >= infl else full * (t - at) / infl
        return cda

    def _accel(
        self, t: float, vx: float, vz: float, z: float, axis: tuple[float, float]
    ) -> tuple[float, float, float]:
        """(ax, az, specific force along the axis) at a state."""
        p = self.p
        rho, _, a_snd = atmosphere(z + p.pad_altitude_m)
        wx = p.wind_mps + self.gust
        ux, uz = vx - wx, vz
        u = math.hypot(ux, uz)
        m = self.p.dry_mass_kg + self.motor.dry_kg + self.motor.propellant(t)
        chutes = self.chute_cda(t)
        cda = _interp(p.cd_mach, u / a_snd) * self.area + self.brake * p.airbrake_cda_m2 + chutes
        thrust = self.motor.thrust(t)
        fx = thrust * axis[0]
        fz = thrust * axis[1]
        if u > 1e-9:
            drag = 0.5 * rho * u * u * cda
            fx -= drag * ux / u
            fz -= drag * uz / u
        sf = (fx * axis[0] + fz * axis[1]) / m
        return fx / m, fz / m - p.g_mps2, sf

    def step(self, dt: float) -> None:
        """Advance ``dt`` seconds (RK4 on position and velocity)."""
        p = self.p
        t = self.t
        if self.landed:
            self.t = t + dt
            self.specific_force = p.g_mps2
            self.pitch_rate = 0.0
            return
        if not self.lifted:
            ax, az, sf = self._accel(t, 0.0, 0.0, 0.0, self.axis)
            # On the pad the rail holds the rocket until thrust beats weight.
            along = ax * self.rail[0] + az * self.rail[1]
            if along <= 0.0:
                self.t = t + dt
                self.specific_force = p.g_mps2 * self.rail[1]
                return
            self.lifted = True
        axis = self.axis
        on_rail = not self.off_rail

        def deriv(tt: float, vx: float, vz: float, z: float) -> tuple[float, float, float, float]:
            ax, az, _ = self._accel(tt, vx, vz, z, axis)
            if on_rail:  # only the component along the rail
                a_along = ax * self.rail[0] + az * self.rail[1]
                ax, az = a_along * self.rail[0], a_along * self.rail[1]
            return vx, vz, ax, az

        x, z, vx, vz = self.x, self.z, self.vx, self.vz
        k1 = deriv(t, vx, vz, z)
        k2 = deriv(t + dt / 2, vx + dt / 2 * k1[2], vz + dt / 2 * k1[3], z + dt / 2 * k1[1])
        k3 = deriv(t + dt / 2, vx + dt / 2 * k2[2], vz + dt / 2 * k2[3], z + dt / 2 * k2[1])
        k4 = deriv(t + dt, vx + dt * k3[2], vz + dt * k3[3], z + dt * k3[1])
        self.x = x + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        self.z = z + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        self.vx = vx + dt / 6 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
        self.vz = vz + dt / 6 * (k1[3] + 2 * k2[3] + 2 * k3[3] + k4[3])
        self.t = t + dt
        _, _, sf = self._accel(self.t, self.vx, self.vz, self.z, axis)
        self.specific_force = sf
        speed = math.hypot(self.vx, self.vz)
        self.max_speed = max(self.max_speed, speed)
        _, _, a_snd = atmosphere(self.z + p.pad_altitude_m)
        self.mach = speed / a_snd
        if self.z > self.apogee_m:
            self.apogee_m = self.z
        elif self.apogee_t is None and self.vz < 0.0:
            self.apogee_t = self.t
        if on_rail and (self.x * self.rail[0] + self.z * self.rail[1]) >= p.rail_length_m:
            self.off_rail = True
        self._turn(dt)
        self._gust(dt)
        if self.z <= 0.0 and self.t > 0.5:
            self._touchdown(dt)

    def _touchdown(self, dt: float) -> None:
        """Ground contact: the airframe stops at ``crush_mps2`` (the impact the
        accelerometer feels), then stands on the ground (landed)."""
        p = self.p
        self.z = 0.0
        self.vx = 0.0
        self.axis = (0.0, 1.0)
        self.pitch_rate = 0.0
        if self.vz < 0.0:
            self.vz = min(0.0, self.vz + p.crush_mps2 * dt)
            self.specific_force = p.crush_mps2 + p.g_mps2
        if self.vz >= 0.0:
            self.vz = 0.0
            self.landed = True
            self.specific_force = p.g_mps2

    def _turn(self, dt: float) -> None:
        """Weathercock the axis toward the air-relative velocity (or hang under a chute)."""
        if not self.off_rail:
            self.pitch_rate = 0.0
            return
        if self.drogue_at is not None or self.main_at is not None:
            want = math.pi / 2
        else:
            ux = self.vx - (self.p.wind_mps + self.gust)
            uz = self.vz
            if math.hypot(ux, uz) < 1.0:
                self.pitch_rate = 0.0
                return
            want = math.atan2(uz, ux)
        have = math.atan2(self.axis[1], self.axis[0])
        err = (want - have + math.pi) % (2 * math.pi) - math.pi
        rate = err / self.p.weathercock_s
        ang = have + rate * dt
        self.pitch_rate = rate
        self.axis = (math.cos(ang), math.sin(ang))

    def _gust(self, dt: float) -> None:
        p = self.p
        if p.gust_mps <= 0.0:
            return
        a = math.exp(-dt / p.gust_tau_s)
        self.gust = a * self.gust + p.gust_mps * math.sqrt(1 - a * a) * self._rng.gauss(0.0, 1.0)

    def set_actuators(self, drogue: bool, main: bool, brake_cmd: float, dt: float) -> None:
        """Latch chute deployments; slew the airbrakes toward ``brake_cmd`` (0..1)."""
        if drogue and self.drogue_at is None and self.ignited:
            self.drogue_at = self.t
        if main and self.main_at is None and self.ignited:
            self.main_at = self.t
        target = min(max(brake_cmd, 0.0), 1.0)
        step = self.p.airbrake_rate * dt
        self.brake += min(max(target - self.brake, -step), step)


class Sensors:
    """Every sensor's flaws, sampled on the physics grid (see :class:`SensorParams`)."""

    def __init__(self, p: SensorParams) -> None:
        self.p = p
        self._rng = random.Random(p.seed)
        g = self._rng.gauss
        self.accel_bias = g(0.0, p.accel_bias_mps2)
        self.gyro_bias = g(0.0, p.gyro_bias_dps)
        self.baro_lagged: float | None = None
        self.fifo: list[float] = []
        self.gyro = 0.0
        self.gps_alt = 0.0
        self.gps_fix = False
        self.gps_epochs = 0
        self._next_gps_ns: int | None = None
        self._imu_frozen = False

    def sample_imu(self, f: Flight, t: float) -> None:
        p = self.p
        if p.imu_fail_s is not None and f.ignited and f.t >= p.imu_fail_s:
            return  # the IMU stopped: its FIFO holds its last samples for ever
        a = f.specific_force + self.accel_bias + self._rng.gauss(0.0, p.accel_noise_mps2)
        a = min(max(a, -p.accel_sat_mps2), p.accel_sat_mps2)
        if p.accel_quantum_mps2 > 0:
            a = round(a / p.accel_quantum_mps2) * p.accel_quantum_mps2
        self.fifo.append(a)
        if len(self.fifo) > 32:
            del self.fifo[:-16]
        w = math.degrees(f.pitch_rate) + self.gyro_bias + self._rng.gauss(0.0, p.gyro_noise_dps)
        self.gyro = min(max(w, -p.gyro_sat_dps), p.gyro_sat_dps)

    def baro(self, f: Flight, dt: float, pad_m: float) -> float:
        """One barometer sample (Pa): lag, transonic dip, noise, quantisation."""
        p = self.p
        _, pres, _ = atmosphere(f.z + pad_m)
        if self.baro_lagged is None or p.baro_lag_s <= 0:
            self.baro_lagged = pres
        else:
            self.baro_lagged += (pres - self.baro_lagged) * min(1.0, dt / p.baro_lag_s)
        out = self.baro_lagged
        m = f.mach
        if 0.8 < m < 1.2:  # a shock over the static port: the reading dips
            rho, _, a = atmosphere(f.z + pad_m)
            q = 0.5 * rho * (m * a) ** 2
            out -= p.baro_transonic * q * (1.0 - abs(m - 1.0) / 0.2)
        out += self._rng.gauss(0.0, p.baro_noise_pa)
        if p.baro_quantum_pa > 0:
            out = round(out / p.baro_quantum_pa) * p.baro_quantum_pa
        return out

    def sample_gps(self, f: Flight, t_ns: int, pad_m: float) -> None:
        """The receiver's solution when one is due at ``t_ns``: on its own
        schedule, every ``1/gps_hz`` s of the world's clock (which runs alike
        on the pad and in flight), taken at the first sample at or after its
        time, the next due a period after that time (not after the sample:
        no drift). ``gps_epochs`` counts them; a dropout or high g is a
        solution without a fix (the flag drops, the altitude holds the last)."""
        p = self.p
        due = self._next_gps_ns
        if due is not None and t_ns < due:
            return
        period = round(1e9 / p.gps_hz)
        self._next_gps_ns = t_ns + period if due is None or t_ns - due >= period else due + period
        self.gps_epochs += 1
        lost = self._rng.random() < p.gps_dropout or abs(f.specific_force) > p.gps_max_g * 9.81
        self.gps_fix = not lost
        if not lost:
            self.gps_alt = f.z + pad_m + self._rng.gauss(0.0, p.gps_noise_m)


class _World:
    """What the hook keeps between calls (in ``world.state``)."""

    def __init__(self, params: VehicleParams) -> None:
        self.flight = Flight(params)
        self.sensors = Sensors(params.sensors)
        # each barometer its own noise (and lag state): seeds apart
        self.baros = [
            Sensors(msgspec.structs.replace(params.sensors, seed=params.sensors.seed + 101 * i))
            for i in range(1, len(params.wiring.baro) + 1)
        ]
        self.next_ns: int | None = None
        self.baro_pa = [0.0] * len(params.wiring.baro)


def vehicle(world: Any, t_ns: int) -> None:
    """The vehicle world's physics hook (:mod:`zplatform.world.model`): advance to ``t_ns``.

    Reads the actuator pins (igniter, chutes' switches, airbrake servo) of
    every board, steps :class:`Flight` on the 400 Hz grid up to ``t_ns``,
    and writes every sensor's pins. Before the igniter pin is on the
    vehicle sits on the pad and the flight clock does not run.
    """
    p: VehicleParams = world.params
    st: _World | None = world.state.get("vehicle")
    if st is None:
        st = _World(p)
        world.state["vehicle"] = st
        st.next_ns = t_ns
    f, s, w = st.flight, st.sensors, p.wiring
    b = world.boards
    dt = STEP_NS / 1e9
    assert st.next_ns is not None
    while st.next_ns <= t_ns:
        if not f.ignited and b[w.ignition[0]].output_digital(w.ignition[1]):
            f.ignited = True
        drogue = all(b[n].output_digital(i) for n, i in w.drogue)
        main = all(b[n].output_digital(i) for n, i in w.main)
        brake = (
            b[w.airbrake[0]].output_analog(w.airbrake[1]) / p.airbrake_full_volts
            if w.airbrake is not None
            else 0.0
        )
        f.set_actuators(drogue, main, brake, dt)
        if f.ignited:
            f.step(dt)
        else:
            f.specific_force = p.g_mps2 * f.rail[1]
        s.sample_imu(f, f.t)
        for i, bs in enumerate(st.baros):
            st.baro_pa[i] = bs.baro(f, dt, p.pad_altitude_m)
        s.sample_gps(f, st.next_ns, p.pad_altitude_m)
        st.next_ns += STEP_NS
    sp = p.sensors
    fifo = s.fifo
    for k, (n, pin) in enumerate(w.accel_fifo):  # the FIFO's newest samples, oldest first
        j = len(fifo) - len(w.accel_fifo) + k
        b[n].inject_analog(pin, fifo[j] / sp.accel_mps2_per_volt if j >= 0 else 0.0)
    if w.gyro is not None:
        b[w.gyro[0]].inject_analog(w.gyro[1], s.gyro / sp.gyro_dps_per_volt)
    for i, (n, pin) in enumerate(w.baro):
        pa = st.baro_pa[i]
        if i == 0 and sp.baro_fail_s is not None and f.ignited and f.t >= sp.baro_fail_s:
            pa = math.nan
        b[n].inject_analog(pin, pa / sp.baro_pa_per_volt)
    if w.gps_alt is not None:
        b[w.gps_alt[0]].inject_analog(w.gps_alt[1], s.gps_alt / sp.gps_m_per_volt)
    if w.gps_fix is not None:
        b[w.gps_fix[0]].inject_digital(w.gps_fix[1], s.gps_fix)
    world.truth = f


def check(world: Any) -> None:
    """Load-time check of the world (:mod:`zplatform.world.model`): the motor file
    reads, and every wired pin is on its board (ValueError otherwise)."""
    p: VehicleParams = world.params
    Motor(p.motor)
    w = p.wiring
    digital = [w.ignition, *w.drogue, *w.main]
    if w.gps_fix is not None:
        digital.append(w.gps_fix)
    analog = [*w.accel_fifo, *w.baro]
    analog += [x for x in (w.airbrake, w.gyro, w.gps_alt) if x is not None]
    for pins, kind in ((digital, "digital"), (analog, "analog")):
        for node, pin in pins:
            board = world.boards.get(node)
            if board is None:
                raise ValueError(
                    f"wiring names board {node!r}; the world has {sorted(world.boards)}"
                )
            n = board.digital_pins if kind == "digital" else board.analog_pins
            if not 0 <= pin < n:
                raise ValueError(f"wiring: {kind} pin {pin} is not on {node} ({n} {kind} pins)")


vehicle.Params = VehicleParams  # type: ignore[attr-defined]
vehicle.check = check  # type: ignore[attr-defined]
