"""Platform CPU overhead on the CN and a DN, the thesis' method (the thesis, 5.2.5).

What is measured: a :class:`SpinController` busy-spins in its enabled run for
a time that grows every loop (``start_ms``, then ``+ step_us`` per loop).
Each loop it records the wall time it spun and the CPU time it actually got
(``time.thread_time_ns``, the thread's CPU clock: the thesis used
``CLOCK_PROCESS_CPUTIME_ID``). The spin length of the last loop that still
met its deadline is the most time control logic can have per loop; the
platform's share of the 10 ms loop is ``1 - max_spin / period``.

Variants (3 DNs at 100 Hz, real-time set-up on, SCHED_FIFO 20):

* ``cn``: the controller runs on the CN. A loop misses its deadline when the
  CN's loop overruns (``cn_loop_overruns``: the step, i.e. sync + logic +
  telemetry, ended after the next deadline) or its sync overran
  (``cn_sync_overruns``).
* ``dn0``: the controller runs on dn0. A loop misses when the CN counts dn0's
  reply as missed or late (``cn_missed_dn0`` / ``cn_late_dn0``) or dn0's step
  took longer than the period (``dn0_loop_overruns``). These are the platform's
  own counters (the brief's criterion). They fire only once the spin nearly
  fills the whole period, because the DN's query handling happens *outside*
  its step; so a stricter figure is also given: ``trigger_*`` counts a loop
  as missed when dn0's step ended after the CN had started the next loop
  (``spin_end_ns(L) > cn_time_ns(L+1)``), i.e. dn0 was still busy when the
  next trigger was sent. That charges the DN with its start lateness (the
  trigger's transport, ~0.3 ms here). The DN's true share lies between the two.

The first miss decides in the thesis. This box is a shared 2-vCPU virtual
machine whose vCPUs stop for 1-200 ms every few seconds (see
``bench/jitter.py``), so an isolated miss in the middle of a ramp is mostly
the host. The ramp therefore goes on until ``SUSTAINED`` consecutive loops
miss (past the real limit every loop misses, since the spin keeps growing)
and ``max_spin`` is the spin of the last loop before that run; isolated
misses before it are counted (``transient_misses``) and the thesis' strict
first-miss figure is reported too (``first_miss_*``).

Each ramp runs on a fresh cluster after a 3 s warm-up, starts from
``safed`` (the hook sets ``spin_mode``) and stops at the sustained miss or
``max_ms``; ``--quick`` runs 1 ramp per variant, the full run 3 (variants
interleaved), and the medians are reported (each ramp in ``runs``).

Also reported: ``sync_p50_us`` (the CN's sync duration during the ramps)
and ``sync_idle_p50_us`` (the same with the spin controller safed), which
make up most of the CN's share; ``bench_hook_p50_us``, the time of this
benchmark's own per-loop hook, which runs inside the CN's step and so is
counted as platform time (about 0.1-0.2 % of the loop); it is fixed work,
so it also shows how fast the shared host was during the run. The thesis'
Table 5 is in ``params.thesis_table5``. Target (issue): CN overhead under
10 % with 3 DNs.

Blocks for about 20 s (quick) to 60 s (full), cluster start-ups included. Run it
under ``flock /tmp/zplatform-bench.lock`` so benchmarks never overlap.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import msgspec
from msgspec import Meta

from zplatform.control.controllers import Controller
from zplatform.core.datavector import DataVector
from zplatform.node.control import ControlNode

from .cluster import BenchCluster, make_mission
from .common import bench_argparser, write_result

__all__ = ["SpinController", "main"]

N_DN = 3
LOOP_HZ = 100.0
PERIOD_NS = 10_000_000
WARMUP_LOOPS = 300
COOLDOWN_LOOPS = 100
SUSTAINED = 3
START_MS = 5.0
STEP_US = 20.0
MAX_MS = 11.0
TARGET_CN_PCT = 10.0

THESIS_TABLE5 = {
    "note": "the thesis, Table 5, real-time kernel, 1 CN + 3 DNs at 100 Hz",
    "cn": {"max_control_logic_ms": 7.85, "overhead_pct": 21.5},
    "dn": {"max_control_logic_ms": 9.89, "overhead_pct": 1.1},
}

SPIN_ELEMENTS = [
    {"name": "spin_target_ns", "type": "i64", "doc": "spin asked for this loop"},
    {"name": "spin_wall_ns", "type": "i64", "doc": "wall time spun (monotonic)"},
    {"name": "spin_cpu_ns", "type": "i64", "doc": "thread CPU time spun"},
    {"name": "spin_end_ns", "type": "i64", "doc": "loop time + wall spun: when the spin ended"},
    {"name": "spin_n", "type": "u32", "doc": "enabled loops since the ramp started"},
]


class SpinController(Controller):
    """Busy-spins ``start_ms + n * step_us`` in its n-th enabled loop; records what it got.

    Benchmark-only: it reads the monotonic and thread CPU clocks, which
    mission controllers must not. ``safed`` resets ``n`` (the next enable
    starts a new ramp). Above ``max_ms`` it stops spinning, so a node left
    enabled by mistake recovers. Writes the ``spin_*`` elements (they must be
    in a region the node writes: ``cn`` on the CN, ``dnX_to_cn`` on a DN).
    """

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        start_ms: Annotated[float, Meta(ge=0)] = START_MS
        step_us: Annotated[float, Meta(ge=0)] = STEP_US
        max_ms: Annotated[float, Meta(gt=0)] = MAX_MS

    config: Config

    def bind(self, dv: DataVector) -> None:
        self._target = self.output("spin_target_ns")
        self._wall = self.output("spin_wall_ns")
        self._cpu = self.output("spin_cpu_ns")
        self._end = self.output("spin_end_ns")
        self._count = self.output("spin_n")
        self._start_ns = round(self.config.start_ms * 1e6)
        self._step_ns = round(self.config.step_us * 1e3)
        self._max_ns = round(self.config.max_ms * 1e6)
        self._n = 0

    def run_enabled(self, t_ns: int) -> None:
        mono = time.monotonic_ns
        cpu = time.thread_time_ns
        self._n += 1
        target = self._start_ns + (self._n - 1) * self._step_ns
        if target > self._max_ns:
            target = 0
        c0 = cpu()
        w0 = mono()
        while mono() - w0 < target:
            pass
        w1 = mono()
        c1 = cpu()
        self._target.set(target)
        self._wall.set(w1 - w0)
        self._cpu.set(c1 - c0)
        self._end.set(t_ns + (w1 - w0))
        self._count.set(self._n)

    def run_safed(self, t_ns: int) -> None:
        self._n = 0
        self._target.set(0)
        self._wall.set(0)
        self._cpu.set(0)
        self._end.set(t_ns)
        self._count.set(0)


@dataclass
class Ramp:
    """One ramp's per-loop records, keyed by the loop the spin ran in."""

    spin: dict[int, tuple[int, int, int, int, int]] = field(default_factory=dict)
    """loop -> (target, wall, cpu, end, n) as the controller recorded it."""
    miss: set[int] = field(default_factory=set)
    """loops that missed by the platform's counters (see the module doc)."""
    cn_time: dict[int, int] = field(default_factory=dict)
    """CN loop -> cn_time_ns (the CN loop top)."""
    sync_ns: list[int] = field(default_factory=list)
    """the CN's sync duration (``cn.sync.duration_ns``) of every loop of the ramp."""
    hook_ns: list[int] = field(default_factory=list)
    """this hook's own time per loop (it runs inside the CN's step: counted as platform)."""


class RampDriver:
    """The CN hook: runs ``repeats`` ramps of the spin controller on ``node``.

    Phases: warm-up (safed), ramp (enabled) until ``SUSTAINED`` consecutive
    misses seen live or the target passes ``MAX_MS``, cool-down (safed), then
    the next ramp; after the last one it stops the CN. Per loop it only reads
    a few handles and stores ints.
    """

    def __init__(self, cn: ControlNode, node: str, repeats: int) -> None:
        self.node = node
        self.repeats = repeats
        self.ramps: list[Ramp] = []
        dv = cn.dv
        self._mode = dv.handle("spin_mode")
        self._enabled = dv.layout.element("spin_mode").enum.index("enabled")  # type: ignore[union-attr]
        self._safed = dv.layout.element("spin_mode").enum.index("safed")  # type: ignore[union-attr]
        self._h = {
            n: dv.handle(n)
            for n in (
                "cn_loop",
                "cn_time_ns",
                "cn_loop_overruns",
                "cn_sync_overruns",
                "cn_missed_dn0",
                "cn_late_dn0",
                "dn0_loop",
                "dn0_loop_overruns",
                *(e["name"] for e in SPIN_ELEMENTS),
            )
        }
        self.phase = "warmup"
        self.phase_loops = 0
        self.prev: dict[str, int] = {}
        self.streak = 0
        self.cur: Ramp | None = None
        self.idle_sync_ns: list[int] = []
        """CN sync durations while the spin controller is safed (late warm-up, cool-down)."""

    def _counters(self) -> dict[str, int]:
        h = self._h
        return {
            k: int(h[k].get())
            for k in (
                "cn_loop_overruns",
                "cn_sync_overruns",
                "cn_missed_dn0",
                "cn_late_dn0",
                "dn0_loop_overruns",
            )
        }

    def __call__(self, loop: int, cn: ControlNode) -> None:
        t0 = time.perf_counter_ns()
        self._step(cn)
        if self.phase == "ramp" and self.cur is not None:
            self.cur.hook_ns.append(time.perf_counter_ns() - t0)

    def _step(self, cn: ControlNode) -> None:
        h = self._h
        self.phase_loops += 1
        if self.phase in ("warmup", "cooldown"):
            if self.phase_loops > WARMUP_LOOPS // 2 or self.phase == "cooldown":
                self.idle_sync_ns.append(cn.sync.duration_ns)
            limit = WARMUP_LOOPS if self.phase == "warmup" else COOLDOWN_LOOPS
            if self.phase_loops >= limit:
                if len(self.ramps) >= self.repeats:
                    cn.stop.set()
                    return
                self.cur = Ramp()
                self.ramps.append(self.cur)
                self.prev = self._counters()
                self.streak = 0
                self.phase, self.phase_loops = "ramp", 0
                self._mode.set(self._enabled)
            return
        r = self.cur
        assert r is not None
        cn_loop = int(h["cn_loop"].get())
        r.cn_time[cn_loop] = int(h["cn_time_ns"].get())
        r.sync_ns.append(cn.sync.duration_ns)
        c = self._counters()
        d = {k: c[k] - self.prev[k] for k in c}
        self.prev = c
        missed = False
        if self.node == "cn":
            # This loop's spin is in the cn region now; an overrun of the
            # previous loop is counted (on_overrun) after its hook ran.
            spin_loop = cn_loop
            if d["cn_sync_overruns"]:
                r.miss.add(cn_loop)
                missed = True
            if d["cn_loop_overruns"] and r.spin:
                r.miss.add(max(r.spin))
                missed = True
        else:
            # dn0's values of its loop L arrive with the reply to query L+1.
            spin_loop = int(h["dn0_loop"].get())
            if d["cn_missed_dn0"] or d["cn_late_dn0"]:
                r.miss.add(cn_loop - 1)  # dn0 was still busy with the previous loop
                missed = True
            if d["dn0_loop_overruns"]:
                r.miss.add(spin_loop)
                missed = True
        n = int(h["spin_n"].get())
        if n > 0 and spin_loop not in r.spin:
            r.spin[spin_loop] = (
                int(h["spin_target_ns"].get()),
                int(h["spin_wall_ns"].get()),
                int(h["spin_cpu_ns"].get()),
                int(h["spin_end_ns"].get()),
                n,
            )
        self.streak = self.streak + 1 if missed else 0
        target_done = n > 0 and int(h["spin_target_ns"].get()) == 0
        if self.streak >= SUSTAINED or target_done or self.phase_loops > 2000:
            self._mode.set(self._safed)
            self.phase, self.phase_loops = "cooldown", 0


def _last_good_before(
    r: Ramp, loops: list[int], bad: set[int], k: int | None
) -> tuple[int, int, int] | None:
    """(target, wall, cpu) of the last recorded loop before ``k`` that did not miss."""
    good = [x for x in loops if (k is None or x < k) and x not in bad]
    if not good:
        return None
    t, w, c, _, _ = r.spin[good[-1]]
    return t, w, c


def analyse_ramp(r: Ramp, node: str) -> dict[str, Any]:
    """Reduce one ramp: last good spin before the sustained miss, first miss, etc."""
    loops = sorted(r.spin)
    miss = set(r.miss)
    trigger_miss: set[int] = set()
    if node != "cn":
        for k in loops:
            nxt = r.cn_time.get(k + 1)
            if nxt is not None and r.spin[k][3] > nxt:
                trigger_miss.add(k)
    out: dict[str, Any] = {"loops": len(loops)}
    for label, bad in (("", miss), ("trigger_", trigger_miss)):
        if node == "cn" and label:
            continue
        first_bad = next((k for k in loops if k in bad), None)
        sustained: int | None = None
        for i, k in enumerate(loops):
            # SUSTAINED recorded loops in a row that all missed
            run = loops[i : i + SUSTAINED]
            if len(run) == SUSTAINED and all(x in bad for x in run):
                sustained = k
                break
        if sustained is None and bad:
            # Fewer records at the end (a DN whose replies were missed): the
            # limit is where the misses start for good.
            tail = [k for k in sorted(bad) if not any(x > k and x not in bad for x in loops)]
            sustained = tail[0] if tail else None

        best = _last_good_before(r, loops, bad, sustained)
        first = _last_good_before(r, loops, bad, first_bad)
        out[f"{label}max_spin_target_ms"] = round(best[0] / 1e6, 3) if best else None
        out[f"{label}max_spin_wall_ms"] = round(best[1] / 1e6, 3) if best else None
        out[f"{label}max_spin_cpu_ms"] = round(best[2] / 1e6, 3) if best else None
        out[f"{label}first_miss_spin_cpu_ms"] = round(first[2] / 1e6, 3) if first else None
        out[f"{label}transient_misses"] = len(
            [k for k in bad if sustained is None or k < sustained]
        )
        out[f"{label}limit_found"] = sustained is not None
    if r.sync_ns:
        out["sync_p50_us"] = round(statistics.median(r.sync_ns) / 1e3, 1)
    if r.hook_ns:
        out["bench_hook_p50_us"] = round(statistics.median(r.hook_ns) / 1e3, 1)
    return out


def _median(runs: list[dict[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in runs if r.get(key) is not None]
    return round(statistics.median(vals), 3) if vals else None


def run_ramps(tmp: Path, node: str, repeats: int) -> list[dict[str, Any]]:
    """Build a cluster with the spin controller on ``node``; run ``repeats`` ramps."""
    region = "cn" if node == "cn" else f"{node}_to_cn"
    path = make_mission(
        tmp / f"overhead_{node}.yaml",
        n_dn=N_DN,
        loop_hz=LOOP_HZ,
        priority=20,
        name=f"overhead_{node}",
        controllers=[
            {
                "name": "spin",
                "class": "bench.overhead:SpinController",
                "node": node,
                "initial_mode": "safed",
                "config": {"start_ms": START_MS, "step_us": STEP_US, "max_ms": MAX_MS},
            }
        ],
        extra={region: SPIN_ELEMENTS},
    )
    budget = WARMUP_LOOPS + repeats * (COOLDOWN_LOOPS + 2100)
    with BenchCluster(path, realtime=True) as c:
        c.start()
        drv = RampDriver(c.cn, node, repeats)
        c.run(budget, drv)
    runs = [analyse_ramp(r, node) for r in drv.ramps]
    if drv.idle_sync_ns:
        for r in runs:
            r["sync_idle_p50_us"] = round(statistics.median(drv.idle_sync_ns) / 1e3, 1)
    return runs


def reduce_runs(runs: list[dict[str, Any]], node: str) -> dict[str, Any]:
    """Medians over the ramps of one variant."""
    fig: dict[str, Any] = {}
    for key in ("max_spin_cpu_ms", "max_spin_wall_ms", "first_miss_spin_cpu_ms"):
        fig[key] = _median(runs, key)
    cpu = fig["max_spin_cpu_ms"]
    wall = fig["max_spin_wall_ms"]
    first = fig["first_miss_spin_cpu_ms"]
    fig["overhead_pct"] = round(100.0 * (1.0 - cpu / 10.0), 2) if cpu is not None else None
    fig["overhead_wall_pct"] = round(100.0 * (1.0 - wall / 10.0), 2) if wall is not None else None
    fig["first_miss_overhead_pct"] = (
        round(100.0 * (1.0 - first / 10.0), 2) if first is not None else None
    )
    if node != "cn":
        t = _median(runs, "trigger_max_spin_cpu_ms")
        fig["trigger_max_spin_cpu_ms"] = t
        fig["trigger_overhead_pct"] = round(100.0 * (1.0 - t / 10.0), 2) if t is not None else None
    fig["transient_misses"] = sum(int(r.get("transient_misses", 0)) for r in runs)
    fig["sync_p50_us"] = _median(runs, "sync_p50_us")
    fig["sync_idle_p50_us"] = _median(runs, "sync_idle_p50_us")
    fig["bench_hook_p50_us"] = _median(runs, "bench_hook_p50_us")
    fig["repeats"] = len(runs)
    fig["runs"] = runs
    return fig


def main(argv: list[str] | None = None) -> None:
    args = bench_argparser(__doc__.splitlines()[0] if __doc__ else "overhead").parse_args(argv)
    repeats = 1 if args.quick else 3
    runs: dict[str, list[dict[str, Any]]] = {"cn": [], "dn0": []}
    with tempfile.TemporaryDirectory(prefix="zp-overhead-") as td:
        # One ramp per fresh cluster, variants interleaved: a bad minute of the
        # shared host does not land on one variant only.
        for _ in range(repeats):
            for node in runs:
                runs[node] += run_ramps(Path(td), node, 1)
    variants = {node: reduce_runs(r, node) for node, r in runs.items()}
    cn_oh = variants["cn"]["overhead_pct"]
    cn_met = cn_oh is not None and cn_oh < TARGET_CN_PCT
    params: dict[str, Any] = {
        "quick": bool(args.quick),
        "n_dn": N_DN,
        "loop_hz": LOOP_HZ,
        "period_ms": PERIOD_NS / 1e6,
        "rt_priority": 20,
        "spin": {"start_ms": START_MS, "step_us": STEP_US, "max_ms": MAX_MS},
        "sustained_misses": SUSTAINED,
        "repeats": repeats,
        "overhead": "1 - max_spin_cpu / period; max_spin = CPU time (thread_time_ns) spun "
        "in the last loop that met its deadline before the sustained miss; medians over repeats",
        "thesis_table5": THESIS_TABLE5,
        "targets": [
            {
                "name": "CN platform overhead (3 DNs)",
                "value": cn_oh,
                "limit": TARGET_CN_PCT,
                "unit": "%",
                "met": cn_met,
            }
        ],
    }
    write_result("overhead", params, variants, args.json)
    print("\noverhead (medians)   max spin cpu/wall ms   overhead %   first-miss overhead %")
    for name, f in variants.items():
        extra = ""
        if name != "cn":
            extra = (
                f"   trigger-bound: max spin {f['trigger_max_spin_cpu_ms']} ms, "
                f"overhead {f['trigger_overhead_pct']} %"
            )
        verdict = ""
        if name == "cn":
            verdict = f"   target < {TARGET_CN_PCT:g} %: {'met' if cn_met else 'MISSED'}"
        print(
            f"{name:<6} {f['max_spin_cpu_ms']} / {f['max_spin_wall_ms']}   {f['overhead_pct']}   "
            f"{f['first_miss_overhead_pct']}   transient misses {f['transient_misses']}, "
            f"sync p50 {f['sync_p50_us']} us (idle {f['sync_idle_p50_us']} us), "
            f"bench hook p50 {f['bench_hook_p50_us']} us"
            f"{extra}{verdict}"
        )
    print("thesis Table 5: CN 7.85 ms / 21.5 %, DN 9.89 ms / 1.1 %")


if __name__ == "__main__":
    main()
