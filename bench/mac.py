"""The cost of a frame's tag: keyed BLAKE3 against HMAC-SHA256, and signatures.

    python -m bench.mac [--quick] [--json PATH]
    python -m bench.mac --full-size [--quick]   # refusing full-size junk and replays

Per MAC (``security.mac``) and frame size (a 256 B region frame, a 325 KB
reply: the 100,000-element point of ``bench.bandwidth``), the time of
:meth:`zplatform.core.auth.Channel.seal` (what a sender adds) and of
:meth:`~zplatform.core.auth.Channel.open` (what a receiver adds), as the
platform calls them: one channel, its buffer and BLAKE3 hasher reused
(reset per frame). Baselines: a plain copy of the frame (``seal`` copies
it once), and, for the report's argument about telemetry to many grounds,
Ed25519 signing and verifying the same bytes (the ``cryptography``
package, the ``bench`` extra; its rows are left out without it).

Figures per variant: ``p50_us``, ``p99_us``, ``max_us`` (each timed call),
``ns_per_frame`` (the least of ten tight-loop means) and
``gb_per_s``. Results: ``bench/results/mac.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import os
import statistics
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from bench.common import REPO_ROOT, bench_argparser, summarize, write_result
from zplatform.core.auth import MACS, Channel

SIZES = {"256B": 256, "325KB": 325_000}
ITERATIONS = {"256B": 200_000, "325KB": 2_000}
KEY = bytes.fromhex("3f8a1c9e27d45b60f1e83a97c2d0456b8e19f7a3c5d2e0b4a6918f3c7e25d0b1")


def _measure(fn: Callable[[], object], n: int) -> dict[str, Any]:
    """Per-call samples (for p50/p99) and a tight loop's mean (for ns/frame)."""
    for _ in range(min(n, 1000)):  # warm caches and the allocator
        fn()
    clock = time.perf_counter_ns
    samples = [0] * n
    gc.disable()
    try:
        for i in range(n):
            t0 = clock()
            fn()
            samples[i] = clock() - t0
        # The least of 10 tight-loop means: the shared box's bursts of other
        # work lengthen some rounds, never shorten one.
        best = None
        rounds = max(n // 10, 5)
        for _ in range(10):
            t0 = clock()
            for _ in range(rounds):
                fn()
            mean = (clock() - t0) / rounds
            best = mean if best is None else min(best, mean)
    finally:
        gc.enable()
    out = summarize(samples)
    out["ns_per_frame"] = round(best or 0.0, 1)
    return out


def _copy(buf: bytearray, frame: bytearray) -> None:
    buf[:] = frame


def _ed25519() -> tuple[Any, Any] | None:
    try:
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    except ImportError:
        return None
    sk = Ed25519PrivateKey.from_private_bytes(KEY)
    return sk, sk.public_key()


# -- the cost of refusing a frame, stage by stage (--refusal) -------------------------

REFUSAL_SIZES = {"trigger": 0, "64KB": 65_536}
"""The refused frames' sizes: a trigger of the flight mission (``cn_to_dn0``,
tag included: filled in at run time) and a 64 KiB frame."""
REFUSAL_RATE = 2000
REFUSAL_FRAMES = 4000


def _refusal_setup() -> tuple[Any, Any, int]:
    """The flight mission, dn0's keys, and the size of its trigger frame."""
    from zplatform.control.intake import max_frame_len
    from zplatform.core.auth import KeySet
    from zplatform.core.datavector import Layout
    from zplatform.mission.load import load_mission

    m = load_mission(REPO_ROOT / "configs" / "flight.yaml")
    keys = KeySet.from_master(m, KEY)
    ch = keys.channel("cn_to_dn0")
    size = max_frame_len(Layout.for_node(m, "cn").region("cn_to_dn0").size, ch)
    return m, keys, size


class _FakeQuery:
    """What an intake or server reads of a zenoh query, without zenoh."""

    __slots__ = ("payload",)

    def __init__(self, payload: Any) -> None:
        self.payload = payload

    def drop(self) -> None:
        pass

    def reply_err(self, _p: bytes) -> None:
        pass


def refusal_stages(quick: bool) -> dict[str, dict[str, Any]]:
    """In process (no transport): each stage a refused frame may cost, as
    the intakes call it, on a junk frame of each size."""
    import zenoh

    from zplatform.control.intake import TriggerIntake
    from zplatform.runtime.clocksync import ClockResponder

    m, keys, trig = _refusal_setup()
    n = 2_000 if quick else 20_000
    out: dict[str, dict[str, Any]] = {}
    for label, size in REFUSAL_SIZES.items():
        size = size or trig
        junk = os.urandom(size)
        zb = zenoh.ZBytes(junk)
        ch = keys.channel("cn_to_dn0")
        intake: TriggerIntake[None] = TriggerIntake(m, "dn0", keys.channel("cn_to_dn0"))
        big = max(trig, size)
        intake.max_len = big  # a 64 KiB junk frame reaches the tag check
        stages: dict[str, Callable[[], object]] = {
            "zbytes_len": partial(len, zb),
            "zbytes_to_bytes": zb.to_bytes,
            "channel_open_junk": partial(_open_junk, ch, junk),
            "intake_check_junk": partial(intake.check, zb, None),
        }
        if label == "trigger":
            resp = ClockResponder(m, keys)
            stages["clock_answer_junk"] = partial(resp.answer, junk, 0, 0)
        for stage, fn in stages.items():
            fig = _measure(fn, n)
            fig["size_bytes"] = size
            out[f"{stage}_{label}"] = fig
    return out


FULL_SIZES = {"325KB": 325_000, "4MB": 4_000_000}
"""Full-size frames (a 100,000-element reply, the largest region frame) for
:func:`full_size_refusal`."""


def full_size_refusal(quick: bool) -> dict[str, dict[str, Any]]:
    """In process: what refusing a full-size junk frame and a replayed
    genuine one costs the receiver, before (the MAC over the body, which
    every refusal paid until the header tag: ``body_mac_*``) and now
    (``TriggerIntake.check_view`` of the frame in place: the header tag,
    the freshness of its header; ``junk``: random bytes, ``forged``: a
    well-formed newer frame with the run word and a random rest of tag, a
    keyless peer's best; ``replay``: a genuine frame again;
    ``check_zbytes_*``: ``TriggerIntake.check``
    of a ``zenoh.ZBytes``, whose ``to_bytes`` copy, zenoh-python's only way
    to read a payload, comes first). Per MAC (``security.mac``)."""
    import zenoh

    from zplatform.control.intake import TriggerIntake
    from zplatform.core.auth import RUN_LEN, TAG_LEN, AuthError, KeySet
    from zplatform.core.codec import encode_frame

    m, _, _ = _refusal_setup()
    n = 200 if quick else 2_000
    out: dict[str, dict[str, Any]] = {}
    for mac in MACS:
        m.security.mac = mac
        keys = KeySet.from_master(m, KEY)
        for label, size in FULL_SIZES.items():
            send = keys.channel("cn_to_dn0")
            genuine = bytes(send.seal(encode_frame(1, 1, 1_700_000_000_000_000_000, bytes(size))))
            junk = os.urandom(len(genuine))
            # A keyless peer's best: a well-formed newer frame (its header
            # copied off the wire, the run word too), the rest of its tag random.
            forged = bytes(send.seal(encode_frame(1, 2, 1_700_000_000_000_000_001, bytes(size))))
            forged = forged[: len(forged) - TAG_LEN + RUN_LEN] + os.urandom(TAG_LEN - RUN_LEN)
            intake: TriggerIntake[None] = TriggerIntake(
                m, "dn0", keys.channel("cn_to_dn0"), now_ns=lambda: 1_700_000_000_000_000_000
            )
            intake.max_len = len(genuine)  # a full-size frame reaches the tag check
            assert intake.check(zenoh.ZBytes(genuine), None) is not None
            recv = keys.channel("cn_to_dn0")

            def body_mac(ch: Any = recv, frame: bytes = junk) -> None:
                with contextlib.suppress(AuthError):
                    ch.check_body(frame)

            jv, gv, fv = memoryview(junk), memoryview(genuine), memoryview(forged)
            stages: dict[str, Callable[[], object]] = {
                "body_mac": body_mac,
                "check_view_junk": partial(intake.check_view, jv, None),
                "check_view_forged": partial(intake.check_view, fv, None),
                "check_view_replay": partial(intake.check_view, gv, None),
                "check_zbytes_junk": partial(intake.check, zenoh.ZBytes(junk), None),
                "check_zbytes_forged": partial(intake.check, zenoh.ZBytes(forged), None),
                "check_zbytes_replay": partial(intake.check, zenoh.ZBytes(genuine), None),
            }
            for stage, fn in stages.items():
                fig = _measure(fn, n)
                fig["size_bytes"] = len(genuine)
                out[f"{mac}_{stage}_{label}"] = fig
            size_, bad, stale = intake.take_counts()
            assert size_ == 0 and bad > 0 and stale > 0, (size_, bad, stale)
    return out


def _open_junk(ch: Any, junk: bytes) -> None:
    from zplatform.core.auth import AuthError

    with contextlib.suppress(AuthError):
        ch.open(junk)


def _victims(m: Any, keys: Any, session: Any, key: str) -> dict[str, Callable[[], Any]]:
    """Per live variant, a function that declares the queryable under test
    on ``key`` and returns what to undeclare/close."""
    import queue
    import threading

    import zenoh

    from zplatform.control.intake import TriggerIntake
    from zplatform.runtime.clocksync import ClockServer

    def plain(cb: Callable[[Any], None]) -> Callable[[], Any]:
        return lambda: session.declare_queryable(key, zenoh.handlers.Callback(cb, indirect=False))

    def floor(q: Any) -> None:
        _ARRIVED.append(1)

    def length(q: Any) -> None:
        _ARRIVED.append(len(q.payload))

    def copy(q: Any) -> None:
        _ARRIVED.append(len(q.payload.to_bytes()))

    ch = keys.channel("cn_to_dn0")

    def tag(q: Any) -> None:
        _ARRIVED.append(1)
        _open_junk(ch, q.payload.to_bytes())

    def reply_err(q: Any) -> None:
        _ARRIVED.append(1)
        q.reply_err(b"refused")

    intake: TriggerIntake[Any] = TriggerIntake(m, "dn0", keys.channel("cn_to_dn0"))
    intake.max_len = 1 << 20

    def trigger_intake(q: Any) -> None:
        _ARRIVED.append(1)
        p = q.payload
        intake.admit(p, q)

    handoff: queue.Queue[Any] = queue.Queue(64)

    def thread_handoff(q: Any) -> None:
        _ARRIVED.append(1)
        with contextlib.suppress(queue.Full):
            handoff.put_nowait(q)

    def drain() -> None:
        while (q := handoff.get()) is not None:
            with q:
                _open_junk(ch, q.payload.to_bytes())
                q.reply_err(b"refused")

    def threaded() -> Any:
        t = threading.Thread(target=drain, daemon=True)
        t.start()
        qa = session.declare_queryable(key, zenoh.handlers.Callback(thread_handoff, indirect=False))

        class _Close:
            def undeclare(self) -> None:
                qa.undeclare()
                handoff.put(None)
                t.join(2)

        return _Close()

    def clock_server() -> Any:
        from zplatform.runtime.transport import KeySpace

        ks = KeySpace(m.vehicle)
        server = ClockServer(session, ks, time.time_ns, m, keys)
        server.queryable.undeclare()  # the same server, counted, on the bench's key
        orig = server.on_query

        def counted(q: Any) -> None:
            _ARRIVED.append(1)
            orig(q)

        server.queryable = session.declare_queryable(
            key, zenoh.handlers.Callback(counted, indirect=False)
        )

        class _Close:
            def undeclare(self) -> None:
                server.close()

        return _Close()

    def recorder_server() -> Any:
        from zplatform.recorder.server import RecorderServer

        rec: Any = None  # junk never reaches the files
        server = RecorderServer(
            session,
            key,
            rec,
            keys.for_node("cn").channel("telemetry"),
            now_ns=time.time_ns,
            max_age_ns=10**9,
            serve_bps=10**9,
        )
        server.queryable.undeclare()
        orig = server.on_query

        def counted(q: Any) -> None:
            _ARRIVED.append(1)
            orig(q)

        server.queryable = session.declare_queryable(
            key, zenoh.handlers.Callback(counted, indirect=False)
        )

        class _Close:
            def undeclare(self) -> None:
                server.close()

        return _Close()

    def fifo_thread() -> Any:
        # zenoh's own channel, drained by a Python thread: zenoh's threads
        # never take the GIL; the thread wakes per query (or per batch).
        qa = session.declare_queryable(key, zenoh.handlers.FifoChannel(256))

        def drain() -> None:
            for _q in qa:
                _ARRIVED.append(1)

        t = threading.Thread(target=drain, daemon=True)
        t.start()

        class _Close:
            def undeclare(self) -> None:
                qa.undeclare()
                t.join(2)

        return _Close()

    class _Nothing:
        def undeclare(self) -> None:
            pass

    return {
        "no_queryable": _Nothing,
        "zenoh_floor": plain(floor),
        "fifo_thread_floor": fifo_thread,
        "len": plain(length),
        "to_bytes": plain(copy),
        "to_bytes_tag": plain(tag),
        "reply_err": plain(reply_err),
        "thread_handoff_tag_reply_err": threaded,
        "trigger_intake": plain(trigger_intake),
        "clock_server": clock_server,
        "recorder_server": recorder_server,
    }


_ARRIVED: list[int] = []


REFUSAL_REPS = 3
"""Rounds of every live variant (round robin, so the shared box's load
spreads over all of them); the figure is the median round."""


def refusal_live(quick: bool) -> dict[str, dict[str, Any]]:
    """Over zenoh on loopback: a keyless attacker process sends junk gets
    at :data:`REFUSAL_RATE` a second; per variant of the victim's
    queryable (this process), the victim's CPU time per refused query
    beyond its idle CPU (``time.process_time``: every thread, zenoh's
    included), the median of :data:`REFUSAL_REPS` rounds."""
    import zenoh

    from bench.baselines import zenoh_config
    from bench.common import free_port

    m, keys, trig = _refusal_setup()
    frames = REFUSAL_FRAMES // (4 if quick else 1)
    reps = 1 if quick else REFUSAL_REPS
    port = free_port()
    session = zenoh.open(zenoh_config(listen_port=port, connect_port=None, lowlatency=False))
    key = "bench/refusal/victim"
    runs: dict[str, list[tuple[float, int, float]]] = {}
    sizes: dict[str, int] = {}
    try:
        t0, c0 = time.monotonic(), time.process_time()
        time.sleep(1.0)
        idle = (time.process_time() - c0) / (time.monotonic() - t0)  # CPU s per s
        for _ in range(reps):
            for label, size in REFUSAL_SIZES.items():
                size = size or trig
                for name, declare in _victims(m, keys, session, key).items():
                    got = _flood_once(name, declare, port, key, size, frames, idle)
                    runs.setdefault(f"live_{name}_{label}", []).append(got)
                    sizes[f"live_{name}_{label}"] = size
                    print(f"live_{name}_{label}: {got}", flush=True)
    finally:
        session.close()
    out: dict[str, dict[str, Any]] = {}
    for v, rounds in runs.items():
        cpu = statistics.median(r[0] for r in rounds)
        out[v] = {
            "size_bytes": sizes[v],
            "frames": statistics.median(r[1] for r in rounds),
            "rate_hz": statistics.median(r[2] for r in rounds),
            "cpu_us_per_frame": round(cpu, 1),
            "cpu_us_per_frame_rounds": [round(r[0], 1) for r in rounds],
            "cpu_pct_of_core_at_1khz": round(cpu / 10, 2),
        }
        if v.startswith("live_no_queryable"):
            out[v]["note"] = (
                "no queryable on the key: zenoh's receive and routing, over the "
                "attacker's whole life (its session's opening and closing too)"
            )
    return out


def _flood_once(
    name: str,
    declare: Callable[[], Any],
    port: int,
    key: str,
    size: int,
    frames: int,
    idle: float,
    rate: int = REFUSAL_RATE,
) -> tuple[float, int, float]:
    """One attacker's flood of one variant: ``(CPU us per query beyond
    idle, queries counted, their rate)``."""
    import subprocess
    import sys

    q = declare()
    _ARRIVED.clear()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "bench.mac",
            "--refusal-attacker",
            f"{port},{key},{size},{rate},{frames}",
        ],
        cwd=REPO_ROOT,
    )
    try:
        deadline = time.monotonic() + 30 + frames / rate
        if name == "no_queryable":  # nothing to count: the attacker's life
            t0, c0 = time.monotonic(), time.process_time()
            proc.wait(deadline - t0)
            t1, c1 = time.monotonic(), time.process_time()
            got = frames
        else:
            while not _ARRIVED and time.monotonic() < deadline:
                time.sleep(0.001)
            t0, c0 = time.monotonic(), time.process_time()
            n0 = n = len(_ARRIVED)
            while len(_ARRIVED) < frames and time.monotonic() < deadline:
                if proc.poll() is not None and len(_ARRIVED) == n:
                    break
                n = len(_ARRIVED)
                time.sleep(0.05)
            t1, c1 = time.monotonic(), time.process_time()
            got = len(_ARRIVED) - n0
    finally:
        proc.wait(30)
        q.undeclare()
    cpu = (c1 - c0) - idle * (t1 - t0)
    return (cpu / got * 1e6 if got else float("nan"), got, got / (t1 - t0) if t1 > t0 else 0.0)


LOOP_PERIOD_NS = 10_000_000
LOOP_WORK_S = 0.0003
LOOP_DEADLINE_NS = 2_000_000
LOOP_RATE = 6000


class _LoopProbe:
    """A 100 Hz loop thread in the victim's process, as the control node's:
    each period it sleeps until its start, then does :data:`LOOP_WORK_S` of
    Python work; a period whose wake-up lateness plus work exceeds
    :data:`LOOP_DEADLINE_NS` (the sync deadline) is a miss."""

    def __init__(self) -> None:
        import threading

        self.late: list[int] = []
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self) -> None:
        nxt = time.monotonic_ns() + LOOP_PERIOD_NS
        while not self._stop.is_set():
            ahead = nxt - time.monotonic_ns()
            if ahead > 0:
                time.sleep(ahead / 1e9)
            woke = time.monotonic_ns()
            end = time.perf_counter() + LOOP_WORK_S
            x = 0
            while time.perf_counter() < end:  # the loop's own Python work
                x += 1
            self.late.append(time.monotonic_ns() - nxt)
            nxt += LOOP_PERIOD_NS
            while nxt < woke:  # an overrun skips periods, as the scheduler does
                nxt += LOOP_PERIOD_NS

    def stop(self) -> list[int]:
        self._stop.set()
        self._t.join(2)
        return self.late


def refusal_loop(quick: bool) -> dict[str, dict[str, Any]]:
    """The control loop beside a flood (:class:`_LoopProbe`): per server
    (the clock's, the recorder's; a callback that does nothing; no
    queryable), a keyless attacker sends junk of the server's request
    length at :data:`LOOP_RATE` a second for 3 s; the loop's lateness (p50, p99, max)
    and its misses, the median of :data:`REFUSAL_REPS` rounds."""
    import struct

    import zenoh

    from bench.baselines import zenoh_config
    from bench.common import free_port
    from zplatform.core.auth import TAG_LEN
    from zplatform.recorder.format import REQUEST

    m, keys, _ = _refusal_setup()
    # Junk of exactly a clock query's length (codecs/FORMAT.md §6.3) and of
    # a recorder request's: each passes the size check and costs what follows.
    sizes = {
        "clock_server": struct.calcsize("<2sBB16sq") + TAG_LEN,
        "recorder_server": REQUEST.size + TAG_LEN,
    }
    port = free_port()
    session = zenoh.open(zenoh_config(listen_port=port, connect_port=None, lowlatency=False))
    key = "bench/refusal/victim"
    frames = LOOP_RATE * (1 if quick else 3)
    rounds: dict[str, list[dict[str, Any]]] = {}
    try:
        for _ in range(1 if quick else REFUSAL_REPS):
            victims = _victims(m, keys, session, key)
            for name in ("no_queryable", "zenoh_floor", "clock_server", "recorder_server"):
                size = sizes.get(name, sizes["clock_server"])
                probe = _LoopProbe()
                _flood_once(name, victims[name], port, key, size, frames, 0.0, LOOP_RATE)
                late = probe.stop()
                fig = summarize(late, LOOP_DEADLINE_NS)
                fig["loops"] = len(late)
                fig["missed"] = sum(x > LOOP_DEADLINE_NS for x in late)
                rounds.setdefault(f"loop_{name}", []).append(fig)
                print(f"loop_{name}: {fig}", flush=True)
    finally:
        session.close()
    out: dict[str, dict[str, Any]] = {}
    for v, figs in rounds.items():
        figs.sort(key=lambda f: f["missed"])
        med = dict(figs[len(figs) // 2])
        med["missed_rounds"] = [f"{f['missed']}/{f['loops']}" for f in figs]
        med["max_us_rounds"] = [f.get("max_us") for f in figs]
        out[v] = med
    return out


def refusal_attacker(spec: str) -> int:
    """The attacker process of :func:`refusal_live`: ``PORT,KEY,SIZE,RATE,N``."""
    import zenoh

    from bench.baselines import zenoh_config

    port, key, size, rate, n = spec.split(",")
    s = zenoh.open(zenoh_config(listen_port=None, connect_port=int(port), lowlatency=False))
    try:
        deadline = time.monotonic() + 10
        while not list(s.info.peers_zid()) and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)  # the victim's queryable declared to this session
        junk = os.urandom(int(size))
        every = 1.0 / float(rate)
        start = time.monotonic()
        for i in range(int(n)):
            ahead = start + i * every - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)
            s.get(
                key,
                handler=_ignore,
                payload=junk,
                congestion_control=zenoh.CongestionControl.BLOCK,
                timeout=1.0,
            )
        time.sleep(0.5)
    finally:
        s.close()
    return 0


def _ignore(_reply: Any) -> None:
    pass


def refusal_main(
    quick: bool, json_path: str | None, before: str | None = None, loop_only: bool = False
) -> int:
    variants = {} if loop_only else {**refusal_stages(quick), **full_size_refusal(quick)}
    if not loop_only:
        variants.update(refusal_live(quick))
    variants.update(refusal_loop(quick))
    params = {
        "quick": quick,
        "what": "the cost of refusing one junk frame. In process (p50/p99 per call): "
        "ZBytes len, to_bytes, Channel.open of junk, TriggerIntake.check of junk, "
        "ClockResponder.answer of junk. Live (cpu_us_per_frame): a keyless attacker "
        f"process sends junk gets at {REFUSAL_RATE}/s to a queryable in this process on "
        "loopback; the victim's process CPU per query beyond idle, for callbacks that do "
        "nothing (zenoh_floor: zenoh-python's dispatch, the Query object and its "
        "finalisation), len(payload), to_bytes, to_bytes + tag check, reply_err, a handoff "
        "to a thread that checks and replies an error (the clock server's shape at "
        "fe55771), the TriggerIntake, and the ClockServer itself",
        "command": "flock /tmp/zplatform-bench.lock python -m bench.mac --refusal",
    }
    if before:
        # The same bench run with fe55771's zplatform/runtime/clocksync.py and
        # zplatform/recorder/server.py checked out (the clock and recorder
        # servers as they were): each variant's figure, for the comparison.
        old = json.loads(Path(before).read_text())["variants"]
        params["before_fe55771"] = {
            k: v.get("cpu_us_per_frame", v.get("p50_us")) for k, v in old.items()
        }
    write_result("refusal", params, variants, json_path)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = bench_argparser(__doc__.splitlines()[0] if __doc__ else "mac")
    p.add_argument("--refusal", action="store_true", help="the cost of refusing a frame, by stage")
    p.add_argument("--refusal-attacker", metavar="SPEC", help=argparse.SUPPRESS)
    p.add_argument(
        "--full-size",
        action="store_true",
        help="the cost of refusing a full-size junk or replayed frame, before and after the "
        "header tag (part of --refusal)",
    )
    p.add_argument("--before", metavar="PATH", help="--refusal: a result file to compare with")
    p.add_argument(
        "--loop-only", action="store_true", help="--refusal: the loop beside a flood only"
    )
    args = p.parse_args(argv)
    if args.refusal_attacker:
        return refusal_attacker(args.refusal_attacker)
    if args.full_size:
        params = {
            "quick": args.quick,
            "what": full_size_refusal.__doc__,
            "command": "flock /tmp/zplatform-bench.lock python -m bench.mac --full-size",
        }
        write_result("refusal_full_size", params, full_size_refusal(args.quick), args.json)
        return 0
    if args.refusal:
        return refusal_main(args.quick, args.json, args.before, args.loop_only)
    scale = 20 if args.quick else 1
    variants: dict[str, dict[str, Any]] = {}
    sig = _ed25519()
    for label, size in SIZES.items():
        n = max(ITERATIONS[label] // scale, 50)
        frame = bytearray(os.urandom(size))
        variants[f"copy_{label}"] = _measure(partial(_copy, bytearray(size), frame), n)
        for mac in MACS:
            ch = Channel(KEY, "rocket", "telemetry", mac)
            sealed = bytes(ch.seal(frame))
            variants[f"{mac}_seal_{label}"] = _measure(partial(ch.seal, frame), n)
            variants[f"{mac}_open_{label}"] = _measure(partial(ch.open, sealed), n)
        if sig is not None:
            sk, pk = sig
            data = bytes(frame)
            signature = sk.sign(data)
            m = max(n // 10, 20)
            variants[f"ed25519_sign_{label}"] = _measure(partial(sk.sign, data), m)
            variants[f"ed25519_verify_{label}"] = _measure(partial(pk.verify, signature, data), m)
        for name, fig in variants.items():
            if name.endswith(label):
                fig["size_bytes"] = size
                ns = fig["ns_per_frame"]
                fig["gb_per_s"] = round(size / ns, 2) if ns else None
    params = {
        "sizes_bytes": SIZES,
        "quick": args.quick,
        "ed25519": sig is not None,
        "what": "Channel.seal / Channel.open as the loop calls them; ns_per_frame: the least "
        "of ten tight-loop means",
    }
    write_result("mac", params, variants, args.json)
    print(f"\n{'variant':<28} {'ns/frame':>10} {'GB/s':>7}")
    for name, fig in variants.items():
        print(f"{name:<28} {fig['ns_per_frame']:>10.1f} {fig['gb_per_s'] or 0:>7.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
