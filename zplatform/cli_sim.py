"""``zplatform sim``: a lockstep run of a whole mission in virtual time (DESIGN.md §6).

``zplatform sim MISSION [--duration S] [--commands FILE] --log CSV
[--summary JSON]`` runs every node in this process
(:class:`~zplatform.lockstep.LockstepRunner`), logs every telemetry snapshot
to CSV, prints the states visited and each command's verdict, and exits 0
on a clean run (no errors, no fault, every scripted command accepted), 1
otherwise, 2 for a bad mission or script.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .errors import CommandError
from .lockstep import LockstepRunner, ScriptCommand, load_commands
from .mission import load_mission
from .telemetry import CsvLogger

__all__ = ["cmd_sim", "register"]


def _default_duration(script: list[ScriptCommand]) -> float:
    last = max((c.at_ns for c in script), default=0) / 1e9
    return max(10.0, last + 5.0)


def cmd_sim(args: argparse.Namespace) -> int:
    mission = load_mission(args.mission)
    script = load_commands(args.commands) if args.commands else []
    duration = args.duration if args.duration is not None else _default_duration(script)
    if duration < 0:
        raise CommandError(f"--duration must be >= 0, got {duration:g}")
    runner = LockstepRunner(mission, commands=script)
    with CsvLogger(args.log, runner.control.layout) as log:
        res = runner.run(duration, log=log)
    out = sys.stdout
    print(
        f"sim {res.mission}: {res.loops} loops ({res.duration_s:g} s virtual) in "
        f"{res.wall_s:.2f} s wall ({res.loops_per_s:,.0f} loops/s)",
        file=out,
    )
    for c in res.commands:
        print(f"  {c.t_ns / 1e9:8.3f} s  #{c.seq:<3} {c.command:<7} {c.status}  ({c.source})")
    for src in res.pending_commands:
        print(f"  not sent before the end of the run: {src}")
    print(f"states: {' -> '.join(res.states)}; final state {res.final_state}")
    print(
        f"errors {res.errors} {res.errors_by_node}; fault {res.fault}; "
        f"telemetry rows {res.telemetry_received} -> {args.log}"
    )
    if args.summary:
        Path(args.summary).write_text(json.dumps(res.summary(), indent=2) + "\n")
    return 0 if res.clean else 1


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "sim",
        help="lockstep run of every node in virtual time (deterministic)",
        description=__doc__.splitlines()[0] if __doc__ else None,
    )
    p.add_argument("mission", help="mission YAML")
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="virtual seconds to run (default: last command + 5 s, at least 10 s)",
    )
    p.add_argument("--commands", metavar="FILE", help="command script ('at 1.0 launch' lines)")
    p.add_argument("--log", metavar="CSV", required=True, help="telemetry CSV to write")
    p.add_argument("--summary", metavar="JSON", help="write a JSON summary of the run")
    p.set_defaults(func=cmd_sim)
