"""Runtime subcommands: ``up``, ``node``, ``log``, ``cmd``, ``tap``.

Thin fronts: each parses its arguments, refuses what it can before anything
starts, calls one library function (:func:`zplatform.cli.supervisor.run_up`,
:func:`zplatform.node.ground.run_ground_logger`,
:func:`zplatform.ground.tools.send_command`, :func:`zplatform.ground.tap.run_tap`)
and prints.
"""

from __future__ import annotations

import argparse
import faulthandler
import logging
import os
import signal
import sys
from pathlib import Path

from ..config import Mission
from ..errors import CommandError, NodeError
from ..ground.script import MIN_DURATION_S, SETTLE_S
from ..ground.tap import TAP_SILENCE_S
from ..mission.load import load_mission
from ..runtime.process import setup_logging
from ..runtime.transport import sessions_left_open
from ..telemetry.logs import events_path
from ..telemetry.summary import CnSummary, DnSummary, GnSummary, write_summary
from .args import (
    check_output,
    check_ports,
    identity_options,
    mission_verb,
    nonnegative_float,
    positive_float,
    positive_int,
    signer_of,
    timeout_option,
)

__all__ = ["register"]


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = mission_verb(sub, "up", help="spawn every node of a mission as its own process")
    _duration(p, "seconds of loops (default: until Ctrl-C)")
    p.add_argument(
        "--log",
        metavar="CSV",
        help="ground telemetry CSV; events go beside it (tm.csv -> tm.events.jsonl)",
    )
    p.add_argument(
        "--summary", metavar="JSON", help="write the run summary JSON here ('-' = stdout)"
    )
    p.add_argument(
        "--free-ports",
        action="store_true",
        help="remap every endpoint to a free port (to run beside another mission); the "
        "remapped mission is registered under the run's name (`zplatform ps`)",
    )
    p.add_argument(
        "--commands", metavar="FILE", help="command script the ground node plays (at 1.0 launch)"
    )
    identity_options(p)
    p.add_argument(
        "--settle",
        type=positive_float,
        metavar="S",
        help="with --commands and no --duration: stop S seconds after the script's last "
        f"verdict (default {SETTLE_S:g} s, and at least {MIN_DURATION_S:g} s in all)",
    )
    p.add_argument("--quiet", action="store_true", help="no live status line, no summary line")
    _node_options(p, "seconds the nodes wait for their peers at start (default 60)")
    p.add_argument(
        "--record",
        metavar="DIR",
        help="record every input of the CN's loop into DIR, for `zplatform replay DIR`",
    )
    p.set_defaults(func=cmd_up)

    p = mission_verb(sub, "node", help="run one node of a mission (multi-host deployments)")
    p.add_argument("name", help="cn, dnX, gn, or cn_b (a standby mission's second control node)")
    _duration(
        p,
        "CN: seconds of loops (for both control nodes of a standby mission: the run ends "
        "at that loop whichever commands); GN: seconds of logging",
    )
    p.add_argument(
        "--log", metavar="CSV", help="GN: telemetry CSV; events beside it (NAME.events.jsonl)"
    )
    p.add_argument("--commands", metavar="FILE", help="GN: command script to play (at 1.0 launch)")
    identity_options(p)
    p.add_argument("--summary", metavar="JSON", help="write this node's summary JSON here")
    _node_options(p, "seconds to wait for the peers at start (default 60)")
    p.add_argument(
        "--ground-wait",
        type=nonnegative_float,
        metavar="S",
        help="CN: seconds to wait for the ground node before the first loop (default: "
        "the ready timeout; 0: do not wait); the CN starts without it after that",
    )
    p.add_argument(
        "--record",
        metavar="DIR",
        help="CN: record every input of the loop into DIR, for `zplatform replay DIR`",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.set_defaults(func=cmd_node)

    p = mission_verb(
        sub,
        "world",
        help="serve a mission's vehicle world (its physics) for the device nodes' boards",
        description="Run the mission's vehicle world (the `world:` section) in real time: "
        "device nodes with `board: {driver: world}` exchange their pins with it over UDP on "
        "loopback, and `serve_serial` nodes reach it through the serial board protocol on a "
        "pty. Prints READY once it serves. `up` starts it by itself; start it by hand before "
        "`zplatform node ... dnX` on one host.",
    )
    p.add_argument("--no-realtime", action="store_true", help="skip SCHED_FIFO set-up")
    p.set_defaults(func=cmd_world)

    p = mission_verb(
        sub,
        "log",
        help="log telemetry snapshots to CSV (events beside it), live or from a flight recorder",
        description="Log the CN's telemetry to CSV and every node's events beside it, live; "
        "gaps a link loss leaves are filled from the CN's flight recorder when the mission "
        "has one. With --from-recorder DIR, read a node's flight recorder directory (the "
        "CN's, or a device node's) into the same files instead.",
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="CSV",
        help="telemetry CSV; events go beside it (tm.csv -> tm.events.jsonl)",
    )
    _duration(p, "seconds (default: until Ctrl-C)")
    p.add_argument(
        "--from-recorder",
        metavar="DIR",
        help="read this node's flight recorder directory (e.g. .../recorder/MISSION/cn) "
        "instead of listening: recorded rows carry the frame's own stamp as rx_time_ns; "
        "the CN's frames are checked with a tool's keys, a device node's with its own key file",
    )
    p.add_argument(
        "--from-archive",
        nargs="?",
        const="",
        metavar="DIR",
        help="read a run of the ground archive (the mission's, or the archive directory DIR: "
        ".../archive/MISSION) instead of listening: the rows as the ground received them; "
        "--run picks the run (default the last)",
    )
    p.add_argument(
        "--run",
        metavar="ID",
        type=_run_id,
        help="with --from-recorder: read only this run (its id, the CN epoch the summary "
        "lists; or 'last'); default every run in the directory. With --from-archive: the "
        "run (default the last)",
    )
    p.add_argument("--summary", metavar="JSON", help="write the logger's summary JSON here")
    p.set_defaults(func=cmd_log)

    p = mission_verb(sub, "cmd", help="send one operator command and wait for its verdict")
    p.add_argument("command", help="launch|abort|noop|hold|resume|arm|write|prm_set|prm_save")
    p.add_argument("args", nargs="*", help="write: ELEMENT VALUE; prm_set: PARAMETER VALUE")
    p.add_argument(
        "--arm",
        action="store_true",
        help="send ARM n first, then the command as n+1 (needed for hazardous commands, "
        "WRITEs of protected elements and PRM_SETs of hazardous parameters)",
    )
    identity_options(p)
    timeout_option(p, "the CN and for each verdict")
    p.set_defaults(func=cmd_cmd)

    p = mission_verb(
        sub,
        "router",
        help="run a zenoh router between the vehicle and its stations (ground.routers)",
        description="Run a zenoh router (zenoh's router mode) with the mission's TLS and "
        "access control: it forwards the stations' subscriptions, requests and queries and "
        "fans the control node's telemetry out. --name takes a router of ground.routers; "
        "--listen/--connect give (or replace) its endpoints. Prints READY once open; runs "
        "until Ctrl-C or SIGTERM. See docs/deployment.md.",
    )
    p.add_argument("--name", metavar="NAME", help="a router of the mission's ground.routers")
    p.add_argument(
        "--listen", action="append", metavar="EP", help="endpoint to listen on (repeatable)"
    )
    p.add_argument(
        "--connect", action="append", metavar="EP", help="endpoint to connect to (repeatable)"
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.set_defaults(func=cmd_router)

    p = mission_verb(
        sub,
        "station",
        help="run as a ground station of the mission (ground.stations): receive, log, archive",
        description="Run as station NAME of the mission's ground.stations: a ground tool "
        "(through the station's router when it has `connect`) that receives the control "
        "node's telemetry and every node's events and writes them into a directory of its "
        "own (events.jsonl; telemetry.csv with --log; its archive under archive/), "
        "appending to what an earlier run or restart wrote there. With an "
        "operator (--operator, or the station's `operator`) it keeps that operator's "
        "command lock while they hold it. `up` starts the stations marked `start: true`. "
        "Prints READY once its session is open; runs until Ctrl-C or SIGTERM.",
    )
    p.add_argument("name", help="a station of ground.stations")
    p.add_argument(
        "--operator",
        metavar="NAME",
        help="the operator it runs as (default: the station's `operator`; none: it watches)",
    )
    p.add_argument(
        "--dir",
        metavar="DIR",
        help="where it writes (default: beside the mission's archive, <archive>.stations/NAME)",
    )
    p.add_argument("--log", action="store_true", help="also log telemetry to DIR/telemetry.csv")
    _duration(p, "seconds (default: until Ctrl-C)")
    p.add_argument("--summary", metavar="JSON", help="write the station's summary JSON here")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.set_defaults(func=cmd_station)

    p = mission_verb(
        sub,
        "tap",
        help="print every sample on matching keys, decoded (events included)",
        description="Print every sample on matching keys, decoded to named values; events "
        "({vehicle}/NODE/events) as severity, id and text. Exits 1 when nothing at all "
        f"arrived within --timeout (without --timeout: within {TAP_SILENCE_S:g} s).",
    )
    p.add_argument(
        "keyexpr",
        nargs="?",
        help="zenoh key expression (default: {vehicle}/**; under access control, "
        "every key a tool may watch)",
    )
    p.add_argument("--count", type=positive_int, metavar="N", help="stop after N samples")
    p.add_argument(
        "--timeout",
        type=positive_float,
        metavar="S",
        help="stop after S seconds (default: until --count or Ctrl-C, but give up, exit 1, "
        f"if nothing at all arrives in the first {TAP_SILENCE_S:g} s)",
    )
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.set_defaults(func=cmd_tap)


def _duration(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--duration", type=positive_float, metavar="S", help=what)


def _node_options(p: argparse.ArgumentParser, ready_help: str) -> None:
    """What every node process takes: real-time set-up, the start-up wait."""
    p.add_argument("--no-realtime", action="store_true", help="skip SCHED_FIFO/affinity set-up")
    p.add_argument(
        "--ready-timeout", type=positive_float, default=60.0, metavar="S", help=ready_help
    )


# ---------------------------------------------------------------- node / log


def _check_outputs(args: argparse.Namespace, *names: str) -> None:
    """Refuse unwritable output paths among ``args.<name>`` before starting."""
    what = {
        "log": "telemetry log",
        "out": "telemetry log",
        "summary": "summary",
        "record": "recording directory",
    }
    for n in names:
        v = getattr(args, n, None)
        if v is None or (n == "summary" and v == "-"):
            continue
        if n == "record":
            # The recording directory is created: its parent must be writable.
            p = Path(v)
            if not p.is_dir():
                check_output(p, what[n])
            continue
        check_output(v, what[n])
        if n in ("log", "out"):
            check_output(events_path(v), "event log")


def cmd_node(args: argparse.Namespace) -> int:
    setup_logging(args.verbose)
    # `kill -USR2 PID` prints every thread's stack to stderr and the node runs
    # on (up does it to a node that does not stop in its grace, before SIGKILL).
    faulthandler.register(signal.SIGUSR2, all_threads=True)
    # The ground node runs no mission code: it needs the mission file only.
    mission = load_mission(args.mission, code=args.name != "gn")
    _check_outputs(args, "log", "summary", "record")
    name = args.name
    realtime = not args.no_realtime
    summary: CnSummary | DnSummary | GnSummary
    if name in mission.control_nodes:
        from ..node.control import run_control_node

        summary = run_control_node(
            mission,
            name=name,
            duration_s=args.duration,
            realtime=realtime,
            ready_timeout_s=args.ready_timeout,
            ground_wait_s=args.ground_wait,
            record=args.record,
            mission_source=args.mission,
        )
    elif args.record is not None:
        raise NodeError(
            "--record records a control node's loop: use it with `node MISSION cn` (or the "
            "standby's name)"
        )
    elif name == "gn":
        from ..control.uplink import load_commands
        from ..node.ground import run_ground_logger

        script = load_commands(args.commands) if args.commands else None
        # Its own operator is needed only for a line that names nobody.
        own = script is not None and any(c.operator is None for c in script)
        signer = signer_of(mission, args, commands=own)
        summary = run_ground_logger(
            mission,
            args.log,
            as_node=True,
            duration_s=args.duration,
            script=script,
            events_out=events_path(args.log) if args.log else None,
            signer=signer,
        )
    elif name in mission.device_nodes:
        from ..node.device import run_device_node

        summary = run_device_node(
            mission, name, realtime=realtime, ready_timeout_s=args.ready_timeout
        )
    else:
        raise NodeError(f"no node {name!r} in mission {mission.mission!r}: {sorted(mission.nodes)}")
    write_summary(args.summary, summary)
    if sessions_left_open():
        # Everything is stopped and written; only zenoh's close is still under
        # way (logged by NodeSession.close). Do not let the interpreter's
        # shutdown wait on it past the stop grace: leave now, cleanly.
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0


def cmd_world(args: argparse.Namespace) -> int:
    from ..sim.world_server import main as world_main

    return world_main(args.mission, realtime=not args.no_realtime)


def cmd_log(args: argparse.Namespace) -> int:
    if args.from_recorder is not None and args.from_archive is not None:
        raise CommandError("--from-recorder or --from-archive: one source at a time")
    if args.from_recorder is not None:
        return _log_from_recorder(args)
    if args.from_archive is not None:
        return _log_from_archive(args)
    if args.run is not None:
        raise CommandError(
            "--run picks a recorded run: use it with --from-recorder or --from-archive"
        )
    setup_logging()
    from ..ground.logger import log_summary_line
    from ..node.ground import run_ground_logger

    mission = load_mission(args.mission, code=False)
    _check_outputs(args, "out", "summary")
    summary = run_ground_logger(
        mission,
        args.out,
        as_node=False,
        duration_s=args.duration,
        events_out=events_path(args.out),
    )
    write_summary(args.summary, summary)
    print(log_summary_line(summary, args.out, events_path(args.out)))
    return 0


MAX_PROBLEM_LINES = 50
"""Lines of damage a recorder read prints before it only counts them."""


def _run_id(text: str) -> str:
    """``--run``: ``last`` or a run id (a non-negative integer)."""
    if text != "last" and not text.isdigit():
        raise argparse.ArgumentTypeError(f"expected a run id (an integer) or 'last', got {text!r}")
    return text


def _log_from_archive(args: argparse.Namespace) -> int:
    """``log --from-archive [DIR]``: a run of the ground archive into the
    ground's files (:func:`zplatform.cli.archive.log_from_archive`). Exit 0
    when written (damage the archive skipped is named on stderr); a bad run
    or a missing archive: ArchiveError (exit 2)."""
    from ..archive import archive_dir
    from .archive import archive_run, log_from_archive

    if args.duration is not None:
        raise CommandError("--duration is for a live log, not --from-archive")
    if args.summary is not None:
        raise CommandError("--summary is for a live log, not --from-archive")
    mission = load_mission(args.mission, code=False)
    _check_outputs(args, "out")
    root = Path(args.from_archive) if args.from_archive else archive_dir(mission)
    ev = events_path(args.out)
    info, rows, events, problems = log_from_archive(
        mission, root, archive_run(args.run), args.out, ev
    )
    for line in problems[:MAX_PROBLEM_LINES]:
        print(f"zplatform log: {line}", file=sys.stderr)
    print(
        f"run {info.run} of the archive {root}: {rows} telemetry row(s) -> {args.out}, "
        f"{events} event(s) -> {ev}"
    )
    return 0


def _log_from_recorder(args: argparse.Namespace) -> int:
    """``log --from-recorder DIR``: a recorder directory into the ground's
    files (:func:`zplatform.recorder.export`). Exit 0 when the files were
    written (every record skipped is named on stderr and counted), 2 when
    nothing could be read."""
    from ..core.auth import load_keys
    from ..recorder import export, reader_role, recorded_node

    if args.duration is not None:
        raise CommandError("--duration is for a live log, not --from-recorder")
    if args.summary is not None:
        raise CommandError("--summary is for a live log, not --from-recorder")
    mission = load_mission(args.mission, code=False)
    _check_outputs(args, "out")
    ev = events_path(args.out)
    # Checked with the keys of the host role that holds the frames' link:
    # the CN's telemetry with a tool's, a DN's replies with that DN's.
    keys = load_keys(mission, reader_role(mission, recorded_node(args.from_recorder)))
    run: int | str | None = None
    if args.run is not None:
        run = "last" if args.run == "last" else int(args.run)
    s = export(args.from_recorder, mission, keys, args.out, ev, run=run)
    for line in s.problems[:MAX_PROBLEM_LINES]:
        print(f"zplatform log: {line}", file=sys.stderr)
    if len(s.problems) > MAX_PROBLEM_LINES:
        print(
            f"zplatform log: ... and {len(s.problems) - MAX_PROBLEM_LINES} more",
            file=sys.stderr,
        )
    loops = f" (loops {s.first_loop}..{s.last_loop})" if s.rows else ""
    print(
        f"read {s.node}'s recorder ({s.segments} file(s), {s.runs} run(s), {s.runs_ended} "
        f"ended cleanly): {s.rows} snapshot(s){loops} -> {args.out}; {s.events} event(s) -> "
        f"{ev}; {s.damaged} damaged record(s) or file(s) skipped, {s.refused} refused, "
        f"{s.not_recorded} loop(s) the recorder had dropped"
    )
    if s.picked is None and len(s.run_ids) > 1:
        print(
            f"zplatform log: the recorder holds {len(s.run_ids)} runs "
            f"({', '.join(str(r) for r in s.run_ids)}), read one after another into one "
            "file; --run ID (or --run last) reads one",
            file=sys.stderr,
        )
    return 0


def cmd_cmd(args: argparse.Namespace) -> int:
    """Exit 0 only when every verdict is ACCEPTED (and every step was sent)."""
    from ..ground.tools import format_result, send_command

    mission = load_mission(args.mission, code=False)
    outcomes, steps = send_command(
        mission,
        args.command,
        args.args,
        armed=args.arm,
        timeout_s=args.timeout,
        signer=signer_of(mission, args),
    )
    for line in format_result(outcomes, steps):
        print(line)
    return 0 if len(outcomes) == len(steps) and all(o.accepted for o in outcomes) else 1


def cmd_router(args: argparse.Namespace) -> int:
    """Run one router until stopped (exit 0); 2 for a bad name or endpoints."""
    from ..config.checks import check_endpoint
    from ..runtime.router import find_router, run_router

    setup_logging(args.verbose)
    mission = load_mission(args.mission, code=False)
    listen, connect = list(args.listen or []), list(args.connect or [])
    name = args.name
    if args.name is not None:
        r = find_router(mission, args.name)
        listen = listen or list(r.listen)
        connect = connect or list(r.connect)
    for flag, eps in (("--listen", listen), ("--connect", connect)):
        for ep in eps:
            check_endpoint(ep, flag)
    if not listen and not connect:
        raise CommandError("router: give --name NAME (ground.routers) or --listen/--connect")
    return run_router(mission, listen, connect, name=name)


def station_operator(mission: Mission, name: str, operator: str | None) -> str | None:
    """The operator station ``name`` runs as: ``operator`` if given, else
    the station's ``operator`` (CommandError for a station the mission does
    not list)."""
    from ..ground.identity import check_names

    g = mission.ground
    st = next((s for s in g.stations if s.name == name), None) if g is not None else None
    if st is None:
        listed = ", ".join(s.name for s in g.stations) if g is not None else "none"
        raise CommandError(
            f"mission {mission.mission!r} lists no station {name!r} (stations: {listed})"
        )
    op = operator if operator is not None else st.operator
    if op is not None:
        check_names(mission, op, name)  # a misspelt operator: the closest names
    return op


def cmd_station(args: argparse.Namespace) -> int:
    """Run one station until stopped (exit 0); 2 for a station or operator
    the mission does not list, or a missing key file."""
    from ..ground.identity import station_signer
    from ..node.ground import run_station, station_dir

    setup_logging(args.verbose)
    mission = load_mission(args.mission, code=False)
    op = station_operator(mission, args.name, args.operator)
    signer = station_signer(mission, op, args.name) if op is not None else None
    _check_outputs(args, "summary")
    # As a node: `kill -USR2 PID` dumps the threads (up does, before a SIGKILL).
    faulthandler.register(signal.SIGUSR2, all_threads=True)
    summary = run_station(
        mission,
        args.name,
        args.dir or station_dir(mission, args.name),
        signer=signer,
        log_csv=args.log,
        duration_s=args.duration,
    )
    write_summary(args.summary, summary)
    if sessions_left_open():  # as `node`: do not let zenoh's close hold the exit
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0


def cmd_tap(args: argparse.Namespace) -> int:
    """Exit 0 after at least one sample; 1, saying why, when none came."""
    from ..ground.tap import run_tap

    mission = load_mission(args.mission, code=False)
    n, why = run_tap(
        mission,
        args.keyexpr,
        count=args.count,
        timeout_s=args.timeout,
        as_json=args.json,
        silence_s=TAP_SILENCE_S,
    )
    if n == 0:
        print(f"zplatform tap: {why}", file=sys.stderr)
        return 1
    return 0


def cmd_up(args: argparse.Namespace) -> int:
    """Refuse what a user can get wrong before any node is spawned (exit 2):
    the mission, the command script, unwritable output paths, listen ports
    already in use; then :func:`zplatform.cli.supervisor.run_up`."""
    from ..core.auth import load_keys
    from ..security.deploy import DEPLOYMENT_ENV, default_deployment_path
    from ..security.pki import ensure_mission_pki
    from .supervisor import run_up

    if args.settle is not None and (not args.commands or args.duration is not None):
        raise CommandError(
            "--settle is how long a run goes on after its script (--commands) without --duration"
        )
    mission = load_mission(args.mission)
    # First use on this host: make the mission's key set (every node finds its
    # own). Every node it spawns needs its keys: a missing one is one error
    # line now, before anything runs...
    for role in (
        *mission.control_nodes,
        *mission.device_nodes,
        *(["gn"] if mission.has_ground else []),
    ):
        load_keys(mission, role, create=True)
    # ...and, for links that run mutual TLS, the mission's PKI beside the key
    # set, where every node's session looks for it (unless ZPLATFORM_DEPLOYMENT
    # names another deployment).
    if mission.mtls and not os.environ.get(DEPLOYMENT_ENV):
        pki = ensure_mission_pki(mission, default_deployment_path(mission).parent)
        if pki.made:
            print(
                f"zplatform up: made the certificates of {mission.mission!r} for mutual TLS "
                f"({', '.join(pki.made)}) in {pki.directory}"
            )
    own = False  # a script line goes as the ground's own --operator
    if args.commands:
        from ..control.uplink import load_commands
        from ..ground.identity import line_signer
        from ..ground.script import ScriptPlayer

        # A bad script fails here, line by line, as `sim` checks it: its
        # syntax and every command, element and value against the mission
        # (before, only the syntax was checked and the ground node died on
        # the rest after every other node had started).
        # A line naming its sender (`as alice@pad: ...`) is checked with its
        # key files, as the ground node will sign it.
        script = load_commands(args.commands)
        ScriptPlayer(mission, script, lambda op, st: line_signer(mission, op, st))
        own = any(c.operator is None for c in script)
    # Who the script's lines that name nobody command as: a missing name or
    # key file fails here.
    signer_of(mission, args, commands=own)
    # The stations `up` starts (ground.stations[].start): their operators'
    # and their own key files, checked here rather than by a dying station.
    from ..ground.identity import station_signer

    for st in mission.ground.stations if mission.ground is not None else []:
        if st.start and st.operator is not None:
            station_signer(mission, st.operator, st.name)
    _check_outputs(args, "log", "summary", "record")
    if not args.free_ports:
        check_ports(mission)  # another `up` of this mission, or anything else, on its ports
    return run_up(
        mission,
        args.mission,
        duration_s=args.duration,
        log=args.log,
        summary=args.summary,
        free_ports=args.free_ports,
        commands=args.commands,
        operator=(args.operator, args.station) if args.operator or args.station else None,
        settle_s=args.settle,
        realtime=not args.no_realtime,
        quiet=args.quiet,
        ready_timeout_s=args.ready_timeout,
        record=args.record,
    )
