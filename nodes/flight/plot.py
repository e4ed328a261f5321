"""Plot a flight: the truth against the flight software's estimate and its apogee target.

``python nodes/flight/plot.py --out flight.png`` (from any directory; or
``python -m nodes.flight.plot`` from the repository's root) flies
configs/flight.yaml with its command script in the lockstep runner and draws,
against mission time: the true altitude (the vehicle world's, which the
flight software never sees), the EKF's altitude, the apogee target, the
airbrake deployment and the chute deployments, with every state change
marked. ``--csv FILE`` plots a telemetry CSV instead (``zplatform up --log``
or ``sim --log``: a flight already flown, no truth in it). Needs matplotlib
(the ``plot`` extra). Deterministic: the same files give the same picture.
"""

from __future__ import annotations

import argparse
import bisect
import csv
from pathlib import Path
from typing import Any

from zplatform import LockstepRunner, load_mission
from zplatform.control.uplink import load_commands

ROOT = Path(__file__).resolve().parents[2]


def fly(mission: Path, commands: Path, seconds: float) -> dict[str, list[Any]]:
    """Fly in lockstep; per loop: time, truth, estimate, airbrake, apogee
    target (the airbrakes' element: a parameter a script may change); state
    changes."""
    m = load_mission(mission)
    r = LockstepRunner(m, commands=load_commands(commands))
    assert r.world is not None
    dv = r.control.dv
    keys = ("t", "truth", "nav", "brake", "target", "states", "chutes")
    out: dict[str, list[Any]] = {k: [] for k in keys}
    target = next(c.config["target_m"] for c in m.controllers if c.name == "airbrakes")
    last = ""
    for _ in range(round(seconds * m.loop_hz)):
        r.step()
        f = r.world.truth
        t = r.loop / m.loop_hz
        out["t"].append(t)
        out["truth"].append(f.z if f is not None else 0.0)
        out["nav"].append(dv.get("nav_h_m"))
        out["brake"].append(f.brake if f is not None else 0.0)
        out["target"].append(dv.get(target) if isinstance(target, str) else target)
        state = dv.get_name("cn_state")
        if state != last:
            out["states"].append((t, state))
            last = state
        if f is not None:
            for name, at in (("drogue", f.drogue_at), ("main", f.main_at)):
                if at is not None and name not in [c for _, c in out["chutes"]]:
                    out["chutes"].append((t, name))
        if state == "LANDED" and f is not None and f.landed and t > out["states"][-1][0] + 2:
            break
    return out


def from_csv(path: Path) -> dict[str, list[Any]]:
    """The same series from a telemetry CSV of the flight mission (no truth:
    telemetry holds what the flight software knew). ValueError naming the
    column for a CSV of another mission."""
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    need = ("cn_time_ns", "cn_state", "nav_h_m", "apogee_target_m", "dn1_airbrake_cmd")
    missing = [c for c in need if rows and c not in rows[0]]
    if not rows or missing:
        raise ValueError(f"{path}: not a telemetry CSV of the flight mission (no {missing})")
    out: dict[str, list[Any]] = {k: [] for k in ("t", "nav", "brake", "target", "states", "chutes")}
    out["truth"] = []
    t0 = int(rows[0]["cn_time_ns"])
    last, fired = "", {"drogue": False, "main": False}
    for r in rows:
        t = (int(r["cn_time_ns"]) - t0) / 1e9
        out["t"].append(t)
        out["nav"].append(float(r["nav_h_m"]))
        out["brake"].append(float(r["dn1_airbrake_cmd"]))
        out["target"].append(float(r["apogee_target_m"]))
        if r["cn_state"] != last:
            out["states"].append((t, r["cn_state"]))
            last = r["cn_state"]
        for name in fired:
            now = r.get(f"{name}_fired") in ("1", "True", "true")
            if now and not fired[name]:
                out["chutes"].append((t, name))
            fired[name] = fired[name] or now
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description="Plot a flight of configs/flight.yaml: altitude (truth and the EKF's "
        "estimate), the apogee target, the airbrakes, the chutes and every state change.",
    )
    ap.add_argument(
        "--mission",
        type=Path,
        default=ROOT / "configs" / "flight.yaml",
        help="the mission to fly in lockstep (default: the repository's configs/flight.yaml)",
    )
    ap.add_argument(
        "--commands",
        type=Path,
        default=ROOT / "configs" / "flight.commands",
        help="its command script (default: configs/flight.commands)",
    )
    ap.add_argument(
        "--seconds", type=float, default=70.0, help="longest flight to fly (default 70 s)"
    )
    ap.add_argument(
        "--csv",
        type=Path,
        help="plot this telemetry CSV (`zplatform up --log`, `sim --log`) instead of flying",
    )
    ap.add_argument("--out", type=Path, required=True, help="the PNG to write")
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = from_csv(a.csv) if a.csv is not None else fly(a.mission, a.commands, a.seconds)
    fig, (ax, bx) = plt.subplots(
        2, 1, figsize=(10, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
    )
    if d["truth"]:
        ax.plot(d["t"], d["truth"], label="truth (physics)", lw=2.2, color="0.6")
    alt = d["truth"] or d["nav"]  # what the chute arrows point at
    ax.plot(d["t"], d["nav"], label="estimate (EKF on the CN)", lw=1.0, color="C0")
    ax.plot(
        d["t"], d["target"], ls="--", color="C3", lw=1, label=f"apogee target {d['target'][-1]:g} m"
    )
    for t, state in d["states"]:
        for x in (ax, bx):
            x.axvline(t, color="0.8", lw=0.8, zorder=0)
        ax.annotate(
            state,
            (t, 0),
            xytext=(2, 4),
            textcoords="offset points",
            rotation=90,
            fontsize=7,
            va="bottom",
        )
    for t, chute in d["chutes"]:
        # The arrow points at the vehicle where the chute came out.
        at = alt[min(bisect.bisect_left(d["t"], t), len(alt) - 1)]
        ax.annotate(
            f"{chute} out",
            (t, at),
            xytext=(12, 36),
            textcoords="offset points",
            fontsize=8,
            color="C2",
            arrowprops={"arrowstyle": "->", "color": "C2"},
        )
    top = max(max(alt), max(d["target"]))
    ax.set_ylim(top=top * 1.15)  # headroom for the labels above the apogee
    ax.set_ylabel("altitude above the pad (m)")
    ax.set_title(
        f"{a.csv.name}: estimate vs apogee target"
        if a.csv is not None
        else "configs/flight.yaml in lockstep: truth vs estimate vs apogee target"
    )
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    bx.plot(d["t"], d["brake"], color="C1", lw=1.2)
    bx.set_ylabel("airbrakes (0..1)")
    bx.set_xlabel("mission time (s)")
    bx.grid(alpha=0.3)
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=100, metadata={"Software": None})
    plt.close(fig)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
