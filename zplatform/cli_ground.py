"""Ground-side subcommands: ``ground`` (console or prompt), ``plot``, ``xtce``."""

from __future__ import annotations

import argparse
import queue
import sys
import threading
import time
from pathlib import Path
from typing import Any

from .cli_args import check_output, positive_float, positive_int
from .errors import CommandError, ZPlatformError
from .mission import load_mission
from .telemetry import read_csv

MISSION_HELP = "mission YAML file, or the name of a running mission (`zplatform ps`)"


def _port(text: str) -> int:
    """argparse type: a TCP port, 0..65535 (0: any free port)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number, got {text!r}") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port number 0..65535, got {text}")
    return v


__all__ = ["register"]

HELP = """commands: launch | abort | noop | hold | resume | arm | write ELEMENT VALUE |
          armed COMMAND (ARM n, then COMMAND n+1) | quit"""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "ground",
        help="the ground console (terminal or --web PORT); a line prompt when stdin is no TTY",
    )
    p.add_argument("mission", help=MISSION_HELP)
    mode = p.add_mutually_exclusive_group()
    mode.add_argument(
        "--console", action="store_true", help="the full-screen console even without a TTY"
    )
    mode.add_argument("--prompt", action="store_true", help="the line prompt even on a TTY")
    mode.add_argument(
        "--web",
        type=_port,
        metavar="PORT",
        help="serve the console to the operator's browser on PORT (0: any free port); "
        "prints the address to open, with its one-time token",
    )
    p.add_argument(
        "--host", default="127.0.0.1", help="address --web listens on (warns beyond loopback)"
    )
    p.add_argument("--watch", nargs="*", default=[], help="elements to show on the status line")
    p.add_argument("--interval", type=positive_float, default=1.0, help="status line period (s)")
    p.add_argument(
        "--timeout", type=positive_float, default=10.0, help="verdict timeout per command (s)"
    )
    p.add_argument(
        "--los", type=positive_float, default=0.3, help="console: seconds of silence that mean LOS"
    )
    p.add_argument(
        "--limits",
        metavar="YAML",
        help="console: element limits {NAME: {yellow: [lo, hi], red: [lo, hi]}} over the mission's",
    )
    p.set_defaults(func=cmd_ground)

    p = sub.add_parser(
        "plot",
        help="plot logged elements against time, state changes and commands marked",
        description="Plot telemetry CSV columns against time: numbers as lines, booleans "
        "and enums as labelled steps; state changes (cn_state) and commands (cn_cmd_seq) "
        "as named vertical lines.",
    )
    p.add_argument("csv", help="telemetry CSV written by up --log, log or sim")
    p.add_argument("elements", nargs="+", help="column names (see the CSV's header)")
    p.add_argument("--out", required=True, help="image path (PNG, SVG, PDF by extension)")
    p.add_argument("--title", help="figure title (default: the CSV name and the elements)")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser(
        "xtce", help="write the mission's telemetry packets and commands as XTCE (Yamcs)"
    )
    p.add_argument("mission", help=MISSION_HELP)
    p.add_argument("--out", help="XML path (default: MISSION_NAME.xtce.xml)")
    p.set_defaults(func=cmd_xtce)

    p = sub.add_parser(
        "ccsds", help="record live telemetry as CCSDS space packets, or decode them to CSV"
    )
    p.add_argument("mission", help=MISSION_HELP)
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--record", metavar="FILE", help="append the downlink's packets to FILE")
    what.add_argument("--decode", metavar="FILE", help="decode a packet file to CSV (--out)")
    p.add_argument("--out", help="CSV path for --decode")
    p.add_argument(
        "--duration", type=positive_float, metavar="S", help="--record: stop after S seconds"
    )
    p.add_argument("--divisor", type=positive_int, default=1, help="downlink every Nth snapshot")
    p.add_argument("--budget", type=positive_int, help="downlink byte budget per second")
    p.add_argument(
        "--max-data", type=positive_int, default=65536, help="packet data field size (bytes)"
    )
    p.add_argument(
        "--timeout",
        type=positive_float,
        default=10.0,
        metavar="S",
        help="--record: wait for the CN (s)",
    )
    p.set_defaults(func=cmd_ccsds)


def cmd_ground(args: argparse.Namespace) -> int:
    """The console on a TTY (or ``--console``), served with ``--web``, else the prompt."""
    if args.web is not None or args.console or (sys.stdin.isatty() and not args.prompt):
        try:
            from .console import run_console, serve_console
        except ImportError as exc:
            raise CommandError(
                f"the console needs the ground extra ({exc.name}): pip install 'zplatform[ground]'"
            ) from None
        limits = _read_limits(args.limits)
        if args.web is not None:
            load_mission(args.mission, code=False)  # a bad file fails here, with its message
            serve_console(
                args.mission,
                args.web,
                host=args.host,
                timeout_s=args.timeout,
                los_s=args.los,
                limits_path=args.limits,
            )
            return 0
        return run_console(args.mission, timeout_s=args.timeout, los_s=args.los, limits=limits)
    return cmd_prompt(args)


def _read_limits(path: str | None) -> dict[str, object] | None:
    """A limits file: ``{element: {yellow: [lo, hi], red: [lo, hi]}}`` (YAML)."""
    if path is None:
        return None
    import yaml

    try:
        raw = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise CommandError(f"cannot read {path}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise CommandError(f"{path} is not valid YAML: {exc}") from None
    if not isinstance(raw, dict):
        raise CommandError(f"{path} must map element names to {{yellow: .., red: ..}}")
    return raw


def cmd_prompt(args: argparse.Namespace) -> int:
    """Status line every ``--interval`` s; one command per stdin line.

    The prompt runs in a reader thread that only queues lines; the main
    thread owns the zenoh session, receives telemetry and sends commands.
    Every node's events are printed as they come (``EVENT cn WARNING id: text``).
    """
    import zenoh

    from .auth import load_keys
    from .events import EventReader
    from .node.ground import CommandSender

    mission = load_mission(args.mission, code=False)
    sender = CommandSender(mission, timeout_s=args.timeout)
    for name in args.watch:
        sender.rx.dv.layout.element(name)  # unknown elements fail now, with their name
    lines: queue.SimpleQueue[str | None] = queue.SimpleQueue()
    ev_q: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
    events = EventReader(mission, load_keys(mission, "gn"))

    def on_event(sample: zenoh.Sample) -> None:
        ev_q.put((str(sample.key_expr), sample.payload.to_bytes()))  # hand off only

    ev_sub = sender.ns.session.declare_subscriber(
        sender.ns.keys.all_events, zenoh.handlers.Callback(on_event, indirect=False)
    )

    def print_events() -> None:
        while True:
            try:
                key, payload = ev_q.get_nowait()
            except queue.Empty:
                return
            try:
                e, verified = events.read(key, payload)
            except ZPlatformError as exc:
                print(f"EVENT (refused on {key}: {exc})", flush=True)
                continue
            mark = " (unverified)" if verified is False else ""
            print(f"EVENT{mark} {e.node} {e.severity_name} {e.id}: {e.text}", flush=True)

    def reader() -> None:
        for line in sys.stdin:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=reader, name="prompt", daemon=True).start()
    print(HELP, flush=True)
    last = 0.0
    try:
        while True:
            try:
                line = lines.get_nowait()
            except queue.Empty:
                line = ""
            print_events()
            if line is None:
                return 0
            words = line.split()
            if words:
                if words[0] in ("quit", "exit"):
                    return 0
                try:
                    if words[0] == "armed" and len(words) == 2:
                        results = sender.send_armed(words[1])
                    else:
                        el = words[1] if len(words) > 1 else None
                        val = words[2] if len(words) > 2 else None
                        results = [sender.send(words[0], el, val)]
                    for r in results:
                        print(f"{r.command} #{r.seq}: {r.status}", flush=True)
                except (CommandError, ZPlatformError) as exc:
                    print(f"refused: {exc}", flush=True)
            if sender.rx.next(0.05) is None:
                continue
            now = time.monotonic()
            if now - last >= args.interval:
                dv = sender.rx.dv
                watched = " ".join(
                    f"{n}={dv.get_name(n) if dv.layout.element(n).enum else dv.get(n)}"
                    for n in args.watch
                )
                misses = " ".join(
                    f"{dn}={int(dv.get(f'cn_missed_{dn}'))}" for dn in mission.device_nodes
                )
                print(
                    f"loop {int(dv.get('cn_loop'))} state {dv.get_name('cn_state')} "
                    f"fault {dv.get_name('cn_fault')} missed {misses or '-'} "
                    f"cmd #{int(dv.get('cn_cmd_seq'))} {dv.get_name('cn_cmd_status')} {watched}",
                    flush=True,
                )
                last = now
    except KeyboardInterrupt:
        return 0
    finally:
        print_events()
        ev_sub.undeclare()
        sender.close()


def cmd_plot(args: argparse.Namespace) -> int:
    """Plot CSV columns against time since the first row (see telemetry.plot_telemetry)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise CommandError("plot needs matplotlib: pip install 'zplatform[plot]'") from None
    from .telemetry import plot_telemetry

    try:
        rows = read_csv(args.csv)
    except FileNotFoundError:
        raise CommandError(f"no such telemetry CSV: {args.csv!r}") from None
    except IsADirectoryError:
        raise CommandError(f"{args.csv!r} is a directory, not a telemetry CSV") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CommandError(f"cannot read telemetry CSV {args.csv!r}: {exc}") from None
    if not rows:
        raise CommandError(f"{args.csv} has no rows")
    if "rx_time_ns" not in rows[0]:
        raise CommandError(f"{args.csv} is not a telemetry CSV (no rx_time_ns column)")
    missing = [e for e in args.elements if e not in rows[0]]
    if missing:
        raise CommandError(f"not in {args.csv}: {missing}")
    check_output(args.out, "plot")
    title = args.title or f"{Path(args.csv).name}: {', '.join(args.elements)}"
    markers = plot_telemetry(rows, args.elements, args.out, title=title)
    print(f"wrote {args.out} ({len(rows)} rows, {len(markers)} state/command markers)")
    return 0


def cmd_xtce(args: argparse.Namespace) -> int:
    """Write the XTCE database of the mission's CCSDS downlink and commands."""
    try:
        from .xtce import write_xtce
    except ImportError:
        raise CommandError("xtce needs yamcs-pymdb: pip install 'zplatform[ground]'") from None
    mission = load_mission(args.mission, code=False)
    out = args.out or f"{mission.mission}.xtce.xml"
    check_output(out, "XTCE file")
    x = write_xtce(mission, out)
    print(f"wrote {out}")
    if x.unplaced:
        print(f"not in any packet (straddle a segment boundary): {', '.join(x.unplaced)}")
    return 0


def _record_radio(mission: Any, args: argparse.Namespace) -> int:
    """The mission's CN packs its own downlink: record the packets it sends."""
    import zenoh

    from .transport import NodeSession

    q: queue.SimpleQueue[bytes] = queue.SimpleQueue()

    def on_packet(sample: zenoh.Sample) -> None:
        q.put(sample.payload.to_bytes())  # zenoh's thread: hand off only

    ns = NodeSession(mission, None)
    sub = ns.session.declare_subscriber(
        ns.keys.downlink, zenoh.handlers.Callback(on_packet, indirect=False)
    )
    n = size = 0
    start = time.monotonic()
    try:
        with open(args.record, "ab") as f:
            while args.duration is None or time.monotonic() - start < args.duration:
                try:
                    pkt = q.get(timeout=0.2)
                except queue.Empty:
                    if not n and time.monotonic() - start > args.timeout:
                        raise CommandError(
                            f"no downlink packet from the control node within {args.timeout:g} s"
                        ) from None
                    continue
                f.write(pkt)
                n += 1
                size += len(pkt)
    except KeyboardInterrupt:
        pass
    finally:
        sub.undeclare()
        ns.close()
    print(f"wrote {args.record}: {n} packets, {size} bytes from the CN's downlink")
    return 0


def cmd_ccsds(args: argparse.Namespace) -> int:
    """``--record``: telemetry -> packets (the radio path, on the ground); ``--decode``: -> CSV."""
    try:
        from . import ccsds
    except ImportError:
        raise CommandError("ccsds needs spacepackets: pip install 'zplatform[ground]'") from None
    mission = load_mission(args.mission, code=False)
    if args.decode:
        if not args.out:
            raise CommandError("--decode needs --out CSV")
        check_output(args.out, "CSV")
        try:
            data = Path(args.decode).read_bytes()
        except OSError as exc:
            raise CommandError(f"cannot read {args.decode}: {exc.strerror}") from None
        dec = ccsds.decode_to_csv(mission, data, args.out, max_data=args.max_data)
        print(
            f"wrote {args.out}: {dec.snapshots} snapshots from {dec.packets} packets; "
            f"refused {sum(dec.bad.values())}{f' {dec.bad}' if dec.bad else ''}, "
            f"incomplete {dec.incomplete}, "
            f"sequence gaps {dec.seq_gaps}"
        )
        return 0
    from .node.ground import TelemetryReceiver
    from .timebase import NodeClock
    from .transport import NodeSession

    check_output(args.record, "packet file")
    if mission.downlink.ccsds:
        return _record_radio(mission, args)
    enc = ccsds.CcsdsEncoder(
        mission, divisor=args.divisor, budget_bps=args.budget, max_data=args.max_data
    )
    ns = NodeSession(mission, None)
    rx = TelemetryReceiver(ns.session, mission, NodeClock().now_ns)
    start = time.monotonic()
    try:
        with open(args.record, "ab") as f:
            while args.duration is None or time.monotonic() - start < args.duration:
                if rx.next(0.2) is None:
                    if not rx.received and time.monotonic() - start > args.timeout:
                        raise CommandError(
                            f"no telemetry from the control node within {args.timeout:g} s"
                        )
                    continue
                dv = rx.dv
                for pkt in enc.encode(dv, int(dv.get("cn_loop")), int(dv.get("cn_time_ns"))):
                    f.write(pkt)
    except KeyboardInterrupt:
        pass
    finally:
        rx.close()
        ns.close()
    print(
        f"wrote {args.record}: {enc.sent_snapshots} snapshots, {enc.sent_packets} packets, "
        f"{enc.sent_bytes} bytes; decimated {enc.decimated}, over budget {enc.dropped_budget}"
    )
    return 0
