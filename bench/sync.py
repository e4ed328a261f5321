"""The control node's sync step, beside raw zenoh and raw UDP doing the same exchange.

Variants, run one after the other in one invocation, all at the same loop
rate (100 Hz), with the same 256 B regions, the same 2 ms deadline and the
same scheduling but the ``_cfs`` rows (see *Scheduling* below):

* ``zplatform_1dn`` / ``zplatform_3dn``: a real zplatform cluster
  (:class:`bench.cluster.BenchCluster`): 1 or 3 device-node processes and the
  control node in this process, running its real loop
  (:meth:`ControlNode.run`). The figure per loop is the CN's own
  ``ControlSync.duration_ns`` (``time.monotonic_ns`` from just before
  the first region is encoded and queried until every reply has been checked
  and applied, or the sync deadline passed);
  These run the mission defaults (``transport.lowlatency`` off: module doc
  of :mod:`zplatform.core.messages`).
  (one get per DN);
* ``zplatform_wildcard_3dn``: the same with ``sync_query: wildcard`` (one
  query per loop with every DN's frame), and ``zplatform_lowlatency_3dn``
  with ``lowlatency: true``: the levers, measured;
* ``zplatform_mtls_1dn`` / ``zplatform_mtls_3dn``: the first two over mutual
  TLS with access control (``security.transport: mtls``, the default of a
  mission with hazardous commands), from a PKI made for the run: what the
  secure default costs (``ratios_p50``: mtls over plain);
* ``raw_zenoh_1`` / ``raw_zenoh_3``: bare zenoh ``get``/``reply`` with zenoh's
  default transport (:func:`bench.baselines.run_baseline`): the floor;
  ``raw_zenoh_lowlatency_3``: the same on the lowlatency transport;
* ``raw_zenoh_wildcard_3`` / ``raw_zenoh_wildcard_lowlatency_3``: one
  wildcard query per loop to every responder, carrying every responder's
  frame, instead of one get each;
* ``raw_udp_1`` / ``raw_udp_3``: Python UDP request/response, the thesis'
  transport;
* ``zplatform_shm_1dn`` / ``zplatform_shm_3dn``: the first two with the sync
  on the intra-host path (``transport.intra_host: shm``: iceoryx2 shared
  memory, docs/architecture.md#intra-host); every other ``zplatform_*`` row
  pins ``intra_host: zenoh``, so it measures zenoh as before;
  ``raw_iceoryx2_1``: bare iceoryx2 request/response with event wake-ups
  (:func:`bench.intrahost.run_raw`), the floor of the shared-memory rows;
* ``zplatform_shm_1dn_cfs`` / ``raw_iceoryx2_1_cfs``: the same two with
  normal scheduling (SCHED_OTHER, whatever ``--priority`` says): what
  real-time priority costs a wake-up. The kernel wakes a SCHED_FIFO thread
  on an idle CPU, where SCHED_OTHER's wake-affine placement keeps it on the
  waker's; on a VM an idle vCPU is halted, and waking it costs about
  200 us (docs/architecture.md#intra-host). Only these rows: on the shared
  memory path the loop threads wake each other; zenoh's runtime threads
  are process-wide and keep the policy they started with, so a zenoh row
  in this process could not be run without real-time priority after one
  with it;
* ``*_325KB``: ``zplatform_1dn``, ``zplatform_shm_1dn``, ``raw_zenoh_1``
  and ``raw_iceoryx2_1`` with 325 KB regions each way (the largest region
  of ``bench.intrahost``, a 100,000-element vector's order);
* ``*_100000el``: the 100,000-element point of ``bench.bandwidth``
  (:func:`bench.bandwidth.run_point`: mixed-type scalars, half sensors and
  half actuators, split evenly across the DNs, BLAKE3 tags) with 1 and 3
  DNs, over shared memory (``zplatform_shm_<D>dn_100000el``) and over zenoh
  (``zplatform_3dn_100000el``), beside ``raw_iceoryx2_<D>_100000el``: bare
  iceoryx2 moving the same bytes (each DN's largest frame, tag included,
  each way) to 1 or 3 responder processes, every request sent before the
  replies are collected, as the sync does (:func:`bench.intrahost.run_raw_many`).

What is measured, per loop: the sync exchange's duration. A loop that missed
its deadline (a DN did not answer in time, or the step ended at or past the
deadline) is recorded as exactly the deadline, as the baselines do, so
``deadline_miss_rate`` counts it; the uncapped maximum of the zplatform
variants is ``max_raw_us``. Figures come from :func:`bench.common.summarize`
(``p50_us``, ``p99_us``, ``max_us``, ``deadline_miss_rate``, ``msgs``); the
zplatform variants add the CN's own counters (``missed``, ``late``,
``sync_overruns``, ``loop_overruns``) and the start lateness of its loop
(``loop_lateness_p50_us`` / ``_p99_us``).

Targets (reported in ``params.targets``, never asserted): the sync step's p99
under 1 ms with 3 DNs, and zplatform's p50 within 1.5x of raw zenoh's with 1
and with 3 DNs (``ratio`` = zplatform p50 / raw_zenoh p50).

Scheduling: with ``--priority P`` (default 20; ``--priority 0`` turns it
off), every node of a zplatform cluster runs SCHED_FIFO P on all its threads
(the mission's ``priority``). So that the baselines are not at a
disadvantage, this process switches its main thread to SCHED_FIFO P before
anything starts: the threads zenoh creates later and the responder processes
the baselines spawn inherit the policy. The ``_cfs`` rows run with normal
scheduling (:func:`normal_scheduling`), their nodes and responders too.

What blocks: :func:`main` blocks for the sum of the variants' durations (10 s
each with ``--quick``, 30 s otherwise) plus the start-up of each variant's
processes (about 1-3 s: DN processes are waited for by liveliness and a
warm-up sync, never by sleeping). ``--minutes M`` runs only
``zplatform_3dn`` for M minutes (the soak) and merges it into the existing
result file as ``zplatform_3dn_soak``.

Run ``python -m bench.sync [--quick] [--json PATH] [--minutes M]``; results go
to ``bench/results/sync.json``.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from bench.baselines import run_baseline
from bench.cluster import BenchCluster, SyncSamples, make_mission
from bench.common import RESULTS_DIR, bench_argparser, summarize, write_result
from zplatform.security.deploy import DEPLOYMENT_ENV
from zplatform.security.pki import DEPLOYMENT_FILE, ensure_pki

RATE_HZ = 100.0
REGION_BYTES = 256
DEADLINE_MS = 2.0
PRIORITY = 20
QUICK_S = 10.0
FULL_S = 30.0
TARGET_P99_3DN_US = 1000.0
TARGET_P50_VS_ZENOH = 1.5
LARGE_BYTES = 325_000  # bench.intrahost.SIZES["325KB"]


@dataclass(frozen=True)
class Variant:
    """One row of the benchmark: which transport, how many responders, low-latency
    or not, one wildcard query or one get each (raw) / the mission's ``sync_query``."""

    name: str
    kind: str  # "zplatform" | "zenoh" | "udp"
    n: int
    lowlatency: bool | str = False
    wildcard: bool = False
    sync_query: str | None = None
    transport: str | None = None  # zplatform: the mission's security.transport
    intra_host: str = "zenoh"  # zplatform: the mission's transport.intra_host
    region_bytes: int = REGION_BYTES
    elements: int | None = None  # bench.bandwidth's element point instead of u8 regions
    realtime: bool = True  # False: SCHED_OTHER whatever --priority says (the ``_cfs`` rows)


ELEMENTS = 100_000

VARIANTS: tuple[Variant, ...] = (
    Variant("zplatform_1dn", "zplatform", 1),
    Variant("zplatform_3dn", "zplatform", 3),
    Variant("zplatform_wildcard_3dn", "zplatform", 3, sync_query="wildcard"),
    Variant("zplatform_lowlatency_3dn", "zplatform", 3, True),
    Variant("zplatform_mtls_1dn", "zplatform", 1, transport="mtls"),
    Variant("zplatform_mtls_3dn", "zplatform", 3, transport="mtls"),
    Variant("raw_zenoh_1", "zenoh", 1),
    Variant("raw_zenoh_3", "zenoh", 3),
    Variant("raw_zenoh_lowlatency_3", "zenoh", 3, True),
    Variant("raw_zenoh_wildcard_3", "zenoh", 3, False, True),
    Variant("raw_zenoh_wildcard_lowlatency_3", "zenoh", 3, True, True),
    Variant("raw_udp_1", "udp", 1),
    Variant("raw_udp_3", "udp", 3),
    Variant("zplatform_shm_1dn", "zplatform", 1, intra_host="shm"),
    Variant("zplatform_shm_3dn", "zplatform", 3, intra_host="shm"),
    Variant("raw_iceoryx2_1", "iceoryx2", 1),
    Variant("zplatform_shm_1dn_cfs", "zplatform", 1, intra_host="shm", realtime=False),
    Variant("raw_iceoryx2_1_cfs", "iceoryx2", 1, realtime=False),
    Variant("zplatform_1dn_325KB", "zplatform", 1, region_bytes=LARGE_BYTES),
    Variant("zplatform_shm_1dn_325KB", "zplatform", 1, intra_host="shm", region_bytes=LARGE_BYTES),
    Variant("raw_zenoh_1_325KB", "zenoh", 1, region_bytes=LARGE_BYTES),
    Variant("raw_iceoryx2_1_325KB", "iceoryx2", 1, region_bytes=LARGE_BYTES),
    Variant("zplatform_shm_1dn_100000el", "zplatform", 1, intra_host="shm", elements=ELEMENTS),
    Variant("raw_iceoryx2_1_100000el", "iceoryx2", 1, elements=ELEMENTS),
    Variant("zplatform_shm_3dn_100000el", "zplatform", 3, intra_host="shm", elements=ELEMENTS),
    Variant("zplatform_3dn_100000el", "zplatform", 3, elements=ELEMENTS),
    Variant("raw_iceoryx2_3_100000el", "iceoryx2", 3, elements=ELEMENTS),
)


def element_frame_bytes(n_elements: int, n_dn: int) -> int:
    """The largest frame (tag included) any DN of ``bench.bandwidth``'s
    ``n_elements`` point over ``n_dn`` DNs sends or receives: what the raw
    rows move each way. Loads the mission (seconds at 100,000 elements)."""
    from bench.bandwidth import element_extra
    from zplatform.core.auth import TAG_LEN
    from zplatform.core.codec import frame_overhead
    from zplatform.core.datavector import Layout
    from zplatform.mission.load import load_mission

    with tempfile.TemporaryDirectory(prefix="zp-bench-") as tmp:
        path = make_mission(
            Path(tmp) / "m.yaml",
            n_dn=n_dn,
            region_bytes=1,
            extra=element_extra(n_elements, n_dn),
        )
        m = load_mission(path)
    sizes = [
        Layout.for_regions(m, [r]).size
        for i in range(n_dn)
        for r in (f"cn_to_dn{i}", f"dn{i}_to_cn")
    ]
    return max(frame_overhead(n) + n + TAG_LEN for n in sizes)


def _us(ns: float) -> float:
    return round(float(ns) / 1e3, 2)


def inherit_fifo(priority: int) -> str:
    """Put the calling thread in SCHED_FIFO ``priority`` so threads and children inherit it.

    Returns a note for the result's params ("SCHED_FIFO 20", or why not).
    Does not block. ``priority`` 0 means: leave the policy alone.
    """
    if priority <= 0:
        return "SCHED_OTHER (realtime off)"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        return f"SCHED_OTHER (SCHED_FIFO refused: {exc})"
    return f"SCHED_FIFO {priority}"


def run_zplatform(
    n_dn: int,
    *,
    rate_hz: float,
    duration_s: float,
    sync_timeout_ms: float,
    region_bytes: int = REGION_BYTES,
    lowlatency: bool | str = False,
    sync_query: str | None = None,
    priority: int = PRIORITY,
    transport: str | None = None,
    intra_host: str = "zenoh",
) -> dict[str, Any]:
    """Run a zplatform cluster (``n_dn`` DN processes, CN here) for ``duration_s``.

    ``intra_host``: the mission's ``transport.intra_host`` (``shm``: the
    sync over iceoryx2 shared memory; the result's ``paths`` says which
    path each DN's link took at the end).

    ``transport="mtls"``: over mutual TLS, with a PKI made in the run's
    temporary directory and named by ``ZPLATFORM_DEPLOYMENT`` for the run
    (this process and the DNs).

    Blocks for the start-up of the DNs plus ``rate_hz × duration_s`` loops of
    the CN's real loop. Returns the :func:`bench.common.summarize` figures of
    the per-loop sync durations (a missed loop counts as the deadline) plus
    the CN's counters: ``loops``, ``missed`` and ``late`` (summed over the
    DNs), ``sync_overruns``, ``loop_overruns``, ``skipped_periods``, the
    uncapped ``max_raw_us`` and the loop's start lateness p50/p99. On failure
    the DN logs are printed before the exception propagates.
    """
    loops = max(1, round(duration_s * rate_hz))
    deadline_ns = round(sync_timeout_ms * 1e6)
    with tempfile.TemporaryDirectory(prefix="zp-bench-") as tmp:
        tmpdir = Path(tmp)
        mission = make_mission(
            tmpdir / "m.yaml",
            n_dn=n_dn,
            loop_hz=rate_hz,
            sync_timeout_ms=sync_timeout_ms,
            region_bytes=region_bytes,
            lowlatency=lowlatency,
            sync_query=sync_query,
            priority=priority if priority > 0 else None,
            transport=transport,
        )
        raw = yaml.safe_load(mission.read_text())
        raw.setdefault("transport", {})["intra_host"] = intra_host
        mission.write_text(yaml.safe_dump(raw, sort_keys=False))
        hook = SyncSamples(loops)
        deployment = os.environ.get(DEPLOYMENT_ENV)
        if transport == "mtls":
            ensure_pki(tmpdir / "pki", ["cn", *(f"dn{i}" for i in range(n_dn))])
            os.environ[DEPLOYMENT_ENV] = str(tmpdir / "pki" / DEPLOYMENT_FILE)

        try:
            with BenchCluster(mission, realtime=priority > 0) as c:
                c.start()
                periodic = c.run(loops, hook, record=loops)
                summary = c.cn.summary()
                lateness = periodic.lateness_ns()
                skipped = periodic.stats().skipped_periods
                wildcard = c.cn.sync.wildcard
                paths = c.cn.sync.paths()
        except BaseException:
            for log in sorted(tmpdir.glob("*.log")):
                print(f"--- {log.name}\n{log.read_text(errors='replace')[-4000:]}", flush=True)
            raise
        finally:
            if deployment is None:
                os.environ.pop(DEPLOYMENT_ENV, None)
            else:
                os.environ[DEPLOYMENT_ENV] = deployment
    got = hook.count
    d = hook.duration_ns[:got]
    ok = (hook.replied[:got] == n_dn) & (d < deadline_ns)
    samples = np.where(ok, d, deadline_ns)
    fig = summarize(samples.tolist(), deadline_ns)
    fig["max_raw_us"] = _us(d.max()) if got else None
    fig["responders"] = n_dn
    fig["loops"] = int(summary.loops)
    fig["missed"] = int(sum(summary.missed.values()))
    fig["late"] = int(sum(summary.late.values()))
    fig["sync_overruns"] = int(summary.sync_overruns)
    fig["loop_overruns"] = int(summary.loop_overruns)
    fig["skipped_periods"] = int(skipped)
    fig["bad_frames"] = int(summary.bad_frames)
    fig["rate_hz_measured"] = round(float(summary.rate_hz), 2)
    fig["wildcard"] = wildcard
    fig["intra_host"] = intra_host
    fig["paths"] = paths
    fig["region_bytes"] = region_bytes
    if lateness.size:
        p50, p99 = np.percentile(lateness, [50.0, 99.0])
        fig["loop_lateness_p50_us"] = _us(p50)
        fig["loop_lateness_p99_us"] = _us(p99)
    return fig


@contextmanager
def normal_scheduling() -> Iterator[str]:
    """The calling thread in SCHED_OTHER for the block (the processes it
    spawns and the threads it starts inherit it), its policy and priority
    restored after. Yields the scheduling it ran with, for the row."""
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    try:
        yield "SCHED_OTHER"
    finally:
        os.sched_setscheduler(0, policy, param)


def run_variant(v: Variant, *, duration_s: float, priority: int) -> dict[str, Any]:
    """Run one variant at :data:`RATE_HZ` for ``duration_s`` (blocks that long plus start-up)."""
    if not v.realtime:
        with normal_scheduling() as sched:
            fig = run_variant(replace(v, realtime=True), duration_s=duration_s, priority=0)
        fig["scheduling"] = sched
        return fig
    deadline_ns = round(DEADLINE_MS * 1e6)
    if v.kind == "zplatform" and v.elements is not None:
        from bench.bandwidth import run_point

        fig = run_point(
            n_elements=v.elements,
            n_dn=v.n,
            rate_hz=RATE_HZ,
            duration_s=duration_s,
            priority=priority,
            intra_host=v.intra_host,
        )
        fig["missed"] = fig["missed_loops"]
        fig["responders"] = v.n
        fig["intra_host"] = v.intra_host
        fig.setdefault("paths", ["zenoh"] * v.n)
    elif v.kind == "zplatform":
        fig = run_zplatform(
            v.n,
            rate_hz=RATE_HZ,
            duration_s=duration_s,
            sync_timeout_ms=DEADLINE_MS,
            region_bytes=v.region_bytes,
            lowlatency=v.lowlatency,
            sync_query=v.sync_query,
            priority=priority,
            transport=v.transport,
            intra_host=v.intra_host,
        )
    elif v.kind == "iceoryx2":
        from bench.intrahost import run_raw, run_raw_many

        size = v.region_bytes if v.elements is None else element_frame_bytes(v.elements, v.n)
        count = max(1, round(duration_s * RATE_HZ))
        many = v.n > 1  # one service per responder, as one link per DN
        iox = run_raw_many(v.n, size, count) if many else run_raw("raw_iceoryx2", size, count)
        fig = summarize(iox["samples_ns"], deadline_ns)
        fig["missed"] = iox["lost"] + int(
            np.count_nonzero(np.asarray(iox["samples_ns"]) >= deadline_ns)
        )
        fig["frame_bytes"] = size
        fig["responders"] = v.n
        fig["cpu_us_per_exchange"] = round(iox["cpu_s"] / max(1, len(iox["samples_ns"])) * 1e6, 1)
    else:
        res = run_baseline(
            v.kind,
            v.n,
            v.region_bytes,
            RATE_HZ,
            duration_s,
            deadline_ns,
            v.lowlatency is True,
            wildcard=v.wildcard,
        )
        fig = summarize(res["samples_ns"], deadline_ns)
        fig["missed"] = res["missed"]
        fig["responders"] = v.n
    fig["transport"] = v.kind
    fig["lowlatency"] = v.lowlatency
    fig.setdefault("wildcard", v.wildcard)
    return fig


def _ratio(variants: dict[str, dict[str, Any]], num: str, den: str) -> float | None:
    a = variants.get(num, {}).get("p50_us")
    b = variants.get(den, {}).get("p50_us")
    if a is None or not b:
        return None
    return round(float(a) / float(b), 3)


def targets(variants: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The sync targets, each ``{name, value, limit, unit, met}`` (``met`` None if not run)."""
    out: list[dict[str, Any]] = []
    p99 = variants.get("zplatform_3dn", {}).get("p99_us")
    out.append(
        {
            "name": "zplatform_3dn sync p99 < 1 ms",
            "value": p99,
            "limit": TARGET_P99_3DN_US,
            "unit": "us",
            "met": None if p99 is None else bool(p99 < TARGET_P99_3DN_US),
        }
    )
    for n in (1, 3):
        r = _ratio(variants, f"zplatform_{n}dn", f"raw_zenoh_{n}")
        out.append(
            {
                "name": f"zplatform_{n}dn p50 within 1.5x of raw_zenoh_{n}",
                "value": r,
                "limit": TARGET_P50_VS_ZENOH,
                "unit": "x",
                "met": None if r is None else bool(r <= TARGET_P50_VS_ZENOH),
            }
        )
    return out


def ratios(variants: dict[str, dict[str, Any]]) -> dict[str, float | None]:
    """p50 ratios of each zplatform variant over its baselines (None where one was not run)."""
    pairs = {
        "zplatform_1dn/raw_zenoh_1": ("zplatform_1dn", "raw_zenoh_1"),
        "zplatform_3dn/raw_zenoh_3": ("zplatform_3dn", "raw_zenoh_3"),
        "zplatform_lowlatency_3dn/raw_zenoh_lowlatency_3": (
            "zplatform_lowlatency_3dn",
            "raw_zenoh_lowlatency_3",
        ),
        "zplatform_lowlatency_3dn/zplatform_3dn": ("zplatform_lowlatency_3dn", "zplatform_3dn"),
        "zplatform_wildcard_3dn/zplatform_3dn": ("zplatform_wildcard_3dn", "zplatform_3dn"),
        "zplatform_wildcard_3dn/raw_zenoh_wildcard_3": (
            "zplatform_wildcard_3dn",
            "raw_zenoh_wildcard_3",
        ),
        "raw_zenoh_wildcard_3/raw_zenoh_3": ("raw_zenoh_wildcard_3", "raw_zenoh_3"),
        "raw_zenoh_wildcard_lowlatency_3/raw_zenoh_lowlatency_3": (
            "raw_zenoh_wildcard_lowlatency_3",
            "raw_zenoh_lowlatency_3",
        ),
        "zplatform_mtls_1dn/zplatform_1dn": ("zplatform_mtls_1dn", "zplatform_1dn"),
        "zplatform_mtls_3dn/zplatform_3dn": ("zplatform_mtls_3dn", "zplatform_3dn"),
        "zplatform_1dn/raw_udp_1": ("zplatform_1dn", "raw_udp_1"),
        "zplatform_3dn/raw_udp_3": ("zplatform_3dn", "raw_udp_3"),
        "raw_zenoh_3/raw_udp_3": ("raw_zenoh_3", "raw_udp_3"),
        "zplatform_shm_1dn/raw_iceoryx2_1": ("zplatform_shm_1dn", "raw_iceoryx2_1"),
        "zplatform_shm_1dn/zplatform_1dn": ("zplatform_shm_1dn", "zplatform_1dn"),
        "zplatform_shm_1dn/raw_zenoh_1": ("zplatform_shm_1dn", "raw_zenoh_1"),
        "zplatform_shm_3dn/zplatform_3dn": ("zplatform_shm_3dn", "zplatform_3dn"),
        "zplatform_shm_3dn/raw_zenoh_3": ("zplatform_shm_3dn", "raw_zenoh_3"),
        "raw_iceoryx2_1/raw_zenoh_1": ("raw_iceoryx2_1", "raw_zenoh_1"),
        "zplatform_shm_1dn_cfs/raw_iceoryx2_1_cfs": (
            "zplatform_shm_1dn_cfs",
            "raw_iceoryx2_1_cfs",
        ),
        "zplatform_shm_1dn/zplatform_shm_1dn_cfs": ("zplatform_shm_1dn", "zplatform_shm_1dn_cfs"),
        "raw_iceoryx2_1/raw_iceoryx2_1_cfs": ("raw_iceoryx2_1", "raw_iceoryx2_1_cfs"),
        "zplatform_shm_1dn_325KB/raw_iceoryx2_1_325KB": (
            "zplatform_shm_1dn_325KB",
            "raw_iceoryx2_1_325KB",
        ),
        "zplatform_shm_1dn_325KB/zplatform_1dn_325KB": (
            "zplatform_shm_1dn_325KB",
            "zplatform_1dn_325KB",
        ),
        "zplatform_1dn_325KB/raw_zenoh_1_325KB": ("zplatform_1dn_325KB", "raw_zenoh_1_325KB"),
        "raw_iceoryx2_1_325KB/raw_zenoh_1_325KB": ("raw_iceoryx2_1_325KB", "raw_zenoh_1_325KB"),
        "zplatform_shm_1dn_100000el/raw_iceoryx2_1_100000el": (
            "zplatform_shm_1dn_100000el",
            "raw_iceoryx2_1_100000el",
        ),
        "zplatform_shm_3dn_100000el/raw_iceoryx2_3_100000el": (
            "zplatform_shm_3dn_100000el",
            "raw_iceoryx2_3_100000el",
        ),
        "zplatform_shm_3dn_100000el/zplatform_3dn_100000el": (
            "zplatform_shm_3dn_100000el",
            "zplatform_3dn_100000el",
        ),
    }
    return {k: _ratio(variants, a, b) for k, (a, b) in pairs.items()}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the variants in sequence, write ``bench/results/sync.json`` and print the tables."""
    parser = bench_argparser(__doc__.splitlines()[0] if __doc__ else "sync")
    parser.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="soak: run only zplatform_3dn for this many minutes, merged into the result file",
    )
    parser.add_argument(
        "--variants",
        default=None,
        help="comma-separated subset of: " + ",".join(v.name for v in VARIANTS),
    )
    parser.add_argument(
        "--priority", type=int, default=PRIORITY, help="SCHED_FIFO priority (0: off)"
    )
    args = parser.parse_args(argv)
    by_name = {v.name: v for v in VARIANTS}
    if args.minutes is not None:
        plan = [by_name["zplatform_3dn"]]
        duration_s = args.minutes * 60.0
    else:
        names = args.variants.split(",") if args.variants else list(by_name)
        unknown = [n for n in names if n not in by_name]
        if unknown:
            parser.error(f"unknown variants: {unknown}")
        plan = [by_name[n] for n in names]
        duration_s = QUICK_S if args.quick else FULL_S
    sched = inherit_fifo(args.priority)

    variants: dict[str, dict[str, Any]] = {}
    for v in plan:
        print(f"running {v.name} ({duration_s:.0f} s) ...", flush=True)
        variants[v.name] = run_variant(v, duration_s=duration_s, priority=args.priority)

    params: dict[str, Any] = {
        "rate_hz": RATE_HZ,
        "region_bytes": REGION_BYTES,
        "deadline_us": DEADLINE_MS * 1e3,
        "duration_s": duration_s,
        "quick": bool(args.quick),
        "scheduling": sched,
        "zplatform_figure": "ControlSync.duration_ns (monotonic_ns), CN loop thread",
        "baseline_figure": "perf_counter_ns first send -> last reply copied out",
    }
    path = Path(args.json) if args.json else RESULTS_DIR / "sync.json"
    if args.minutes is not None:
        # The soak joins the last full run's file instead of replacing it.
        soak = variants.pop("zplatform_3dn")
        soak["minutes"] = args.minutes
        soak["scheduling"] = sched
        previous: dict[str, Any] = {}
        if path.exists():
            previous = json.loads(path.read_text(encoding="utf-8"))
        if previous.get("bench") == "sync":
            params = dict(previous.get("params", {}))
            variants = dict(previous.get("variants", {}))
        variants["zplatform_3dn_soak"] = soak
        params["soak_minutes"] = args.minutes
    params["ratios_p50"] = ratios(variants)
    params["targets"] = targets(variants)
    doc = write_result("sync", params, variants, str(path))

    print("\nratios (p50):")
    for k, r in params["ratios_p50"].items():
        print(f"  {k:<50} {'-' if r is None else f'{r:.2f}x'}")
    for t in params["targets"]:
        verdict = {True: "met", False: "NOT met", None: "not run"}[t["met"]]
        print(f"target {t['name']}: {verdict} ({t['value']} {t['unit']})")
    for name, fig in variants.items():
        if "sync_overruns" in fig:
            print(
                f"{name}: missed {fig['missed']}, late {fig['late']}, "
                f"sync_overruns {fig['sync_overruns']}, loop_overruns {fig['loop_overruns']}, "
                f"max_raw {fig['max_raw_us']} us"
            )
    return doc


if __name__ == "__main__":
    main()
