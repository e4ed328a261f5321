"""What recording costs the CN's loop (``up --record``, ``zplatform replay``).

Two variants run interleaved in one process on the led_test mission, fed the
same frames (the DN replies and a command frame every 100th loop, made once
by a lockstep run): the CN's loop (``ControlLogic.begin``, ``reply`` per DN,
``finish``) without a recorder, and with a :class:`zplatform.Recorder`
writing to a temporary directory. The loop here is the CN's own work
without the network; it is what recording adds to, so the difference is the
recording's cost. ``time.perf_counter_ns`` around each loop, gc off while
timing, after a warm-up. Also reported: loops the recorder dropped (must be
0) and bytes written per loop.

Run ``python -m bench.record [--quick] [--json PATH]``; results go to
``bench/results/record.json``.
"""

from __future__ import annotations

import gc
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.common import bench_argparser, summarize, write_result
from zplatform import ControlLogic, LockstepRunner, Recorder, load_mission
from zplatform.config import Mission
from zplatform.control.uplink import load_commands
from zplatform.sim.lockstep import sim_keys

ROOT = Path(__file__).resolve().parents[1]
MISSION = ROOT / "configs" / "led_test.yaml"


def loop_inputs(
    m: Mission, loops: int, commands: Path | None = None
) -> list[tuple[int, int, list[bytes], list[bytes]]]:
    """(loop, t, replies, grounds) of ``loops`` loops of a lockstep run of
    ``m`` (playing the script ``commands``), captured once (``bench.health``
    and ``bench.recorder`` feed them too)."""
    r = LockstepRunner(m, commands=load_commands(commands) if commands is not None else None)
    out: list[tuple[int, int, list[bytes], list[bytes]]] = []
    captured: list[bytes] = []
    cn = r.control

    class Tap:
        def begin(self, loop: int, t_ns: int, final: bool, standby: bool = False) -> None:
            captured.clear()

        def reply(self, i: int, payload: Any) -> None:
            captured.append(bytes(payload))

        def foreign(self, source: str) -> None:
            pass  # a lockstep run has no foreign repliers

        def health(self, block: Any) -> None:
            pass  # a lockstep run without health ports copies none

        def finish(self, grounds: Any, *a: Any) -> None:
            loop, t = cn.loop, cn.t_ns
            out.append((loop, t, list(captured), [bytes(g) for g in grounds]))

    cn.recorder = Tap()
    for _ in range(loops):
        r.step()
    return out


def _run(
    inputs: list[tuple[int, int, list[bytes], list[bytes]]], record_dir: Path | None
) -> tuple[list[int], Recorder | None]:
    m = load_mission(MISSION)
    cn = ControlLogic(m, keys=sim_keys(m), epoch=1)
    rec = Recorder(record_dir, m, MISSION, cn.dv) if record_dir is not None else None
    cn.recorder = rec
    samples: list[int] = []
    clock = time.perf_counter_ns
    gc.disable()
    try:
        for loop, t, replies, grounds in inputs:
            t0 = clock()
            cn.begin(loop, t)
            for i, p in enumerate(replies):
                cn.reply(i, p)
            cn.finish(grounds)
            samples.append(clock() - t0)
    finally:
        gc.enable()
        if rec is not None:
            rec.close()
    return samples, rec


def main() -> None:
    args = bench_argparser(__doc__.splitlines()[0]).parse_args()
    loops = 2_000 if args.quick else 20_000
    rounds = 2 if args.quick else 5
    inputs = loop_inputs(load_mission(MISSION), loops)
    plain: list[int] = []
    recorded: list[int] = []
    dropped = 0
    written = 0
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(rounds):  # interleaved: drift on the box hits both alike
            s, _ = _run(inputs, None)
            plain += s[loops // 10 :]
            d = Path(tmp) / f"r{k}"
            s, rec = _run(inputs, d)
            recorded += s[loops // 10 :]
            assert rec is not None
            dropped += rec.dropped_loops
            written += (d / "cn.zrec").stat().st_size
    a, b = summarize(plain), summarize(recorded)
    b["vs_plain_p50"] = round(b["p50_us"] / a["p50_us"], 3)
    b["added_p50_us"] = round(b["p50_us"] - a["p50_us"], 2)
    b["dropped_loops"] = dropped
    b["bytes_per_loop"] = round(written / (rounds * loops), 1)
    write_result(
        "record",
        {"mission": "led_test", "loops": loops, "rounds": rounds},
        {"cn_loop": a, "cn_loop_recording": b},
        args.json,
    )


if __name__ == "__main__":
    main()
