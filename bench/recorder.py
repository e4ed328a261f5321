"""What the flight recorder costs the control node's loop, and what it writes per loop.

Three variants run interleaved (round robin, so drift on the shared box hits
each alike) in one process on the flight mission (``configs/flight.yaml``,
which turns the recorder on), fed the same inputs: the DN replies and
command frames of a lockstep run of its script, made once. Each loop is the
CN's own work as the runtime does it (``ControlLogic.begin``, ``reply`` per
DN, ``finish``), paced at the mission's 100 Hz so the recorder's writer
thread runs in the slack as it does live, timed with ``perf_counter_ns``
(gc off while timing):

* ``cn_loop``: no recorder;
* ``cn_loop_recording``: the flight recorder as the CN runs it
  (:func:`zplatform.recorder.open_recorder` with the mission's section: the
  telemetry frame copied into its buffer and its counters brought up to date
  each loop; its writer thread writing and fsyncing every 500 ms);
* ``cn_loop_recording_serving``: the same while the recorder's gap-fill
  server answers an asker that asks again the moment an answer ends (the
  last 1000 loops each time: a hostile or a very unlucky ground), over an
  in-process zenoh session, paced at the mission's ``serve_bps``.

Figures: the loop's ``p50_us``, ``p99_us``, ``max_us``; against the plain
loop ``added_p50_us``, ``added_p99_us``; ``recorder_calls_p50_us``/``_p99_us``,
the recorder's own calls in the loop (``tick`` and ``frame``) timed alone,
which the load of a shared box blurs less; ``bytes_per_loop`` (the recorder's
files over the loops kept), ``dropped_loops`` (must be 0), and for the
serving variant ``served_frames``. Writes go to a temporary directory
(``params.storage`` says which filesystem).

Takes about ``3 * rounds * loops / 100`` seconds (about 4.5 min; ``--quick``
about 15 s). Run ``python -m bench.recorder [--quick] [--json PATH]``;
results go to ``bench/results/recorder.json``.
"""

from __future__ import annotations

import gc
import os
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from bench.common import REPO_ROOT, bench_argparser, summarize, write_result
from bench.record import loop_inputs
from zplatform import ControlLogic, load_mission
from zplatform.core.auth import channel
from zplatform.ground.logic import default_max_age_ns
from zplatform.recorder import RECORDER_DIR_ENV, open_recorder
from zplatform.recorder.format import REQUEST, REQUEST_MAGIC
from zplatform.recorder.server import RecorderServer
from zplatform.sim.lockstep import sim_keys

MISSION = REPO_ROOT / "configs" / "flight.yaml"
COMMANDS = REPO_ROOT / "configs" / "flight.commands"
KEYEXPR = "bench/cn/recorder"
EPOCH = 1


class _Asker:
    """Asks the recorder for the last 1000 loops, again as soon as each answer ends."""

    def __init__(self, session: zenoh.Session, mission: Any, now: Any) -> None:
        self.session = session
        self.channel = channel(sim_keys(mission), "telemetry")
        self.now = now
        self.loop = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            last = self.loop - 1
            if last < 2:
                time.sleep(0.01)
                continue
            body = REQUEST.pack(REQUEST_MAGIC, EPOCH, max(1, last - 999), last, self.now())
            assert self.channel is not None
            for _ in self.session.get(
                KEYEXPR,
                payload=bytes(self.channel.seal(body)),
                timeout=10,
                consolidation=zenoh.ConsolidationMode.NONE,
            ):
                pass


def _run(
    inputs: list[tuple[int, int, list[bytes], list[bytes]]],
    variant: str,
    directory: Path,
    period_s: float,
) -> tuple[list[int], dict[str, Any]]:
    m = load_mission(MISSION)
    keys = sim_keys(m)
    cn = ControlLogic(m, keys=keys, epoch=EPOCH)
    rec = server = asker = session = None
    if variant != "cn_loop":
        os.environ[RECORDER_DIR_ENV] = str(directory)
        rec = open_recorder(m, "cn", cn.dv, run=EPOCH, authenticated=True)
        rec.attach(cn.dv, cn.events)
    if variant == "cn_loop_recording_serving":
        assert rec is not None and m.recorder is not None
        cfg = zenoh.Config()
        cfg.insert_json5("scouting/multicast/enabled", "false")
        session = zenoh.open(cfg)
        server = RecorderServer(
            session,
            KEYEXPR,
            rec,
            channel(keys, "telemetry"),
            now_ns=time.time_ns,
            max_age_ns=default_max_age_ns(m),
            serve_bps=m.recorder.serve_bps,
        )
        asker = _Asker(session, m, time.time_ns)
    samples: list[int] = []
    own: list[int] = []  # the recorder's calls alone
    clock = time.perf_counter_ns
    nxt = time.perf_counter()
    gc.disable()
    try:
        for loop, t, replies, grounds in inputs:
            nxt += period_s
            t0 = clock()
            if rec is not None:
                rec.tick(t)
            t1 = clock()
            cn.begin(loop, t)
            for i, p in enumerate(replies):
                cn.reply(i, p)
            tm = cn.finish(grounds)
            t2 = clock()
            if rec is not None and tm is not None:
                rec.frame(loop, tm, t)
            t3 = clock()
            samples.append(t3 - t0)
            if rec is not None:
                own.append(t1 - t0 + t3 - t2)
            cn.events.drain()
            if asker is not None:
                asker.loop = loop
            delay = nxt - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
    finally:
        gc.enable()
        if asker is not None:
            asker.stop.set()
        if server is not None:
            server.close()
        if asker is not None:
            asker.thread.join(15)
        if session is not None:
            session.close()
        if rec is not None:
            rec.close()
    figures: dict[str, Any] = {"own": own}
    if rec is not None:
        files = list((directory / m.mission / "cn").glob("seg-*.zfr"))
        figures["bytes"] = sum(f.stat().st_size for f in files)
        figures["loops"] = rec.loops
        figures["dropped_loops"] = rec.dropped
    if server is not None:
        figures["served_frames"] = server.frames_sent
    return samples, figures


def _storage(path: str) -> str:
    try:
        out = subprocess.run(
            ["stat", "-f", "-c", "%T", path], capture_output=True, text=True, check=True
        )
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> None:
    args = bench_argparser(__doc__.splitlines()[0]).parse_args()
    loops = 500 if args.quick else 3000
    rounds = 1 if args.quick else 3
    m = load_mission(MISSION)
    inputs = loop_inputs(m, loops, COMMANDS)
    period_s = m.period_ns / 1e9
    variants = ("cn_loop", "cn_loop_recording", "cn_loop_recording_serving")
    samples: dict[str, list[int]] = {v: [] for v in variants}
    totals: dict[str, dict[str, int]] = {v: {} for v in variants}
    own: dict[str, list[int]] = {v: [] for v in variants}
    with tempfile.TemporaryDirectory() as tmp:
        storage = _storage(tmp)
        for k in range(rounds):
            for v in variants:
                s, fig = _run(inputs, v, Path(tmp) / f"{v}-{k}", period_s)
                samples[v] += s[loops // 10 :]  # past the warm-up
                own[v] += fig.pop("own")[loops // 10 :]
                for name, value in fig.items():
                    totals[v][name] = totals[v].get(name, 0) + value
    out: dict[str, dict[str, Any]] = {}
    base = summarize(samples["cn_loop"])
    out["cn_loop"] = base
    for v in variants[1:]:
        f = summarize(samples[v])
        f["added_p50_us"] = round(f["p50_us"] - base["p50_us"], 2)
        f["added_p99_us"] = round(f["p99_us"] - base["p99_us"], 2)
        mine = summarize(own[v])
        f["recorder_calls_p50_us"] = mine["p50_us"]
        f["recorder_calls_p99_us"] = mine["p99_us"]
        t = totals[v]
        f["dropped_loops"] = t.get("dropped_loops", 0)
        f["bytes_per_loop"] = round(t["bytes"] / max(t["loops"], 1), 1)
        if "served_frames" in t:
            f["served_frames"] = t["served_frames"]
        out[v] = f
    assert m.recorder is not None
    write_result(
        "recorder",
        {
            "mission": "flight",
            "loops": loops,
            "rounds": rounds,
            "loop_hz": m.loop_hz,
            "fsync_ms": m.recorder.fsync_ms,
            "serve_bps": m.recorder.serve_bps,
            "storage": storage,
        },
        out,
        args.json,
    )


if __name__ == "__main__":
    main()
