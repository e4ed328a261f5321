"""zplatform: run, watch and command Zenoh flight-software missions.

Each subcommand is a small function that parses its arguments, calls the
library, prints, and returns an exit code. Errors of the ZPlatformError tree
and OS errors on the user's paths print one line (``zplatform: error: ...``)
and exit 2; a closed stdout (``zplatform check --json | head``) ends quietly.
Nothing prints a traceback for a user mistake.

Every MISSION argument is a mission file or the name of a running mission
(``zplatform ps``): :func:`zplatform.cli.registry.resolve_mission`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import msgspec

from .. import __version__
from ..config import Mission
from ..core.datavector import Layout
from ..errors import ZPlatformError
from ..mission.load import load_mission
from .registry import resolve_mission

__all__ = ["main"]

Handler = Callable[[argparse.Namespace], int]


def _mission_report(m: Mission) -> dict[str, object]:
    layout = Layout.for_node(m, "cn")
    from ..core.codec import frame_overhead

    regions = []
    per_loop = 0
    for r in layout.regions.values():
        frame = r.size + frame_overhead(r.size)
        if r.name != "cn":
            per_loop += frame
        regions.append(
            {
                "region": r.name,
                "layout_id": f"{r.layout_id:#010x}",
                "size": r.size,
                "frame_bytes": frame,
                "elements": [
                    {
                        "name": e.name,
                        "type": e.type_text,
                        "offset": e.offset - r.offset,
                        "size": e.size,
                        "initial": e.initial,
                    }
                    for e in r.elements
                ],
            }
        )
    telemetry = layout.size + frame_overhead(layout.size)
    per_loop_tm = telemetry / m.telemetry_divisor
    return {
        "mission": m.mission,
        "vehicle": m.vehicle,
        "loop_hz": m.loop_hz,
        "sync_timeout_ms": m.sync_timeout_ms,
        "nodes": sorted(m.nodes),
        "vector_size": layout.size,
        "vector_layout_id": f"{layout.layout_id:#010x}",
        "regions": regions,
        "sync_bytes_per_loop": per_loop,
        "telemetry_bytes_per_loop": per_loop_tm,
        # With a standby, the commander's mirror to it every loop too.
        "bandwidth_bps": (per_loop + per_loop_tm + (telemetry if m.standby else 0)) * 8 * m.loop_hz,
        "standby": (
            {
                "node": m.standby,
                "takeover_loops": m.takeover.takeover_loops,
                "lease_loops": m.takeover.lease_loops,
                # The standby's copy of the vector, every loop, whatever the divisor.
                "mirror_bytes_per_loop": telemetry,
            }
            if m.standby is not None
            else None
        ),
    }


def _links_report(m: Mission) -> tuple[dict[str, object], str]:
    """How the mission's links are secured, and the deployment a session on
    this host would use (checked to fit: DeploymentError otherwise), as
    report fields and one line of text."""
    from ..config import transport_reason
    from ..security.deploy import find_deployment, require_deployment

    why = transport_reason(m)
    if not m.mtls:
        return {"transport": "plain", "deployment": None}, f"links: plain ({why})"
    path = find_deployment(m)
    if path is None:
        where = (
            "no deployment on this host yet (`zplatform keygen MISSION_FILE` makes the "
            "mission's PKI; `up` does on first use)"
        )
    else:
        require_deployment(m)
        where = f"deployment {path}"
    text = f"links: mutual TLS with access control ({why}); {where}"
    return {"transport": "mtls", "deployment": None if path is None else str(path)}, text


def cmd_check(args: argparse.Namespace) -> int:
    """Validate; print the report, the links' security and the safety
    warnings (:mod:`zplatform.mission.safety`).

    Exit 0 with warnings, 2 with ``--strict`` (each warning printed as an
    error line), 2 for a mission that does not load or a deployment that
    does not fit it."""
    from ..control.commands import refused_while_faulted
    from ..mission.safety import doors, safety_warnings

    # load_mission builds every controller and device on scratch vectors,
    # so a bad class path or component config fails here, not on the pad.
    m = load_mission(args.mission)
    warnings = safety_warnings(m)
    rep = _mission_report(m)
    links, links_text = _links_report(m)
    rep.update(links)
    writable, outputs = doors(m)
    rep["writable"] = [msgspec.to_builtins(w) for w in writable]
    rep["hazardous_outputs"] = [msgspec.to_builtins(h) for h in outputs]
    faulted = refused_while_faulted(m)
    rep["hazardous_commands"] = list(m.commands.hazardous)
    rep["refused_while_faulted"] = faulted
    rc = 2 if args.strict and warnings else 0
    if args.json:
        rep["warnings"] = [msgspec.to_builtins(w) for w in warnings]
        rep["ok"] = rc == 0
        print(json.dumps(rep, indent=2))
        return rc
    level = "error" if args.strict else "warning"
    for w in warnings:
        print(f"zplatform: {level}: {w}", file=sys.stderr)
    if rc:
        return rc
    flagged = f", {len(warnings)} safety warning(s) (above)" if warnings else ""
    print(
        f"mission {rep['mission']}: OK{flagged}  ({len(m.nodes)} nodes, {m.loop_hz:g} Hz, "
        f"sync deadline {m.sync_timeout_ms:g} ms)"
    )
    print(links_text)
    if m.has_ground:
        print(
            f"WRITE may set {len(writable)} element(s) (commands.writable; deny by default)"
            + (":" if writable else "")
        )
        for e in writable:
            arm = "  (ARM n, then WRITE n+1)" if e.protected else ""
            print(f"  {e.element:<24} in {', '.join(e.states)}{arm}")
    if m.commands.hazardous or faulted:
        print(
            f"hazardous commands: {', '.join(m.commands.hazardous) or 'none'} (ARM n, then n+1); "
            f"refused while a fault is latched: {', '.join(faulted) or 'none'} "
            "(commands.refused_while_faulted)"
        )
    if outputs:
        print(f"hazardous outputs: {len(outputs)} (hazardous_outputs; interlocked on their node):")
        for h in outputs:
            safe = str(h.safe).lower() if isinstance(h.safe, bool) else f"{h.safe:g}"
            print(
                f"  {h.element:<24} {h.node}: driven only in {', '.join(h.states) or 'no state'}"
                f"; else {safe}"
            )
    if m.standby is not None:
        f = m.takeover
        print(
            f"standby control node {m.standby}: takes command after {f.takeover_loops} loops "
            f"without the commander (device nodes' lease {f.lease_loops} loops, watchdog "
            f"{m.faults.dn_watchdog_loops}); its mirror of the vector "
            f"{rep['standby']['mirror_bytes_per_loop']} B per loop"  # type: ignore[index]
        )
    for r in rep["regions"]:  # type: ignore[attr-defined]
        print(
            f"\nregion {r['region']}  {r['size']} B  frame {r['frame_bytes']} B  "
            f"layout_id {r['layout_id']}"
        )
        for e in r["elements"]:
            print(f"  {e['offset']:>6}  {e['size']:>5} B  {e['type']:<24} {e['name']}")
    bw = float(rep["bandwidth_bps"])  # type: ignore[arg-type]
    print(
        f"\nper loop: {rep['sync_bytes_per_loop']} B sync + "
        f"{rep['telemetry_bytes_per_loop']:g} B telemetry; "
        f"bandwidth at {m.loop_hz:g} Hz: {bw / 1e6:.3f} Mbit/s"
    )
    return 0


def cmd_ps(args: argparse.Namespace) -> int:
    """The running missions ``up`` registered (stale entries are dropped)."""
    import time

    from .registry import entries_json, running

    entries = running()
    if args.json:
        print(entries_json(entries))
        return 0
    if not entries:
        print("no mission is running")
        return 0
    print(f"{'NAME':<20} {'PID':>8} {'UP':>8}  {'MISSION FILE':<40} LOGS")
    now = time.time()
    for e in entries:
        logs = " ".join(e.logs.values()) or "-"
        # The file the user started, not `up --free-ports`' remapped copy.
        shown = e.source_file or e.mission_file
        print(f"{e.name:<20} {e.pid:>8} {now - e.started:>7.0f}s  {shown:<40} {logs}")
    return 0


MISSION_HELP = "mission YAML file, or the name of a running mission (`zplatform ps`)"


def _keygen_pki(mission: Mission, where: Path) -> None:
    """keygen's PKI step (:mod:`zplatform.security.pki`): for a mission whose links run
    mutual TLS, make what its PKI in ``where`` (beside the key set) lacks and
    say which file goes to which host."""
    from ..config import transport_reason
    from ..security.pki import ensure_mission_pki, host_files

    if not mission.mtls:
        print(f"no certificates: its links are plain ({transport_reason(mission)})")
        return
    pki = ensure_mission_pki(mission, where)
    made = f"made {', '.join(pki.made)}" if pki.made else "every certificate was there"
    print(f"the PKI of its mutual TLS links ({transport_reason(mission)}) is beside it ({made}):")
    for who, files in host_files(mission):
        print(f"  {' '.join(files):<32} -> {who}")


def _keygen_identities(mission: Mission, where: Path, *, replace: bool) -> None:
    """keygen's operator and station keys (a mission with ``ground:``): the
    missing ones (or those whose ``key_id`` the mission raised), derived
    from ``cn.keys``: the vehicle is never re-keyed for them."""
    from ..security.identities import write_identity_files

    if mission.ground is None:
        return
    made = write_identity_files(mission, where, replace=replace)
    if not made:
        print("every operator and station key file is there (ground:)")
        return
    print("operator and station keys (ground:), one file each, to that operator or station:")
    for name in made:
        print(f"  {name}")


def cmd_keygen(args: argparse.Namespace) -> int:
    """Write a new key set (one file per host role, mode 0600, in a 0700
    directory) and, for a mission whose links run mutual TLS, the mission's
    PKI beside it (only what is missing); say which file goes to which host.
    An existing set is kept (said so, exit 0) unless ``--rotate``."""
    from ..core.auth import (
        KEY_FILE_ENV,
        default_key_dir,
        host_roles,
        key_file_name,
        read_key_file,
        role_host,
        role_links,
        write_key_set,
    )

    mission = load_mission(resolve_mission(args.target), code=False)
    where = Path(args.out) if args.out else default_key_dir(mission)
    have = [where / key_file_name(r) for r in host_roles(mission)]
    if not args.rotate and all(p.is_file() for p in have):
        # The documented order (docs/operations.md) runs `up` (which makes the set on first use)
        # before `keygen`: the set is there, and it is what every host needs.
        read_key_file(have[0], mission)  # a damaged or foreign set still says so
        print(
            f"the key set of mission {mission.mission!r} is in {where}/ already (made by "
            "`up` on first use or an earlier keygen): nothing written; `--rotate` replaces "
            "it (every host then needs its new file)"
        )
        _keygen_identities(mission, where, replace=False)
        _keygen_pki(mission, where)
        return 0
    files = write_key_set(mission, where, replace=args.rotate)
    print(f"wrote the key set of mission {mission.mission!r} to {where}/ (one file per host role):")
    for role in host_roles(mission):
        links = ", ".join(role_links(mission, role))
        print(f"  {files[role].name:<10} -> {role_host(role):<46} {links}")
    _keygen_identities(mission, where, replace=args.rotate)
    _keygen_pki(mission, where)
    print(
        "copy each file to its host only, into the same directory (or point "
        f"{KEY_FILE_ENV} at it); a single host (zplatform up) uses the directory as it is"
    )
    return 0


def cmd_schema(args: argparse.Namespace) -> int:
    """The mission file's JSON Schema (or its markdown reference, or the key
    space's table), to stdout or a file."""
    from pathlib import Path

    from ..mission.schema import mission_schema_json, reference_markdown
    from ..security.keyspace import keyspace_markdown
    from .args import check_output

    if args.keyspace:
        text, what = keyspace_markdown(), "the key space"
    elif args.markdown:
        text, what = reference_markdown(), "the mission reference"
    else:
        text, what = mission_schema_json(), "the mission schema"
    if args.out is None:
        sys.stdout.write(text)
        return 0
    check_output(args.out, what)
    Path(args.out).write_text(text, encoding="utf-8")
    print(f"wrote {what} to {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="zplatform",
        description=__doc__.splitlines()[0] if __doc__ else None,
        epilog="`zplatform VERB --help` describes a verb; MISSION is a " + MISSION_HELP + ".",
    )
    p.add_argument("--version", action="version", version=f"zplatform {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="VERB")
    c = sub.add_parser(
        "check",
        help="validate a mission; print regions, offsets, bandwidth and safety warnings",
    )
    c.add_argument("mission", help=MISSION_HELP)
    c.add_argument(
        "--json", action="store_true", help="machine-readable report (with its warnings)"
    )
    c.add_argument(
        "--strict",
        action="store_true",
        help="safety warnings are errors (exit 2): for CI and flight missions",
    )
    c.set_defaults(func=cmd_check)
    c = sub.add_parser(
        "keygen",
        help="make the mission's key set (one key file per host role: cn, each dn, gn, "
        "tool) and the certificates of a mission whose links run mutual TLS",
    )
    # Not `mission`: main() would load it with its code; keygen needs only the nodes.
    c.add_argument("target", metavar="MISSION", help=MISSION_HELP)
    c.add_argument(
        "--out",
        metavar="DIR",
        help="the directory to write the set into (default: the mission's key directory)",
    )
    c.add_argument(
        "--rotate",
        action="store_true",
        help="replace an existing key set with new keys (every host then needs its new file)",
    )
    c.set_defaults(func=cmd_keygen)
    c = sub.add_parser(
        "schema",
        help="print the mission file's JSON Schema (for editor completion and validation)",
        description="Print the JSON Schema of a mission file, or with --markdown the mission "
        "reference (docs/mission-reference.md), or with --keyspace the key space's table "
        "(docs/keyspace.md). Point an editor at the schema with a first "
        "line `# yaml-language-server: $schema=mission.schema.json` in the mission file.",
    )
    c.add_argument("--out", metavar="FILE", help="write it to FILE instead of stdout")
    form = c.add_mutually_exclusive_group()
    form.add_argument(
        "--markdown", action="store_true", help="the mission reference (markdown) instead"
    )
    form.add_argument(
        "--keyspace",
        action="store_true",
        help="the key space's table (markdown, docs/keyspace.md) instead",
    )
    c.set_defaults(func=cmd_schema)
    c = sub.add_parser("ps", help="list the running missions (registered by `up`)")
    c.add_argument("--json", action="store_true", help="the registry entries as JSON")
    c.set_defaults(func=cmd_ps)
    for register in _EXTRA:
        register(sub)
    return p


# Subcommands contributed by other modules (runtime, ground tools, sim, archive).
_EXTRA: list[Callable[[argparse._SubParsersAction[argparse.ArgumentParser]], None]] = []


def _load_extras() -> None:
    import importlib

    if _EXTRA:  # once per process: main() may be called again (tests)
        return
    for mod in (
        "zplatform.cli.runtime",
        "zplatform.cli.ground",
        "zplatform.cli.sim",
        "zplatform.cli.archive",
    ):
        try:
            m = importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                raise
            continue
        _EXTRA.append(m.register)


def main(argv: Sequence[str] | None = None) -> int:
    _load_extras()
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Handler = args.func
    try:
        if getattr(args, "mission", None) is not None:
            args.mission = resolve_mission(args.mission)
        rc = func(args)
        sys.stdout.flush()  # here, not at exit, so a closed pipe is caught below
        return rc
    except ZPlatformError as exc:
        print(f"zplatform: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader went away (`| head`): stop quietly, like any Unix tool.
        # Point stdout at /dev/null so the interpreter's final flush is silent.
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 141
    except OSError as exc:
        # A path the user gave that cannot be read or written.
        where = f" {exc.filename!r}" if exc.filename else ""
        print(f"zplatform: error: cannot use{where}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
