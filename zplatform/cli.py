"""The ``zplatform`` command (DESIGN.md §6).

Each subcommand is a small function that parses its arguments, calls the
library, prints, and returns an exit code. Errors of the ZPlatformError tree
print one line (``zplatform: error: ...``) and exit 2; nothing prints a
traceback for a user mistake.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence

from .config import Mission
from .datavector import Layout
from .errors import ZPlatformError
from .mission import load_mission

__all__ = ["main"]

Handler = Callable[[argparse.Namespace], int]


def _mission_report(m: Mission) -> dict[str, object]:
    layout = Layout.for_node(m, "cn")
    from .codec import frame_overhead

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
        "bandwidth_bps": (per_loop + per_loop_tm) * 8 * m.loop_hz,
    }


def cmd_check(args: argparse.Namespace) -> int:
    # load_mission builds every controller and device on scratch vectors,
    # so a bad class path or component config fails here, not on the pad.
    m = load_mission(args.mission)
    rep = _mission_report(m)
    if args.json:
        print(json.dumps(rep, indent=2))
        return 0
    print(
        f"mission {rep['mission']}: OK  ({len(m.nodes)} nodes, {m.loop_hz:g} Hz, "
        f"sync deadline {m.sync_timeout_ms:g} ms)"
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="zplatform", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("check", help="validate a mission; print regions, offsets, bandwidth")
    c.add_argument("mission")
    c.add_argument("--json", action="store_true", help="machine-readable report")
    c.set_defaults(func=cmd_check)
    for register in _EXTRA:
        register(sub)
    return p


# Subcommands contributed by other modules (runtime, ground tools, sim).
_EXTRA: list[Callable[[argparse._SubParsersAction[argparse.ArgumentParser]], None]] = []


def _load_extras() -> None:
    import importlib

    if _EXTRA:  # once per process: main() may be called again (tests)
        return
    for mod in ("zplatform.cli_runtime", "zplatform.cli_ground", "zplatform.cli_sim"):
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
        return func(args)
    except ZPlatformError as exc:
        print(f"zplatform: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
