"""Closing the gap to the floor, lever by lever: led_test's 3-DN sync under
each transport and scheduling lever, interleaved in rounds.

Each variant is one ``python -m bench.sync_trace --ground`` run (a fresh
process: zenoh reads its runtime settings once per process) of the full
led_test mission with its ground node; variants take turns, round after
round, so they share the box's moods. Per variant: the median over rounds
of the sync p50/p99 (the CN's ``ControlSync.duration_ns``), the missed
loops summed, and the per-hop p50s of :mod:`bench.sync_trace`.

Variants (``shipped`` is the mission's defaults; each other changes one thing):

* ``shipped``: one get per DN, lowlatency off, zenoh's own thread pools,
  every node thread SCHED_FIFO 20;
* ``wildcard``: one query per loop with every DN's frame (``sync_query: wildcard``);
* ``lowlatency``: zenoh's lowlatency transport (``lowlatency: true``);
* ``rx_pool_1``: zenoh's receive pool at one thread (``ZENOH_RUNTIME``);
* ``zenoh_above_loop`` / ``zenoh_below_loop``: every thread of the CN and DNs
  but the loop thread at SCHED_FIFO 30 / 10 (loop threads stay at 20);
* ``pinned``: the CN on CPU 0, every DN on CPU 1 (the ground node unpinned
  and unprivileged throughout, as shipped).

What a lever costs besides time is in the report (bench/REPORT.md, "levers"):
lowlatency and the one-thread receive pool each froze the CN's loop on a cut
cable in tests/faults, so neither ships, whatever they win here.

Run ``python -m bench.levers [--quick] [--rounds N] [--seconds S]``; blocks
about rounds x variants x (seconds + 15 s of start-up).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import REPO_ROOT, bench_argparser
from bench.common import write_result as _write

VARIANTS: dict[str, list[str]] = {
    "shipped": [],
    "wildcard": ["--sync-query", "wildcard"],
    "lowlatency": ["--lowlatency", "true"],
    "rx_pool_1": ["--env", "ZENOH_RUNTIME=(rx:(worker_threads:1))"],
    "zenoh_above_loop": ["--zenoh-priority", "30"],
    "zenoh_below_loop": ["--zenoh-priority", "10"],
    "pinned": ["--pin", "cn=0,dn=1"],
}


def run_once(name: str, seconds: float, out: Path, priority: int = 20) -> dict[str, Any]:
    """One sync_trace run of variant ``name``; returns its result document."""
    args = [sys.executable, "-m", "bench.sync_trace", "--ground", "--seconds", str(seconds)]
    args += ["--priority", str(priority)]
    args += ["--json", str(out), *VARIANTS[name]]
    r = subprocess.run(args, cwd=REPO_ROOT, capture_output=True, text=True, timeout=600)
    if r.returncode != 0:
        raise RuntimeError(f"{name}: sync_trace failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
    doc: dict[str, Any] = json.loads(out.read_text())
    return doc


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = bench_argparser(__doc__.splitlines()[0] if __doc__ else "levers")
    parser.add_argument("--rounds", type=int, default=None)
    parser.add_argument("--seconds", type=float, default=None, help="per run")
    parser.add_argument("--only", default=None, help="comma-separated variant names")
    parser.add_argument("--priority", type=int, default=20, help="SCHED_FIFO (0: off)")
    args = parser.parse_args(argv)
    rounds = args.rounds or (1 if args.quick else 3)
    seconds = args.seconds or (4.0 if args.quick else 12.0)
    names = args.only.split(",") if args.only else list(VARIANTS)
    runs: dict[str, list[dict[str, Any]]] = {n: [] for n in names}
    with tempfile.TemporaryDirectory(prefix="zp-levers-") as tmp:
        for k in range(rounds):
            for n in names:
                doc = run_once(n, seconds, Path(tmp) / f"{n}_{k}.json", args.priority)
                runs[n].append(doc)
                v = doc["variants"]["trace"]
                print(f"round {k + 1} {n}: p50 {v['p50_us']} us p99 {v['p99_us']} us", flush=True)
    variants: dict[str, dict[str, Any]] = {}
    for n, docs in runs.items():
        vs = [d["variants"]["trace"] for d in docs]
        fig: dict[str, Any] = {
            "p50_us": round(float(np.median([v["p50_us"] for v in vs])), 1),
            "p99_us": round(float(np.median([v["p99_us"] for v in vs])), 1),
            "max_us": round(float(max(v["max_us"] for v in vs)), 1),
            "deadline_miss_rate": float(np.mean([v["deadline_miss_rate"] for v in vs])),
            "msgs": int(sum(v["msgs"] for v in vs)),
            "missed_loops": int(sum(d["params"]["missed_loops"] for d in docs)),
            "p50_each_round_us": [v["p50_us"] for v in vs],
            "p99_each_round_us": [v["p99_us"] for v in vs],
            "args": " ".join(VARIANTS[n]) or "(defaults)",
        }
        for hop in vs[0]["hops"]:
            fig[f"hop_{hop}_p50_us"] = round(
                float(np.median([v["hops"][hop]["p50_us"] or 0 for v in vs])), 1
            )
        variants[n] = fig
    base = variants.get("shipped")
    ratios: dict[str, float] = {}
    ratios_p99: dict[str, float] = {}
    if base:
        for n, f in variants.items():
            ratios[f"{n}/shipped"] = round(f["p50_us"] / base["p50_us"], 3)
            ratios_p99[f"{n}/shipped"] = round(f["p99_us"] / base["p99_us"], 3)
    params = {
        "mission": "configs/led_test.yaml (3 DNs) with its ground node, free ports, auth on",
        "rounds": rounds,
        "seconds_per_run": seconds,
        "interleaving": "variants take turns within each round; medians over rounds",
        "figure": "ControlSync.duration_ns per loop (missed loops count as the deadline)",
        "ratios_p50": ratios,
        "ratios_p99": ratios_p99,
        "quick": bool(args.quick),
    }
    doc = _write("levers", params, variants, args.json)
    for n, f in variants.items():
        print(f"{n}: p50 {f['p50_us']} us p99 {f['p99_us']} us missed {f['missed_loops']}")
    return doc


if __name__ == "__main__":
    main()
