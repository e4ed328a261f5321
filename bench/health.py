"""What health sampling costs the CN's loop (``health:``, zplatform.core.health).

The recovery igniter mission's CN loop (``ControlLogic.begin``, ``reply`` per
DN, ``finish``, its monitors included) runs paced at 100 Hz on a
``PeriodicLoop`` with a ``GcGuard``, as the live CN does, fed the same DN
replies every time (captured once from a lockstep run). Variants, interleaved
round by round so drift on the shared box hits them alike: ``cn_loop``, no
health port and no health thread (the health elements stay as they are);
``cn_loop_health_2hz`` and ``cn_loop_health_10hz``, a live
:class:`zplatform.node.health.NodeHealth` (its psutil sampling thread, its
zenoh probe on a session of its own, the gc hook) attached at the mission's
2 Hz and at the 10 Hz maximum, the loop reporting its lateness every loop,
copying the block on health loops and waking the sampler after its work
(``NodeHealth.kick``: it samples in the loop's slack). Figures: the loop's
work time per loop (``time.perf_counter_ns`` around begin..finish, after a
warm-up), its p50/p99
against ``cn_loop`` (``added_p50_us``, ``added_p99_us``), the health loops'
own work time (``health_loop_p50_us``, ``health_loop_max_us``) and the
sampling thread's time per sample (``sample_p50_us``, ``sample_max_us``).

Run ``python -m bench.health [--quick] [--json PATH]``; results go to
``bench/results/health.json``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from bench.common import bench_argparser, summarize, write_result
from bench.record import loop_inputs
from zplatform import ControlLogic, GcGuard, PeriodicLoop, load_mission
from zplatform.config import Mission
from zplatform.core.health import Heartbeat, Liveness, health_divisor, thread_deadlines_ns
from zplatform.node.health import NodeHealth
from zplatform.sim.lockstep import sim_keys

ROOT = Path(__file__).resolve().parents[1]
MISSION = ROOT / "configs" / "recovery_igniter.yaml"


def _with_rate(m: Mission, rate_hz: float | None) -> Mission:
    assert m.health is not None
    if rate_hz is not None:
        m.health.rate_hz = rate_hz
    return m


def _run(
    replies: list[list[bytes]], rate_hz: float | None, session: zenoh.Session | None
) -> tuple[list[int], list[int], list[int]]:
    """One paced run; returns (work ns per loop, work ns of health loops, sample ns)."""
    m = _with_rate(load_mission(MISSION), rate_hz)
    cn = ControlLogic(m, keys=sim_keys(m), epoch=1)
    health: NodeHealth | None = None
    if rate_hz is not None:
        live = Liveness(thread_deadlines_ns(m))
        live.add(Heartbeat("loop"))
        health = NodeHealth(m, "cn", live, session=session)
        cn.attach_health(health)
        health.start()
    divisor = health_divisor(m)
    work: list[int] = []
    health_loops: list[int] = []
    samples: list[int] = []
    clock = time.perf_counter_ns
    mono = time.monotonic_ns
    last_sample = 0

    def step(k: int, deadline_ns: int) -> bool:
        nonlocal last_sample
        loop = k + 1
        if loop > len(replies):
            return False
        t0 = clock()
        if health is not None:
            health.note(mono() - deadline_ns)
        cn.begin(loop, loop * m.period_ns)
        for i, p in enumerate(replies[loop - 1]):
            cn.reply(i, p)
        cn.finish()
        d = clock() - t0
        work.append(d)
        if loop % divisor == 0 and health is not None:
            health_loops.append(d)
            if health.samples != last_sample:
                last_sample = health.samples
                samples.append(health.sample_ns)
        if cn.events.pending:
            cn.events.drain()
        if health is not None:
            health.kick()  # as the live CN does: sample in the slack
        return True

    guard = GcGuard()
    guard.freeze_after_startup()
    try:
        PeriodicLoop(m.period_ns, slack_hook=guard.on_slack).run(step)
    finally:
        guard.restore()
        if health is not None:
            health.close()
    return work, health_loops, samples


def main() -> None:
    args = bench_argparser(__doc__.splitlines()[0]).parse_args()
    seconds = 1 if args.quick else 10
    rounds = 2 if args.quick else 5
    m = load_mission(MISSION)
    loops = round(seconds * m.loop_hz)
    warm = loops // 10
    replies = [r for _, _, r, _ in loop_inputs(m, loops)]
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    rates: dict[str, float | None] = {
        "cn_loop": None,
        "cn_loop_health_2hz": 2.0,
        "cn_loop_health_10hz": 10.0,
    }
    work: dict[str, list[int]] = {k: [] for k in rates}
    hloops: dict[str, list[int]] = {k: [] for k in rates}
    samples: dict[str, list[int]] = {k: [] for k in rates}
    try:
        for _ in range(rounds):  # interleaved: drift on the box hits every variant alike
            for name, rate in rates.items():
                w, h, s = _run(replies, rate, session)
                work[name] += w[warm:]
                hloops[name] += h
                samples[name] += s
    finally:
        session.close()
    variants: dict[str, dict[str, Any]] = {}
    base = summarize(work["cn_loop"])
    variants["cn_loop"] = base
    for name in list(rates)[1:]:
        v = summarize(work[name])
        v["added_p50_us"] = round(v["p50_us"] - base["p50_us"], 2)
        v["added_p99_us"] = round(v["p99_us"] - base["p99_us"], 2)
        hl = np.asarray(hloops[name], dtype=np.int64)
        sa = np.asarray(samples[name], dtype=np.int64)
        v["health_loops"] = int(hl.size)
        v["health_loop_p50_us"] = round(float(np.percentile(hl, 50)) / 1e3, 2) if hl.size else None
        v["health_loop_max_us"] = round(float(hl.max()) / 1e3, 2) if hl.size else None
        v["samples_taken"] = int(sa.size)
        v["sample_p50_us"] = round(float(np.percentile(sa, 50)) / 1e3, 1) if sa.size else None
        v["sample_max_us"] = round(float(sa.max()) / 1e3, 1) if sa.size else None
        variants[name] = v
    write_result(
        "health",
        {
            "mission": "recovery_igniter",
            "loop_hz": m.loop_hz,
            "seconds_per_run": seconds,
            "rounds": rounds,
            "warmup_loops": warm,
        },
        variants,
        args.json,
    )


if __name__ == "__main__":
    main()
