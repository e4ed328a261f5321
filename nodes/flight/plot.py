"""Plot a flight: the truth against the flight software's estimate and its apogee target.

``python -m nodes.flight.plot [--mission configs/flight.yaml] [--commands
configs/flight.commands] --out docs/flight.png`` flies the mission in the
lockstep runner and draws, against mission time: the true altitude (the
vehicle world's, which the flight software never sees), the EKF's
altitude, the apogee target, the airbrake deployment and the chute
deployments, with every state change marked. Needs matplotlib (the
``plot`` extra). Deterministic: the same files give the same picture.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from zplatform import LockstepRunner, load_mission
from zplatform.uplink import load_commands

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


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--mission", type=Path, default=ROOT / "configs" / "flight.yaml")
    ap.add_argument("--commands", type=Path, default=ROOT / "configs" / "flight.commands")
    ap.add_argument("--seconds", type=float, default=70.0)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = fly(a.mission, a.commands, a.seconds)
    fig, (ax, bx) = plt.subplots(
        2, 1, figsize=(10, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
    )
    ax.plot(d["t"], d["truth"], label="truth (physics)", lw=2.2, color="0.6")
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
        ax.annotate(
            f"{chute} out",
            (t, 0),
            xytext=(0, 40),
            textcoords="offset points",
            fontsize=8,
            color="C2",
            arrowprops={"arrowstyle": "->", "color": "C2"},
        )
    ax.set_ylabel("altitude above the pad (m)")
    ax.set_title("configs/flight.yaml in lockstep: truth vs estimate vs apogee target")
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
