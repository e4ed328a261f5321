"""Bandwidth: the sync step against element count, DN split and region size (thesis 4.3.2, 5.2.4).

Each point is a real zplatform cluster (:class:`bench.cluster.BenchCluster`:
DN processes, the CN's real loop in this process, every frame authenticated
as shipped) whose regions carry ``N`` scalar elements of mixed types
(``f32 i32 u16 bool f64 u8 i16 u32`` in turn): ``N/2`` sensors in the
``dnX_to_cn`` regions and ``N/2`` actuators in the ``cn_to_dnX`` regions,
split evenly across 1, 3 or 6 DNs. The missions (up to 100,000 elements) are
generated into a temporary directory and never committed.

Every zplatform point runs once per MAC (``--macs``, default both: keyed
BLAKE3 and HMAC-SHA256, the mission's ``security.mac``); ``<M>`` in a
variant's name is ``blake3`` or ``hmac`` and its ``mac`` figure the mission's
name. Variants:

* ``zp_<N>el_<D>dn_<M>``: N elements over D DNs at 100 Hz (``N`` in 10, 100,
  1k, 10k, 100k; ``--quick``: 10, 1k, 10k with 1 and 3 DNs);
* ``zp_region_<B>B_3dn_<M>``: plain ``u8[B]`` regions of B bytes, 3 DNs;
* ``zp_<N>el_3dn_<R>hz_<M>``: the highest-rate search at 3 DNs (200, 500, 1000
  Hz, sync deadline min(2 ms, period / 2); stops at the first rate not held);
* ``raw_zenoh_<D>x<S>B`` / ``raw_udp_<D>x<S>B``: the floors, the same bytes
  (S = the largest zplatform frame of that point, both ways) by bare zenoh
  get/reply and by Python UDP (skipped over one datagram, 65,000 B), in the
  same run (:func:`bench.baselines.run_baseline`).

Figures per zplatform point: ``bytes_per_loop`` (every cn_to_dnX frame plus
every reply, as sent, tags included), ``mbit_s`` (at the measured loop rate),
the sync step's ``p50_us``/``p99_us``/``max_us`` (a missed loop counts as the
deadline, as in :mod:`bench.sync`), ``deadline_miss_rate`` (loops whose sync
missed, plus periods the CN skipped, over all periods), ``cpu_cn_pct`` (this
process, the CN) and ``cpu_dn_pct`` (the busiest DN), in % of one core over
the measured loops, ``shm_reply_fraction`` (replies whose payload came
through zenoh shared memory: ``payload.as_shm() is not None``, checked in the
CN's reply callback: the ``sync.shm`` point of :mod:`zplatform.trace`) and
``holds_100hz`` (rate held within 2% and miss rate under 1e-4: with a few
thousand loops per point, "0 misses" bounds the true rate only near 1e-3;
the reliability bench is the long run) and
``vs_raw_zenoh_p50`` (its sync p50 over the raw-zenoh floor's p50, the same
bytes).

``params.largest_holding_100hz`` is the largest N that holds 100 Hz (per MAC
and DN split). The targets, per MAC and DN split, are the 100,000-element
point's: hold 100 Hz (the thesis supported 200 elements) and a sync p50
within 1.15x of raw zenoh moving the same bytes.

``--merge`` joins the existing result file instead of replacing it: its
variants stay (each keeps the ``run_utc`` and ``run_cpu`` of its run: a merged
file may hold more than one machine's), a point measured now
replaces the earlier variant of the same point (elements, DNs, region, rate,
MAC; one that recorded no MAC is replaced by any MAC's), and floors no
zplatform point refers to any more are dropped.

Blocks for a few minutes (``--quick``: about 3 min with both MACs): each
point runs ``--seconds`` (quick 5, full 15) per MAC plus its start-up (a
100k-element mission takes each process about 10-20 s to load).

``--intra-host shm|both`` runs the element points (also) with the sync over
iceoryx2 (``zp_<N>el_<D>dn_shm_<M>``, ``transport.intra_host: shm``) beside
a ``raw_iceoryx2_<D>x<S>B`` floor (:func:`bench.intrahost.run_raw`, or
``run_raw_many`` for several DNs), and its target: the 100,000-element point
with 0 missed loops and a p50 within 1.15x of raw iceoryx2. ``--bulk N``
adds the 4 MB bulk one-way rows (``bulk_<variant>_4MB``,
:func:`bench.intrahost.run_bulk`: zplatform over iceoryx2 and over zenoh,
tagged and checked as a node's samples are, raw iceoryx2, raw zenoh; N
samples each at 20 Hz) and ``params.bulk_4MB_ratios``.

Run ``python -m bench.bandwidth [--quick] [--json PATH] [--macs blake3,hmac]
[--counts N,...] [--splits D,...] [--regions B,...] [--seconds S] [--no-rates]
[--merge] [--intra-host zenoh|shm|both] [--bulk N]``. Only a full run
without ``--json`` writes the committed ``bench/results/bandwidth.json`` and
``bench/plots/``; ``--quick`` writes to a scratch folder under the temporary
directory (:func:`output_paths`).
"""

from __future__ import annotations

import json
import os
import secrets
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import yaml

from bench.baselines import run_baseline
from bench.cluster import BenchCluster, SyncSamples, make_mission
from bench.common import RESULTS_DIR, bench_argparser, machine_info, summarize, write_result
from bench.sync import PRIORITY, inherit_fifo
from zplatform import trace
from zplatform.core.auth import MACS
from zplatform.core.messages import lowlatency_for

TYPES = ("f32", "i32", "u16", "bool", "f64", "u8", "i16", "u32")
COUNTS_FULL = (10, 100, 1_000, 10_000, 100_000)
COUNTS_QUICK = (10, 1_000, 10_000)
SPLITS_FULL = (1, 3, 6)
SPLITS_QUICK = (1, 3)
REGIONS_FULL = (256, 4096, 65536, 1 << 20)
REGIONS_QUICK = (4096,)
RATES = (200.0, 500.0, 1000.0)
RATE_HZ = 100.0
DEADLINE_MS = 2.0
MISS_LIMIT = 1e-4
UDP_MAX = 65_000
TARGET_ELEMENTS = 100_000
RATIO_LIMIT = 1.15


def mac_suffix(mac: str) -> str:
    """A ``security.mac``'s short name: the ``--macs`` name and the variants' suffix."""
    return mac.split("-")[0]


#: ``--macs`` names -> ``security.mac``.
MAC_SHORT = {mac_suffix(m): m for m in MACS}


def element_extra(n_elements: int, n_dn: int) -> dict[str, list[dict[str, Any]]]:
    """``n_elements`` mixed-type scalars: half sensors (dnX_to_cn), half actuators (cn_to_dnX)."""
    extra: dict[str, list[dict[str, Any]]] = {}
    n_s = n_elements // 2
    n_a = n_elements - n_s
    for i in range(n_s):
        extra.setdefault(f"dn{i % n_dn}_to_cn", []).append(
            {"name": f"s{i}", "type": TYPES[i % len(TYPES)]}
        )
    for i in range(n_a):
        extra.setdefault(f"cn_to_dn{i % n_dn}", []).append(
            {"name": f"a{i}", "type": TYPES[(i + 3) % len(TYPES)]}
        )
    return extra


def _cpu_s(procs: list[psutil.Process]) -> list[float]:
    out = []
    for p in procs:
        try:
            t = p.cpu_times()
            out.append(t.user + t.system)
        except psutil.Error:
            out.append(float("nan"))
    return out


class _Sizes:
    """A :class:`zplatform.trace.Tracer` counting the CN's replies (and those
    whose payload zenoh delivered in shared memory: ``sync.shm``) and keeping
    each DN's last reply size (``sync.back``) and its first query sizes
    (``sync.issued``). ``sync.back`` and ``sync.shm`` come from zenoh's
    threads: one writer each per DN, read after the run."""

    def __init__(self, n_dn: int) -> None:
        self.replies = 0
        self.shm = 0
        self.up = [0] * n_dn
        self.down: list[int] = []
        self.n_dn = n_dn

    def mark(self, name: str, n: int = 0, v: int = 0) -> None:
        if name == "sync.back":
            self.replies += 1
            self.up[n] = v
        elif name == "sync.shm":
            self.shm += 1
        elif name == "sync.issued" and len(self.down) < self.n_dn:
            self.down.append(v)


def run_point(
    *,
    n_elements: int,
    n_dn: int,
    rate_hz: float,
    duration_s: float,
    region_bytes: int | None = None,
    priority: int = PRIORITY,
    mac: str = MACS[0],
    intra_host: str = "zenoh",
) -> dict[str, Any]:
    """One zplatform cluster: N elements (or plain ``region_bytes`` regions) over ``n_dn`` DNs,
    every frame tagged with ``mac`` (``security.mac``); ``intra_host``: the
    mission's ``transport.intra_host`` (``shm``: the sync over iceoryx2;
    the figures' ``paths`` say which path each DN's link took at the end).

    Blocks for the DNs' start-up plus ``rate_hz × duration_s`` loops.
    """
    loops = max(1, round(duration_s * rate_hz))
    sync_ms = min(DEADLINE_MS, 0.5 * 1e3 / rate_hz)
    deadline_ns = round(sync_ms * 1e6)
    with tempfile.TemporaryDirectory(prefix="zp-bw-") as tmp:
        tmpdir = Path(tmp)
        t0 = time.monotonic()
        mission = make_mission(
            tmpdir / "m.yaml",
            n_dn=n_dn,
            loop_hz=rate_hz,
            sync_timeout_ms=sync_ms,
            region_bytes=region_bytes if region_bytes is not None else 1,
            priority=priority if priority > 0 else None,
            extra=element_extra(n_elements, n_dn) if region_bytes is None else None,
            mac=mac,
        )
        # Pinned either way: the mission default (auto) would put a zenoh
        # point's sync on shared memory, the nodes sharing this host.
        raw = yaml.safe_load(mission.read_text())
        raw.setdefault("transport", {})["intra_host"] = intra_host
        mission.write_text(yaml.safe_dump(raw, sort_keys=False))
        hook = SyncSamples(loops)
        paths: list[str] = []

        sizes = _Sizes(n_dn)
        try:
            with BenchCluster(mission, realtime=priority > 0) as c:
                c.start(timeout_s=300.0)
                startup_s = time.monotonic() - t0
                dn_ps = [psutil.Process(p.pid) for p in c.procs]
                me = psutil.Process()
                trace.install(sizes)  # the CN's replies and frames (class _Sizes)
                cpu0, me0, w0 = _cpu_s(dn_ps), _cpu_s([me])[0], time.monotonic()
                try:
                    periodic = c.run(loops, hook, record=loops)
                finally:
                    trace.uninstall()
                cpu1, me1, w1 = _cpu_s(dn_ps), _cpu_s([me])[0], time.monotonic()
                summary = c.cn.summary()
                paths = c.cn.sync.paths()
                lateness = periodic.lateness_ns()
                skipped = int(periodic.stats().skipped_periods)
                lowlatency = lowlatency_for(c.mission)
        except BaseException:
            for log in sorted(tmpdir.glob("*.log")):
                print(f"--- {log.name}\n{log.read_text(errors='replace')[-3000:]}", flush=True)
            raise
    got = hook.count
    d = hook.duration_ns[:got]
    ok = (hook.replied[:got] == n_dn) & (d < deadline_ns)
    samples = np.where(ok, d, deadline_ns)
    fig = summarize(samples.tolist(), deadline_ns)
    missed_loops = int(np.count_nonzero(~ok))
    fig["deadline_miss_rate"] = (missed_loops + skipped) / max(1, got + skipped)
    fig["missed_loops"] = missed_loops
    fig["skipped_periods"] = skipped
    fig["elements"] = n_elements if region_bytes is None else None
    fig["n_dn"] = n_dn
    fig["rate_hz"] = rate_hz
    fig["rate_hz_measured"] = round(float(summary.rate_hz), 2)
    fig["deadline_us"] = sync_ms * 1e3
    down = list(sizes.down)
    up = list(sizes.up)
    fig["frame_bytes_down"] = down
    fig["frame_bytes_up"] = up
    fig["frame_bytes_max"] = max([*down, *up, 0])
    fig["bytes_per_loop"] = int(sum(down) + sum(up))
    fig["mbit_s"] = round(fig["bytes_per_loop"] * 8 * float(summary.rate_hz) / 1e6, 3)
    wall = max(w1 - w0, 1e-9)
    dn_pct = [round(100.0 * (b - a) / wall, 1) for a, b in zip(cpu0, cpu1, strict=True)]
    fig["cpu_cn_pct"] = round(100.0 * (me1 - me0) / wall, 1)
    fig["cpu_dn_pct"] = max(dn_pct) if dn_pct else None
    fig["cpu_dn_pct_each"] = dn_pct
    fig["shm_replies"] = int(sizes.shm)
    fig["shm_reply_fraction"] = round(sizes.shm / sizes.replies, 4) if sizes.replies else None
    fig["startup_s"] = round(startup_s, 1)
    fig["lowlatency"] = lowlatency
    fig["bad_frames"] = int(summary.bad_frames)
    fig["holds"] = bool(
        fig["deadline_miss_rate"] < MISS_LIMIT and summary.rate_hz >= 0.98 * rate_hz
    )
    if lateness.size:
        p50, p99 = np.percentile(lateness, [50.0, 99.0])
        fig["loop_lateness_p50_us"] = round(float(p50) / 1e3, 2)
        fig["loop_lateness_p99_us"] = round(float(p99) / 1e3, 2)
    fig["transport"] = "zplatform"
    if intra_host != "zenoh":  # absent on zenoh's: the same point as before (point_key)
        fig["intra_host"] = intra_host
        fig["paths"] = paths
    fig["mac"] = mac
    return fig


def run_floor_iceoryx2(size: int, rate_hz: float, duration_s: float, n: int = 1) -> dict[str, Any]:
    """The same bytes by bare iceoryx2 request/response, ``size`` B each way:
    one responder (:func:`bench.intrahost.run_raw`) or ``n``, each on a
    service of its own, every request sent before any reply is collected,
    as the sync does (:func:`bench.intrahost.run_raw_many`): the floor of
    an intra-host point with ``n`` DNs."""
    from bench.intrahost import run_raw, run_raw_many

    deadline_ns = round(min(DEADLINE_MS, 0.5 * 1e3 / rate_hz) * 1e6)
    count = max(1, round(duration_s * rate_hz))
    if n == 1:
        res = run_raw("raw_iceoryx2", size, count, 1.0 / rate_hz)
    else:
        res = run_raw_many(n, size, count, 1.0 / rate_hz)
    fig = summarize(res["samples_ns"], deadline_ns)
    fig["missed"] = res["lost"] + int(
        np.count_nonzero(np.asarray(res["samples_ns"]) >= deadline_ns)
    )
    fig["cpu_us_per_exchange"] = round(res["cpu_s"] / max(1, fig["msgs"]) * 1e6, 1)
    fig["n_dn"] = n
    fig["frame_bytes_max"] = size
    fig["bytes_per_loop"] = 2 * n * size
    fig["transport"] = "raw_iceoryx2"
    return fig


def run_floor(kind: str, n: int, size: int, rate_hz: float, duration_s: float) -> dict[str, Any]:
    """The same bytes by bare zenoh or Python UDP: ``n`` responders, ``size`` B each way."""
    deadline_ns = round(min(DEADLINE_MS, 0.5 * 1e3 / rate_hz) * 1e6)
    res = run_baseline(kind, n, size, rate_hz, duration_s, deadline_ns)
    fig = summarize(res["samples_ns"], deadline_ns)
    fig["missed"] = res["missed"]
    fig["n_dn"] = n
    fig["frame_bytes_max"] = size
    fig["bytes_per_loop"] = 2 * n * size
    fig["mbit_s"] = round(2 * n * size * 8 * rate_hz / 1e6, 3)
    fig["transport"] = f"raw_{kind}"
    return fig


def plot_bandwidth(variants: dict[str, dict[str, Any]], out_dir: Path) -> Path:
    """Log-log sync p99 and CPU against element count, one line per DN split and MAC
    (``earlier run`` for merged variants measured before the MAC was recorded)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = [
        v
        for k, v in variants.items()
        if k.startswith("zp_") and v.get("elements") and v.get("rate_hz") == RATE_HZ
    ]
    lines = sorted({(v["n_dn"], v.get("mac") or "earlier run") for v in pts})
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for d, mac in lines:
        row = sorted(
            (v for v in pts if v["n_dn"] == d and (v.get("mac") or "earlier run") == mac),
            key=lambda v: v["elements"],
        )
        xs = [v["elements"] for v in row]
        axes[0].plot(xs, [v["p99_us"] for v in row], "o-", label=f"{d} DN, {mac}")
        axes[1].plot(xs, [v["cpu_cn_pct"] for v in row], "o-", label=f"CN, {d} DN, {mac}")
        axes[1].plot(xs, [v["cpu_dn_pct"] for v in row], "s--", label=f"busiest DN, {d} DN, {mac}")
    axes[0].axhline(DEADLINE_MS * 1e3, color="r", lw=0.8, ls=":", label="2 ms deadline")
    axes[0].set_ylabel("sync p99 (us)")
    axes[1].set_ylabel("CPU (% of one core)")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("elements (sensors + actuators)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("bench.bandwidth: 100 Hz, mixed-type elements, auth on")
    fig.tight_layout()
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "bandwidth.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def parse_macs(text: str) -> list[str]:
    """``--macs``: comma-separated short names (``blake3``, ``hmac``) or ``security.mac``
    names, in order, each once; raises ValueError naming the bad one."""
    out: list[str] = []
    for x in (t.strip() for t in text.split(",")):
        mac = MAC_SHORT.get(x, x)
        if mac not in MACS:
            known = ", ".join(dict.fromkeys([*MAC_SHORT, *MACS]))
            raise ValueError(f"--macs: unknown MAC {x!r}; one of {known}")
        if mac not in out:
            out.append(mac)
    return out


def point_key(v: dict[str, Any]) -> tuple[Any, ...]:
    """What makes two zplatform variants the same point: elements, DNs, region,
    rate, intra-host path (None: zenoh), MAC."""
    keys = ("elements", "n_dn", "region_bytes", "rate_hz", "intra_host", "mac")
    return tuple(v.get(k) for k in keys)


def floor_names(v: dict[str, Any]) -> list[str]:
    """The floor variants of zplatform variant ``v``: the same bytes by bare zenoh and UDP."""
    kinds = ("zenoh", "udp", "iceoryx2") if v.get("intra_host") else ("zenoh", "udp")
    return [f"raw_{k}_{v.get('n_dn')}x{v.get('frame_bytes_max')}B" for k in kinds]


def merge_previous(path: Path, variants: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """``variants`` joined to the result file at ``path`` (``--merge``).

    The file's variants stay, stamped with its run's ``run_utc`` and
    ``run_cpu`` (its machine's time and CPU model) unless they carry them;
    a variant measured now replaces the file's variant of the same name or
    of the same point (:func:`point_key`; a variant that recorded no
    MAC, from before ``--macs``, is the same point as any MAC's); floors no
    zplatform point refers to any more are dropped. A missing file, or another bench's, adds
    nothing; an unreadable one raises (a merge never silently discards).
    """
    if not path.exists():
        return dict(variants)
    previous = json.loads(path.read_text(encoding="utf-8"))
    if previous.get("bench") != "bandwidth":
        return dict(variants)
    machine = previous.get("machine") or {}
    stamp = {"run_utc": machine.get("time_utc"), "run_cpu": machine.get("cpu_model")}
    new_points = {point_key(v) for k, v in variants.items() if k.startswith("zp_")}
    new_points |= {(*k[:-1], None) for k in new_points}
    merged: dict[str, dict[str, Any]] = {}
    for name, v in (previous.get("variants") or {}).items():
        if name in variants or (name.startswith("zp_") and point_key(v) in new_points):
            continue
        merged[name] = v if "run_utc" in v else {**v, **stamp}
    merged.update(variants)
    wanted = {f for k, v in merged.items() if k.startswith("zp_") for f in floor_names(v)}
    return {k: v for k, v in merged.items() if not k.startswith("raw_") or k in wanted}


def add_floor_ratios(variants: dict[str, dict[str, Any]]) -> None:
    """Set ``vs_raw_zenoh_p50`` on every zplatform variant whose raw-zenoh floor ran."""
    for name, v in variants.items():
        floor = variants.get(floor_names(v)[0], {})
        if name.startswith("zp_") and v.get("p50_us") and floor.get("p50_us"):
            v["vs_raw_zenoh_p50"] = round(v["p50_us"] / floor["p50_us"], 3)
        names = floor_names(v)
        iox = variants.get(names[2], {}) if len(names) > 2 else {}
        if name.startswith("zp_") and v.get("p50_us") and iox.get("p50_us"):
            v["vs_raw_iceoryx2_p50"] = round(v["p50_us"] / iox["p50_us"], 3)


def targets(
    variants: dict[str, dict[str, Any]], macs: list[str], splits: list[int]
) -> list[dict[str, Any]]:
    """Per MAC and DN split, the 100,000-element point: holds 100 Hz, p50 within
    :data:`RATIO_LIMIT` of raw zenoh. ``met`` is None where the point did not run."""
    out: list[dict[str, Any]] = []
    for mac in macs:
        for d in splits:
            v = variants.get(f"zp_{TARGET_ELEMENTS}el_{d}dn_{mac_suffix(mac)}", {})
            holds, ratio = v.get("holds"), v.get("vs_raw_zenoh_p50")
            out.append(
                {
                    "name": f"{TARGET_ELEMENTS:,} elements, {d} DN, {mac}: hold 100 Hz "
                    f"(< {MISS_LIMIT:g} misses)",
                    "value": v.get("deadline_miss_rate"),
                    "limit": MISS_LIMIT,
                    "unit": "",
                    "met": None if holds is None else bool(holds),
                }
            )
            out.append(
                {
                    "name": f"{TARGET_ELEMENTS:,} elements, {d} DN, {mac}: sync p50 vs raw zenoh",
                    "value": ratio,
                    "limit": RATIO_LIMIT,
                    "unit": "x",
                    "met": None if ratio is None else bool(ratio <= RATIO_LIMIT),
                }
            )
            v = variants.get(f"zp_{TARGET_ELEMENTS}el_{d}dn_shm_{mac_suffix(mac)}", {})
            if v:
                ratio = v.get("vs_raw_iceoryx2_p50")
                out.append(
                    {
                        "name": f"{TARGET_ELEMENTS:,} elements, {d} DN, {mac}, intra-host: "
                        "0 missed loops, sync p50 vs raw iceoryx2",
                        "value": [v.get("missed_loops"), ratio],
                        "limit": [0, RATIO_LIMIT],
                        "unit": "x",
                        "met": None
                        if ratio is None
                        else bool(v.get("missed_loops") == 0 and ratio <= RATIO_LIMIT),
                    }
                )
    return out


def output_paths(*, quick: bool, json_path: str | None) -> tuple[Path, Path]:
    """Where a run writes its JSON and its plot.

    Only a full run to the default path writes the repository's files
    (``bench/results/bandwidth.json``, ``bench/plots/``); a ``--quick`` run
    writes to a scratch folder under the temporary directory, and a run given
    ``--json PATH`` puts its plot beside PATH, so a try-out never overwrites
    the committed figures."""
    if json_path:
        path = Path(json_path)
        return path, path.parent / "plots"
    if quick:
        scratch = Path(tempfile.gettempdir()) / "zplatform-bench"
        return scratch / "bandwidth-quick.json", scratch / "plots"
    return RESULTS_DIR / "bandwidth.json", Path(__file__).resolve().parent / "plots"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = bench_argparser(__doc__.splitlines()[0] if __doc__ else "bandwidth")
    parser.add_argument("--seconds", type=float, default=None, help="per point")
    parser.add_argument("--counts", default=None, help="comma-separated element counts")
    parser.add_argument("--splits", default=None, help="comma-separated DN counts")
    parser.add_argument(
        "--regions", default=None, help="comma-separated region sizes in bytes ('' for none)"
    )
    parser.add_argument(
        "--macs",
        default=",".join(MAC_SHORT),
        help=f"comma-separated MACs, each point once per MAC (default: {','.join(MAC_SHORT)})",
    )
    parser.add_argument("--no-rates", action="store_true", help="skip the highest-rate search")
    parser.add_argument("--no-floors", action="store_true", help="skip raw zenoh/UDP floors")
    parser.add_argument("--no-plot", action="store_true")
    parser.add_argument(
        "--merge", action="store_true", help="join the existing result file instead of replacing it"
    )
    parser.add_argument("--priority", type=int, default=PRIORITY)
    parser.add_argument(
        "--intra-host",
        choices=("zenoh", "shm", "both"),
        default="zenoh",
        help="the element points' sync path (transport.intra_host; shm adds a raw iceoryx2 floor)",
    )
    parser.add_argument(
        "--bulk",
        type=int,
        default=0,
        metavar="N",
        help="also the 4 MB bulk one-way rows, N samples per variant (bench.intrahost.run_bulk)",
    )
    args = parser.parse_args(argv)
    try:
        macs = parse_macs(args.macs)
    except ValueError as exc:
        parser.error(str(exc))
    os.environ.setdefault("ZPLATFORM_KEY", secrets.token_hex(32))
    quick = bool(args.quick)
    seconds = args.seconds or (5.0 if quick else 15.0)
    counts = (
        [int(x) for x in args.counts.split(",")]
        if args.counts
        else list(COUNTS_QUICK if quick else COUNTS_FULL)
    )
    splits = (
        [int(x) for x in args.splits.split(",")]
        if args.splits
        else list(SPLITS_QUICK if quick else SPLITS_FULL)
    )
    sched = inherit_fifo(args.priority)
    variants: dict[str, dict[str, Any]] = {}
    floors_done: set[tuple[int, int]] = set()

    def floors(n: int, size: int) -> None:
        if args.no_floors or (n, size) in floors_done:
            return
        floors_done.add((n, size))
        fs = min(seconds, 10.0)
        print(f"  floor raw_zenoh {n}x{size}B ...", flush=True)
        variants[f"raw_zenoh_{n}x{size}B"] = run_floor("zenoh", n, size, RATE_HZ, fs)
        if size <= UDP_MAX:
            print(f"  floor raw_udp {n}x{size}B ...", flush=True)
            variants[f"raw_udp_{n}x{size}B"] = run_floor("udp", n, size, RATE_HZ, fs)

    # Both MACs of a point run back to back, its floors between them: the
    # comparison that matters is within a point, on a box whose load drifts.
    paths_run = ["zenoh", "shm"] if args.intra_host == "both" else [args.intra_host]
    for n, d, mac, ih in (
        (n, d, mac, ih) for n in counts for d in splits for mac in macs for ih in paths_run
    ):
        name = f"zp_{n}el_{d}dn_{'shm_' if ih == 'shm' else ''}{mac_suffix(mac)}"
        print(f"running {name} ({seconds:.0f} s) ...", flush=True)
        try:
            fig = run_point(
                n_elements=n,
                n_dn=d,
                rate_hz=RATE_HZ,
                duration_s=seconds,
                priority=args.priority,
                mac=mac,
                intra_host=ih,
            )
        except Exception as exc:  # a point that cannot run is reported, not hidden
            err = {"error": repr(exc)[:300], "elements": n, "n_dn": d, "mac": mac}
            variants[name] = err
            print(f"  {name} failed: {exc!r}", flush=True)
            continue
        variants[name] = fig
        print(
            f"  {fig['bytes_per_loop']} B/loop, {fig['mbit_s']} Mbit/s,"
            f" p50 {fig['p50_us']} us, p99 {fig['p99_us']} us,"
            f" miss {fig['deadline_miss_rate']:.2e}, CN {fig['cpu_cn_pct']}%,"
            f" DN {fig['cpu_dn_pct']}%, shm {fig['shm_reply_fraction']}",
            flush=True,
        )
        floors(d, int(fig["frame_bytes_max"]))
        size = int(fig["frame_bytes_max"])
        iox_floor = f"raw_iceoryx2_{d}x{size}B"
        if ih == "shm" and not args.no_floors and iox_floor not in variants:
            print(f"  floor raw_iceoryx2 {d}x{size}B ...", flush=True)
            variants[iox_floor] = run_floor_iceoryx2(size, RATE_HZ, min(seconds, 10.0), d)
    if args.bulk:
        from bench.intrahost import run_bulk

        print(f"running the 4 MB bulk one-way rows ({args.bulk} samples each) ...", flush=True)
        variants.update(run_bulk(args.bulk, 0.05))
    regions = (
        [int(x) for x in args.regions.split(",") if x]
        if args.regions is not None
        else list(REGIONS_QUICK if quick else REGIONS_FULL)
    )
    for rb in regions:
        for mac in macs:
            name = f"zp_region_{rb}B_3dn_{mac_suffix(mac)}"
            print(f"running {name} ...", flush=True)
            try:
                variants[name] = run_point(
                    n_elements=0,
                    n_dn=3,
                    rate_hz=RATE_HZ,
                    duration_s=seconds,
                    region_bytes=rb,
                    priority=args.priority,
                    mac=mac,
                )
                variants[name]["region_bytes"] = rb
                floors(3, int(variants[name]["frame_bytes_max"]))
            except Exception as exc:
                err = {"error": repr(exc)[:300], "region_bytes": rb, "n_dn": 3, "mac": mac}
                variants[name] = err
    max_rate: dict[str, dict[str, float | None]] = {}
    if not args.no_rates:
        for mac in macs:
            short = mac_suffix(mac)
            for n in counts:
                base = variants.get(f"zp_{n}el_3dn_{short}", {})
                held: float | None = RATE_HZ if base.get("holds") else None
                if held is not None:
                    for r in RATES:
                        name = f"zp_{n}el_3dn_{int(r)}hz_{short}"
                        print(f"running {name} ...", flush=True)
                        try:
                            fig = run_point(
                                n_elements=n,
                                n_dn=3,
                                rate_hz=r,
                                duration_s=min(seconds, 5.0),
                                priority=args.priority,
                                mac=mac,
                            )
                        except Exception as exc:
                            variants[name] = {"error": repr(exc)[:300], "mac": mac}
                            break
                        variants[name] = fig
                        if not fig["holds"]:
                            break
                        held = r
                max_rate.setdefault(mac, {})[str(n)] = held

    path, plots_dir = output_paths(quick=quick, json_path=args.json)
    stamp = {
        "run_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "run_cpu": machine_info().get("cpu_model"),
    }
    for v in variants.values():
        v.update(stamp)
    if args.merge:
        variants = merge_previous(path, variants)
    add_floor_ratios(variants)
    largest: dict[str, dict[str, int | None]] = {}
    for mac in macs:
        for d in splits:
            ok = [
                int(v["elements"])
                for k, v in variants.items()
                if k.startswith("zp_")
                and v.get("mac") == mac
                and v.get("n_dn") == d
                and v.get("rate_hz") == RATE_HZ
                and v.get("elements")
                and v.get("holds")
                and not v.get("intra_host")
            ]
            largest.setdefault(mac, {})[f"{d}dn"] = max(ok) if ok else None
    params: dict[str, Any] = {
        "rate_hz": RATE_HZ,
        "deadline_us": DEADLINE_MS * 1e3,
        "seconds_per_point": seconds,
        "counts": counts,
        "splits": splits,
        "macs": macs,
        "types": list(TYPES),
        "auth": "on: per-link keys, each variant's `mac` (security.mac)",
        "quick": quick,
        "merged": bool(args.merge),
        "scheduling": sched,
        "miss_limit": MISS_LIMIT,
        "ratio_limit": RATIO_LIMIT,
        "largest_holding_100hz": largest,
        "highest_rate_held_3dn": max_rate,
        "thesis_elements": 200,
        "targets": targets(variants, macs, splits),
        "intra_host": args.intra_host,
    }
    bulk_iox = variants.get("bulk_zplatform_iox_4MB", {}).get("p50_us")
    if bulk_iox:
        params["bulk_4MB_ratios"] = {
            f"zplatform_iox/{k}": round(bulk_iox / p50, 2)
            for k in ("raw_iceoryx2", "raw_zenoh", "zplatform_zenoh")
            if (p50 := variants.get(f"bulk_{k}_4MB", {}).get("p50_us"))
        }
    if not args.no_plot:
        try:
            # Relative to bench/, so the result and the report name the same
            # file on any checkout.
            bench_dir = Path(__file__).resolve().parent
            plot = plot_bandwidth(variants, plots_dir)
            where = plot.relative_to(bench_dir) if plot.is_relative_to(bench_dir) else plot
            params["plots"] = [str(where)]
        except Exception as exc:  # plotting never loses the measurement
            params["plot_error"] = repr(exc)
    doc = write_result("bandwidth", params, variants, str(path))
    print(f"largest N holding 100 Hz: {largest}; highest rate held (3 DN): {max_rate}")
    for t in params["targets"]:
        verdict = {True: "met", False: "NOT met", None: "not run"}[t["met"]]
        print(f"target {t['name']}: {verdict} ({t['value']} {t['unit']})")
    return doc


if __name__ == "__main__":
    main()
