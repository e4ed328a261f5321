"""Lockstep runs in virtual time: ``zplatform sim`` and ``zplatform replay``.

``zplatform sim MISSION [--duration S] [--commands FILE] [--log CSV]
[--summary JSON]`` runs every node in this process
(:class:`~zplatform.sim.lockstep.LockstepRunner`), logs every snapshot to CSV
(events beside it), prints the states visited and each verdict; without
``--duration``, until :data:`~zplatform.ground.script.SETTLE_S` virtual
seconds past the script's last command.

``zplatform replay DIR --mission FILE [--log CSV]`` feeds a recording made by
``up --record DIR`` through the control loop of the mission in ``FILE`` (which
must be the recorded mission: a replay never runs code a recording names) and
checks the telemetry is bit-identical; without ``--mission`` only ``--list``
and ``--log`` run (they need no mission code).

Contract, exit codes: sim 0 on a clean run (no errors, no fault, every
scripted command accepted), 1 otherwise; replay 0 when identical, 1 naming
the first differing loop and element; 2 for a bad mission, script or
recording (one line, never a traceback). See docs/operations.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import msgspec

from ..control.uplink import load_commands
from ..core.datavector import Layout
from ..errors import CommandError
from ..ground.identity import check_names
from ..ground.script import MIN_DURATION_S, SETTLE_S, script_duration_s
from ..mission.load import load_mission
from ..security.identities import sim_signer
from ..sim.lockstep import LockstepRunner, replay, sim_keys
from ..telemetry.logs import CsvLogger, EventWriter, events_path
from ..telemetry.records import EventRecord, format_outcome
from .args import check_output, identity_options, positive_float

__all__ = ["cmd_replay", "cmd_sim", "register"]


def cmd_sim(args: argparse.Namespace) -> int:
    mission = load_mission(args.mission)
    script = load_commands(args.commands) if args.commands else []
    duration = args.duration if args.duration is not None else script_duration_s(script)
    ev_path = events_path(args.log) if args.log else None
    if ev_path is not None:
        check_output(args.log, "telemetry log")
        check_output(ev_path, "event log")
    if args.summary:
        check_output(args.summary, "summary")
    signer = None
    named = args.operator is not None or args.station is not None
    own = any(c.operator is None for c in script)  # a line sent as --operator
    if (own or named) and check_names(mission, args.operator, args.station):
        # In virtual time the keys are the run's own (sim_keys): no key files.
        keys = sim_keys(mission)
        if keys is None:
            raise CommandError(
                f"mission {mission.mission!r} does not authenticate (security.auth): its "
                "requests cannot name an operator"
            )
        signer = sim_signer(keys, mission, args.operator, args.station)
    runner = LockstepRunner(mission, commands=script, signer=signer)
    if ev_path is not None:
        with CsvLogger(args.log, runner.control.layout) as log:
            res = runner.run(duration, log=log)
        with EventWriter(ev_path) as ev:
            for e in res.events:  # virtual time: the event's own loop time is its "receive" time
                ev.write(EventRecord.of(e, e.t_ns))
    else:
        res = runner.run(duration)
    out = sys.stdout
    print(
        f"sim {res.mission}: {res.loops} loops ({res.duration_s:g} s virtual) in "
        f"{res.wall_s:.2f} s wall ({res.loops_per_s:,.0f} loops/s)",
        file=out,
    )
    for c in res.commands:
        print(f"  {c.t_ns / 1e9:8.3f} s  {format_outcome(c)}  ({c.source})")
    for src in res.pending_commands:
        print(f"  not sent before the end of the run: {src}")
    print(f"states: {' -> '.join(res.states)}; final state {res.final_state}")
    print(
        f"errors {res.errors} ({', '.join(f'{n} {c}' for n, c in res.errors_by_node.items())}); "
        f"fault {res.fault}; "
        f"telemetry rows {res.telemetry_received} -> {args.log or '(no --log)'}; "
        f"events {len(res.events)} -> {ev_path or '(no --log)'}"
    )
    if args.summary:
        Path(args.summary).write_text(json.dumps(res.summary(), indent=2) + "\n")
    return 0 if res.clean else 1


def cmd_replay(args: argparse.Namespace) -> int:
    from .archive import is_archive

    if is_archive(args.directory):
        return _replay_archive(args)
    if args.run is not None:
        raise CommandError("--run picks a run of a ground archive; DIR is a recording")
    if args.mission is None and not (args.list or args.log):
        raise CommandError(
            "a replay runs the mission's code, which is never taken from a recording: pass "
            "the mission file that was recorded (--mission FILE); without it, --list shows "
            "the recorded loops and --log CSV writes the recorded telemetry"
        )
    if args.log:
        check_output(args.log, "telemetry log")
    if args.summary:
        check_output(args.summary, "summary")
    if args.mission is None:
        return _read_recording(args)
    mission = args.mission
    if args.log:
        with CsvLogger(args.log, Layout.for_node(load_mission(mission), "cn")) as log:
            res = replay(args.directory, mission, log=log)
    else:
        res = replay(args.directory, mission)
    print(
        f"replay {res.mission}: loops {res.first_loop}..{res.last_loop} ({res.loops} loops, "
        f"{res.telemetry_frames} telemetry frames compared); final state {res.final_state}"
    )
    if not res.complete:
        print(
            f"  the recording is incomplete (dropped loops: {res.dropped_loops}); "
            "replayed up to the gap"
        )
    if args.summary:
        Path(args.summary).write_text(json.dumps(msgspec.to_builtins(res), indent=2) + "\n")
    d = res.first_difference
    if d is not None:
        print(
            f"  DIFFERS at loop {d.loop}: {d.element} recorded {d.recorded}, replayed {d.replayed}"
        )
        return 1
    if res.loops == 0:
        print("  the recording holds no complete loop")
        return 1
    print("  telemetry bit-identical to the live run")
    return 0


def _replay_archive(args: argparse.Namespace) -> int:
    """``replay ARCHIVE --mission FILE --log CSV [--run R]``: a run of the
    ground archive written as the recorded telemetry (its events beside
    it). The archive keeps the control node's telemetry, not the device
    nodes' replies a replay feeds the loop: nothing is replayed, the
    mission file is read only for the layout (no code runs)."""
    from .archive import archive_run, log_from_archive

    if args.mission is None or not args.log or args.list:
        raise CommandError(
            f"{args.directory} is a ground archive: it keeps the telemetry the ground received, "
            "not the device nodes' replies a replay needs; write a run of it as CSV with "
            "--mission FILE (its layout: no code runs) --log CSV [--run R]"
        )
    if args.summary:
        raise CommandError("--summary is a replay's: a ground archive is not replayed")
    check_output(args.log, "telemetry log")
    mission = load_mission(args.mission, code=False)
    ev = events_path(args.log)
    info, rows, events, problems = log_from_archive(
        mission, args.directory, archive_run(args.run), args.log, ev
    )
    for line in problems:
        print(f"zplatform replay: {line}", file=sys.stderr)
    print(
        f"archive of {info.mission}, run {info.run}: loops {info.first_loop}..{info.last_loop} "
        f"({rows} rows -> {args.log}, {events} events -> {ev}); last state "
        f"{info.final_state or '-'}; outcome {info.outcome}"
    )
    print("  not replayed: a ground archive holds no device node replies")
    return 0


def _read_recording(args: argparse.Namespace) -> int:
    """``replay DIR --list/--log`` without a mission file: no code runs."""
    from ..sim.replay_recording import RecordReader, read_recording

    listing = sys.stdout if args.list else None
    if args.log:
        with RecordReader(args.directory) as reader:  # the layout, from the recorded mission
            layout = reader.layout
        with CsvLogger(args.log, layout) as log:
            s = read_recording(args.directory, log=log, listing=listing)
    else:
        s = read_recording(args.directory, listing=listing)
    print(
        f"recording of {s.mission}: loops {s.first_loop}..{s.last_loop} ({s.loops} loops, "
        f"{s.telemetry_frames} telemetry frames"
        + (f" -> {args.log}" if args.log else "")
        + f"); last recorded state {s.final_state or '-'}"
    )
    if not s.complete:
        print(f"  the recording is incomplete (dropped loops: {s.dropped_loops})")
    if args.summary:
        Path(args.summary).write_text(json.dumps(msgspec.to_builtins(s), indent=2) + "\n")
    print("  not replayed: pass the recorded mission's file (--mission FILE) to replay it")
    return 0


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "sim",
        help="lockstep run of every node in virtual time (deterministic)",
        description="Run every node of the mission in one process, loop by loop in virtual "
        "time: the same logic as a live run, deterministic, as fast as the CPU allows. "
        "Prints the states reached and every command's verdict; --log writes the telemetry "
        "CSV and its events beside it (NAME.events.jsonl).",
    )
    p.add_argument(
        "mission", help="mission YAML file, or the name of a running mission (`zplatform ps`)"
    )
    p.add_argument(
        "--duration",
        type=positive_float,
        default=None,
        metavar="S",
        help=f"virtual seconds to run (default: last command + {SETTLE_S:g} s, "
        f"at least {MIN_DURATION_S:g} s)",
    )
    p.add_argument("--commands", metavar="FILE", help="command script ('at 1.0 launch' lines)")
    identity_options(p)
    p.add_argument(
        "--log", metavar="CSV", help="telemetry CSV to write, events beside it (default: none)"
    )
    p.add_argument("--summary", metavar="JSON", help="write a JSON summary of the run")
    p.set_defaults(func=cmd_sim)

    p = sub.add_parser(
        "replay",
        help="replay a recorded live run through the lockstep runner; check it bit for bit",
        description="Replay a recording (`up --record DIR`) through the control loop of the "
        "mission file given with --mission, which must be the recorded mission, and check "
        "the telemetry bit for bit. A recording is never trusted: no code it names is "
        "imported, and without --mission only --list and --log read it.",
    )
    p.add_argument(
        "directory",
        metavar="DIR",
        help="a recording made by `up --record DIR`, or a ground archive (its run's telemetry "
        "with --mission FILE --log CSV)",
    )
    how = p.add_mutually_exclusive_group()
    how.add_argument(
        "--mission",
        metavar="FILE",
        help="the recorded mission's file, or a running mission's name (its code runs; the "
        "recording must be of it)",
    )
    how.add_argument(
        "--list", action="store_true", help="list the recorded loops (no mission code runs)"
    )
    p.add_argument(
        "--log",
        metavar="CSV",
        help="write the telemetry as CSV: replayed with --mission, else as recorded",
    )
    p.add_argument("--summary", metavar="JSON", help="write the result as JSON")
    p.add_argument(
        "--run",
        metavar="R",
        help="DIR a ground archive (.../archive/MISSION): the run --log writes (default the last)",
    )
    p.set_defaults(func=cmd_replay)
