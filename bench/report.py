"""Turn ``bench/results/*.json`` into ``bench/REPORT.md`` and PNG plots in ``bench/plots/``.

Measures nothing: it reads the result files the benchmarks wrote
(docs/architecture.md#files: ``{"bench", "machine", "params", "variants"}``) and writes one
report section per file: what the bench measures (the first paragraph of
``bench/<name>.py``'s docstring, read without importing it), the machine, the
params, a table of variants × figures, the ratios against baselines where the
result has them, and the verdict on each target. Plots (matplotlib, Agg
backend; the project's optional ``plot`` extra):

* ``sync``, ``baselines`` and any other latency bench: p50/p99 bars per variant;
* ``rate``: miss rate vs loop rate per topology, with the 1e-4 limit, and the
  sync p50/p99 vs loop rate;
* ``codec``: time vs data size, log-log, against the plain-copy floor;
* any variant carrying a ``samples`` list or a ``histogram``
  (``{"edges"|"bins", "counts"}``): a histogram per bench.

Robust by design: a missing results directory gives a report that says so; an
unknown bench gets the generic table; a file that cannot be read or drawn gets
a note in its section instead of stopping the report; without matplotlib the
report is written without plots.

Blocks for about a second (matplotlib's import and the PNG writes). Run
``python -m bench.report [--results DIR] [--out FILE] [--plots DIR]``.
"""

from __future__ import annotations

import argparse
import ast
import json
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from bench.common import BENCH_DIR, RESULTS_DIR

#: Sections come in this order; any other bench follows, alphabetically.
ORDER = (
    "sync",
    "levers",
    "sync_trace",
    "rate",
    "bandwidth",
    "frame_trace",
    "reliability",
    "telemetry_latency",
    "clock",
    "jitter",
    "overhead",
    "reaction",
    "baselines",
    "codec",
    "mac",
)
#: The docs/architecture.md#files figures, the first columns of every variants table.
STANDARD = ("p50_us", "p99_us", "max_us", "deadline_miss_rate", "msgs")
#: Figures that are long arrays or nested: plotted, never tabled.
BULKY = ("samples", "samples_ns", "samples_us", "histogram")
#: Benches whose variants all do the same work, so "p50 vs the best p50" means something.
VS_BEST = ("sync", "baselines")
#: Params shown in their own tables instead of the params list.
STRUCTURED_PARAMS = (
    "targets",
    "ratios_p50",
    "misses",
    "floods",
    "keyfloods",
    "keyflood_medians",
    "declaration_flood",
)


# ----------------------------------------------------------------------------- loading


def load_results(results_dir: Path) -> list[tuple[str, dict[str, Any] | None, str | None]]:
    """Every ``*.json`` in ``results_dir`` as ``(bench, doc or None, error or None)``, in order."""
    out: list[tuple[str, dict[str, Any] | None, str | None]] = []
    if not results_dir.is_dir():
        return out
    for path in sorted(results_dir.glob("*.json")):
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(doc, dict):
                raise ValueError("not a JSON object")
            name = str(doc.get("bench") or path.stem)
            out.append((name, doc, None))
        except (OSError, ValueError) as exc:
            out.append((path.stem, None, f"{path.name}: cannot read ({exc})"))

    def key(item: tuple[str, dict[str, Any] | None, str | None]) -> tuple[int, str]:
        name = item[0]
        return (ORDER.index(name) if name in ORDER else len(ORDER), name)

    return sorted(out, key=key)


def bench_description(name: str) -> str:
    """The first paragraph of ``bench/<name>.py``'s docstring (parsed, not imported), or ''."""
    path = BENCH_DIR / f"{name}.py"
    try:
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))
    except (OSError, SyntaxError, ValueError):
        return ""
    if not doc:
        return ""
    return " ".join(doc.split("\n\n", 1)[0].split())


# ----------------------------------------------------------------------------- formatting


def fmt(value: Any) -> str:
    """A cell: None as '-', floats compactly (rates in scientific notation), bools as yes/no."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if value == 0.0:
            return "0"
        if abs(value) < 0.01 or abs(value) >= 1e7:
            return f"{value:.2e}"
        if abs(value) >= 100:
            return f"{value:.1f}"
        return f"{value:.3g}" if abs(value) < 1 else f"{value:.2f}"
    if isinstance(value, dict | list):
        return "`" + json.dumps(value, separators=(",", ":")) + "`"
    return str(value).replace("|", "\\|")


def is_scalar(value: Any) -> bool:
    return value is None or isinstance(value, bool | int | float | str)


def md_table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    """A Markdown table; the first column left-aligned, the others right-aligned."""
    lines = ["| " + " | ".join(header) + " |"]
    lines.append("|" + "|".join([":---", *["---:"] * (len(header) - 1)]) + "|")
    for row in rows:
        lines.append("| " + " | ".join(fmt(c) if i else str(c) for i, c in enumerate(row)) + " |")
    return lines


def verdict(met: Any) -> str:
    return {True: "**met**", False: "**NOT met**"}.get(met, "not run")


# ----------------------------------------------------------------------------- sections


def variant_tables(variants: dict[str, dict[str, Any]], *, vs_best: bool = True) -> list[str]:
    """The standard-figures table (with p50 vs the best p50 when ``vs_best``: variants
    that do the same work) and tables of the other scalar figures."""
    lines: list[str] = []
    std = [k for k in STANDARD if any(k in f for f in variants.values())]
    p50s = [f["p50_us"] for f in variants.values() if isinstance(f.get("p50_us"), int | float)]
    best = min(p50s) if p50s and vs_best else None
    header = ["variant", *std]
    if best:
        header.append("p50 vs best")
    rows = []
    for name, fig in variants.items():
        row: list[Any] = [name, *(fig.get(k) for k in std)]
        if best:
            p50 = fig.get("p50_us")
            row.append(f"{p50 / best:.2f}x" if isinstance(p50, int | float) else None)
        rows.append(row)
    if std:
        lines += md_table(header, rows)
    extra: list[str] = []
    for fig in variants.values():
        for k, v in fig.items():
            if k not in STANDARD and k not in BULKY and k not in extra and is_scalar(v):
                extra.append(k)
    extra = [k for k in extra if k not in ("min_us", "mean_us")] + [
        k for k in ("min_us", "mean_us") if k in extra
    ]
    if extra:
        # Wide results are split into tables of at most 8 figure columns.
        for i in range(0, len(extra), 8):
            cols = extra[i : i + 8]
            lines += [
                "",
                *md_table(
                    ["variant", *cols],
                    ([n, *(f.get(k) for k in cols)] for n, f in variants.items()),
                ),
            ]
    return lines


def targets_section(params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """Targets from ``params.targets`` (a list of {name, value, limit, unit, met}) and
    from variants carrying ``target_met``."""
    rows: list[list[Any]] = []
    for t in params.get("targets") or []:
        if isinstance(t, dict):
            value = t.get("value")
            unit = t.get("unit", "")
            rows.append(
                [
                    t.get("name", "?"),
                    f"{fmt(value)} {unit}".strip(),
                    f"{fmt(t.get('limit'))} {unit}".strip(),
                    verdict(t.get("met")),
                ]
            )
    for name, fig in variants.items():
        if "target_met" in fig:
            limits = {k: v for k, v in fig.items() if k.startswith("target_") and k != "target_met"}
            limit = ", ".join(f"{k[7:]} {fmt(v)}" for k, v in limits.items()) or "-"
            value = fig.get("vs_copy_p50") if "target_vs_copy" in fig else fig.get("p50_us")
            rows.append([name, fmt(value), limit, verdict(fig.get("target_met"))])
    if not rows:
        return []
    return ["", "**Targets**", "", *md_table(["target", "measured", "limit", "verdict"], rows)]


def ratios_section(params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """Ratios vs baselines: ``params.ratios_p50`` and any ``vs_*`` figure of the variants."""
    rows: list[list[Any]] = []
    for k, r in (params.get("ratios_p50") or {}).items():
        rows.append([k, f"{r:.2f}x" if isinstance(r, int | float) else "-"])
    for name, fig in variants.items():
        for k, v in fig.items():
            if k.startswith("vs_") and isinstance(v, int | float) and v != 1.0:
                rows.append([f"{name} {k}", f"{v:.2f}x"])
    if not rows:
        return []
    return ["", "**Ratios (p50)**", "", *md_table(["ratio", "value"], rows)]


def rate_section(params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """The rate ladder per topology, then the highest passing rate of each."""
    lines: list[str] = [
        "",
        "_miss rate_ = DN replies not in by the sync deadline / (loops × DNs); "
        "_overrun rate_ = loop overruns / loops; a rate passes when both are under "
        f"{fmt(params.get('max_miss_rate'))}. `deadline_miss_rate` above is per loop "
        "(a loop whose sync hit its deadline).",
    ]
    topos: dict[str, list[tuple[str, dict[str, Any]]]] = {}
    for name, fig in variants.items():
        topos.setdefault(str(fig.get("topology", "?")), []).append((name, fig))
    for topo, items in topos.items():
        lines += ["", f"**Ladder, {topo}**", ""]
        lines += md_table(
            [
                "rate (Hz)",
                "sync deadline (us)",
                "loops",
                "miss rate",
                "overrun rate",
                "sync p50 (us)",
                "sync p99 (us)",
                "result",
            ],
            (
                [
                    fmt(f.get("rate_hz")),
                    f.get("sync_timeout_us"),
                    f.get("loops"),
                    f.get("miss_rate"),
                    f.get("overrun_rate"),
                    f.get("p50_us"),
                    f.get("p99_us"),
                    "pass" if f.get("passed") else "FAIL",
                ]
                for _, f in items
            ),
        )
    highest = params.get("highest_passing_hz") or {}
    fails = params.get("first_failing_hz") or {}
    if highest:
        lines += ["", "**Highest rate held**", ""]
        lines += md_table(
            ["topology", "highest passing (Hz)", "first failing (Hz)"],
            (
                [t, h, fails.get(t) if fails.get(t) is not None else "none (ladder exhausted)"]
                for t, h in highest.items()
            ),
        )
    return lines


def bandwidth_section(params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """Element count x DN split (x MAC) at 100 Hz, each beside its raw floors and its p50
    over raw zenoh's; the headline count."""
    rows: list[list[Any]] = []
    for name, v in variants.items():
        if not name.startswith("zp_"):
            continue
        floor_z = variants.get(f"raw_zenoh_{v.get('n_dn')}x{v.get('frame_bytes_max')}B", {})
        floor_u = variants.get(f"raw_udp_{v.get('n_dn')}x{v.get('frame_bytes_max')}B", {})
        rows.append(
            [
                name,
                v.get("elements")
                or (f"{v.get('region_bytes')} B" if v.get("region_bytes") else None),
                v.get("n_dn"),
                v.get("mac"),
                v.get("rate_hz"),
                v.get("bytes_per_loop"),
                v.get("mbit_s"),
                v.get("p50_us"),
                v.get("p99_us"),
                v.get("max_us"),
                v.get("deadline_miss_rate"),
                v.get("cpu_cn_pct"),
                v.get("cpu_dn_pct"),
                v.get("shm_reply_fraction"),
                floor_z.get("p50_us"),
                floor_z.get("p99_us"),
                floor_u.get("p99_us"),
                f"{v['vs_raw_zenoh_p50']:.2f}x" if v.get("vs_raw_zenoh_p50") else None,
                verdict(v.get("holds")) if "holds" in v else v.get("error"),
            ]
        )
    if not rows:
        return []
    loose: dict[str, int | None] = {}
    for v in variants.values():
        if v.get("elements") and v.get("rate_hz") == 100.0 and "deadline_miss_rate" in v:
            key = f"{v.get('n_dn')}dn" + (f" {v['mac']}" if v.get("mac") else "")
            ok = v["deadline_miss_rate"] < 1e-3 and (v.get("rate_hz_measured") or 0) >= 98.0
            cur = loose.get(key)
            if ok and (cur is None or v["elements"] > cur):
                loose[key] = int(v["elements"])
            else:
                loose.setdefault(key, None)
    header = [
        "point",
        "elements",
        "DNs",
        "MAC",
        "Hz",
        "B/loop",
        "Mbit/s",
        "p50 us",
        "p99 us",
        "max us",
        "miss rate",
        "CPU CN %",
        "CPU DN %",
        "SHM replies",
        "raw zenoh p50",
        "raw zenoh p99",
        "raw UDP p99",
        "p50 / raw zenoh",
        "holds",
    ]
    return [
        "",
        "**Sweep** (floors: the same bytes by bare zenoh and Python UDP, same run)",
        "",
        *md_table(header, rows),
        "",
        f"Largest element count holding 100 Hz with < 1e-4 misses, per DN split: "
        f"{fmt(params.get('largest_holding_100hz'))}; highest rate held with 3 DNs: "
        f"{fmt(params.get('highest_rate_held_3dn'))}. Looser, for a noisy shared box: "
        f"largest count with < 1e-3 misses at 100 Hz, per DN split: {fmt(loose)}. "
        "MAC `-`: a variant merged from a run that did not record its MAC; a merged "
        "file's variants may come from other runs and machines (`run_utc`, `run_cpu`).",
    ]


def reliability_section(params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """Misses per million beside the floor, the thesis' figure, and every miss (first 40)."""
    lines = ["", "**Reliability**", ""]
    rows = [
        [
            n,
            v.get("messages"),
            v.get("misses"),
            v.get("sync_misses"),
            v.get("tm_misses"),
            v.get("misses_per_million"),
            f"{v['in_deadline_pct']:.4f}"
            if isinstance(v.get("in_deadline_pct"), int | float)
            else None,
            v.get("tm_latency_p50_us"),
            v.get("tm_latency_p99_us"),
        ]
        for n, v in variants.items()
    ]
    lines += md_table(
        [
            "system",
            "messages",
            "misses",
            "sync",
            "telemetry",
            "per million",
            "in deadline %",
            "tm p50 us",
            "tm p99 us",
        ],
        rows,
    )
    lines += [
        "",
        f"Ratio to the raw-zenoh floor: {fmt(params.get('ratio_to_floor'))} "
        f"({params.get('ratio_note', '')}). Beside it, {params.get('thesis', '')}. "
        f"Mean host CPU steal over the run: {fmt(params.get('host_steal_mean_pct'))} %.",
    ]
    misses = params.get("misses") or []
    if misses:
        mrows = []
        for m in misses[:40]:
            h = m.get("host") or {}
            mrows.append(
                [
                    m.get("loop"),
                    m.get("what"),
                    ",".join(m.get("answered", [])) if "answered" in m else "-",
                    m.get("sync_us", m.get("latency_us")),
                    m.get("cn_lateness_us"),
                    h.get("steal_pct"),
                    h.get("idle_pct"),
                    h.get("procs_running"),
                    fmt(h.get("cpu_pct")),
                ]
            )
        lines += [
            "",
            f"Each loop with a zplatform miss (first 40 of {len(misses)}; a loop where two DNs "
            "missed is one row), with the host's 100 ms window:",
            "",
            *md_table(
                [
                    "loop",
                    "what",
                    "answered",
                    "sync/latency us",
                    "CN lateness us",
                    "steal %",
                    "idle %",
                    "run queue",
                    "CPU % per node",
                ],
                mrows,
            ),
        ]
    return lines


def sync_trace_section(params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """The hop table: where a sync's time goes, per exchange (bench.sync_trace)."""
    hops = (variants.get("trace") or {}).get("hops") or {}
    if not hops:
        return []
    rows = [
        [hop, h.get("p50_us"), h.get("p99_us"), h.get("max_us"), h.get("missed_loops_p50_us")]
        for hop, h in hops.items()
    ]
    return [
        "",
        "**Hops** (per DN exchange; `sync_total` = issued -> taken)",
        "",
        *md_table(["hop", "p50 us", "p99 us", "max us", "p50 us in missed loops"], rows),
    ]


def frame_trace_section(params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """The large-frame hop tables (bench.frame_trace): per DN split and MAC, one column
    pair (p50, copies) per label side by side (a before and an after), and each
    variant's sync p50 over the raw zenoh floor of its own run."""
    traced = {k: v for k, v in variants.items() if v.get("hops")}
    if not traced:
        return []
    groups: dict[tuple[Any, Any], dict[str, dict[str, Any]]] = {}
    for k, v in traced.items():
        groups.setdefault((v.get("n_dn"), v.get("mac")), {})[k] = v
    tables: list[str] = []
    for (n_dn, mac), group in groups.items():
        names: list[str] = []  # chain order as first seen (a hop one variant merged)
        for v in group.values():
            names += [h for h in v["hops"] if h not in names]
        header = ["hop"]
        for v in group.values():
            header += [f"{v.get('label')} p50 us", "copies"]
        rows = []
        for h in names:
            row: list[Any] = [h]
            for v in group.values():
                cell = v["hops"].get(h) or {}
                row += [cell.get("p50_us"), cell.get("copies")]
            rows.append(row)
        tables += ["", f"**Hops, {n_dn} DN, {mac}**", "", *md_table(header, rows)]
    summary = [
        [
            k,
            v.get("label"),
            v.get("n_dn"),
            v.get("mac"),
            v.get("p50_us"),
            v.get("deadline_miss_rate"),
            f"{v['vs_raw_zenoh_p50']:.2f}x" if v.get("vs_raw_zenoh_p50") else None,
            " ".join(str(x) for x in v.get("loadavg") or []) or None,
        ]
        for k, v in traced.items()
    ]
    return [
        "",
        "**Sync step per variant** (p50 over the raw zenoh floor of the same bytes, "
        "measured in the same run; load average after the run)",
        "",
        *md_table(
            ["variant", "label", "DNs", "MAC", "sync p50 us", "miss rate", "vs raw zenoh", "load"],
            summary,
        ),
        "",
        "Hops: p50 per DN exchange; `a->b` between two stamps of one exchange, the others "
        "timed on their own; copies of the payload counted from the code path.",
        *tables,
    ]


def clock_section(params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """Residual error per case and estimator; which one is more accurate."""
    cases = [c["case"] for c in params.get("cases") or []]
    ests = sorted({str(v["estimator"]) for v in variants.values() if v.get("estimator")})
    rows = []
    for c in cases:
        row: list[Any] = [c]
        for e in ests:
            v = variants.get(f"{e}_{c}", {})
            row += [v.get("err_p50_us"), v.get("abs_err_max_us")]
        rows.append(row)
    header = ["case"]
    for e in ests:
        header += [f"{e} bias us", f"{e} worst us"]
    return [
        "",
        "**Residual error after correction** (estimate minus truth)",
        "",
        *md_table(header, rows),
        "",
        f"Median |error| over all cases: {fmt(params.get('abs_err_p50_us'))} us; "
        f"more accurate here: **{params.get('more_accurate')}**.",
    ]


def faults_section(params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """Issue 9's table: per fault case, detection, misses, end state, forgeries."""
    rows = []
    for case, v in variants.items():
        failed = [k for k, c in (v.get("checks") or {}).items() if not c.get("ok")]
        targets = v.get("targets") or {}
        missed = [k for k, t in targets.items() if not t.get("met")]
        rows.append(
            [
                case,
                v.get("detect_ms"),
                v.get("dn_lost_ms"),
                v.get("loops_missed"),
                v.get("final_state"),
                v.get("expected_state"),
                v.get("forged_applied"),
                "all pass" if not failed else "FAIL: " + ", ".join(failed),
                "-" if not targets else "all met" if not missed else "missed: " + ", ".join(missed),
            ]
        )
    head = ["case", "detect ms", "DN_LOST ms", "loops missed", "final", "configured"]
    lines = [
        "",
        "**Fault cases** (each on live node processes; `tests/faults/live.py`)",
        "",
        *md_table([*head, "forged applied", "checks", "targets"], rows),
    ]
    floods = params.get("floods") or []
    if floods:
        lines += [
            "",
            "**Floods from a keyless peer** (a recovery_igniter flight each; "
            "`tests/faults/floods.py`): misses in the attack's window and in a reference "
            "window of the same flight without one; misses added per 1,000 frames/s (target "
            "under 1e-4); the CPU the node under attack spent per flood frame beyond its "
            "reference; the largest RSS growth of any node over the attack",
            "",
            *md_table(
                list(floods[0]),
                ([r.get(k) for k in floods[0]] for r in floods),
            ),
        ]
    medians = params.get("keyflood_medians") or {}
    if medians:
        lines += [
            "",
            "**The flood suite generated from the key space** (`tests/faults/keyfloods.py`: "
            "every row a keyless peer reaches, 6,000 frames/s of junk of the row's frame size "
            "and of genuine frames of the same flight replayed, one flight per mission and "
            "scheduling): per mission and scheduling, the median over the channels of the CPU "
            "the node under attack spent per frame and of the misses each flood added per "
            "1,000 frames/s (target under 1e-4)",
            "",
            *md_table(
                ["flight", *next(iter(medians.values()))],
                ([k, *m.values()] for k, m in medians.items()),
            ),
        ]
    for key, title in (
        (
            "keyfloods",
            "Per channel (flood), nodes as configured (rt) and without real-time "
            "priority (no_rt); counted: by the victim's counter / sent",
        ),
        (
            "declaration_flood",
            "**Declaration flood** (`tests/faults/decl_flood.py`): per "
            "transport and attack, the CPU it added to the busiest node and the misses per loop",
        ),
    ):
        table: list[dict[str, Any]] = params.get(key) or []
        if table:
            lines += [
                "",
                title,
                "",
                *md_table(list(table[0]), ([r.get(k) for k in table[0]] for r in table)),
            ]
    return lines


def failover_section(params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """Issue 21's table: per case, the takeovers (fault -> the new term's first
    loop), the device nodes' loops without a trigger, safings, two-term loops,
    the final state; then each case's takeovers by their length."""
    rows = []
    for case, v in variants.items():
        if "error" in v:
            rows.append([case, v["error"][:120], *[None] * 12])
            continue
        rows.append(
            [
                case,
                v.get("faults"),
                f"{fmt(v.get('takeovers'))} ({fmt(v.get('spurious_takeovers'))})",
                f"{fmt(v.get('takeover_loops_p50'))} / {fmt(v.get('takeover_loops_max'))}",
                f"{fmt(v.get('first_trigger_loops_p50'))} / "
                f"{fmt(v.get('first_trigger_loops_max'))} "
                f"({fmt(v.get('term_loop_not_run'))})",
                f"{fmt(v.get('takeover_ms_p50'))} / {fmt(v.get('takeover_ms_max'))}",
                v.get("dn_untriggered_max"),
                v.get("dn_safed_events"),
                v.get("two_term_loops"),
                f"{fmt(v.get('rejoin_s_p50'))} / {fmt(v.get('rejoin_s_max'))}",
                f"{fmt(v.get('standby_ready_again'))} of {fmt(v.get('faults'))}",
                v.get("final_state"),
                v.get("expected_state"),
                all(
                    v.get(k)
                    for k in (
                        "met_p50",
                        "met_max",
                        "met_p50_first_trigger",
                        "met_max_first_trigger",
                        "met_no_safings",
                        "met_no_two_term_loops",
                    )
                )
                and bool(v.get("final_as_configured")),
            ]
        )
    head = [
        "case",
        "faults",
        "term changes (spurious)",
        "takeover loops p50 / max",
        "first trigger loops p50 / max (term's first loop not run)",
        "takeover ms p50 / max",
        "DN loops untriggered, max",
        "DN safings",
        "two-term loops",
        "rejoin s p50 / max",
        "standby ready again",
        "final",
        "configured",
        "all targets",
    ]
    lines = [
        "",
        "**Takeovers** (loops: from the fault's loop on the commander's schedule to "
        "`cn_term_loop`; first trigger: to the first loop a device node ran in the new "
        "term, and how often `cn_term_loop` itself never ran; DN loops untriggered: "
        "from the device nodes' flight recorders; "
        "term changes: every new term the telemetry showed, spurious: those no fault "
        "of the bench caused)",
        "",
        *md_table(head, rows),
    ]
    for case, v in variants.items():
        each = v.get("each") or []
        if not each:
            continue
        counts: dict[int, int] = {}
        for t in each:
            counts[int(t["loops"])] = counts.get(int(t["loops"]), 0) + 1
        dist = ", ".join(f"{k} loops x{n}" for k, n in sorted(counts.items()))
        lines += ["", f"_{case}_: takeovers by length: {dist}."]
        if "drogue_fired" in v:
            lines[-1] += (
                f" The flight: killed in {v.get('state_at_kill')}, ended "
                f"{v.get('final_state')}; drogue fired: {fmt(v.get('drogue_fired'))}, "
                f"main fired: {fmt(v.get('main_fired'))}."
            )
        for x in v.get("spurious") or []:
            gaps = [g for g in (x.get("dn_untriggered") or {}).values() if g is not None]
            lines[-1] += (
                f" Spurious term {x.get('old')} -> {x.get('new')} from loop {x.get('loop')} "
                f"(DN loops untriggered: {fmt(max(gaps, default=None))})."
            )
        for text in v.get("dn_safed") or []:
            lines[-1] += f" Safing: {fmt(text)}."
    return lines


def params_section(params: dict[str, Any]) -> list[str]:
    """Short params inline; long nested ones (over 100 characters of JSON) folded away."""
    short: list[tuple[str, Any]] = []
    long: dict[str, Any] = {}
    for k, v in params.items():
        if k in STRUCTURED_PARAMS:
            continue
        if isinstance(v, dict | list) and len(json.dumps(v)) > 100:
            long[k] = v
        else:
            short.append((k, v))
    lines: list[str] = []
    if short:
        lines += ["", "**Params:** " + "; ".join(f"`{k}` = {fmt(v)}" for k, v in short)]
    if long:
        lines += [
            "",
            f"<details><summary>More params: {', '.join(long)}</summary>",
            "",
            "```json",
            json.dumps(long, indent=1),
            "```",
            "",
            "</details>",
        ]
    return lines


def machine_line(machine: dict[str, Any]) -> str:
    if not machine:
        return ""
    keys = ("cpu_model", "cores_logical", "python", "zenoh", "kernel", "loadavg_1m", "time_utc")
    return "**Machine:** " + ", ".join(f"{k} {machine[k]}" for k in keys if k in machine)


# ----------------------------------------------------------------------------- plots


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_latency_bars(bench: str, variants: dict[str, dict[str, Any]], out: Path) -> Path | None:
    """Grouped p50/p99 bars per variant (µs, log scale when the spread is wide)."""
    names = [n for n, f in variants.items() if isinstance(f.get("p50_us"), int | float)]
    if not names:
        return None
    plt = _plt()
    p50 = [float(variants[n]["p50_us"]) for n in names]
    p99 = [float(variants[n].get("p99_us") or 0.0) for n in names]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(names) + 2), 4.5))
    xs = range(len(names))
    w = 0.4
    ax.bar([x - w / 2 for x in xs], p50, w, label="p50")
    ax.bar([x + w / 2 for x in xs], p99, w, label="p99")
    ax.set_xticks(list(xs))
    ax.set_xticklabels(names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("µs")
    ax.set_title(f"{bench}: p50 / p99 per variant")
    if max(p99 + p50) / max(min(p50), 1e-9) > 50:
        ax.set_yscale("log")
    ax.grid(axis="y", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = out / f"{bench}_latency.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_rate(
    variants: dict[str, dict[str, Any]], params: dict[str, Any], out: Path
) -> Path | None:
    """Miss and overrun rate vs loop rate per topology (log y; zero drawn at the floor),
    beside the sync p50/p99 vs loop rate."""
    topos: dict[str, list[dict[str, Any]]] = {}
    for fig in variants.values():
        if isinstance(fig.get("rate_hz"), int | float):
            topos.setdefault(str(fig.get("topology", "?")), []).append(fig)
    if not topos:
        return None
    plt = _plt()
    limit = float(params.get("max_miss_rate") or 1e-4)
    floor = limit / 100
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
    for topo, figs in sorted(topos.items()):
        figs.sort(key=lambda f: float(f["rate_hz"]))
        rates = [float(f["rate_hz"]) for f in figs]
        miss = [max(float(f.get("miss_rate") or 0.0), floor) for f in figs]
        over = [max(float(f.get("overrun_rate") or 0.0), floor) for f in figs]
        (line,) = ax.plot(rates, miss, "o-", label=f"{topo} miss rate")
        ax.plot(rates, over, "x--", color=line.get_color(), alpha=0.6, label=f"{topo} overrun rate")
        ax2.plot(
            rates,
            [f.get("p50_us") for f in figs],
            "o-",
            color=line.get_color(),
            label=f"{topo} sync p50",
        )
        ax2.plot(
            rates,
            [f.get("p99_us") for f in figs],
            "x--",
            color=line.get_color(),
            label=f"{topo} sync p99",
        )
        ax2.plot(rates, [f.get("sync_timeout_us") for f in figs], ":", color="grey")
    ax.axhline(limit, color="red", lw=1, label=f"limit {limit:g}")
    ax.set_yscale("log")
    ax.set_xlabel("loop rate (Hz)")
    ax.set_ylabel(f"rate (0 drawn at {floor:g})")
    ax.set_title("deadline misses vs loop rate")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax2.set_xlabel("loop rate (Hz)")
    ax2.set_ylabel("sync duration (µs); dotted: deadline")
    ax2.set_title("sync step vs loop rate")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8)
    fig.tight_layout()
    path = out / "rate.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_codec(variants: dict[str, dict[str, Any]], out: Path) -> Path | None:
    """p50 time vs data size (log-log) per codec family; the copy is the floor."""
    families: dict[str, list[tuple[float, float, float]]] = {}
    for name, fig in variants.items():
        size, p50 = fig.get("size_bytes"), fig.get("p50_us")
        if isinstance(size, int | float) and isinstance(p50, int | float):
            fam = name.rsplit("_", 1)[0]
            families.setdefault(fam, []).append(
                (float(size), float(p50), float(fig.get("p99_us") or p50))
            )
    if not families:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 5))
    for fam, pts in sorted(families.items(), key=lambda kv: kv[0] != "copy"):
        pts.sort()
        style = {"color": "black", "ls": "--"} if fam == "copy" else {}
        ax.plot(
            [p[0] for p in pts],
            [p[1] for p in pts],
            marker="o",
            label=f"{fam} p50" + (" (floor)" if fam == "copy" else ""),
            **style,
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("data bytes")
    ax.set_ylabel("µs per frame (p50)")
    ax.set_title("codec: encode + apply vs the plain copy")
    ax.grid(which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = out / "codec.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_distributions(bench: str, variants: dict[str, dict[str, Any]], out: Path) -> Path | None:
    """Histograms of any ``samples*`` list or ``histogram`` dict the variants carry."""
    series: list[tuple[str, Any]] = []
    for name, fig in variants.items():
        for key in BULKY:
            v = fig.get(key)
            if isinstance(v, list) and v and all(isinstance(x, int | float) for x in v):
                scale = 1e-3 if key == "samples_ns" else 1.0
                series.append((name, ("samples", [float(x) * scale for x in v])))
            elif isinstance(v, dict):
                edges = v.get("edges") or v.get("bins") or v.get("edges_us")
                counts = v.get("counts")
                if isinstance(edges, list) and isinstance(counts, list) and counts:
                    series.append((name, ("hist", (edges, counts))))
    if not series:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, (kind, data) in series:
        if kind == "samples":
            ax.hist(data, bins=100, histtype="step", label=name)
        else:
            edges, counts = data
            if len(edges) == len(counts) + 1:
                ax.stairs(counts, edges, label=name)
            else:
                ax.step(edges[: len(counts)], counts, where="post", label=name)
    ax.set_yscale("log")
    ax.set_xlabel("µs (as recorded)")
    ax.set_ylabel("count")
    ax.set_title(f"{bench}: distribution")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / f"{bench}_distribution.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def make_plots(bench: str, doc: dict[str, Any], out: Path) -> list[Path]:
    """The plots for one result; raises whatever matplotlib raises."""
    variants = doc.get("variants") or {}
    params = doc.get("params") or {}
    paths: list[Path | None] = []
    if bench == "rate":
        paths.append(plot_rate(variants, params, out))
    elif bench == "codec":
        paths.append(plot_codec(variants, out))
    elif bench == "bandwidth":
        from bench.bandwidth import plot_bandwidth

        paths.append(plot_bandwidth(variants, out))
        paths.append(plot_latency_bars(bench, variants, out))
    else:
        paths.append(plot_latency_bars(bench, variants, out))
    paths.append(plot_distributions(bench, variants, out))
    return [p for p in paths if p is not None]


# ----------------------------------------------------------------------------- report


def section(bench: str, doc: dict[str, Any], plots_dir: Path | None, report_dir: Path) -> list[str]:
    """One report section: description, machine, params, tables, targets, plots."""
    lines = [f"## {bench}", ""]
    desc = bench_description(bench)
    if desc:
        lines += [desc, ""]
    machine = machine_line(doc.get("machine") or {})
    if machine:
        lines.append(machine)
    params = doc.get("params") or {}
    variants = doc.get("variants") or {}
    lines += params_section(params)
    lines.append("")
    if variants:
        # "vs best" only where every variant does the same work (one exchange).
        lines += variant_tables(variants, vs_best=bench in VS_BEST)
    else:
        lines.append("_No variants in this result._")
    if bench == "rate":
        lines += rate_section(params, variants)
    elif bench == "bandwidth":
        lines += bandwidth_section(params, variants)
    elif bench == "reliability":
        lines += reliability_section(params, variants)
    elif bench == "clock":
        lines += clock_section(params, variants)
    elif bench == "sync_trace":
        lines += sync_trace_section(params, variants)
    elif bench == "frame_trace":
        lines += frame_trace_section(params, variants)
    elif bench == "faults":
        lines += faults_section(params, variants)
    elif bench == "failover":
        lines += failover_section(params, variants)
    lines += ratios_section(params, variants)
    lines += targets_section(params, variants)
    if plots_dir is not None:
        try:
            for p in make_plots(bench, doc, plots_dir):
                rel = p.relative_to(report_dir) if p.is_relative_to(report_dir) else p
                lines += ["", f"![{p.stem}]({rel.as_posix()})"]
        except Exception as exc:  # a plot must not take the report down
            lines += ["", f"_Plot failed: {type(exc).__name__}: {exc}_"]
    lines.append("")
    return lines


def build_report(results_dir: Path, out: Path, plots_dir: Path | None) -> str:
    """Write the report (and plots) and return its text."""
    results = load_results(results_dir)
    lines = [
        "# zplatform benchmark report",
        "",
        f"Generated by `python -m bench.report` from `{results_dir.name}/*.json` "
        "(docs/architecture.md#files). Latencies are in µs; miss rates are fractions of loops.",
        "",
    ]
    if plots_dir is not None:
        try:
            _plt()
            plots_dir.mkdir(parents=True, exist_ok=True)
        except ImportError:
            lines += ["_matplotlib is not installed (`pip install .[plot]`): no plots._", ""]
            plots_dir = None
    if not results:
        lines += [f"_No results in `{results_dir}`: run the benchmarks first._", ""]
    else:
        lines += ["Contents: " + ", ".join(f"[{n}](#{n})" for n, _, _ in results), ""]
    for name, doc, error in results:
        if doc is None:
            lines += [f"## {name}", "", f"_{error}_", ""]
            continue
        try:
            lines += section(name, doc, plots_dir, out.parent)
        except Exception as exc:  # an odd file gets a note, the rest still reports
            lines += [f"## {name}", "", f"_Cannot report: {type(exc).__name__}: {exc}_", ""]
    text = "\n".join(lines).rstrip() + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    return text


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else "report")
    p.add_argument("--results", type=Path, default=RESULTS_DIR)
    p.add_argument("--out", type=Path, default=BENCH_DIR / "REPORT.md")
    p.add_argument("--plots", type=Path, default=BENCH_DIR / "plots")
    p.add_argument("--no-plots", action="store_true")
    a = p.parse_args(argv)
    build_report(a.results, a.out, None if a.no_plots else a.plots)
    print(f"wrote {a.out}" + ("" if a.no_plots else f" and plots in {a.plots}"))


if __name__ == "__main__":
    main()
