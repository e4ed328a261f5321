"""The flight's physics against RocketPy: the same rocket, motor and chutes in both.

``nodes/flight/physics.py`` (the vehicle world of ``configs/flight.yaml``) is
our own small model; RocketPy (the reference simulator of amateur and
university rocketry, a 6-DOF solver) flies the same rocket: the mission's
motor file, dry mass, diameter, ``Cd(Mach)`` curve (handed to RocketPy as a
dense table, so both interpolate it linearly), rail, chutes' Cd.A with the
drogue at apogee and the main at the mission's main altitude, ISA air and
constant gravity, no wind, a vertical rail. Both fly without the flight
software (chutes deploy on the truth, instantly), so only the physics is
compared. Variants ``zplatform_model`` and ``rocketpy``; figures: apogee
(m above the pad), time to apogee (s), maximum speed (m/s), descent rates
under drogue (mean between 400 m and the main altitude) and under the main
(mean below 100 m), wall time; ``err_*_pct`` on the model are its errors
relative to RocketPy. Targets (issue 19): apogee and time to apogee within
2 %. The descent rates differ by design and are reported, not targets:
RocketPy counts only the newest chute's Cd.S, while our model adds the
body's drag and keeps the drogue on the main's line (dual deploy), so it
descends a little slower (by the ratio of the square roots of the Cd.A).

RocketPy is an optional extra (``pip install -e '.[validation]'``), not a
runtime dependency. Takes about 5 s. Run ``python -m bench.flight_validation
[--json PATH]``; results go to ``bench/results/flight_validation.json``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import msgspec

from bench.common import REPO_ROOT, bench_argparser, write_result
from nodes.flight.physics import STEP_NS, Flight, Motor, VehicleParams, _interp

MISSION = REPO_ROOT / "configs" / "flight.yaml"
TARGET_PCT = 2.0
DROGUE_BAND = (400.0, None)  # (top, bottom): bottom is the main altitude


def vehicle_params() -> tuple[VehicleParams, float]:
    """The mission's vehicle (no wind, chutes opening at once) and its main altitude."""
    raw = msgspec.yaml.decode(MISSION.read_bytes())
    params = dict(raw["world"]["params"])
    params.update(wind_mps=0.0, gust_mps=0.0, drogue_inflation_s=0.0, main_inflation_s=0.0)
    main_m = next(c["config"]["main_m"] for c in raw["controllers"] if "main_m" in c["config"])
    if isinstance(main_m, str):  # a parameter of the mission (params:): its default
        main_m = next(p["default"] for p in raw.get("params", []) if p["name"] == main_m)
    return msgspec.convert(params, VehicleParams), float(main_m)


def _descent(ts: list[float], zs: list[float], vs: list[float], top: float, bottom: float) -> float:
    """Mean descent speed (m/s, positive) while ``bottom < z < top`` after apogee."""
    apo = max(range(len(zs)), key=zs.__getitem__)
    sel = [-v for t, z, v in zip(ts[apo:], zs[apo:], vs[apo:], strict=True) if bottom < z < top]
    return sum(sel) / len(sel) if sel else float("nan")


def fly_model(p: VehicleParams, main_m: float) -> dict[str, Any]:
    w0 = time.perf_counter()
    f = Flight(p)
    f.ignited = True
    dt = STEP_NS / 1e9
    ts: list[float] = []
    zs: list[float] = []
    vs: list[float] = []
    drogue = main = False
    while not f.landed and f.t < 600:
        drogue = drogue or f.apogee_t is not None
        main = main or (drogue and f.z < main_m)
        f.set_actuators(drogue, main, 0.0, dt)
        f.step(dt)
        ts.append(f.t)
        zs.append(f.z)
        vs.append(f.vz)
    return _figures(f.apogee_m, f.apogee_t or 0.0, f.max_speed, ts, zs, vs, main_m, w0)


def fly_rocketpy(p: VehicleParams, main_m: float) -> dict[str, Any]:
    from rocketpy import Environment, GenericMotor, Rocket
    from rocketpy import Flight as RocketPyFlight

    w0 = time.perf_counter()
    env = Environment(gravity=p.g_mps2, elevation=p.pad_altitude_m)
    env.set_atmospheric_model(type="standard_atmosphere")
    m = Motor(p.motor)
    r = m.diameter_m / 2
    motor = GenericMotor(
        thrust_source=str(m.path),
        burn_time=None,
        chamber_radius=r,
        chamber_height=0.3,
        chamber_position=0.15,
        propellant_initial_mass=m.propellant_kg,
        nozzle_radius=0.4 * r,
        dry_mass=m.dry_kg,
        center_of_dry_mass_position=0.15,
        dry_inertia=(0.01, 0.01, 0.001),
    )
    # Cd(Mach) as a dense table: both simulators then interpolate the same curve.
    cd = [(i * 0.01, _interp(p.cd_mach, i * 0.01)) for i in range(301)]
    rocket = Rocket(
        radius=p.diameter_m / 2,
        mass=p.dry_mass_kg,
        inertia=(4.0, 4.0, 0.02),
        power_off_drag=cd,
        power_on_drag=cd,
        center_of_mass_without_motor=1.0,
        coordinate_system_orientation="tail_to_nose",
    )
    rocket.add_motor(motor, position=0.0)
    rocket.add_nose(length=0.4, kind="ogive", position=2.0)
    rocket.add_trapezoidal_fins(n=4, root_chord=0.15, tip_chord=0.07, span=0.1, position=0.2)
    rocket.add_parachute("drogue", cd_s=p.drogue_cda_m2, trigger="apogee", sampling_rate=400)
    rocket.add_parachute("main", cd_s=p.main_cda_m2, trigger=main_m, sampling_rate=400)
    fl = RocketPyFlight(
        rocket=rocket,
        environment=env,
        rail_length=p.rail_length_m,
        inclination=p.launch_angle_deg,
        heading=0,
        max_time=600,
    )
    sol = fl.solution
    ts = [float(s[0]) for s in sol]
    zs = [float(s[3]) - p.pad_altitude_m for s in sol]
    vs = [float(s[6]) for s in sol]
    return _figures(
        float(fl.apogee) - p.pad_altitude_m,
        float(fl.apogee_time),
        float(fl.max_speed),
        ts,
        zs,
        vs,
        main_m,
        w0,
    )


def _figures(
    apogee: float,
    t_apogee: float,
    vmax: float,
    ts: list[float],
    zs: list[float],
    vs: list[float],
    main_m: float,
    w0: float,
) -> dict[str, Any]:
    return {
        "apogee_m": round(apogee, 2),
        "time_to_apogee_s": round(t_apogee, 3),
        "max_speed_mps": round(vmax, 2),
        "drogue_descent_mps": round(_descent(ts, zs, vs, DROGUE_BAND[0], main_m), 2),
        "main_descent_mps": round(_descent(ts, zs, vs, 100.0, 5.0), 2),
        "wall_s": round(time.perf_counter() - w0, 3),
    }


def _pct(a: float, b: float) -> float:
    return round(100.0 * (a - b) / b, 3)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = bench_argparser(__doc__.splitlines()[0] if __doc__ else "flight_validation")
    args = ap.parse_args(argv)
    p, main_m = vehicle_params()
    ours = fly_model(p, main_m)
    ref = fly_rocketpy(p, main_m)
    for k in ("apogee_m", "time_to_apogee_s", "max_speed_mps", "drogue_descent_mps",
              "main_descent_mps"):  # fmt: skip
        ours[f"err_{k}_pct"] = _pct(ours[k], ref[k])
    targets = [
        {
            "name": f"{k} vs RocketPy",
            "value": abs(ours[f"err_{k}_pct"]),
            "limit": TARGET_PCT,
            "unit": "%",
            "met": abs(ours[f"err_{k}_pct"]) <= TARGET_PCT,
        }
        for k in ("apogee_m", "time_to_apogee_s")
    ]
    from importlib.metadata import version

    params = {
        "mission": str(MISSION.relative_to(REPO_ROOT)),
        "motor": Path(p.motor).name,
        "dry_mass_kg": p.dry_mass_kg,
        "diameter_m": p.diameter_m,
        "main_m": main_m,
        "rocketpy": version("rocketpy"),
        "wind_mps": 0.0,
        "targets": targets,
    }
    return write_result(
        "flight_validation", params, {"zplatform_model": ours, "rocketpy": ref}, args.json
    )


if __name__ == "__main__":
    main()
