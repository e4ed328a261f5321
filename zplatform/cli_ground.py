"""Ground-side subcommands: ``ground`` (live view + command prompt) and ``plot``."""

from __future__ import annotations

import argparse
import queue
import sys
import threading
import time
from pathlib import Path

from .errors import CommandError, ZPlatformError
from .mission import load_mission
from .telemetry import read_csv

__all__ = ["register"]

HELP = """commands: launch | abort | noop | hold | resume | arm | write ELEMENT VALUE |
          armed COMMAND (ARM n, then COMMAND n+1) | quit"""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("ground", help="live telemetry view and operator command prompt")
    p.add_argument("mission")
    p.add_argument("--watch", nargs="*", default=[], help="elements to show on the status line")
    p.add_argument("--interval", type=float, default=1.0, help="status line period (s)")
    p.add_argument("--timeout", type=float, default=10.0, help="verdict timeout per command (s)")
    p.set_defaults(func=cmd_ground)

    p = sub.add_parser("plot", help="plot logged elements against time")
    p.add_argument("csv")
    p.add_argument("elements", nargs="+")
    p.add_argument("--out", required=True, help="PNG path")
    p.set_defaults(func=cmd_plot)


def cmd_ground(args: argparse.Namespace) -> int:
    """Status line every ``--interval`` s; one command per stdin line.

    The prompt runs in a reader thread that only queues lines; the main
    thread owns the zenoh session, receives telemetry and sends commands.
    """
    from .node.ground import CommandSender

    mission = load_mission(args.mission)
    sender = CommandSender(mission, timeout_s=args.timeout)
    for name in args.watch:
        sender.rx.dv.layout.element(name)  # unknown elements fail now, with their name
    lines: queue.SimpleQueue[str | None] = queue.SimpleQueue()

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
        sender.close()


def cmd_plot(args: argparse.Namespace) -> int:
    """Plot CSV columns against time since the first row; enums as their codes."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise CommandError("plot needs matplotlib: pip install 'zplatform[plot]'") from None
    rows = read_csv(args.csv)
    if not rows:
        raise CommandError(f"{args.csv} has no rows")
    missing = [e for e in args.elements if e not in rows[0]]
    if missing:
        raise CommandError(f"not in {args.csv}: {missing}")
    t0 = int(rows[0]["rx_time_ns"])
    t = [(int(r["rx_time_ns"]) - t0) / 1e9 for r in rows]
    fig, axes = plt.subplots(
        len(args.elements), 1, sharex=True, squeeze=False, figsize=(10, 2.2 * len(args.elements))
    )
    for ax, name in zip(axes[:, 0], args.elements, strict=True):
        raw = [r[name] for r in rows]
        try:
            ax.plot(t, [float(v) for v in raw], drawstyle="steps-post")
        except ValueError:  # an enum written by name: plot its codes, label the axis
            names = sorted(set(raw), key=raw.index)
            ax.plot(t, [names.index(v) for v in raw], drawstyle="steps-post")
            ax.set_yticks(range(len(names)), names)
        ax.set_ylabel(name)
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("time since first snapshot (s)")
    fig.tight_layout()
    fig.savefig(Path(args.out), dpi=100)
    print(f"wrote {args.out}")
    return 0
