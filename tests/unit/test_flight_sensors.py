"""The flight physics' sensors and their flaws (``nodes/flight/physics.py``, issue 19).

Each flaw the issue lists, alone, against its parameter: barometer noise,
lag, quantisation and transonic dip; accelerometer and gyro noise, bias,
saturation (and the accelerometer's quantisation); GPS at its rate, with
dropouts and no fix under high g. Then the sensors behind the vehicle
world's pins (:func:`~nodes.flight.physics.vehicle`): seeded (the same seed
reads the same, another seed other values), the GPS fixing all flight long,
and the fault injections. Every draw is seeded, so each count here is exact
run to run; the bounds only say what the parameter means.
"""

from __future__ import annotations

import itertools
import math
import statistics
from pathlib import Path
from typing import Any

import msgspec
import pytest

from nodes.flight import Ekf
from nodes.flight.physics import (
    STEP_NS,
    Flight,
    SensorParams,
    Sensors,
    VehicleParams,
    atmosphere,
    pressure_altitude,
)
from zplatform import load_mission
from zplatform.world.model import World

FLIGHT_YAML = Path(__file__).resolve().parents[2] / "configs" / "flight.yaml"
DT = STEP_NS / 1e9
G = 9.80665
T0_NS = 1_700_000_000_000_000_000  # the lockstep runner's epoch: world time is not flight time


def vehicle_at(z: float = 0.0, *, sf: float = G, mach: float = 0.0, rate: float = 0.0) -> Flight:
    """The shipped rocket, held at altitude ``z`` with the given specific
    force, Mach number and pitch rate (what the sensors sample)."""
    p = msgspec.convert(
        {"motor": "Cesaroni_J360.eng", "dry_mass_kg": 6.5, "diameter_m": 0.102,
         "wiring": {"ignition": ["dn0", 0], "drogue": [], "main": []}},
        VehicleParams,
    )  # fmt: skip
    f = Flight(p)
    f.z, f.specific_force, f.mach, f.pitch_rate = z, sf, mach, rate
    return f


def sensors(**params: Any) -> Sensors:
    return Sensors(SensorParams(**params))


def on_grid(x: float, step: float) -> bool:
    return abs(x / step - round(x / step)) < 1e-6


# -- barometer -------------------------------------------------------------------


def test_barometer_noise_has_its_sigma_around_the_isa_pressure() -> None:
    s = sensors(baro_noise_pa=6.0, baro_quantum_pa=0.0, baro_lag_s=0.0)
    f = vehicle_at(100.0)
    xs = [s.baro(f, DT, 0.0) for _ in range(4000)]
    assert statistics.fmean(xs) == pytest.approx(atmosphere(100.0)[1], abs=0.5)
    assert statistics.stdev(xs) == pytest.approx(6.0, rel=0.05)
    quiet = sensors(baro_noise_pa=0.0, baro_quantum_pa=0.0, baro_lag_s=0.0)
    assert {quiet.baro(f, DT, 0.0) for _ in range(10)} == {atmosphere(100.0)[1]}


def test_barometer_readings_are_quantised_in_steps_of_its_quantum() -> None:
    """Every reading is a whole number of quanta; without noise, a slow climb
    reads as a staircase of exactly one quantum per step."""
    q = 1.2
    noisy = sensors(baro_noise_pa=6.0, baro_quantum_pa=q, baro_lag_s=0.0)
    f = vehicle_at(50.0)
    assert all(on_grid(noisy.baro(f, DT, 0.0), q) for _ in range(1000))
    s = sensors(baro_noise_pa=0.0, baro_quantum_pa=q, baro_lag_s=0.0)
    reads = []
    for k in range(500):  # 0 to 5 m in 1 cm steps: about 0.12 Pa a step
        f.z = k * 0.01
        reads.append(s.baro(f, DT, 0.0))
    assert reads == [round(atmosphere(k * 0.01)[1] / q) * q for k in range(500)]
    steps = {round(b - a, 6) for a, b in itertools.pairwise(reads)}
    assert steps == {0.0, -q}


def test_barometer_lag_is_first_order_with_its_time_constant() -> None:
    tau = 0.03
    s = sensors(baro_noise_pa=0.0, baro_quantum_pa=0.0, baro_lag_s=tau)
    f = vehicle_at(0.0)
    p0 = s.baro(f, DT, 0.0)  # the first sample starts the lag at the truth
    assert p0 == atmosphere(0.0)[1]
    f.z = 100.0  # a step of 100 m
    p1 = atmosphere(100.0)[1]
    frac = [(p0 - s.baro(f, DT, 0.0)) / (p0 - p1) for _ in range(60)]
    for n, x in enumerate(frac, 1):
        assert x == pytest.approx(1.0 - (1.0 - DT / tau) ** n, rel=1e-9)
    assert 0.6 < frac[11] < 0.7  # 63 % after one time constant (12 steps)
    assert frac[59] > 0.99  # settled after five
    none = sensors(baro_noise_pa=0.0, baro_quantum_pa=0.0, baro_lag_s=0.0)
    none.baro(vehicle_at(0.0), DT, 0.0)
    assert none.baro(f, DT, 0.0) == p1


@pytest.mark.parametrize(
    ("mach", "share"), [(0.5, 0.0), (0.8, 0.0), (0.9, 0.5), (1.0, 1.0), (1.1, 0.5), (1.2, 0.0)]
)
def test_barometer_transonic_dip_peaks_at_mach_1(mach: float, share: float) -> None:
    """Between Mach 0.8 and 1.2 the static port reads low by up to
    ``baro_transonic`` of the dynamic pressure, most at Mach 1."""
    s = sensors(baro_noise_pa=0.0, baro_quantum_pa=0.0, baro_lag_s=0.0, baro_transonic=0.2)
    rho, p, a = atmosphere(1000.0)
    dip = p - s.baro(vehicle_at(1000.0, mach=mach), DT, 0.0)
    assert dip == pytest.approx(share * 0.2 * 0.5 * rho * (mach * a) ** 2, abs=1e-6)


def test_the_transonic_dip_reads_a_kilometre_high_unless_turned_off() -> None:
    f = vehicle_at(1000.0, mach=1.0)
    s = sensors(baro_noise_pa=0.0, baro_quantum_pa=0.0, baro_lag_s=0.0)
    assert pressure_altitude(s.baro(f, DT, 0.0)) - 1000.0 > 1000.0
    off = sensors(baro_noise_pa=0.0, baro_quantum_pa=0.0, baro_lag_s=0.0, baro_transonic=0.0)
    assert pressure_altitude(off.baro(f, DT, 0.0)) == pytest.approx(1000.0, abs=1e-6)


# -- accelerometer and gyro -----------------------------------------------------------


def test_accelerometer_bias_is_drawn_once_a_flight_from_the_seed() -> None:
    s = sensors(seed=7, accel_noise_mps2=0.0, accel_quantum_mps2=0.0, accel_bias_mps2=0.4)
    f = vehicle_at(sf=20.0)
    for _ in range(100):
        s.sample_imu(f, 0.0)
    assert set(s.fifo) == {20.0 + s.accel_bias} and s.accel_bias != 0.0
    assert sensors(seed=7).accel_bias == s.accel_bias
    biases = [sensors(seed=n, accel_bias_mps2=0.4).accel_bias for n in range(1, 401)]
    assert len(set(biases)) == 400
    assert abs(statistics.fmean(biases)) < 0.1
    assert statistics.stdev(biases) == pytest.approx(0.4, rel=0.15)


def test_accelerometer_noise_has_its_sigma_and_the_fifo_keeps_the_newest() -> None:
    s = sensors(accel_noise_mps2=0.4, accel_bias_mps2=0.0, accel_quantum_mps2=0.0)
    f = vehicle_at(sf=50.0)
    xs = []
    for _ in range(4000):
        s.sample_imu(f, 0.0)
        xs.append(s.fifo[-1])
        assert len(s.fifo) <= 32  # a FIFO, not a log
    assert statistics.fmean(xs) == pytest.approx(50.0, abs=0.03)
    assert statistics.stdev(xs) == pytest.approx(0.4, rel=0.05)
    assert s.fifo[-16:] == xs[-16:]


def test_accelerometer_readings_are_quantised() -> None:
    q = 0.0048
    s = sensors(accel_quantum_mps2=q)
    f = vehicle_at(sf=33.3)
    for _ in range(500):
        s.sample_imu(f, 0.0)
    assert all(on_grid(a, q) for a in s.fifo)
    assert len(set(s.fifo)) > 10  # the noise (0.4) spans many quanta


@pytest.mark.parametrize("sf", [300.0, -300.0])
def test_accelerometer_saturates_at_its_range(sf: float) -> None:
    """Beyond 16 g the reading clips (to within one quantum when quantised),
    and the flight software's EKF calls such a reading lost before it clips."""
    sat = 156.9
    clean = sensors(accel_sat_mps2=sat, accel_quantum_mps2=0.0)
    quantised = sensors(accel_sat_mps2=sat)
    f = vehicle_at(sf=sf)
    for _ in range(200):
        clean.sample_imu(f, 0.0)
        quantised.sample_imu(f, 0.0)
    assert set(clean.fifo) == {math.copysign(sat, sf)}
    q = quantised.p.accel_quantum_mps2
    assert all(abs(abs(a) - sat) <= q / 2 + 1e-12 for a in quantised.fifo)
    fields = msgspec.structs.fields(Ekf.Config)
    ekf_sat = next(x.default for x in fields if x.name == "saturation_mps2")
    assert ekf_sat < SensorParams().accel_sat_mps2 - q


def test_gyro_has_its_noise_bias_and_range() -> None:
    s = sensors(seed=3, gyro_noise_dps=0.2, gyro_bias_dps=0.5)
    f = vehicle_at(rate=math.radians(30.0))
    ws = []
    for _ in range(4000):
        s.sample_imu(f, 0.0)
        ws.append(s.gyro)
    assert s.gyro_bias != 0.0 and sensors(seed=3).gyro_bias == s.gyro_bias
    assert statistics.fmean(ws) == pytest.approx(30.0 + s.gyro_bias, abs=0.02)
    assert statistics.stdev(ws) == pytest.approx(0.2, rel=0.05)
    for rate in (5000.0, -5000.0):
        f.pitch_rate = math.radians(rate)
        s.sample_imu(f, 0.0)
        assert s.gyro == math.copysign(2000.0, rate)


# -- GPS -------------------------------------------------------------------------


def gps_track(s: Sensors, f: Flight, seconds: float) -> list[tuple[int, bool, float]]:
    """Sample the GPS on the physics grid for ``seconds`` of world time (from
    the lockstep epoch); each attempted fix as (grid step, fix, altitude)."""
    out = []
    for k in range(round(seconds / DT)):
        n = s.gps_epochs
        s.sample_gps(f, T0_NS + k * STEP_NS, 0.0)
        if s.gps_epochs != n:
            out.append((k, s.gps_fix, s.gps_alt))
    return out


@pytest.mark.parametrize("hz", [5.0, 7.0, 10.0, 20.0])
def test_gps_fixes_at_its_rate_without_drifting(hz: float) -> None:
    """``gps_hz`` fixes a second, each on the first physics step at or after
    its time on the receiver's own schedule: no step late, no drift."""
    s = sensors(gps_hz=hz, gps_dropout=0.0)
    track = gps_track(s, vehicle_at(300.0), 20.0)
    assert len(track) == round(20 * hz)
    period_ns = round(1e9 / hz)
    for n, (k, fix, alt) in enumerate(track):
        assert k == -(-n * period_ns // STEP_NS), n  # the n-th fix's grid step
        assert fix and abs(alt - 300.0) < 5 * s.p.gps_noise_m


def test_gps_drops_fixes_at_its_dropout_rate_and_says_so() -> None:
    s = sensors(gps_hz=10.0, gps_dropout=0.2)
    track = gps_track(s, vehicle_at(300.0), 500.0)
    lost = [i for i, (_, fix, _) in enumerate(track) if not fix]
    assert len(track) == 5000
    assert len(lost) / len(track) == pytest.approx(0.2, abs=0.02)
    for i in lost:  # no fix: the flag drops, the altitude is the last fix's
        assert track[i][2] == track[i - 1][2]
    assert all(fix for _, fix, _ in gps_track(sensors(gps_dropout=0.0), vehicle_at(), 10.0))
    assert not any(fix for _, fix, _ in gps_track(sensors(gps_dropout=1.0), vehicle_at(), 10.0))


def test_gps_has_no_fix_under_high_g() -> None:
    s = sensors(gps_dropout=0.0, gps_max_g=4.0)
    assert not any(fix for _, fix, _ in gps_track(s, vehicle_at(sf=5 * G), 5.0))
    assert all(fix for _, fix, _ in gps_track(s, vehicle_at(sf=3 * G), 5.0))


# -- behind the pins: the vehicle world ----------------------------------------------


def world(**sensor_params: Any) -> World:
    m = load_mission(FLIGHT_YAML)
    assert m.world is not None
    m.world.params["sensors"] = {**m.world.params.get("sensors", {}), **sensor_params}
    return World(m)


def readings(w: World, seconds: float, *, ignite_at_s: float = 1.0) -> list[tuple[Any, ...]]:
    """Every sensor pin at 100 Hz for ``seconds`` of world time, the motor
    igniter on from ``ignite_at_s``: dn0's four FIFO samples, gyro and
    barometer; dn1's barometer, GPS altitude and fix."""
    d0, d1 = w.boards["dn0"], w.boards["dn1"]
    out = []
    for k in range(round(seconds * 100)):
        if k == round(ignite_at_s * 100):
            d0.set_digital(0, True)
        w.advance(T0_NS + k * 10_000_000)
        out.append((*(d0.get_analog(p) for p in range(6)), d1.get_analog(0),
                    d1.get_analog(1), d1.get_digital(0)))  # fmt: skip
    return out


def test_the_same_seed_reads_the_same_and_another_seed_reads_otherwise() -> None:
    a, b, c = (readings(w, 12.0) for w in (world(seed=1), world(seed=1), world(seed=2)))
    assert a == b
    for pin in range(8):  # every sensor's stream comes from the seed
        assert [r[pin] for r in a] != [r[pin] for r in c], pin
    # dn0's and dn1's barometers: the same air, each its own noise
    assert sum(r[5] == r[6] for r in a) < len(a) // 10


def test_the_gps_keeps_fixing_all_flight_at_its_rate() -> None:
    """Through the vehicle world, as the flight software sees it: dn1's GPS
    pins hold a new fix every 0.1 s on the pad and again once the boost's
    4 g is over, each within 5 sigma of the truth; no fix under the boost
    (the flag drops)."""
    w = world(gps_dropout=0.0)
    d0, d1 = w.boards["dn0"], w.boards["dn1"]
    fixes: list[tuple[float, float]] = []  # (flight s, GPS altitude - truth)
    no_fix = 0
    last = None
    for k in range(2000):  # 20 s, the igniter on at 1 s
        if k == 100:
            d0.set_digital(0, True)
        w.advance(T0_NS + k * 10_000_000)
        f = w.truth
        alt = d1.get_analog(1) * 1000.0
        if not d1.get_digital(0):
            no_fix += 1
        elif alt != last and f.ignited:
            fixes.append((f.t, alt - f.z))
        last = alt
    f = w.truth
    assert f.ignited and f.t > 18.0 and f.apogee_m > 500.0
    assert 100 < no_fix < 400  # the boost (about 3 s at over 4 g)
    after = [t for t, _ in fixes if t > 4.0]  # coast: 10 Hz
    assert len(after) == pytest.approx(10 * (f.t - 4.0), abs=2)
    assert all(abs(e) < 5 * 2.5 for _, e in fixes)


def test_fault_injections_freeze_the_imu_and_kill_dn0s_barometer() -> None:
    """``imu_fail_s``: from then on the FIFO pins never change (the IMU
    stopped); ``baro_fail_s``: dn0's barometer reads nan, dn1's reads on."""
    r = readings(world(imu_fail_s=2.0, baro_fail_s=3.0), 6.0)  # flight s = world s - 1
    imu = [x[:5] for x in r]
    assert len(set(imu[310:])) == 1 and len(set(imu[250:300])) > 10
    assert all(math.isnan(x[5]) for x in r[410:])
    assert not any(math.isnan(x[5]) for x in r[:390])
    assert not any(math.isnan(x[6]) for x in r)
