"""Runtime subcommands: ``up``, ``node``, ``log``, ``cmd``, ``tap`` (DESIGN.md §6)."""

from __future__ import annotations

import argparse
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import zenoh

from .auth import TAG_LEN, load_keys
from .bulk import bulk_key, decode_sample
from .cli_args import check_output, check_ports, nonnegative_float, positive_float, positive_int
from .codec import RegionCodec
from .config import Mission
from .datavector import DataVector, Layout
from .errors import CodecError, CommandError, NodeError, TransportError
from .events import EventReader
from .mission import load_mission
from .node.runtime import PARENT_ENV, setup_logging
from .summary import (
    CnSummary,
    DnSummary,
    GnSummary,
    RunSummary,
    cn_summary,
    read_summary,
    write_summary,
)
from .telemetry import events_path
from .transport import KeySpace, NodeSession, rewrite_endpoints

__all__ = ["register"]

TAP_SILENCE_S = 5.0  # `tap` gives up when nothing at all arrived this long


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    mission_help = "mission YAML file, or the name of a running mission (`zplatform ps`)"
    p = sub.add_parser("up", help="spawn every node of a mission as its own process")
    p.add_argument("mission", help=mission_help)
    p.add_argument(
        "--duration",
        type=positive_float,
        metavar="S",
        help="seconds of loops (default: until Ctrl-C)",
    )
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
    p.add_argument("--no-realtime", action="store_true", help="skip SCHED_FIFO/affinity set-up")
    p.add_argument("--quiet", action="store_true", help="no live status line, no summary line")
    p.add_argument(
        "--ready-timeout",
        type=positive_float,
        default=60.0,
        metavar="S",
        help="seconds the nodes wait for their peers at start (default 60)",
    )
    p.add_argument(
        "--record",
        metavar="DIR",
        help="record every input of the CN's loop into DIR, for `zplatform replay DIR`",
    )
    p.set_defaults(func=cmd_up)

    p = sub.add_parser("node", help="run one node of a mission (multi-host deployments)")
    p.add_argument("mission", help=mission_help)
    p.add_argument("name", help="cn, dnX or gn")
    p.add_argument(
        "--duration",
        type=positive_float,
        metavar="S",
        help="CN: seconds of loops; GN: seconds of logging",
    )
    p.add_argument(
        "--log", metavar="CSV", help="GN: telemetry CSV; events beside it (NAME.events.jsonl)"
    )
    p.add_argument("--commands", metavar="FILE", help="GN: command script to play (at 1.0 launch)")
    p.add_argument("--summary", metavar="JSON", help="write this node's summary JSON here")
    p.add_argument("--no-realtime", action="store_true", help="skip SCHED_FIFO/affinity set-up")
    p.add_argument(
        "--ready-timeout",
        type=positive_float,
        default=60.0,
        metavar="S",
        help="seconds to wait for the peers at start (default 60)",
    )
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

    p = sub.add_parser("log", help="log telemetry snapshots to CSV (events beside it)")
    p.add_argument("mission", help=mission_help)
    p.add_argument(
        "--out",
        required=True,
        metavar="CSV",
        help="telemetry CSV; events go beside it (tm.csv -> tm.events.jsonl)",
    )
    p.add_argument(
        "--duration", type=positive_float, metavar="S", help="seconds (default: until Ctrl-C)"
    )
    p.add_argument("--summary", metavar="JSON", help="write the logger's summary JSON here")
    p.set_defaults(func=cmd_log)

    p = sub.add_parser("cmd", help="send one operator command and wait for its verdict")
    p.add_argument("mission", help=mission_help)
    p.add_argument("command", help="launch|abort|noop|hold|resume|arm|write")
    p.add_argument("args", nargs="*", help="write: ELEMENT VALUE")
    p.add_argument("--arm", action="store_true", help="send ARM n first, then the command as n+1")
    p.add_argument(
        "--timeout",
        type=positive_float,
        default=10.0,
        metavar="S",
        help="seconds to wait for the CN and its verdict (default 10)",
    )
    p.set_defaults(func=cmd_cmd)

    p = sub.add_parser(
        "tap",
        help="print every sample on matching keys, decoded (events included)",
        description="Print every sample on matching keys, decoded to named values; events "
        "({vehicle}/NODE/events) as severity, id and text. Exits 1 when nothing at all "
        f"arrived within --timeout (without --timeout: within {TAP_SILENCE_S:g} s).",
    )
    p.add_argument("mission", help=mission_help)
    p.add_argument("keyexpr", nargs="?", help="zenoh key expression (default: {vehicle}/**)")
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
    # The ground node runs no mission code: it needs the mission file only.
    mission = load_mission(args.mission, code=args.name != "gn")
    _check_outputs(args, "log", "summary", "record")
    name = args.name
    realtime = not args.no_realtime
    summary: CnSummary | DnSummary | GnSummary
    if name == "cn":
        from .node.control import run_control_node

        summary = run_control_node(
            mission,
            duration_s=args.duration,
            realtime=realtime,
            ready_timeout_s=args.ready_timeout,
            ground_wait_s=args.ground_wait,
            record=args.record,
            mission_source=args.mission,
        )
    elif args.record is not None:
        raise NodeError("--record records the control node's loop: use it with `node MISSION cn`")
    elif name == "gn":
        from .node.ground import run_ground_logger
        from .uplink import load_commands

        script = load_commands(args.commands) if args.commands else None
        summary = run_ground_logger(
            mission,
            args.log,
            as_node=True,
            duration_s=args.duration,
            script=script,
            events_out=events_path(args.log) if args.log else None,
        )
    elif name in mission.device_nodes:
        from .node.device import run_device_node

        summary = run_device_node(
            mission, name, realtime=realtime, ready_timeout_s=args.ready_timeout
        )
    else:
        raise NodeError(f"no node {name!r} in mission {mission.mission!r}: {sorted(mission.nodes)}")
    write_summary(args.summary, summary)
    return 0


def cmd_log(args: argparse.Namespace) -> int:
    setup_logging()
    from .node.ground import run_ground_logger

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
    return 0


# ---------------------------------------------------------------- cmd


def cmd_cmd(args: argparse.Namespace) -> int:
    from .node.ground import CommandSender
    from .uplink import validate_command

    mission = load_mission(args.mission, code=False)
    element = args.args[0] if len(args.args) > 0 else None
    value = args.args[1] if len(args.args) > 1 else None
    if len(args.args) > 2:
        raise CommandError(f"too many arguments: {args.args}")
    # Refused before anything is sent (before any session is opened):
    # unknown command, unknown element, value that does not fit.
    validate_command(mission, args.command, element, value)
    sender = CommandSender(mission, timeout_s=args.timeout)
    try:
        if args.arm:
            results = sender.send_armed(args.command)
        else:
            results = [sender.send(args.command, element, value)]
    finally:
        sender.close()
    for r in results:
        print(f"{r.command} #{r.seq}: {r.status}")
    return 0 if all(r.accepted for r in results) else 1


# ---------------------------------------------------------------- tap


class _TapDecoder:
    """Decodes any sample of the key space into named values.

    Frames and events of an authenticating mission are checked with the
    keys a read-only tool holds (the downlink's and every node's event
    keys: ``tool.keys``) when they are at hand; what they do not cover
    (the triggers and replies of the cn<->dnX links, command requests) and
    everything without them is still decoded, marked ``"verified": false``."""

    def __init__(self, mission: Mission) -> None:
        from .auth import KeyError_, link_of

        self.mission = mission
        space = KeySpace(mission.vehicle)
        self._auth = mission.security.auth
        try:
            keys = load_keys(mission, "tool")
        except KeyError_:
            keys = None

        def chan(name: str) -> Any:
            return keys.channel(name) if keys is not None and keys.has(link_of(name)) else None

        self._events = EventReader(mission, keys)
        self._by_key: dict[str, Any] = {}
        self._bulk = {bulk_key(mission.vehicle, ch): ch for ch in mission.bulk}
        cn = DataVector(Layout.for_node(mission, "cn"))
        self._by_key[space.telemetry] = (RegionCodec(cn), cn, chan("telemetry"))
        for region in mission.region_names():
            if region == "cn":
                continue
            dv = DataVector(Layout.for_regions(mission, [region]))
            self._by_key[space.region(region)] = (RegionCodec(dv, region), dv, chan(region))

    def decode(self, key: str, payload: bytes) -> dict[str, Any]:
        if key.endswith("/events"):
            try:
                e, verified = self._events.read(key, payload)
            except CodecError as exc:
                return {"key": key, "error": str(exc)}
            return {
                "key": key,
                **({} if verified is None else {"verified": verified}),
                "event": {
                    "node": e.node,
                    "seq": e.seq,
                    "t_ns": e.t_ns,
                    "severity": e.severity,
                    "severity_name": e.severity_name,
                    "id": e.id,
                    "text": e.text,
                },
            }
        ch = self._bulk.get(key)
        if ch is not None:
            try:
                hdr, arr = decode_sample(payload, ch)
            except TransportError as exc:
                return {"key": key, "error": str(exc)}
            return {
                "key": key,
                "seq": hdr.seq,
                "loop": hdr.loop,
                "t_ns": hdr.t_ns,
                "bulk": {
                    "channel": ch.name,
                    "bytes": len(payload),
                    "min": float(arr.min()),
                    "max": float(arr.max()),
                    "mean": float(arr.mean()),
                },
            }
        entry = self._by_key.get(key)
        if entry is None:
            return {"key": key, "bytes": len(payload), "hex": payload[:64].hex()}
        codec, dv, channel = entry
        verified = None
        try:
            body: bytes | memoryview = payload
            if channel is not None:
                body, verified = channel.open(payload), True
            elif self._auth:
                body, verified = payload[:-TAG_LEN], False
            frame = codec.apply(body)
        except CodecError as exc:
            return {"key": key, "error": str(exc)}
        values: dict[str, Any] = {}
        for name, spec in dv.layout.elements.items():
            values[name] = (
                dv.get_name(name)
                if spec.enum is not None
                else (dv.get(name).tolist() if spec.count else dv.get(name))
            )
        out: dict[str, Any] = {"key": key, "seq": frame.seq, "t_ns": frame.t_ns}
        if verified is not None:
            out["verified"] = verified
        out["values"] = values
        return out


def _check_keyexpr(keyexpr: str) -> None:
    """CommandError for a key expression zenoh refuses, with zenoh's reason."""
    try:
        zenoh.KeyExpr(keyexpr)
    except zenoh.ZError as exc:
        reason = str(exc).split(" at /", 1)[0]  # drop the Rust source location
        raise CommandError(
            f"{keyexpr!r} is not a zenoh key expression ({reason}); e.g. 'rocket/**', "
            "'rocket/dn0/*', 'rocket/*/events'"
        ) from None


# A tap line says when its tag could not be checked (no key for that channel).
_UNVERIFIED = {None: "", True: "", False: " (unverified)"}


def _print_tap(d: dict[str, Any], as_json: bool) -> None:
    key = d["key"]
    if as_json:
        print(json.dumps(d, default=str), flush=True)
    elif "values" in d:
        vals = " ".join(f"{k}={v}" for k, v in d["values"].items())
        print(
            f"{key} seq={d['seq']} t_ns={d['t_ns']} via={d.get('via')} {vals}"
            f"{_UNVERIFIED[d.get('verified')]}",
            flush=True,
        )
    elif "event" in d:
        e = d["event"]
        print(
            f"{key} EVENT {e['severity_name']:<8} {e['id']}: {e['text']}  "
            f"(seq={e['seq']} t_ns={e['t_ns']}){_UNVERIFIED[d.get('verified')]}",
            flush=True,
        )
    else:
        print(f"{key} {json.dumps({k: v for k, v in d.items() if k != 'key'})}", flush=True)


def cmd_tap(args: argparse.Namespace) -> int:
    """Print samples until --count, --timeout or Ctrl-C.

    Exit 0 after at least one sample; exit 1 when nothing arrived before
    the deadline (--timeout, or :data:`TAP_SILENCE_S` without it), with a
    line saying so on stderr.
    """
    mission = load_mission(args.mission, code=False)
    dec = _TapDecoder(mission)
    keyexpr = args.keyexpr or KeySpace(mission.vehicle).everything
    _check_keyexpr(keyexpr)
    q: queue.SimpleQueue[tuple[str, bytes, bool]] = queue.SimpleQueue()
    ns = NodeSession(mission, None)
    via: dict[str, list[int]] = {}  # per key: [through shared memory, copied]

    def on_sample(sample: zenoh.Sample) -> None:
        p = sample.payload  # hand off only (and whether shared memory carried it)
        q.put((str(sample.key_expr), p.to_bytes(), p.as_shm() is not None))

    sub = ns.session.declare_subscriber(keyexpr, zenoh.handlers.Callback(on_sample, indirect=False))
    n = 0
    start = time.monotonic()
    deadline = start + args.timeout if args.timeout else None
    # With no bound at all, silence still ends the tap: a typo in the key or
    # a mission that is not running must not look like a quiet vehicle.
    silence = args.timeout or TAP_SILENCE_S
    try:
        while args.count is None or n < args.count:
            now = time.monotonic()
            if n == 0 and now - start >= silence:
                break
            left = None if deadline is None else deadline - now
            if left is not None and left <= 0:
                break
            try:
                key, payload, shm = q.get(timeout=min(left, 0.5) if left is not None else 0.5)
            except queue.Empty:
                continue
            n += 1
            counts = via.setdefault(key, [0, 0])
            counts[0 if shm else 1] += 1
            d = dec.decode(key, payload)
            d["via"] = "shm" if shm else "copied"
            d["shm_copied"] = counts
            _print_tap(d, args.json)
    except KeyboardInterrupt:
        pass
    finally:
        sub.undeclare()
        ns.close()
    if n == 0:
        print(
            f"zplatform tap: no sample on {keyexpr} within {silence:g} s (is the mission "
            "running? `zplatform ps`)",
            file=sys.stderr,
        )
        return 1
    return 0


# ---------------------------------------------------------------- up


class _Children:
    """The node processes ``up`` spawned; every one is reaped on exit."""

    def __init__(self) -> None:
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def spawn(self, name: str, argv: list[str]) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env[PARENT_ENV] = str(os.getpid())
        # A new session: a Ctrl-C in the terminal reaches `up` alone, which
        # then stops the nodes in order (CN first, so the ground logs the end).
        self.procs[name] = subprocess.Popen(
            [sys.executable, "-m", "zplatform", *argv], env=env, start_new_session=True
        )

    def dead(self) -> list[tuple[str, int]]:
        return [(n, p.returncode) for n, p in self.procs.items() if p.poll() is not None]

    def stop(self, names: list[str], timeout_s: float = 10.0) -> dict[str, int]:
        codes: dict[str, int] = {}
        for n in names:
            p = self.procs.get(n)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for n in names:
            p = self.procs.get(n)
            if p is None:
                continue
            try:
                codes[n] = p.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                p.kill()
                codes[n] = p.wait()
        return codes

    def stop_all(self) -> dict[str, int]:
        order = [n for n in self.procs if n == "cn"] + [n for n in self.procs if n != "cn"]
        return self.stop(order)


def cmd_up(args: argparse.Namespace) -> int:
    """Run every node; see :func:`_watch` for what a node's death does.

    Everything a user can get wrong is refused before any node is spawned
    (exit 2): the mission, the command script, unwritable output paths,
    listen ports already in use. While it runs, the mission is registered
    (:mod:`zplatform.registry`) so ``ps`` lists it and every verb finds it by
    name; the entry, the remapped mission of ``--free-ports`` and the
    scratch folder of the nodes' summaries are removed on exit.
    """
    from . import registry

    mission = load_mission(args.mission)  # refuse a bad mission before spawning
    # First use on this host: make the mission's key set (every node finds its own).
    # Every node it spawns needs its keys: a missing one is one error line now.
    for role in ("cn", *mission.device_nodes, *(["gn"] if mission.has_ground else [])):
        load_keys(mission, role, create=True)
    if args.commands:
        from .uplink import load_commands

        load_commands(args.commands)  # and a bad script
    _check_outputs(args, "log", "summary", "record")
    if not args.free_ports:
        check_ports(mission)  # another `up` of this mission, or anything else, on its ports
    # Until the nodes run (then _run_up takes SIGTERM over), a SIGTERM ends
    # `up` like Ctrl-C: through the finally below, which unregisters.
    signal.signal(signal.SIGTERM, _interrupt)
    reg = registry.register(mission.mission, args.mission)
    tmp = Path(tempfile.mkdtemp(prefix="zplatform-up-"))
    try:
        return _run_up(args, mission, reg, tmp)
    finally:
        reg.remove()
        shutil.rmtree(tmp, ignore_errors=True)


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _run_up(args: argparse.Namespace, mission: Mission, reg: Any, tmp: Path) -> int:
    path = str(Path(args.mission).resolve())
    if args.free_ports:
        path = reg.mission_file
        rewrite_endpoints(args.mission, path)
        mission = load_mission(path)
    logs: dict[str, str] = {}
    if args.log:
        logs["telemetry"] = str(Path(args.log).resolve())
        logs["events"] = str(events_path(args.log).resolve())
    reg.update(
        mission_file=path,
        endpoints={n: list(node.listen) for n, node in mission.nodes.items()},
        logs=logs,
    )
    if not args.quiet:
        where = f" (remapped mission {path})" if args.free_ports else ""
        print(
            f"zplatform up: running as {reg.name!r}{where}; other verbs take that name "
            f"as MISSION (`zplatform ground {reg.name}`), `zplatform ps` lists it",
            flush=True,
        )
    children = _Children()
    common = ["--ready-timeout", str(args.ready_timeout)]
    if args.no_realtime:
        common.append("--no-realtime")
    summaries = {n: tmp / f"{n}.json" for n in mission.nodes}
    stopping = False

    def on_signal(signum: int, frame: Any) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    watch = _Watch()
    try:
        # Spawn everything before opening our own zenoh session: never fork
        # a process that holds one (DESIGN.md §8).
        for dn in mission.device_nodes:
            children.spawn(dn, ["node", path, dn, "--summary", str(summaries[dn]), *common])
        if mission.has_ground:
            gn = ["node", path, "gn", "--summary", str(summaries["gn"])]
            if args.log:
                gn += ["--log", str(Path(args.log).resolve())]
            if args.commands:
                gn += ["--commands", str(Path(args.commands).resolve())]
            children.spawn("gn", gn)
        cn = ["node", path, "cn", "--summary", str(summaries["cn"]), *common]
        if args.record:
            cn += ["--record", str(Path(args.record).resolve())]
        if args.duration is not None:
            cn += ["--duration", str(args.duration)]
        children.spawn("cn", cn)
        reg.update(nodes={n: p.pid for n, p in children.procs.items()})
        _watch(mission, children, args, lambda: stopping, watch)
    finally:
        codes = children.stop_all()
    rc = 0 if watch.ok else 1
    for name, code in codes.items():
        if code not in (0, -signal.SIGTERM) and name not in watch.died:
            print(f"zplatform up: node {name} exited with code {code}", file=sys.stderr)
            rc = 1
    summary = _merge_summaries(mission, summaries, codes, watch.last_cn)
    write_summary(args.summary, summary)
    if not args.quiet:
        _print_summary(summary)
    if args.log and not args.quiet:
        print(f"telemetry -> {args.log}; events -> {events_path(args.log)}")
    return rc


class _Watch:
    """What :func:`_watch` saw: nodes that died, and the CN's last telemetry."""

    def __init__(self) -> None:
        self.died: dict[str, int] = {}
        self.ok = True
        self.last_cn: CnSummary | None = None


def _cn_from_telemetry(mission: Mission, dv: DataVector, first_t: int) -> CnSummary:
    """The CN's figures as its last telemetry showed them (for a CN that died
    before it could write its summary)."""
    dur = (int(dv.get("cn_time_ns")) - first_t) / 1e9
    return cn_summary(mission, dv, loops=int(dv.get("cn_loop")), duration_s=dur)


def _watch(
    mission: Mission,
    children: _Children,
    args: argparse.Namespace,
    stopping: Any,
    watch: _Watch,
) -> None:
    """Live status until the CN finishes or Ctrl-C.

    The flight never depends on the ground link, and a lost DN is the CN's
    to handle (DN_LOST and the mission's fault response): when a DN or the
    ground node dies, ``up`` says so and keeps the rest running (the run
    then ends non-zero). When the CN dies, the flight is over: ``up`` says
    so, stops the rest, and fills the summary from the CN's last telemetry.
    """
    from .node.ground import TelemetryReceiver
    from .timebase import NodeClock

    ns = NodeSession(mission, None)
    rx = TelemetryReceiver(ns.session, mission, NodeClock().now_ns)
    tty = sys.stdout.isatty()
    first_t = 0
    try:
        last_print = time.monotonic()
        last_loop = 0
        ready_deadline = time.monotonic() + args.ready_timeout + 30
        while not stopping():
            for n, c in children.dead():
                if n in watch.died:
                    continue
                watch.died[n] = c
                if n == "cn":
                    # Drain what the CN sent before it went: the summary's figures.
                    while rx.next(0.0) is not None:
                        pass
                    if c != 0:
                        watch.ok = False
                        print(
                            f"\nzplatform up: the control node died (exit code {c}): the flight "
                            f"is over; last telemetry: loop {int(rx.dv.get('cn_loop'))}, state "
                            f"{rx.dv.get_name('cn_state') if rx.received else 'none'}",
                            file=sys.stderr,
                        )
                        if rx.received:
                            watch.last_cn = _cn_from_telemetry(mission, rx.dv, first_t)
                    return
                watch.ok = False
                what = (
                    "the vehicle flies on without the ground link"
                    if n == "gn"
                    else "the control node carries on (DN_LOST and the mission's fault response)"
                )
                print(f"\nzplatform up: node {n} died (exit code {c}); {what}", file=sys.stderr)
            got = rx.next(0.2)
            if got is not None and first_t == 0:
                first_t = int(rx.dv.get("cn_time_ns"))
            if rx.received == 0 and got is None and time.monotonic() > ready_deadline:
                print("zplatform up: no telemetry from the control node", file=sys.stderr)
                watch.ok = False
                return
            now = time.monotonic()
            if not args.quiet and rx.received and now - last_print >= 1.0:
                dv = rx.dv
                loop = int(dv.get("cn_loop"))
                rate = (loop - last_loop) / (now - last_print) if last_loop else 0.0
                misses = " ".join(
                    f"{dn}={int(dv.get(f'cn_missed_{dn}'))}" for dn in mission.device_nodes
                )
                line = (
                    f"loop {loop:>8}  {rate:6.1f} Hz  missed {misses or '-'}  "
                    f"overruns {int(dv.get('cn_loop_overruns'))}/{int(dv.get('cn_sync_overruns'))}"
                    f"  state {dv.get_name('cn_state')}  fault {dv.get_name('cn_fault')}"
                    f"  cmd {dv.get_name('cn_cmd_status')}"
                )
                print(("\r" + line) if tty else line, end="" if tty else "\n", flush=True)
                last_print, last_loop = now, loop
    finally:
        if tty and not args.quiet:
            print()
        rx.close()
        ns.close()


def _merge_summaries(
    mission: Mission,
    paths: dict[str, Path],
    codes: dict[str, int],
    cn_fallback: CnSummary | None = None,
) -> RunSummary:
    nodes: dict[str, CnSummary | DnSummary | GnSummary | None] = {}
    cn = read_summary(paths["cn"], CnSummary) or cn_fallback
    gn = read_summary(paths["gn"], GnSummary) if "gn" in paths else None
    for name, p in paths.items():
        if name == "cn":
            nodes[name] = cn
        elif name == "gn":
            nodes[name] = gn
        else:
            nodes[name] = read_summary(p, DnSummary)
    return RunSummary(
        mission=mission.mission,
        loops=cn.loops if cn else 0,
        duration_s=cn.duration_s if cn else 0.0,
        rate_hz=cn.rate_hz if cn else 0.0,
        loop_overruns=cn.loop_overruns if cn else None,
        sync_overruns=cn.sync_overruns if cn else None,
        missed=cn.missed if cn else {},
        late=cn.late if cn else {},
        bad_frames=cn.bad_frames if cn else None,
        telemetry_received=gn.telemetry_received if gn else None,
        telemetry_gaps=gn.telemetry_gaps if gn else None,
        commands=gn.commands if gn else [],
        errors=cn.errors if cn else None,
        final_state=cn.final_state if cn else None,
        nodes=nodes,
        exit_codes=codes,
    )


def _print_summary(s: RunSummary) -> None:
    if s.loops == 0:
        print(f"{s.mission}: no loop ran (see the messages above)")
        return
    print(
        f"{s.mission}: {s.loops} loops in {s.duration_s:.2f} s "
        f"({s.rate_hz:.2f} Hz); overruns loop {s.loop_overruns} sync {s.sync_overruns}; "
        f"missed {s.missed}; late {s.late}; telemetry {s.telemetry_received} "
        f"(gaps {s.telemetry_gaps}); errors {s.errors}; final state {s.final_state}"
    )
