"""Ground-side subcommands: ``ground`` (console or prompt), ``params``, ``plot``, ``xtce``."""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path
from typing import Any

from ..errors import CommandError
from ..mission.load import load_mission
from ..telemetry.logs import read_csv
from .args import (
    check_output,
    identity_options,
    mission_verb,
    positive_float,
    positive_int,
    signer_of,
    timeout_option,
)


def _port(text: str) -> int:
    """argparse type: a TCP port, 0..65535 (0: any free port)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number, got {text!r}") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port number 0..65535, got {text}")
    return v


def _minutes(text: str) -> float:
    """argparse type: minutes, 0 or more (finite)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected minutes, got {text!r}") from None
    if not 0 <= v <= 1e6:
        raise argparse.ArgumentTypeError(f"must be 0..1000000 minutes, got {text}")
    return v


__all__ = ["register"]


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = mission_verb(
        sub,
        "ground",
        help="the ground console (terminal or --web PORT); a line prompt when stdin is no TTY",
    )
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
    identity_options(p)
    p.add_argument("--interval", type=positive_float, default=1.0, help="status line period (s)")
    timeout_option(p, "each command's verdict")
    p.add_argument(
        "--los", type=positive_float, default=0.3, help="console: seconds of silence that mean LOS"
    )
    p.add_argument(
        "--limits",
        metavar="YAML",
        help="console: element limits {NAME: {yellow: [lo, hi], red: [lo, hi]}} over the mission's",
    )
    p.add_argument(
        "--history",
        type=_minutes,
        metavar="MIN",
        help="console: open with the last MIN minutes of the ground archive (default 10; 0: none)",
    )
    p.add_argument(
        "--plot", nargs="+", metavar="ELEMENT", help="console: plot these from the start"
    )
    p.set_defaults(func=cmd_ground)

    p = mission_verb(
        sub,
        "params",
        help="list the mission's parameters (live values when it runs), or set one",
        description="Without NAME VALUE: every parameter with its value (from live telemetry "
        "when the control node runs, else from this host's parameter file), default, bounds, "
        "units, the states it may change in, and whether it is hazardous. With NAME VALUE: "
        "PRM_SET (--arm: ARM n, then PRM_SET n+1, for a hazardous parameter), then with "
        "--save PRM_SAVE, waiting until the control node has written its parameter file. "
        "Exits 0 only when everything was accepted (and saved).",
    )
    p.add_argument("name", nargs="?", metavar="NAME", help="the parameter to set")
    p.add_argument("value", nargs="?", metavar="VALUE", help="its new value")
    p.add_argument(
        "--arm", action="store_true", help="send ARM n first (a hazardous parameter needs it)"
    )
    p.add_argument(
        "--save", action="store_true", help="then PRM_SAVE: write every parameter to the file"
    )
    p.add_argument("--json", action="store_true", help="list as JSON")
    identity_options(p)
    timeout_option(p, "telemetry and for each verdict")
    p.set_defaults(func=cmd_params)

    p = sub.add_parser(
        "plot",
        help="plot logged elements against time, state changes and commands marked",
        description="Plot telemetry CSV columns against time: numbers as lines, booleans "
        "and enums as labelled steps; state changes (cn_state) and commands (cn_cmd_seq) "
        "as named vertical lines.",
    )
    p.add_argument(
        "csv",
        help="telemetry CSV written by up --log, log or sim; with --run, the mission file "
        "whose ground archive to read",
    )
    p.add_argument("elements", nargs="+", help="column names (see the CSV's header)")
    p.add_argument("--out", required=True, help="image path (PNG, SVG, PDF by extension)")
    p.add_argument("--title", help="figure title (default: the CSV name and the elements)")
    p.add_argument(
        "--run",
        metavar="R",
        help="plot run R (or 'last') of the mission's ground archive instead of a CSV",
    )
    p.add_argument(
        "--archive", metavar="DIR", help="with --run: this archive directory (.../archive/MISSION)"
    )
    p.set_defaults(func=cmd_plot)

    p = mission_verb(
        sub, "xtce", help="write the mission's telemetry packets and commands as XTCE (Yamcs)"
    )
    p.add_argument("--out", help="XML path (default: MISSION_NAME.xtce.xml)")
    p.set_defaults(func=cmd_xtce)

    p = mission_verb(
        sub, "ccsds", help="record live telemetry as CCSDS space packets, or decode them to CSV"
    )
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
    timeout_option(p, "the CN with --record")
    p.set_defaults(func=cmd_ccsds)


def cmd_ground(args: argparse.Namespace) -> int:
    """The console on a TTY (or ``--console``), served with ``--web``, else the prompt."""
    if args.web is not None or args.console or (sys.stdin.isatty() and not args.prompt):
        # A console that only watches needs no operator; one named signs its
        # commands (an unknown operator or station fails here, in one line).
        signer = signer_of(load_mission(args.mission, code=False), args, commands=False)
        try:
            from ..console import run_console, serve_console
        except ImportError as exc:
            raise CommandError(
                f"the console needs {exc.name}, a dependency of zplatform that is not "
                "installed here: reinstall zplatform (pip install --force-reinstall zplatform)"
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
                history_min=args.history,
                plot=args.plot,
                operator=args.operator,
                station=args.station,
            )
            return 0
        return run_console(
            args.mission,
            timeout_s=args.timeout,
            los_s=args.los,
            limits=limits,
            history_min=args.history,
            plot=args.plot,
            signer=signer,
        )
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
    """The line prompt (:func:`zplatform.ground.tools.run_prompt`)."""
    from ..ground.tools import run_prompt

    mission = load_mission(args.mission, code=False)
    return run_prompt(
        mission,
        watch=args.watch,
        interval_s=args.interval,
        timeout_s=args.timeout,
        # A prompt that only watches needs no operator; one named commands.
        signer=signer_of(mission, args, commands=False),
    )


def cmd_params(args: argparse.Namespace) -> int:
    """List (exit 0), or set and/or save (exit 0 only when all succeeded)."""
    import json

    import msgspec

    from ..ground.tools import list_params, set_param

    mission = load_mission(args.mission, code=False)
    if args.name is not None and args.value is None:
        raise CommandError(f"params {args.name}: give its VALUE too")
    if args.name is None and not (args.save or args.arm):
        listing = list_params(mission, timeout_s=args.timeout)
        if args.json:
            print(json.dumps(msgspec.to_builtins(listing), indent=2))
            return 0
        print(f"{listing.mission}: {listing.source}")
        header = ("NAME", "VALUE", "DEFAULT", "BOUNDS", "STATES", "")
        rows = [header] + [
            (r.name, r.value, r.default, r.bounds, ",".join(r.states), "hazardous" * r.hazardous)
            for r in listing.rows
        ]
        widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
        for row in rows:
            print("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip())
        return 0
    lines, ok = set_param(
        mission,
        args.name,
        args.value,
        armed=args.arm,
        save=args.save,
        timeout_s=args.timeout,
        signer=signer_of(mission, args),
    )
    for line in lines:
        print(line)
    return 0 if ok else 1


def _needs(module: str, verb: str, package: str, extra: str) -> Any:
    """``module``, imported; CommandError naming the extra that brings
    ``package`` when it cannot be (one line, exit 2)."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise CommandError(f"{verb} needs {package}: pip install 'zplatform[{extra}]'") from None


def cmd_plot(args: argparse.Namespace) -> int:
    """Plot CSV columns against time since the first row (see telemetry.plot_telemetry)."""
    _needs("matplotlib", "plot", "matplotlib", "plot")
    from ..telemetry.logs import plot_telemetry

    if args.run is not None:
        return _plot_archive(args)
    if args.archive is not None:
        raise CommandError("--archive is read with --run R: the run to plot")
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


PLOT_MARKER_ELEMENTS = ("cn_state", "cn_cmd_seq", "cn_cmd", "cn_cmd_status")
"""What plot's markers read (state changes, commands), asked of the archive too."""


def _plot_archive(args: argparse.Namespace) -> int:
    """``plot MISSION ELEMENTS --run R``: the rows of run R of the mission's
    archive, as its telemetry CSV would hold them, plotted the same way."""
    import io

    from ..archive import archive_dir
    from ..telemetry.logs import plot_telemetry
    from .archive import archive_run, log_from_archive

    mission = load_mission(args.csv, code=False)
    root = Path(args.archive) if args.archive else archive_dir(mission)
    names = list(_cn_elements(mission))
    want = dict.fromkeys(e.split("[", 1)[0] for e in args.elements)
    unknown = [e for e in want if e not in names]
    if unknown:
        from ..control.uplink import did_you_mean

        raise CommandError(
            f"not an element of {mission.mission}: {unknown[0]!r}" + did_you_mean(unknown[0], names)
        )
    want.update((m, None) for m in PLOT_MARKER_ELEMENTS if m in names)
    check_output(args.out, "plot")
    buf = io.StringIO()
    info, n, _, problems = log_from_archive(
        mission, root, archive_run(args.run), buf, elements=",".join(want)
    )
    for line in problems:
        print(f"zplatform plot: {line}", file=sys.stderr)
    buf.seek(0)
    rows = read_csv(buf)
    if not rows:
        raise CommandError(f"run {info.run} of the archive {root} has no rows")
    missing = [e for e in args.elements if e not in rows[0]]
    if missing:
        raise CommandError(f"not columns of the telemetry log: {missing} (an array: NAME[i])")
    title = args.title or f"{mission.mission} run {info.run}: {', '.join(args.elements)}"
    markers = plot_telemetry(rows, args.elements, args.out, title=title)
    print(f"wrote {args.out} (run {info.run}: {n} rows, {len(markers)} state/command markers)")
    return 0


def _cn_elements(mission: Any) -> list[str]:
    """The elements of the control node's vector (what the archive keeps)."""
    from ..core.datavector import Layout

    return list(Layout.for_node(mission, "cn").elements)


def cmd_xtce(args: argparse.Namespace) -> int:
    """Write the XTCE database of the mission's CCSDS downlink and commands."""
    write_xtce = _needs("zplatform.cli.xtce", "xtce", "yamcs-pymdb", "ground").write_xtce
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
    from ..ground.link import GroundLink

    link = GroundLink(mission, keys=None, telemetry=False, events=False)
    link.tap(link.keys.downlink)
    n = size = 0
    start = time.monotonic()
    try:
        with open(args.record, "ab") as f:
            while args.duration is None or time.monotonic() - start < args.duration:
                got = link.next_tap(0.2)
                if got is None:
                    if not n and time.monotonic() - start > args.timeout:
                        raise CommandError(
                            f"no downlink packet from the control node within {args.timeout:g} s"
                        )
                    continue
                f.write(got[1])
                n += 1
                size += len(got[1])
    except KeyboardInterrupt:
        pass
    finally:
        link.close()
    print(f"wrote {args.record}: {n} packets, {size} bytes from the CN's downlink")
    return 0


def cmd_ccsds(args: argparse.Namespace) -> int:
    """``--record``: telemetry -> packets (the radio path, on the ground); ``--decode``: -> CSV."""
    ccsds = _needs("zplatform.telemetry.ccsds", "ccsds", "spacepackets", "ground")
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
    from ..ground.link import GroundLink

    check_output(args.record, "packet file")
    if mission.downlink.ccsds:
        return _record_radio(mission, args)
    enc = ccsds.CcsdsEncoder(
        mission, divisor=args.divisor, budget_bps=args.budget, max_data=args.max_data
    )
    link = GroundLink(mission, events=False)
    start = time.monotonic()
    try:
        with open(args.record, "ab") as f:
            while args.duration is None or time.monotonic() - start < args.duration:
                if link.next(0.2) is None:
                    if not link.logic.received and time.monotonic() - start > args.timeout:
                        raise CommandError(link.why_no_telemetry(args.timeout))
                    continue
                dv = link.dv
                for pkt in enc.encode(dv, int(dv.get("cn_loop")), int(dv.get("cn_time_ns"))):
                    f.write(pkt)
    except KeyboardInterrupt:
        pass
    finally:
        link.close()
    print(
        f"wrote {args.record}: {enc.sent_snapshots} snapshots, {enc.sent_packets} packets, "
        f"{enc.sent_bytes} bytes; decimated {enc.decimated}, over budget {enc.dropped_budget}"
    )
    return 0
