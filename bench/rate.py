"""The highest loop rate each topology (1 and 3 DNs) holds with under 1e-4 deadline misses.

For each topology, a zplatform cluster (:func:`bench.sync.run_zplatform`: DN
processes, the CN's real loop in this process, SCHED_FIFO as in
:mod:`bench.sync`) runs at rising loop rates (100, 200, 300, 500, 700, 1000,
1500, 2000 Hz by default), each for 30 s (``--quick``: 5 s), with the sync
deadline at 60% of the period and 256 B regions. A rate *passes* when

* the miss rate, ``missed / (loops × DNs)`` (a DN's reply not in by the sync
  deadline, the CN's ``cn_missed_dnX`` counters), is under 1e-4, and
* the overrun rate, ``loop_overruns / loops`` (a step that ended past the
  next period's start), is under 1e-4.

A topology stops at its first failing rate; its result is the highest rate
that passed (``None`` if even the lowest failed). Every tried rate is a
variant ``zplatform_<n>dn_<rate>hz`` with its miss and overrun rates, the
sync duration p50/p99/max (``summarize``; a missed loop counts as the
deadline), and ``passed``. ``params.highest_passing_hz`` holds the answer
per topology and ``params.targets`` the verdict on the target, 1 kHz with
1 DN.

What blocks: :func:`main` blocks for every tried rate's duration plus each
cluster's start-up (about 1-3 s; DNs are waited for by liveliness and a
warm-up sync, never by sleeping): at most 16 × 30 s plus start-ups.

Run ``python -m bench.rate [--quick] [--json PATH]``; results go to
``bench/results/rate.json``.
"""

from __future__ import annotations

from typing import Any

from bench.common import bench_argparser, write_result
from bench.sync import PRIORITY, REGION_BYTES, inherit_fifo, run_zplatform
from bench.sync_trace import LOWLATENCY_ARG

LADDER_HZ: tuple[float, ...] = (100, 200, 300, 500, 700, 1000, 1500, 2000)
TOPOLOGIES = (1, 3)
TIMEOUT_FRACTION = 0.6
MAX_MISS_RATE = 1e-4
MAX_OVERRUN_RATE = 1e-4
TARGET_HZ_1DN = 1000.0
QUICK_S = 5.0
FULL_S = 30.0


def try_rate(
    n_dn: int, rate_hz: float, duration_s: float, *, priority: int, lowlatency: bool | str
) -> dict[str, Any]:
    """Run ``n_dn`` DNs at ``rate_hz`` for ``duration_s``; return the figures and ``passed``.

    Blocks for the cluster's start-up plus ``duration_s``.
    """
    timeout_ms = TIMEOUT_FRACTION * 1e3 / rate_hz
    fig = run_zplatform(
        n_dn,
        rate_hz=rate_hz,
        duration_s=duration_s,
        sync_timeout_ms=timeout_ms,
        region_bytes=REGION_BYTES,
        lowlatency=lowlatency,
        priority=priority,
    )
    loops = max(int(fig["loops"]), 1)
    miss_rate = fig["missed"] / (loops * n_dn)
    overrun_rate = fig["loop_overruns"] / loops
    fig["rate_hz"] = rate_hz
    fig["sync_timeout_us"] = round(timeout_ms * 1e3, 1)
    fig["miss_rate"] = miss_rate
    fig["overrun_rate"] = overrun_rate
    fig["passed"] = bool(miss_rate < MAX_MISS_RATE and overrun_rate < MAX_OVERRUN_RATE)
    return fig


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Climb the rate ladder for each topology; write ``bench/results/rate.json``."""
    parser = bench_argparser(__doc__.splitlines()[0] if __doc__ else "rate")
    parser.add_argument(
        "--rates",
        default=",".join(f"{r:g}" for r in LADDER_HZ),
        help="comma-separated ascending loop rates (Hz)",
    )
    parser.add_argument(
        "--topologies", default="1,3", help="comma-separated DN counts (default 1,3)"
    )
    parser.add_argument(
        "--lowlatency",
        choices=["auto", "true", "false"],
        default="false",
        help="the mission's transport.lowlatency (default: false, as shipped)",
    )
    parser.add_argument(
        "--priority", type=int, default=PRIORITY, help="SCHED_FIFO priority (0: off)"
    )
    args = parser.parse_args(argv)
    ll = LOWLATENCY_ARG[args.lowlatency]
    rates = sorted(float(r) for r in args.rates.split(","))
    topologies = [int(n) for n in args.topologies.split(",")]
    duration_s = QUICK_S if args.quick else FULL_S
    sched = inherit_fifo(args.priority)

    variants: dict[str, dict[str, Any]] = {}
    highest: dict[str, float | None] = {}
    first_fail: dict[str, float | None] = {}
    for n in topologies:
        topo = f"{n}dn"
        highest[topo] = None
        first_fail[topo] = None
        for rate in rates:
            name = f"zplatform_{topo}_{rate:g}hz"
            print(f"running {name} ({duration_s:.0f} s) ...", flush=True)
            fig = try_rate(n, rate, duration_s, priority=args.priority, lowlatency=ll)
            fig["topology"] = topo
            variants[name] = fig
            print(
                f"  miss rate {fig['miss_rate']:.2e}, overrun rate {fig['overrun_rate']:.2e}, "
                f"sync p50 {fig['p50_us']} us p99 {fig['p99_us']} us: "
                f"{'pass' if fig['passed'] else 'FAIL'}",
                flush=True,
            )
            if not fig["passed"]:
                first_fail[topo] = rate
                break
            highest[topo] = rate

    h1 = highest.get("1dn")
    params: dict[str, Any] = {
        "rates_hz": rates,
        "topologies": topologies,
        "duration_s": duration_s,
        "quick": bool(args.quick),
        "region_bytes": REGION_BYTES,
        "sync_timeout_fraction_of_period": TIMEOUT_FRACTION,
        "max_miss_rate": MAX_MISS_RATE,
        "max_overrun_rate": MAX_OVERRUN_RATE,
        "lowlatency": args.lowlatency,
        "scheduling": sched,
        "highest_passing_hz": highest,
        "first_failing_hz": first_fail,
        "targets": [
            {
                "name": "1 DN holds 1 kHz",
                "value": h1,
                "limit": TARGET_HZ_1DN,
                "unit": "Hz",
                "met": None
                if "1dn" not in highest
                else bool(h1 is not None and h1 >= TARGET_HZ_1DN),
            }
        ],
    }
    doc = write_result("rate", params, variants, args.json)
    print()
    for topo, h in highest.items():
        print(f"{topo}: highest passing rate {h} Hz (first failure: {first_fail[topo]} Hz)")
    t = params["targets"][0]
    print(f"target {t['name']}: {'met' if t['met'] else 'NOT met'} ({h1} Hz)")
    return doc


if __name__ == "__main__":
    main()
