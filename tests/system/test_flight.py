"""The flight mission in lockstep (issue 19): recovery, airbrakes, faults, determinism.

Every check compares the flight software's decisions with the physics'
truth (the vehicle world's :class:`~nodes.flight.physics.Flight`), which the
flight software never sees: the drogue deploys after the true apogee, the
main at its altitude, the airbrakes land the apogee on the target.
"""

from __future__ import annotations

import math
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from nodes.flight.physics import STEP_NS, Flight, VehicleParams
from zplatform import load_mission
from zplatform.config import Mission
from zplatform.control.uplink import load_commands, parse_commands
from zplatform.sim.lockstep import LockstepRunner, SimResult
from zplatform.telemetry.logs import CsvLogger

ROOT = Path(__file__).resolve().parents[2]
FLIGHT_YAML = ROOT / "configs" / "flight.yaml"
FLIGHT_CMDS = ROOT / "configs" / "flight.commands"
MAIN_M = 150.0
TARGET_M = 600.0


@dataclass
class Flown:
    """What a lockstep flight did, against the truth."""

    result: SimResult
    truth: Flight
    states: list[tuple[float, str]] = field(default_factory=list)  # (mission s, state)
    drogue_alt: float | None = None
    main_alt: float | None = None
    runner: Any = None

    def entered(self, state: str) -> float:
        return next(t for t, s in self.states if s == state)


def fly(
    mission: Mission,
    script: str | None = None,
    *,
    seconds: float = 70.0,
    until_landed: bool = True,
    lose: tuple[float, str] | None = None,
    each: Callable[[LockstepRunner], None] | None = None,
) -> Flown:
    """Fly ``mission`` in lockstep (the shipped script unless ``script``),
    loop by loop, recording the truth at each chute's deployment;
    ``each(runner)`` after every loop (to watch the vector against the truth)."""
    cmds = load_commands(FLIGHT_CMDS) if script is None else parse_commands(script)
    r = LockstepRunner(mission, commands=cmds)
    assert r.world is not None
    state = r.control.dv.handle("cn_state")
    out = Flown(result=r.result(), truth=None, runner=r)  # type: ignore[arg-type]
    last = -1
    for _ in range(round(seconds * mission.loop_hz)):
        if lose is not None and r.loop * 0.01 >= lose[0]:
            r.lost.add(lose[1])
        r.step()
        if each is not None:
            each(r)
        f = r.world.truth
        s = state.get()
        if s != last:
            out.states.append((r.loop * 0.01, state.spec.name_of(s)))
            last = s
        if f is None:
            continue
        if f.drogue_at is not None and out.drogue_alt is None:
            out.drogue_alt = f.z
        if f.main_at is not None and out.main_alt is None:
            out.main_alt = f.z
        if until_landed and out.states[-1][1] == "LANDED":
            break
    out.result = r.result()
    out.truth = r.world.truth
    return out


def flight(**params: Any) -> Mission:
    """The shipped mission with world params replaced (``sensors`` merged)."""
    m = load_mission(FLIGHT_YAML)
    assert m.world is not None
    sensors = {**m.world.params.get("sensors", {}), **params.pop("sensors", {})}
    m.world.params.update(params, sensors=sensors)
    return m


@pytest.fixture(scope="module")
def nominal() -> Flown:
    return fly(load_mission(FLIGHT_YAML))


def test_the_shipped_flight_flies_every_state_and_lands_under_both_chutes(nominal: Flown) -> None:
    f, res = nominal.truth, nominal.result
    assert [s for _, s in nominal.states] == [
        "SAFE", "ARMED", "BOOST", "COAST", "DROGUE", "MAIN", "LANDED",
    ]  # fmt: skip
    assert res.errors == 0 and res.fault == "NONE"
    assert [c.status for c in res.commands] == ["ACCEPTED"] * 3
    assert f.landed and f.drogue_at is not None and f.main_at is not None
    dv = nominal.runner.control.dv
    assert dv.get("drogue_fired") and dv.get("main_fired")
    # The motor lit when the countdown ended, not at node start.
    assert nominal.entered("ARMED") == pytest.approx(1.11, abs=0.02)
    assert nominal.entered("BOOST") == pytest.approx(3.1, abs=0.15)


def test_recovery_and_airbrakes_meet_their_marks_on_the_shipped_flight(nominal: Flown) -> None:
    f = nominal.truth
    assert f.apogee_t is not None and f.drogue_at is not None
    assert 0.0 < f.drogue_at - f.apogee_t <= 0.5
    assert nominal.main_alt is not None and abs(nominal.main_alt - MAIN_M) <= 10.0
    assert abs(f.apogee_m - TARGET_M) <= 0.03 * TARGET_M


def _free_and_braked_apogee(params: dict[str, Any]) -> tuple[float, float]:
    """The truth model alone: apogee with the brakes in, and fully out after burnout."""
    out = []
    for brake in (0.0, 1.0):
        p = msgspec.convert(params, VehicleParams)
        f = Flight(p)
        f.ignited = True
        dt = STEP_NS / 1e9
        while f.apogee_t is None and f.t < 60:
            f.set_actuators(False, False, brake if f.t > f.motor.burn_time else 0.0, dt)
            f.step(dt)
        out.append(f.apogee_m)
    return out[0], out[1]


_WEATHER = given(
    seed=st.integers(1, 10_000),
    wind=st.floats(0.0, 8.0),
    gust=st.floats(0.0, 2.0),
    dry=st.floats(5.5, 7.5),
    aim=st.floats(0.15, 0.85),
)


def _weathers(n: int) -> Any:
    """``n`` weathers, the same ones every run. Each is a 40 s flight in
    lockstep (about a second of CPU): the default suite flies 3 (the shipped
    flight's own marks are checked above), the soaks (-m slow) 40."""
    return settings(
        max_examples=n,
        deadline=None,
        derandomize=True,
        suppress_health_check=[HealthCheck.too_slow],
    )


@_weathers(3)
@_WEATHER
def test_recovery_and_airbrakes_over_seeded_noise_and_wind(
    seed: int, wind: float, gust: float, dry: float, aim: float
) -> None:
    """Drogue within 0.5 s after the true apogee, never before; main within
    10 m of its altitude; apogee within 3 % of any target the rocket (its
    dry mass drawn too, and known to its airbrake controller) can reach."""
    _recovery_and_airbrakes(seed, wind, gust, dry, aim)


@pytest.mark.slow
@_weathers(40)
@_WEATHER
def test_recovery_and_airbrakes_over_many_weathers(
    seed: int, wind: float, gust: float, dry: float, aim: float
) -> None:
    """The same property over 40 weathers."""
    _recovery_and_airbrakes(seed, wind, gust, dry, aim)


def _recovery_and_airbrakes(seed: int, wind: float, gust: float, dry: float, aim: float) -> None:
    m = flight(wind_mps=wind, gust_mps=gust, dry_mass_kg=dry, sensors={"seed": seed})
    assert m.world is not None
    free, braked = _free_and_braked_apogee({**m.world.params, "gust_mps": 0.0})
    target = braked + aim * (free - braked)  # a target the rocket can reach, in this wind
    assume(braked + 15.0 < target < free - 15.0)  # with a margin for the gusts
    brakes = next(c for c in m.controllers if c.name == "airbrakes")
    brakes.config["target_m"] = target
    brakes.config["mass_kg"] = dry + 0.498  # the motor's case (Cesaroni_J360.eng)
    fl = fly(m, seconds=40.0, until_landed=False)
    f = fl.truth
    assert f.apogee_t is not None and f.drogue_at is not None, fl.states
    assert 0.0 < f.drogue_at - f.apogee_t <= 0.5
    assert fl.main_alt is not None and abs(fl.main_alt - MAIN_M) <= 10.0
    assert abs(f.apogee_m - target) <= 0.03 * target, (f.apogee_m, target)


# A light 76 mm rocket (3 kg dry, airbrakes scaled to its airframe) on a
# Cesaroni K490 (nodes/flight/Cesaroni_K490.eng): Mach 1.05 at burnout, so
# both barometers see the transonic dip of physics.Sensors.baro (a shock over
# the static port, up to 0.2 q: 1.2 km of false altitude), rising through
# Mach 0.8 in boost and receding through it in coast 4.7 s after lift-off,
# when the apogee detector is armed (FlightEvents.min_coast_s) and a dip that
# recedes reads as a fall. The flight software is the shipped one: its
# airbrakes, aiming at 600 m, go fully out at burnout (apogee about 2 km).
TRANSONIC = {"motor": "Cesaroni_K490.eng", "dry_mass_kg": 3.0, "diameter_m": 0.076,
             "airbrake_cda_m2": 0.006}  # fmt: skip


@dataclass
class Transonic:
    """What the flight software read while the truth was between Mach 0.8 and
    1.2 (the dip's band), against the truth, loop by loop."""

    mach: float = 0.0  # the truth's highest
    last_s: float = 0.0  # mission time of the band's last loop
    baro_high_m: float = 0.0  # the barometers' worst reading above the truth
    nav_err_m: list[float] = field(default_factory=list)  # nav_h_m - truth
    nav_v_err_mps: list[float] = field(default_factory=list)  # nav_v_mps - truth
    at_apogee_m: float | None = None  # nav_h_m - truth in the loop of the true apogee

    def watch(self, r: LockstepRunner) -> None:
        f, dv = r.world.truth, r.control.dv
        if f is None:
            return
        if f.apogee_t is not None and self.at_apogee_m is None:
            self.at_apogee_m = dv.get("nav_h_m") - f.z
        if not 0.8 < f.mach < 1.2:
            return
        ground = dv.get("nav_ground_m")
        self.mach = max(self.mach, f.mach)
        self.last_s = r.loop * 0.01
        for baro in ("dn0_baro_m", "dn1_baro_m"):
            self.baro_high_m = max(self.baro_high_m, dv.get(baro) - ground - f.z)
        self.nav_err_m.append(dv.get("nav_h_m") - f.z)
        self.nav_v_err_mps.append(dv.get("nav_v_mps") - f.vz)


def test_a_transonic_flight_ignores_the_barometers_dip_and_deploys_after_apogee() -> None:
    """Through Mach 1 and back, the barometers read up to 1.2 km high; the
    EKF takes none of it (above transonic_mps it does not use them, and the
    gate refuses the rest): its altitude stays within 30 m of the truth (the
    barometers' own lag, which it followed in boost) and never above it, its
    velocity within 8 m/s. Once subsonic it takes the barometers back (it
    is within 2 m of the truth at apogee: no lock-out after the blackout),
    and the drogue fires after the true apogee, within 0.5 s, never before.
    No IMU warning: the accelerometer (16 g) never saturates."""
    seen = Transonic()
    fl = fly(flight(**TRANSONIC), seconds=22.0, until_landed=False, each=seen.watch)
    f, res = fl.truth, fl.result
    assert [s for _, s in fl.states] == ["SAFE", "ARMED", "BOOST", "COAST", "DROGUE"]
    assert seen.mach > 1.0 and seen.baro_high_m > 1000.0  # the dip's peak, both ways
    assert seen.last_s - fl.entered("BOOST") > 4.0  # it recedes with the detector armed
    assert len(seen.nav_err_m) > 150  # loops in the band (about 2.2 s)
    assert max(seen.nav_err_m) < 0.0 and min(seen.nav_err_m) > -30.0, seen.nav_err_m
    assert max(abs(e) for e in seen.nav_v_err_mps) < 8.0, seen.nav_v_err_mps
    assert seen.at_apogee_m is not None and abs(seen.at_apogee_m) < 2.0
    assert f.apogee_t is not None and f.drogue_at is not None
    assert 0.0 < f.drogue_at - f.apogee_t <= 0.5
    assert res.errors == 0 and res.fault == "NONE"
    assert [e.text for e in res.events if e.id == "component_warning"] == []
    assert fl.runner.control.dv.get_name("nav_mode") == "ACCEL"


@settings(max_examples=6, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
@given(seed=st.integers(1, 10_000), wind=st.floats(0.0, 8.0), gust=st.floats(0.0, 2.0))
def test_a_transonic_flight_over_seeded_noise_and_wind(seed: int, wind: float, gust: float) -> None:
    """The transonic flight's drogue, over seeds and wind: after the true
    apogee, within 0.5 s, never before."""
    fl = fly(flight(**TRANSONIC, wind_mps=wind, gust_mps=gust, sensors={"seed": seed}),
             seconds=22.0, until_landed=False)  # fmt: skip
    f = fl.truth
    assert [s for _, s in fl.states] == ["SAFE", "ARMED", "BOOST", "COAST", "DROGUE"]
    assert f.max_speed > 340.0  # through Mach 1
    assert f.apogee_t is not None and f.drogue_at is not None
    assert 0.0 < f.drogue_at - f.apogee_t <= 0.5


def test_an_estimate_knocked_past_the_gate_comes_back_to_the_barometers() -> None:
    """No lock-out: in coast (8 s), the estimate is moved 40 m above the
    truth, well past the gate, so every barometer is refused. Blind, its
    covariance grows until they are taken again: 3 s later it is back within
    3 m of the truth, and the flight goes on as the shipped one: the drogue
    after the true apogee, the main within 10 m of its altitude. (Without
    the blind loops' growth it refused the barometers for the rest of the
    flight and the main opened 40 m low.)"""
    errs: dict[int, float] = {}

    def knock(r: LockstepRunner) -> None:
        dv, f = r.control.dv, r.world.truth
        if r.loop == 800:
            assert dv.get_name("cn_state") == "COAST"
            dv.set("nav_h_m", dv.get("nav_h_m") + 40.0)
        if r.loop in (801, 1100):
            errs[r.loop] = dv.get("nav_h_m") - f.z

    fl = fly(load_mission(FLIGHT_YAML), each=knock)
    f = fl.truth
    assert errs[801] > 35.0 and abs(errs[1100]) < 3.0, errs
    assert [s for _, s in fl.states] == [
        "SAFE", "ARMED", "BOOST", "COAST", "DROGUE", "MAIN", "LANDED",
    ]  # fmt: skip
    assert f.apogee_t is not None and f.drogue_at is not None
    assert 0.0 < f.drogue_at - f.apogee_t <= 0.5
    assert fl.main_alt is not None and abs(fl.main_alt - MAIN_M) <= 10.0


PARAM_SCRIPT = """\
at 0.3 prm_set apogee_target_m 550
at 0.4 arm
at 0.5 prm_set main_deploy_m 250
at 0.6 prm_save
at 1.0 arm
at 1.1 launch
at 5.0 prm_set apogee_target_m 700
at 55 prm_set apogee_target_m 650
"""


def test_a_script_that_sets_parameters_changes_the_flight(nominal: Flown) -> None:
    """The apogee target and the main-chute altitude are parameters: set on
    the pad (the main's armed, it is hazardous) and saved, they move the
    apogee to 550 m and the main to 250 m; in flight and after landing
    PRM_SET is refused (the whitelist in BOOST, the parameter's states once
    LANDED), and nothing changes."""
    fl = fly(load_mission(FLIGHT_YAML), PARAM_SCRIPT, seconds=56.0, until_landed=False)
    f, res = fl.truth, fl.result
    assert [(c.command, c.status) for c in res.commands] == [
        ("PRM_SET", "ACCEPTED"), ("ARM", "ACCEPTED"), ("PRM_SET", "ACCEPTED"),
        ("PRM_SAVE", "ACCEPTED"), ("ARM", "ACCEPTED"), ("LAUNCH", "ACCEPTED"),
        ("PRM_SET", "REJECTED_NOT_ALLOWED"), ("PRM_SET", "REJECTED_PARAM_STATE"),
    ]  # fmt: skip
    assert [s for _, s in fl.states] == [
        "SAFE", "ARMED", "BOOST", "COAST", "DROGUE", "MAIN", "LANDED",
    ]  # fmt: skip
    assert abs(f.apogee_m - 550.0) <= 0.03 * 550.0
    assert nominal.truth.apogee_m - f.apogee_m > 30.0  # the default flight's is ~600 m
    assert fl.main_alt is not None and abs(fl.main_alt - 250.0) <= 10.0
    dv = fl.runner.control.dv
    assert dv.get("apogee_target_m") == 550.0 and dv.get("main_deploy_m") == 250.0
    assert dv.get_name("cn_prm_save_status") == "SAVED"  # in memory: a sim writes no file
    saved = fl.runner.saver.data
    assert saved is not None
    from zplatform.control.params import decode_params

    assert decode_params(fl.runner.mission, saved).values["main_deploy_m"] == 250.0


def test_a_parameter_script_is_byte_identical_run_to_run(tmp_path: Path) -> None:
    paths = [tmp_path / "a.csv", tmp_path / "b.csv"]
    for path in paths:
        r = LockstepRunner(load_mission(FLIGHT_YAML), commands=parse_commands(PARAM_SCRIPT))
        with CsvLogger(path, r.control.layout) as log:
            r.run(20.0, log=log)
    assert paths[0].read_bytes() == paths[1].read_bytes()
    assert "apogee_target_m" in paths[0].read_text().splitlines()[0]


def test_sim_is_byte_identical_run_to_run_and_from_the_command_line(tmp_path: Path) -> None:
    a, b, c = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "c.csv"
    # The command line's run (a process) flies beside the two in this one.
    p = subprocess.Popen(
        [sys.executable, "-m", "zplatform", "sim", str(FLIGHT_YAML), "--commands",
         str(FLIGHT_CMDS), "--log", str(c)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        for path in (a, b):
            r = LockstepRunner(load_mission(FLIGHT_YAML), commands=load_commands(FLIGHT_CMDS))
            with CsvLogger(path, r.control.layout) as log:
                r.run(60.0, log=log)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    assert a.read_bytes() == b.read_bytes()
    assert p.returncode == 0, out + err
    assert "SAFE -> ARMED -> BOOST -> COAST -> DROGUE -> MAIN -> LANDED" in out
    assert c.read_bytes() == a.read_bytes()  # the default duration (60 s) ends the same


def test_a_lost_imu_in_flight_falls_back_to_the_barometers_and_says_so() -> None:
    """The IMU freezes 2 s after ignition (in boost): the EKF falls back to
    barometers and GPS (an event, nav_mode BARO), and the flight goes on:
    the drogue still never fires before the true apogee."""
    fl = fly(flight(sensors={"imu_fail_s": 2.0}))
    f, res = fl.truth, fl.result
    warn = [e for e in res.events if e.id == "component_warning"]
    assert len(warn) == 1 and "IMU lost" in warn[0].text and warn[0].severity_name == "WARNING_HI"
    assert fl.runner.control.dv.get_name("nav_mode") == "BARO"
    assert [s for _, s in fl.states][-4:] == ["COAST", "DROGUE", "MAIN", "LANDED"]
    assert f.apogee_t is not None and f.drogue_at is not None
    assert 0.0 < f.drogue_at - f.apogee_t <= 1.5  # barometers alone: later, never early
    assert f.main_at is not None and f.landed


def test_a_dead_barometer_keeps_navigation_but_its_node_refuses_to_fire() -> None:
    """dn0's barometer reads nan from 1 s after ignition. The EKF outvotes it
    (the other barometer and the GPS; it stays on the accelerometer) and
    detects apogee as usual; but dn0's igniter rule checks dn0's *own*
    altitude (configs/recovery_igniter.yaml's agreement), which is no
    number: dn0 refuses, so the drogue cannot open. Each node's barometer is
    part of its vote: that is the agreement's price, shown, not hidden."""
    fl = fly(flight(sensors={"baro_fail_s": 1.0}), seconds=25.0, until_landed=False)
    f, dv = fl.truth, fl.runner.control.dv
    assert dv.get_name("nav_mode") == "ACCEL"
    assert math.isnan(dv.get("dn0_baro_m"))
    assert [s for _, s in fl.states][:5] == ["SAFE", "ARMED", "BOOST", "COAST", "DROGUE"]
    assert f.apogee_t is not None and fl.entered("DROGUE") > f.apogee_t + 3.1  # mission time
    assert f.drogue_at is None and not dv.get("drogue_fired")
    assert not dv.get("dn0_drogue_ok") and not dv.get("dn0_drogue_out")


def test_a_device_node_lost_in_coast_ends_in_the_configured_response() -> None:
    """dn1 (barometer, GPS, airbrakes, one switch of each chute) dies 6 s
    after launch: the CN latches DN_LOST and goes to ABORTED (airbrakes
    safed); the recovery still runs from there on dn0's sensors (apogee ->
    DROGUE), though no chute can open with one switch of its pair gone."""
    fl = fly(load_mission(FLIGHT_YAML), lose=(9.0, "dn1"), seconds=30.0, until_landed=False)
    res, dv = fl.result, fl.runner.control.dv
    names = [s for _, s in fl.states]
    assert names[:5] == ["SAFE", "ARMED", "BOOST", "COAST", "ABORTED"]
    assert res.fault == "DN_LOST"
    lost_at = fl.entered("ABORTED")
    assert 9.0 < lost_at <= 9.0 + 0.6  # faults.dn_lost_loops (50) + a loop or two
    assert names[5] == "DROGUE"  # recovery goes on from ABORTED at apogee
    assert dv.get_name("airbrakes_mode") == "safed"
    assert fl.truth.drogue_at is None  # dn1's switch never closed


def test_abort_in_coast_safes_the_airbrakes_and_still_recovers() -> None:
    fl = fly(load_mission(FLIGHT_YAML), "at 1.0 arm\nat 1.1 launch\nat 8 abort\n")
    names = [s for _, s in fl.states]
    assert names == ["SAFE", "ARMED", "BOOST", "COAST", "ABORTED", "DROGUE", "MAIN", "LANDED"]
    f = fl.truth
    assert f.drogue_at is not None and f.main_at is not None and f.landed
    assert f.apogee_t is not None and f.drogue_at > f.apogee_t


def test_abort_in_the_countdown_never_lights_the_motor() -> None:
    fl = fly(load_mission(FLIGHT_YAML), "at 1.0 arm\nat 1.1 launch\nat 2.5 abort\n", seconds=10.0)
    assert [s for _, s in fl.states] == ["SAFE", "ARMED", "ABORTED"]
    assert not fl.truth.ignited and fl.truth.z == 0.0
    assert not fl.runner.control.dv.get("dn0_pyro_armed")


def test_the_controllers_keep_their_state_in_the_data_vector() -> None:
    """A standby CN that mirrors the Data Vector can take over (issue 17): a
    fresh control logic given a copy of the vector mid-coast computes the
    same next loop as the one it replaces."""
    from zplatform.control.loop import ControlLogic

    m = load_mission(FLIGHT_YAML)
    r = LockstepRunner(m, commands=load_commands(FLIGHT_CMDS))
    r.run(8.0)
    assert r.control.dv.get_name("cn_state") == "COAST"
    twin = ControlLogic(m, epoch=r.start_ns)
    twin.dv.write_all(bytes(r.control.dv.buf))
    a, b = r.control, twin
    t = r.start_ns + r.loop * r.period_ns
    for logic in (a, b):
        logic.begin(r.loop + 1, t)
        logic.controllers.run(r.loop + 1, t)
    watch = ("nav_h_m", "nav_v_mps", "nav_bias_mps2", "dn1_airbrake_cmd", "apogee_pred_m")
    for name in watch:
        assert a.dv.get(name) == b.dv.get(name), name
    assert list(a.dv.get("nav_cov")) == list(b.dv.get("nav_cov"))
    assert math.isfinite(a.dv.get("nav_h_m"))


# ---------------------------------------------------------------------------
# An attacker holding the ground key (issue "Every door locked by construction")


def _outcome(fl: Flown, name: str) -> Any:
    (c,) = [c for c in fl.result.commands if c.command == name]
    return c


def test_a_ground_write_of_the_apogee_flag_in_aborted_fires_no_drogue() -> None:
    """An ABORT in BOOST, then a plain WRITE (no ARM) of ``ev_apogee`` while
    the rocket still climbs: ABORTED allows WRITE and leaves for DROGUE on
    that flag. Refused (the flag is not writable), and no drogue fires: the
    state stays ABORTED and both drogue switches stay off."""
    drogue_out: list[bool] = []
    at_write: dict[str, Any] = {}

    def watch(r: LockstepRunner) -> None:
        drogue_out.extend(bool(d.dv.get(f"{d.node}_drogue_out")) for d in r.devices)
        if r.loop == 600:  # the WRITE's loop (6.0 s)
            t = r.world.truth  # type: ignore[union-attr]
            at_write.update(z=t.z, vz=t.vz, state=r.control.dv.get_name("cn_state"))

    script = "at 1.0 arm\nat 1.1 launch\nat 4.0 abort\nat 6.0 write ev_apogee true\n"
    fl = fly(load_mission(FLIGHT_YAML), script, seconds=10.0, until_landed=False, each=watch)
    # The attack's set-up is real: aborted, climbing, inside the drogue's altitude window.
    assert at_write["state"] == "ABORTED" and at_write["vz"] > 50 and 150 < at_write["z"] < 3000
    w = _outcome(fl, "WRITE")
    assert w.status == "REJECTED_BAD_ARGUMENT"
    assert "element ev_apogee is not writable: commands.writable does not list it" in w.reason
    assert [s for _, s in fl.states] == ["SAFE", "ARMED", "BOOST", "ABORTED"]
    assert fl.truth.drogue_at is None and not any(drogue_out)


def test_an_armed_write_of_the_motor_command_in_safe_lights_no_motor() -> None:
    """ARM, then WRITE ``dn0_motor_cmd`` true on the pad: refused by the CN
    (the motor command is a hazardous output of ARMED, never writable), and
    the motor igniter stays off while the vehicle stays SAFE."""
    motor: list[bool] = []

    def watch(r: LockstepRunner) -> None:
        motor.append(bool(r.devices[0].dv.get("dn0_motor_fb")))

    fl = fly(
        load_mission(FLIGHT_YAML),
        "at 1.0 arm\nat 1.1 write dn0_motor_cmd true\n",
        seconds=4.0,
        until_landed=False,
        each=watch,
    )
    assert _outcome(fl, "ARM").status == "ACCEPTED"
    w = _outcome(fl, "WRITE")
    assert w.status == "REJECTED_BAD_ARGUMENT"
    assert "element dn0_motor_cmd is not writable" in w.reason
    assert [s for _, s in fl.states] == ["SAFE"]
    assert not fl.truth.ignited and not any(motor)
    assert fl.runner.devices[0].dv.get("dn0_interlocked") == 0  # nothing reached the node
