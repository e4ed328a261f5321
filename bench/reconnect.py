"""Reconnect after a stop: how soon a peer stopped past its lease gets data again.

Three zenoh peers in processes of their own, their sessions built by
:func:`zplatform.runtime.transport.zenoh_config` from ``configs/minimal.yaml`` on
free ports and plain TCP (``dn0`` and ``gn`` connect to ``cn``; gossip
introduces ``gn`` and ``dn0``): ``cn`` publishes a stamp
(``CLOCK_MONOTONIC``, shared by the host's processes) every 10 ms, as a
commander publishes its mirror; ``gn`` subscribes, as the standby does;
``dn0`` is the third peer whose gossip tells ``cn`` about ``gn``. Each
trial SIGSTOPs ``gn`` until ``cn``'s publisher matches no subscriber (the
1 s lease ran out: ``cn`` closed its session with it), at least ``--stop-s``,
SIGCONTs it, and measures from the SIGCONT to the
first sample published after it that ``gn`` receives (``reconnect``); a
trial with none within ``--give-up-s`` is ``lost`` (the split session of
eclipse-zenoh/zenoh#2806 never heals by itself). ``sessions_closed``: the
trials in which ``cn`` saw ``gn``'s subscriber go (the others, if any,
measured no reconnect).

Variants (one set of processes each, ``--trials`` trials):

* ``one_way``: the configs as the platform makes them: ids ordered by the
  connect lists, gossip autoconnect ``greater-zid`` (``gn`` dials ``cn``,
  never ``cn`` ``gn``);
* ``both_ways``: the same with gossip's ``autoconnect_strategy`` ``always``
  (what the platform ran before issue 25): ``cn`` dials ``gn`` too.

``python -m bench.reconnect [--quick] [--json PATH]``: JSON (``reconnect``
p50/max in ``*_us``, ``lost``, ``trials``) and the usual table.
"""

from __future__ import annotations

import json
import os
import queue
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from bench.common import REPO_ROOT, bench_argparser, summarize, write_result

VARIANTS = ("one_way", "both_ways")
ROLES = ("cn", "dn0", "gn")
PERIOD_S = 0.01


def _mission(tmp: Path) -> Path:
    from zplatform.runtime.transport import rewrite_endpoints

    path = tmp / "minimal.yaml"
    rewrite_endpoints(REPO_ROOT / "configs" / "minimal.yaml", path)
    raw = yaml.safe_load(path.read_text())
    raw.setdefault("security", {})["transport"] = "plain"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def child(role: str, mission_path: str, variant: str) -> None:
    """One peer (module doc); prints ``ready``, then (``gn``) one line per
    sample: ``<receipt ns> <stamp ns>``; (``cn``) one per change of its
    publisher's matching status (``gn``'s subscriber): ``<ns> 1|0``. Ends when stdin closes."""
    import zenoh

    from zplatform.mission.load import load_mission
    from zplatform.runtime.transport import open_session, zenoh_config

    m = load_mission(mission_path)
    cfg = zenoh_config(m, role)
    if variant == "both_ways":
        cfg.insert_json5("scouting/gossip/autoconnect_strategy", json.dumps("always"))
    s = open_session(cfg)
    key = "bench/reconnect/mirror"
    out: queue.SimpleQueue[tuple[int, int]] = queue.SimpleQueue()
    if role == "gn":

        def on_sample(sample: zenoh.Sample) -> None:  # hand off only
            out.put((time.monotonic_ns(), int.from_bytes(sample.payload.to_bytes(), "little")))

        s.declare_subscriber(key, zenoh.handlers.Callback(on_sample, indirect=False))
    pub = s.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
    if role == "cn":  # whether the stop closed the session: gn's subscriber goes

        def on_matching(status: zenoh.MatchingStatus) -> None:  # hand off only
            out.put((time.monotonic_ns(), int(status.matching)))

        pub.declare_matching_listener(zenoh.handlers.Callback(on_matching, indirect=False))
    print("ready", flush=True)
    while not select.select([sys.stdin], [], [], 0)[0]:
        if role == "cn":
            pub.put(time.monotonic_ns().to_bytes(8, "little"))
        while not out.empty():
            t, stamp = out.get()
            print(t, stamp, flush=True)
        time.sleep(PERIOD_S)  # the publishing period
    s.close()


class Peers:
    def __init__(self, mission: Path, variant: str) -> None:
        self.procs: dict[str, subprocess.Popen[str]] = {}
        for role in ROLES:
            self.procs[role] = subprocess.Popen(
                [sys.executable, "-m", "bench.reconnect", "--child", role, str(mission), variant],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
                cwd=REPO_ROOT,
            )
            assert self.line(role, 30) == "ready"

    def line(self, role: str, timeout_s: float) -> str | None:
        p = self.procs[role]
        assert p.stdout is not None
        if not select.select([p.stdout], [], [], timeout_s)[0]:
            return None
        return p.stdout.readline().strip()

    def fresh_after(self, t0_ns: int, timeout_s: float) -> int | None:
        """The receipt time of the first sample ``gn`` gets that was published after ``t0_ns``."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            line = self.line("gn", left)
            if not line:
                return None
            t, stamp = (int(x) for x in line.split())
            if stamp >= t0_ns:
                return t
        return None

    def close(self) -> None:
        for p in self.procs.values():
            os.kill(p.pid, signal.SIGCONT)
            if p.stdin is not None:
                p.stdin.close()
        for p in self.procs.values():
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def run_variant(variant: str, trials: int, stop_s: float, give_up_s: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="zp-reconnect-") as td:
        peers = Peers(_mission(Path(td)), variant)
        samples: list[int] = []
        lost = closed = 0
        try:
            gn = peers.procs["gn"]
            for _ in range(trials):
                # Flowing first (a lost trial before: wait for the flow longer).
                if peers.fresh_after(time.monotonic_ns(), give_up_s) is None:
                    lost += 1
                    continue
                t_stop = time.monotonic()
                os.kill(gn.pid, signal.SIGSTOP)
                # Stopped until cn's session with gn closed (no subscriber matches).
                while (line := peers.line("cn", give_up_s)) is not None:
                    if line.endswith(" 0"):
                        closed += 1
                        break
                time.sleep(max(0.0, stop_s - (time.monotonic() - t_stop)))  # the stop lasts
                t_cont = time.monotonic_ns()
                os.kill(gn.pid, signal.SIGCONT)
                t = peers.fresh_after(t_cont, give_up_s)
                if t is None:
                    lost += 1
                else:
                    samples.append(t - t_cont)
        finally:
            peers.close()
    v = summarize(samples)
    v.update(trials=trials, lost=lost, sessions_closed=closed, stop_s=stop_s, give_up_s=give_up_s)
    return v


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        child(*argv[1:4])
        return
    p = bench_argparser(__doc__.splitlines()[0] if __doc__ else "reconnect")
    p.add_argument("--trials", type=int, default=None, help="stops per variant (20; --quick 3)")
    p.add_argument("--stop-s", type=float, default=1.0, help="least seconds stopped")
    p.add_argument("--give-up-s", type=float, default=10.0, help="a trial without data: lost")
    p.add_argument("--variant", action="append", choices=VARIANTS, help="only this variant")
    args = p.parse_args(argv)
    trials = args.trials if args.trials is not None else (3 if args.quick else 20)
    variants = {
        v: run_variant(v, trials, args.stop_s, args.give_up_s) for v in args.variant or VARIANTS
    }
    params = {
        "command": " ".join(["python -m bench.reconnect", *argv]),
        "trials": trials,
        "stop_s": args.stop_s,
        "give_up_s": args.give_up_s,
        "loadavg_after": os.getloadavg(),
    }
    write_result("reconnect", params, variants, args.json)


if __name__ == "__main__":
    main()
