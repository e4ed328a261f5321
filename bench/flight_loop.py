"""What the flight software costs the control node's loop: its logic step, EKF and controllers.

The flight mission (``configs/flight.yaml``) flies its script in the
lockstep runner (the same :class:`~zplatform.control.loop.ControlLogic` a live CN
runs), and every loop's logic step, :meth:`~zplatform.control.loop.ControlLogic.finish`
(faults, commands, state machine, controllers, telemetry framing), is timed
with ``perf_counter_ns``, as is each flight controller's own ``run_enabled``
(EKF, flight events, airbrakes). The recovery igniter mission's logic step
(no EKF, no airbrakes) is the baseline. Figures: ``p50_us``, ``p99_us``,
``max_us`` over the loops where the part ran, ``msgs`` (samples),
``cpu_pct`` (mean time over the 10 ms period: the share of one core the
part takes at 100 Hz), ``vs_baseline_p50`` for the flight's logic step.
Only the CN's logic is timed: the sync exchange is the other benchmarks'.

Takes about 10 s. Run ``python -m bench.flight_loop [--quick] [--json
PATH]``; results go to ``bench/results/flight_loop.json``.
"""

from __future__ import annotations

import gc
import time
from collections.abc import Callable
from typing import Any

from bench.common import REPO_ROOT, bench_argparser, summarize, write_result
from zplatform import LockstepRunner, load_mission
from zplatform.control.uplink import load_commands

CONFIGS = REPO_ROOT / "configs"


def _timed(fn: Callable[..., Any], samples: list[int]) -> Callable[..., Any]:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter_ns()
        out = fn(*args, **kwargs)
        samples.append(time.perf_counter_ns() - t0)
        return out

    return wrapper


def measure(
    mission: str, script: str, seconds: float, parts: tuple[str, ...]
) -> dict[str, list[int]]:
    """Fly ``mission`` in lockstep; the logic step's and ``parts``' (controller
    names) durations in ns, one sample per loop they ran in."""
    m = load_mission(CONFIGS / mission)
    r = LockstepRunner(m, commands=load_commands(CONFIGS / script))
    out: dict[str, list[int]] = {"logic_step": []}
    cn = r.control
    cn.finish = _timed(cn.finish, out["logic_step"])  # type: ignore[method-assign]
    for c in cn.controllers.controllers:
        if c.name in parts:
            out[c.name] = []
            c.run_enabled = _timed(c.run_enabled, out[c.name])  # type: ignore[method-assign]
    gc.collect()
    gc.disable()
    try:
        r.run(seconds)
    finally:
        gc.enable()
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = bench_argparser(__doc__.splitlines()[0] if __doc__ else "flight_loop")
    args = ap.parse_args(argv)
    seconds = 20.0 if args.quick else 60.0
    period_ns = 10_000_000
    flight = measure("flight.yaml", "flight.commands", seconds, ("ekf", "events", "airbrakes"))
    base = measure("recovery_igniter.yaml", "recovery_igniter.commands", seconds, ())
    variants: dict[str, dict[str, Any]] = {}
    for prefix, samples in (("flight", flight), ("recovery_igniter", base)):
        for part, ns in samples.items():
            fig = summarize(ns)
            fig["cpu_pct"] = round(100.0 * sum(ns) / len(ns) / period_ns, 3) if ns else None
            variants[f"{prefix}_{part}"] = fig
    b = variants["recovery_igniter_logic_step"]["p50_us"]
    f = variants["flight_logic_step"]["p50_us"]
    if b and f:
        variants["flight_logic_step"]["vs_baseline_p50"] = round(f / b, 2)
    params = {
        "virtual_seconds": seconds,
        "loop_hz": 100,
        "timer": "perf_counter_ns around ControlLogic.finish and each controller's run_enabled",
        "gc": "disabled while timing",
    }
    return write_result("flight_loop", params, variants, args.json)


if __name__ == "__main__":
    main()
