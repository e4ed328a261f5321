"""The intra-host carrier beside raw iceoryx2 request/response and raw zenoh get/reply.

One trigger and one reply of the same size (256 B and 325 KB), paced at
100 Hz, between this process (the control node's end) and one responder
process per variant, all three running in one invocation, in interleaved
rounds (each round visits every size and variant):

* ``carrier``: :class:`zplatform.runtime.intrahost.IntraHostClient` /
  :class:`~zplatform.runtime.intrahost.IntraHostServer`: the client copies the frame
  into its loaned request (the encode), the server reads the trigger in place
  and copies its reply into a loan, the client copies the reply once into a
  preallocated array (the Data Vector);
* ``raw_iceoryx2``: the same iceoryx2 services and event wake-ups written
  bare (``loan_slice_uninit``, ``memmove``, ``send``, ``notify``;
  ``timed_wait``, ``receive``, one copy out): the floor the carrier adds to;
* ``raw_iceoryx2_waitset``: the same, each end waiting in an iceoryx2
  ``WaitSet`` with the listener attached (then ``try_wait`` to consume the
  event) instead of the listener's own ``timed_wait``: the other way to
  block, measured to choose;
* ``raw_zenoh``: ``session.get`` with the payload, the queryable replies
  from its callback, ``to_bytes()`` and a copy into the array; zplatform's
  own zenoh config (loopback TCP, shared memory as the mission default).

Per exchange: the round trip from before the trigger is written until the
reply is in the array (``p50_us``/``p99_us``/``max_us``, ``time.perf_counter_ns``),
and ``cpu_us_per_exchange``: both processes' CPU time (user + system, every
thread) over the exchanges, divided by their number. Waits block (event
listener, zenoh's reply); nothing spins. ``ratios``: p50 and CPU of each
over raw iceoryx2 and raw zenoh. ``carrier_unpaced_256B`` and
``raw_iceoryx2_unpaced_256B`` run the same exchanges back to back (no
pacing): what a wake-up of a process that slept 10 ms costs over one that
just ran shows as ``*_paced_over_unpaced_p50_256B``.

Scheduling: ``--priority P`` (default 20, as ``bench.sync``; 0 turns it
off) puts this process in SCHED_FIFO P before the responders start, so
every end of every variant runs at that priority.

Run ``python -m bench.intrahost [--quick] [--priority P] [--json PATH]``; results go to
``bench/results/intrahost.json``. Blocks about 70 s (``--quick``: 15 s).

``--copies`` (results: ``bench/results/intrahost_copies.json``, a few
seconds): one hop's copies, in one process over a real link, at 325 KB and
4 MB: a region framed and tagged by the sender, then the receiver's
intake check and the copy into a preallocated array (the Data Vector).
``encode_into`` (the sync's path now: framed and tagged straight in the
loaned sample, checked in place,
:meth:`~zplatform.control.intake.Intake.check_view`) beside
``encode_copy`` (framed in the sender's buffer, then copied into the loan:
the path before) and ``copy_out`` (that, and the intake's ``to_bytes`` copy
out of the sample first: the path before the in-place check). Per
exchange: ``alloc_bytes`` (tracemalloc's peak above the start: a
frame-sized figure is a copy), ``memcpy_bytes`` (the copies the path
makes, the encode's included, counted), and the one-way time from the
encode until the frame is in the array (p50/p99, no pacing, no wake-up:
the copies' and the tag's cost).

``--misses`` (results: ``bench/results/intrahost_misses.json``, about 10 s):
what a reply that never comes costs the control node, per deadline (0.5,
2 and 10 ms), beside a bare listener's own ``timed_wait`` of the same
length (:func:`run_misses`).
"""

from __future__ import annotations

import ctypes
import json
import os
import resource
import sys
import time
from typing import Any

import numpy as np

from bench.common import (
    Child,
    bench_argparser,
    commands,
    free_port,
    next_command,
    say,
    summarize,
    two_node_mission,
    write_result,
)

SIZES = {"256B": 256, "325KB": 325_000}
VARIANTS = ("carrier", "raw_iceoryx2", "raw_iceoryx2_waitset", "raw_zenoh")
PERIOD_S = 0.01  # 100 Hz
UNPACED = ("carrier", "raw_iceoryx2")  # also run back to back, 256 B: the warm wake-up
ROUNDS = 4
PER_ROUND = 250  # exchanges per round, size and variant
DEADLINE_S = 0.002  # the zenoh sync's deadline; a later reply is a miss
WAIT_S = 1.0  # how long an exchange waits before it is counted lost
PREFIX = f"zpbench{os.getpid()}_"  # the orchestrator's pid, inherited by the children


#: A size besides SIZES that run_raw's ends carry (bench.bandwidth's floors:
#: a point's largest frame), set in the environment the responder inherits.
EXTRA_SIZE_ENV = "ZP_BENCH_EXTRA_SIZE"
#: Which of several raw iceoryx2 responders a child is (:func:`run_raw_many`):
#: each serves a service of its own, as each DN its own link.
RESPONDER_ENV = "ZP_BENCH_RESPONDER"


def _raw_name(pid: int, variant: str, index: str | None) -> str:
    return f"bench/{pid}/{variant}" + (f"/{index}" if index else "")


def _sizes() -> list[int]:
    extra = os.environ.get(EXTRA_SIZE_ENV)
    return [*SIZES.values(), *([int(extra)] if extra else [])]


def _cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _iox_services(prefix: str, name: str) -> tuple[Any, Any, Any, Any, Any]:
    import iceoryx2 as iox

    from zplatform.runtime.intrahost import iceoryx2_config

    iox.set_log_level(iox.LogLevel.Error)
    node = (
        iox.NodeBuilder.new()
        .config(iceoryx2_config(prefix))
        .signal_handling_mode(iox.SignalHandlingMode.Disabled)
        .create(iox.ServiceType.Ipc)
    )
    u8 = iox.Slice[ctypes.c_uint8]
    svc = node.service_builder(iox.ServiceName.new(name)).request_response(u8, u8).open_or_create()
    req = node.service_builder(iox.ServiceName.new(name + "/req")).event().open_or_create()
    res = node.service_builder(iox.ServiceName.new(name + "/res")).event().open_or_create()
    return iox, node, svc, req, res


def _blocker(iox: Any, listener: Any, waitset: bool) -> Any:
    """A blocking wait on ``listener`` with a timeout: its own ``timed_wait``,
    or a ``WaitSet`` it is attached to. Returns whether an event came."""
    if not waitset:
        return listener.timed_wait
    ws = (
        iox.WaitSetBuilder.new()
        .signal_handling_mode(iox.SignalHandlingMode.Disabled)
        .create(iox.ServiceType.Ipc)
    )
    guard = ws.attach_notification(listener)

    def block(timeout: Any) -> bool:
        ids, _result = ws.wait_and_process_with_timeout(timeout)
        block.guard = guard  # type: ignore[attr-defined]  # keeps the attachment alive
        return bool(ids) and bool(listener.try_wait())

    return block


# -- responder (the device node's end) ----------------------------------------


def _responder(variant: str, mission_text: str) -> None:
    big = max(_sizes())
    reply = {n: os.urandom(n) for n in _sizes()}
    if variant == "carrier":
        from zplatform.runtime.intrahost import IntraHostServer, link_names

        server = IntraHostServer(
            link_names("bench", "rocket", os.getppid(), "cn", "dn0"), big, big, prefix=PREFIX
        )
        say({"ready": True})
        for cmd in commands():
            if cmd["cmd"] == "quit":
                break
            c0, served = _cpu_s(), 0
            while served < cmd["n"]:
                view = server.wait(WAIT_S)
                if view is None:
                    break
                n = len(view)
                buf = server.reply(n)
                if buf is not None:
                    buf[:] = reply[n]  # the reply's encode, into the loan
                    server.send()
                served += 1
            say({"cpu_s": _cpu_s() - c0, "served": served})
        server.close()
    elif variant.startswith("raw_iceoryx2"):
        iox, _node, svc, req_ev, res_ev = _iox_services(
            PREFIX, _raw_name(os.getppid(), variant, os.environ.get(RESPONDER_ENV))
        )
        srv = svc.server_builder().initial_max_slice_len(big).create()
        listener = req_ev.listener_builder().create()
        notifier = res_ev.notifier_builder().create()
        wait = iox.Duration.from_secs_f64(WAIT_S)
        block = _blocker(iox, listener, variant.endswith("waitset"))
        src = {n: (ctypes.c_char * n).from_buffer(bytearray(b)) for n, b in reply.items()}
        say({"ready": True})
        for cmd in commands():
            if cmd["cmd"] == "quit":
                break
            c0, served = _cpu_s(), 0
            t_idle = time.monotonic() + WAIT_S
            while served < cmd["n"]:
                active = srv.receive()
                if active is None:
                    if time.monotonic() >= t_idle:
                        break
                    block(wait)
                    continue
                t_idle = time.monotonic() + WAIT_S
                n = active.header.number_of_elements
                loan = active.loan_slice_uninit(n)
                ctypes.memmove(loan.payload_ptr, src[n], n)
                loan.assume_init().send()
                notifier.notify()
                del active
                served += 1
            say({"cpu_s": _cpu_s() - c0, "served": served})
    else:
        import zenoh

        from zplatform.mission.load import decode_mission
        from zplatform.runtime.transport import open_session, zenoh_config

        session = open_session(zenoh_config(decode_mission(mission_text), "dn0"))
        count = [0]

        def on_query(query: Any) -> None:
            with query:
                payload = query.payload
                n = len(payload) if payload is not None else 0
                query.reply(query.key_expr, reply.get(n, b""))
                count[0] += 1

        qbl = session.declare_queryable(
            "bench/intrahost/q", zenoh.handlers.Callback(on_query, indirect=False)
        )
        say({"ready": True})
        for cmd in commands():
            if cmd["cmd"] == "quit":
                break
            c0, k0 = _cpu_s(), count[0]
            # The callback serves; this thread waits for the orchestrator.
            say({"ack": True})
            next_command()
            say({"cpu_s": _cpu_s() - c0, "served": count[0] - k0})
        qbl.undeclare()
        session.close()


# -- the control node's end ------------------------------------------------------


class _Asker:
    """The control node's end of one variant: ``exchange(n)`` returns the
    round trip in ns, or None when no reply came within ``WAIT_S``."""

    def __init__(self, variant: str, mission_text: str, index: str | None = None) -> None:
        self.variant = variant
        big = max(_sizes())
        self.src = {n: os.urandom(n) for n in _sizes()}
        self.dst = np.empty(big, np.uint8)
        self.dst_mv = self.dst.data  # a memoryview, no copy
        if variant == "carrier":
            from zplatform.runtime.intrahost import IntraHostClient, link_names

            self.client = IntraHostClient(
                link_names("bench", "rocket", os.getpid(), "cn", "dn0"),
                big,
                big,
                prefix=PREFIX,
                deadline_s=WAIT_S,
            )
        elif variant.startswith("raw_iceoryx2"):
            iox, self._node, svc, req_ev, res_ev = _iox_services(
                PREFIX, _raw_name(os.getpid(), variant, index)
            )
            self.iox = iox
            self.cli = svc.client_builder().initial_max_slice_len(big).create()
            self.notifier = req_ev.notifier_builder().create()
            self.listener = res_ev.listener_builder().create()
            self.block = _blocker(iox, self.listener, variant.endswith("waitset"))
            self.wait = iox.Duration.from_secs_f64(WAIT_S)
            self.csrc = {
                n: (ctypes.c_char * n).from_buffer(bytearray(b)) for n, b in self.src.items()
            }
        else:
            import zenoh

            from zplatform.mission.load import decode_mission
            from zplatform.runtime.transport import open_session, zenoh_config

            self.zenoh = zenoh
            self.session = open_session(zenoh_config(decode_mission(mission_text), "cn"))

    def exchange(self, n: int) -> int | None:
        t0 = time.perf_counter_ns()
        if self.variant == "carrier":
            buf = self.client.trigger(n)
            if buf is None:
                return None
            buf[:] = self.src[n]  # the trigger's encode, into the loan
            reply = self.client.exchange()
            if reply is None:
                return None
            self.dst_mv[: len(reply)] = reply  # the one copy, into the vector
            self.client.release()
        elif self.variant.startswith("raw_iceoryx2"):
            loan = self.cli.loan_slice_uninit(n)
            ctypes.memmove(loan.payload_ptr, self.csrc[n], n)
            pending = loan.assume_init().send()
            self.notifier.notify()
            t_end = time.monotonic() + WAIT_S
            while (response := pending.receive()) is None:
                if time.monotonic() >= t_end:
                    return None
                self.block(self.wait)
            k = response.header.number_of_elements
            ctypes.memmove(self.dst.ctypes.data, response.payload_ptr, k)
            del response, pending
        else:
            got = None
            for answer in self.session.get(
                "bench/intrahost/q",
                payload=self.src[n],
                consolidation=self.zenoh.ConsolidationMode.NONE,
                timeout=WAIT_S,
            ):
                if answer.ok is not None:
                    got = answer.ok.payload.to_bytes()
                    self.dst_mv[: len(got)] = got
                break
            if got is None:
                return None
        return time.perf_counter_ns() - t0

    def close(self) -> None:
        if self.variant == "carrier":
            self.client.close()
        elif self.variant == "raw_zenoh":
            self.session.close()


def _responder_role(variant: str) -> None:
    _responder(variant, os.environ["ZP_BENCH_MISSION"])


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = bench_argparser(__doc__.split("\n")[0] if __doc__ else "bench.intrahost")
    ap.add_argument(
        "--priority",
        type=int,
        default=20,
        help="SCHED_FIFO priority of this process and the responders (0: off), as bench.sync",
    )
    ap.add_argument("--copies", action="store_true", help="one hop's copies alone (module doc)")
    ap.add_argument(
        "--misses", action="store_true", help="what a reply that never comes costs (module doc)"
    )
    ap.add_argument("--role", help=argparse_hidden())
    ap.add_argument("--variant", help=argparse_hidden())
    args = ap.parse_args(argv)
    if args.role:
        global PREFIX
        PREFIX = f"zpbench{os.getppid()}_"
        if args.role == "bulk":
            _bulk_publisher(args.variant, os.environ["ZP_BENCH_MISSION"])
        else:
            _responder_role(args.variant)
        return {}
    if args.copies:
        count = 50 if args.quick else 200
        rows = run_copies(COPY_SIZES, count)
        doc = write_result(
            "intrahost_copies",
            {"sizes": COPY_SIZES, "count": count, "notes": [run_copies.__doc__]},
            rows,
            args.json,
        )
        return doc

    if args.misses:
        count = 10 if args.quick else 40
        rows = run_misses(MISS_DEADLINES_S, count)
        return write_result(
            "intrahost_misses",
            {"deadlines_s": MISS_DEADLINES_S, "count": count, "notes": [run_misses.__doc__]},
            rows,
            args.json,
        )

    rounds = 2 if args.quick else ROUNDS
    from bench.sync import inherit_fifo

    # Before any child starts: the responders inherit the policy.
    scheduling = inherit_fifo(args.priority)
    per_round = 60 if args.quick else PER_ROUND
    procs: dict[str, Child] = {}
    askers: dict[str, _Asker] = {}
    lat: dict[str, list[int]] = {f"{v}_{s}": [] for v in VARIANTS for s in SIZES}
    for v in UNPACED:
        lat[f"{v}_unpaced_256B"] = []
    lost: dict[str, int] = dict.fromkeys(lat, 0)
    cpu: dict[str, float] = dict.fromkeys(lat, 0.0)
    try:
        for v in VARIANTS:
            mission_text = two_node_mission("bench_intrahost", free_port(), free_port())
            procs[v] = Child("bench.intrahost", ["--role", "respond", "--variant", v], mission_text)
            procs[v].read()
            askers[v] = _Asker(v, mission_text)
        for v in VARIANTS:  # warm up: zenoh's routes, every segment touched once
            for n in SIZES.values():
                _run_block(procs[v], askers[v], v, n, 5, [], 0)
        for rnd in range(rounds):
            for s, n in SIZES.items():
                for v in VARIANTS:
                    print(f"round {rnd + 1}/{rounds} {v} {s} x{per_round}", file=sys.stderr)
                    key = f"{v}_{s}"
                    c, k = _run_block(procs[v], askers[v], v, n, per_round, lat[key], PERIOD_S)
                    cpu[key] += c
                    lost[key] += k
            for v in UNPACED:  # back to back: the peer never sleeps long
                key = f"{v}_unpaced_256B"
                c, k = _run_block(procs[v], askers[v], v, SIZES["256B"], per_round, lat[key], 0)
                cpu[key] += c
                lost[key] += k
    finally:
        for a in askers.values():
            a.close()
        for p in procs.values():
            p.close()
        _clean_up()

    result: dict[str, dict[str, Any]] = {}
    for key, samples in lat.items():
        fig = summarize(samples, int(DEADLINE_S * 1e9))
        fig["lost"] = lost[key]
        fig["cpu_us_per_exchange"] = round(cpu[key] / max(1, len(samples)) * 1e6, 1)
        result[key] = fig

    def ratio(a: str, b: str, what: str = "p50_us") -> float | None:
        pa, pb = result[a].get(what), result[b].get(what)
        return round(pa / pb, 2) if pa and pb else None

    ratios: dict[str, float | None] = {}
    for v in UNPACED:
        ratios[f"{v}_paced_over_unpaced_p50_256B"] = ratio(f"{v}_256B", f"{v}_unpaced_256B")
    for s in SIZES:
        ratios[f"waitset_over_listener_p50_{s}"] = ratio(
            f"raw_iceoryx2_waitset_{s}", f"raw_iceoryx2_{s}"
        )
        ratios[f"waitset_over_listener_cpu_{s}"] = ratio(
            f"raw_iceoryx2_waitset_{s}", f"raw_iceoryx2_{s}", "cpu_us_per_exchange"
        )
        ratios[f"carrier_over_raw_iceoryx2_p50_{s}"] = ratio(f"carrier_{s}", f"raw_iceoryx2_{s}")
        ratios[f"carrier_over_raw_zenoh_p50_{s}"] = ratio(f"carrier_{s}", f"raw_zenoh_{s}")
        ratios[f"raw_zenoh_over_raw_iceoryx2_p50_{s}"] = ratio(
            f"raw_zenoh_{s}", f"raw_iceoryx2_{s}"
        )
        ratios[f"carrier_over_raw_zenoh_cpu_{s}"] = ratio(
            f"carrier_{s}", f"raw_zenoh_{s}", "cpu_us_per_exchange"
        )
        ratios[f"carrier_over_raw_iceoryx2_cpu_{s}"] = ratio(
            f"carrier_{s}", f"raw_iceoryx2_{s}", "cpu_us_per_exchange"
        )
    params = {
        "quick": args.quick,
        "scheduling": scheduling,
        "sizes": SIZES,
        "rounds": rounds,
        "per_round": per_round,
        "period_s": PERIOD_S,
        "deadline_s": DEADLINE_S,
        "ratios": ratios,
        "targets": {"carrier_over_raw_iceoryx2_p50_256B": 1.3, "carrier_p50_256B_us": 150},
        "notes": [
            "round trip: trigger written to reply in the receiver's array, same size each way",
            "cpu_us_per_exchange: both processes, every thread, user + system",
            "deadline_miss_rate: replies at or after the zenoh sync's 2 ms deadline",
            "lost: no reply within 1 s",
        ],
    }
    doc = write_result("intrahost", params, result, args.json)
    print(json.dumps(ratios, indent=1))
    return doc


def run_raw(variant: str, n: int, count: int, period_s: float = PERIOD_S) -> dict[str, Any]:
    """One variant's exchanges alone (``bench.sync``'s raw rows): a responder
    process, a warm-up of 5 exchanges, then ``count`` exchanges of ``n``
    bytes each way paced at ``period_s``. Returns ``{"samples_ns": [...],
    "lost": k, "cpu_s": both ends}``. Blocks ``count * period_s`` plus the
    responder's start; cleans its iceoryx2 files up."""
    if n not in SIZES.values():
        os.environ[EXTRA_SIZE_ENV] = str(n)  # the responder inherits it
    mission_text = two_node_mission("bench_intrahost", free_port(), free_port())
    proc = Child("bench.intrahost", ["--role", "respond", "--variant", variant], mission_text)
    asker: _Asker | None = None
    samples: list[int] = []
    try:
        proc.read()
        asker = _Asker(variant, mission_text)
        _run_block(proc, asker, variant, n, 5, [], 0)
        cpu, lost = _run_block(proc, asker, variant, n, count, samples, period_s)
    finally:
        if asker is not None:
            asker.close()
        proc.close()
        _clean_up()
    return {"samples_ns": samples, "lost": lost, "cpu_s": cpu}


def _clean_up() -> None:
    """Remove the iceoryx2 files a run made (its services' and this process's)."""
    from zplatform.runtime.intrahost import remove_stale

    remove_stale(PREFIX)
    for path in _own_files():
        try:
            os.unlink(path)
        except OSError:
            pass


def run_raw_many(responders: int, n: int, count: int, period_s: float = PERIOD_S) -> dict[str, Any]:
    """Raw iceoryx2 request/response to ``responders`` processes at once, each
    on a service of its own, ``n`` bytes each way (the floor of a sync with
    that many DNs: ``bench.sync``'s ``raw_iceoryx2_3_*`` rows): per exchange
    every request is written and sent (each responder woken), then each
    reply is waited for and copied out, as the control node's sync does. A
    warm-up of 5, then ``count`` exchanges paced at ``period_s``. Returns
    ``{"samples_ns": [...], "lost": k, "cpu_s": every end}``. Blocks
    ``count * period_s`` plus the responders' start; cleans its files up."""
    if n not in SIZES.values():
        os.environ[EXTRA_SIZE_ENV] = str(n)  # the responders inherit it
    mission_text = two_node_mission("bench_intrahost", free_port(), free_port())
    variant = "raw_iceoryx2"
    procs: list[Child] = []
    askers: list[_Asker] = []
    samples: list[int] = []
    lost = 0
    try:
        for k in range(responders):
            os.environ[RESPONDER_ENV] = str(k + 1)
            procs.append(
                Child("bench.intrahost", ["--role", "respond", "--variant", variant], mission_text)
            )
        os.environ.pop(RESPONDER_ENV, None)
        for k, proc in enumerate(procs):
            proc.read()
            askers.append(_Asker(variant, mission_text, str(k + 1)))
        cpu = 0.0
        for block, paced in ((5, False), (count, True)):
            for proc in procs:
                proc.send({"cmd": "serve", "n": block})
            c0 = _cpu_s()
            t_next = time.monotonic()
            for _ in range(block):
                rt = _exchange_many(askers, n)
                if paced:
                    if rt is None:
                        lost += 1
                    else:
                        samples.append(rt)
                    t_next += period_s
                    while (left := t_next - time.monotonic()) > 0:
                        time.sleep(left)
            mine = _cpu_s() - c0
            theirs = sum(proc.read()["cpu_s"] for proc in procs)
            cpu = mine + theirs
    finally:
        os.environ.pop(RESPONDER_ENV, None)
        for a in askers:
            a.close()
        for proc in procs:
            proc.close()
        _clean_up()
    return {"samples_ns": samples, "lost": lost, "cpu_s": cpu}


def _exchange_many(askers: list[_Asker], n: int) -> int | None:
    """One exchange of :func:`run_raw_many`: ns from the first request until
    the last reply is copied out, or None when one did not come in ``WAIT_S``."""
    t0 = time.perf_counter_ns()
    pendings = []
    for a in askers:
        loan = a.cli.loan_slice_uninit(n)
        ctypes.memmove(loan.payload_ptr, a.csrc[n], n)
        pendings.append(loan.assume_init().send())
        a.notifier.notify()
    t_end = time.monotonic() + WAIT_S
    for a, pending in zip(askers, pendings, strict=True):
        while (response := pending.receive()) is None:
            if time.monotonic() >= t_end:
                return None
            a.block(a.wait)
        ctypes.memmove(a.dst.ctypes.data, response.payload_ptr, response.header.number_of_elements)
        del response
    return time.perf_counter_ns() - t0


COPY_SIZES = {"325KB": 325_000, "4MB": 4_000_000}


MISS_DEADLINES_S = (0.0005, 0.002, 0.01)


def run_misses(deadlines_s: tuple[float, ...], count: int) -> dict[str, dict[str, Any]]:
    """What a reply that never comes costs (``--misses``): per deadline,
    ``carrier_<ms>`` times :meth:`IntraHostClient.exchange
    <zplatform.runtime.intrahost.IntraHostClient.exchange>` with that
    deadline against a server attached that never replies (a device node
    hung: trigger, send, wait, the miss counted), and
    ``listener_timed_wait_<ms>`` a bare iceoryx2 listener's own
    ``timed_wait`` of the same duration, nothing notifying it (the way the
    carrier waited before: the socket's SO_RCVTIMEO, counted in the
    kernel's jiffies). ``over_deadline``: each p50 over the deadline. One
    process, interleaved, this run's prefix removed after; blocks about
    ``count`` x the deadlines' sum x 5."""
    from zplatform.runtime.intrahost import IntraHostClient, IntraHostServer, link_names

    names = link_names(f"misses{os.getpid()}", "bench", "m", "cn", "dn0")
    server = IntraHostServer(names, 64, 64, prefix=PREFIX, check=False)
    client = IntraHostClient(names, 64, 64, prefix=PREFIX, check=False, stall_after=1 << 30)
    iox, _node, _svc, ev, _res = _iox_services(PREFIX, _raw_name(os.getpid(), "misses", None))
    listener = ev.listener_builder().create()
    rows: dict[str, dict[str, Any]] = {}
    try:
        for d in deadlines_s:
            label = f"{d * 1e3:g}ms"
            client.set_deadline(d)
            dur = iox.Duration.from_secs_f64(d)
            samples: dict[str, list[int]] = {"carrier": [], "listener_timed_wait": []}
            for _ in range(count):
                view = client.trigger(8)
                assert view is not None, "no loan for the trigger"
                view[:] = bytes(8)
                t0 = time.perf_counter_ns()
                got = client.exchange()
                samples["carrier"].append(time.perf_counter_ns() - t0)
                assert got is None, "the server never replies"
                server.poll()  # take the trigger, as a hung DN's queue would hold it
                t0 = time.perf_counter_ns()
                listener.timed_wait(dur)
                samples["listener_timed_wait"].append(time.perf_counter_ns() - t0)
            for what, xs in samples.items():
                fig = summarize(xs)
                fig["over_deadline"] = round(fig["p50_us"] / (d * 1e6), 2)
                rows[f"{what}_{label}"] = fig
    finally:
        del listener
        client.close()
        server.close()
    _clean_up()
    return rows


def run_copies(sizes: dict[str, int], count: int) -> dict[str, dict[str, Any]]:
    """One hop's copies per exchange (module doc, ``--copies``):
    ``{"encode_into_325KB": {...}, "encode_copy_325KB": {...},
    "copy_out_325KB": {...}, ...}``. The sender frames a region of the size
    (:class:`~zplatform.core.codec.FrameEncoder`, the header and the
    region's bytes) and tags it in place (``Channel.seal_tail``): straight
    in the loaned sample (``encode_into``, the sync's path now), or in its
    own buffer and then copied into the loan (``encode_copy``, the path
    before); the receiver checks it in place (``Intake.check_view``) and
    copies the data into a preallocated array (the Data Vector).
    ``copy_out``: ``encode_copy`` with the receiver's ``to_bytes`` copy out
    of the sample before its check (the path before the in-place check).
    One process, one real link (this run's prefix, removed after); blocks a
    few seconds."""
    import tracemalloc

    from zplatform.control.intake import Intake
    from zplatform.core.auth import TAG_LEN, Channel
    from zplatform.core.codec import FrameEncoder
    from zplatform.runtime.intrahost import IntraHostClient, IntraHostServer, link_names

    class _AnyFresh(Intake[None]):
        def _fresh(self, body: memoryview, handle: None) -> bool:
            return True

    class _CopyOut:  # the path before check_view: to_bytes copies out of the segment
        def __init__(self, view: memoryview) -> None:
            self.view = view

        def __len__(self) -> int:
            return len(self.view)

        def to_bytes(self) -> bytes:
            return bytes(self.view)

    key = bytes(range(32))
    out_rows: dict[str, dict[str, Any]] = {}
    for label, n in sizes.items():
        names = link_names(f"copies{os.getpid()}", "bench", label, "cn", "dn0")
        enc = FrameEncoder(n, tail=TAG_LEN)
        flen = enc.frame_len(n)
        seal = Channel(key, "bench", "bench/copies")
        intake = _AnyFresh("bench", flen, Channel(key, "bench", "bench/copies"))
        client = IntraHostClient(names, flen, 8, prefix=PREFIX, check=False)
        server = IntraHostServer(names, flen, 8, prefix=PREFIX, check=False)
        region = memoryview(bytearray(os.urandom(n)))
        dv_mv = memoryview(bytearray(n))
        try:
            ends = (client, server, intake, enc, seal, region, dv_mv)
            modes = ("encode_into", "encode_copy", "copy_out")
            samples: dict[str, list[int]] = {m: [] for m in modes}
            for k in range(5 + count):  # interleaved: the box's load falls on each alike
                for mode in modes:
                    ns = _copy_once(ends, mode, _CopyOut)
                    if k >= 5:
                        samples[mode].append(ns)
            for mode in modes:
                tracemalloc.start()
                try:
                    peaks = []
                    for _ in range(5):
                        base = tracemalloc.get_traced_memory()[0]
                        tracemalloc.reset_peak()
                        _copy_once(ends, mode, _CopyOut)
                        peaks.append(tracemalloc.get_traced_memory()[1] - base)
                finally:
                    tracemalloc.stop()
                fig = summarize(samples[mode])
                fig["alloc_bytes"] = int(np.median(peaks))
                # Counted: the encode's copy of the region, the copy of the
                # tagged frame into the loan (not encode_into's), copy_out's
                # to_bytes of the whole frame, and the copy into the vector.
                fig["memcpy_bytes"] = (
                    n
                    + (flen if mode != "encode_into" else 0)
                    + (flen if mode == "copy_out" else 0)
                    + n
                )
                out_rows[f"{mode}_{label}"] = fig
        finally:
            client.close()
            server.close()
    _clean_up()
    return out_rows


def _copy_once(ends: tuple[Any, ...], mode: str, copy_out: Any) -> int:
    """One exchange of :func:`run_copies`; returns ns from the encode until
    the frame is in the vector. ``ends``: client, server, intake, the
    encoder, the sending channel, the region and the vector (memoryviews)."""
    client, server, intake, enc, seal, region, dv_mv = ends
    n = len(region)
    buf = client.trigger(enc.frame_len(n))
    assert buf is not None
    t0 = time.perf_counter_ns()
    if mode == "encode_into":  # framed and tagged in the loan: no copy of the frame
        seal.seal_tail(enc.encode_into(buf, 1, 2, 3, region))
    else:  # framed and tagged in the encoder's buffer, then the one copy into the loan
        buf[:] = seal.seal_tail(enc.encode(1, 2, 3, region))
    client.send()
    view = server.wait(WAIT_S)
    assert view is not None
    if mode == "copy_out":
        data: Any = intake.check(copy_out(view), None)
    else:
        data = intake.check_view(view, None)
    assert data is not None, "the frame's tag must check"
    dv_mv[:] = memoryview(data)[len(data) - n :]  # the decode's copy into the vector
    t1 = time.perf_counter_ns()
    server.respond(b"ok")
    client.collect()
    client.release()
    return t1 - t0


def _run_block(
    proc: Child, asker: _Asker, variant: str, n: int, count: int, out: list[int], period: float
) -> tuple[float, int]:
    """``count`` exchanges of ``n`` bytes paced at ``period``; returns (CPU s of
    both ends, exchanges lost)."""
    proc.send({"cmd": "serve", "n": count})
    if variant == "raw_zenoh":
        proc.read()  # its ack: the responder's CPU clock has started
    c0 = _cpu_s()
    lost = 0
    t_next = time.monotonic()
    for _ in range(count):
        rt = asker.exchange(n)
        if rt is None:
            lost += 1
        else:
            out.append(rt)
        if period:
            t_next += period
            while (left := t_next - time.monotonic()) > 0:
                time.sleep(left)
    mine = _cpu_s() - c0
    if variant == "raw_zenoh":
        proc.send({"cmd": "done"})
    theirs = proc.read()
    return mine + theirs["cpu_s"], lost


# -- bulk one-way (the 4 MB row of bench.bandwidth) ------------------------------

BULK_VARIANTS = ("zplatform_iox", "zplatform_zenoh", "raw_iceoryx2", "raw_zenoh")
BULK_BYTES = 4_194_304  # a 2048 x 2048 mono8 frame (configs/camera.yaml)


def bulk_mission(n: int, intra_host: str) -> str:
    """A two-node mission with one bulk channel ``frame`` of ``u8[n]`` owned by
    ``dn0`` and read by ``cn`` (``transport.intra_host``: ``intra_host``)."""
    text = two_node_mission(f"bench_bulk_{intra_host}", free_port(), free_port())
    return (
        text
        + f"transport: {{intra_host: {intra_host}}}\n"
        + f"bulk:\n  - {{name: frame, node: dn0, type: 'u8[{n}]', readers: [cn]}}\n"
    )


def _bulk_event(name: str) -> tuple[Any, Any]:
    """iceoryx2 and the event service that wakes the bulk bench's reader
    (its ``name``), opened under this run's prefix."""
    import iceoryx2 as iox

    from zplatform.runtime.intrahost import iceoryx2_config

    iox.set_log_level(iox.LogLevel.Error)
    node = (
        iox.NodeBuilder.new()
        .config(iceoryx2_config(PREFIX))
        .signal_handling_mode(iox.SignalHandlingMode.Disabled)
        .create(iox.ServiceType.Ipc)
    )
    ev = node.service_builder(iox.ServiceName.new(name)).event().open_or_create()
    return iox, (node, ev)


def _bulk_keys(m: Any, mission_text: str, role: str) -> tuple[Any, Any]:
    """``role``'s keys and run for the zplatform bulk rows, as a node's: the
    samples tagged and checked (link ``bulk-frame-cn``) when the mission
    authenticates. Both processes derive one master key from the mission's
    text (a bench's key, not a secret) and share run 1."""
    import hashlib

    from zplatform.core.auth import KeySet, Run

    if not m.security.auth:
        return None, None
    master = hashlib.sha256(mission_text.encode()).digest()
    return KeySet.from_master(m, master).for_node(role), Run(1)


def _bulk_publisher(variant: str, mission_text: str) -> None:
    """Child: the owner of one bulk variant; on ``{"cmd": "run", "n", "period"}``
    publishes ``n`` samples of :data:`BULK_BYTES`, each stamped (monotonic ns,
    before its first copy) at the start, then says its CPU seconds."""
    from zplatform.mission.load import decode_mission
    from zplatform.runtime.bulk import NodeBulk, bulk_key
    from zplatform.runtime.transport import open_session, zenoh_config

    m = decode_mission(mission_text)
    session = open_session(zenoh_config(m, "dn0"))
    iox, (node, ev) = _bulk_event(f"bench/{os.getppid()}/bulk/{variant}/wake")
    notifier = ev.notifier_builder().create()
    n = m.bulk[0].sample_bytes - 32
    src = bytearray(BULK_BYTES + 8)
    send: Any
    if variant.startswith("zplatform"):
        keys, run = _bulk_keys(m, mission_text, "dn0")
        bulk = NodeBulk(session, m.vehicle, m.bulk, "dn0", intra_host=m, keys=keys, run=run)
        w = bulk.writers["frame"]
        w.array[:] = np.frombuffer(os.urandom(n), np.uint8)

        def send(i: int) -> None:
            w.publish(i, time.monotonic_ns())
            notifier.notify()

    elif variant == "raw_iceoryx2":
        svc = (
            node.service_builder(iox.ServiceName.new(f"bench/{os.getppid()}/bulk/raw"))
            .publish_subscribe(iox.Slice[ctypes.c_uint8])
            .subscriber_max_buffer_size(1)
            .enable_safe_overflow(True)
            .open_or_create()
        )
        pub = svc.publisher_builder().initial_max_slice_len(len(src)).create()
        csrc = (ctypes.c_char * len(src)).from_buffer(src)

        def send(i: int) -> None:
            src[:8] = time.monotonic_ns().to_bytes(8, "little")
            loan = pub.loan_slice_uninit(len(src))
            ctypes.memmove(loan.payload_ptr, csrc, len(src))  # the sample's one copy
            loan.assume_init().send()
            notifier.notify()

    else:
        zpub = session.declare_publisher(bulk_key(m.vehicle, m.bulk[0]))

        def send(i: int) -> None:
            src[:8] = time.monotonic_ns().to_bytes(8, "little")
            zpub.put(src)

    say({"ready": True})
    for cmd in commands():
        if cmd["cmd"] == "quit":
            break
        c0 = _cpu_s()
        t_next = time.monotonic()
        for i in range(cmd["n"]):
            send(i)
            t_next += cmd["period"]
            time.sleep(max(0.0, t_next - time.monotonic()))  # the owner's period
        say({"cpu_s": _cpu_s() - c0})
    session.close()


class _BulkReader:
    """The reader's end of one bulk variant: ``take(timeout_s)`` returns the
    one-way time of the next sample (from its stamp until it is in the
    reader's array, ns), or None after ``timeout_s`` without one."""

    def __init__(self, variant: str, mission_text: str) -> None:
        import zenoh

        from zplatform.mission.load import decode_mission
        from zplatform.runtime.bulk import NodeBulk, bulk_key
        from zplatform.runtime.transport import open_session, zenoh_config

        self.variant = variant
        m = decode_mission(mission_text)
        self.session = open_session(zenoh_config(m, "cn"))
        iox, self._ev = _bulk_event(f"bench/{os.getpid()}/bulk/{variant}/wake")
        self.iox = iox
        self.listener = self._ev[1].listener_builder().create()
        self.dst = np.empty(BULK_BYTES + 8, np.uint8)
        self._got: list[Any] = []
        self._event = __import__("threading").Event()
        if variant.startswith("zplatform"):
            keys, run = _bulk_keys(m, mission_text, "cn")
            self.bulk = NodeBulk(
                self.session, m.vehicle, m.bulk, "cn", intra_host=m, keys=keys, run=run
            )
            self.reader = self.bulk.readers["frame"]
        elif variant == "raw_iceoryx2":
            svc = (
                self._ev[0]
                .service_builder(iox.ServiceName.new(f"bench/{os.getpid()}/bulk/raw"))
                .publish_subscribe(iox.Slice[ctypes.c_uint8])
                .subscriber_max_buffer_size(1)
                .enable_safe_overflow(True)
                .open_or_create()
            )
            self.sub = svc.subscriber_builder().buffer_size(1).create()
        else:

            def on_sample(sample: Any) -> None:  # zenoh's thread: hand off
                self._got.append(sample)
                self._event.set()

            self.zsub = self.session.declare_subscriber(
                bulk_key(m.vehicle, m.bulk[0]), zenoh.handlers.Callback(on_sample, indirect=False)
            )

    def take(self, timeout_s: float) -> int | None:
        t_end = time.monotonic() + timeout_s
        v = self.variant
        while time.monotonic() < t_end:
            if v == "zplatform_iox":
                self.listener.timed_wait(self.iox.Duration.from_secs_f64(0.05))
                if self.reader.poll():
                    assert self.reader.header is not None
                    return time.monotonic_ns() - self.reader.header.t_ns
            elif v == "zplatform_zenoh":
                if self.reader.wait(0.05):
                    assert self.reader.header is not None
                    return time.monotonic_ns() - self.reader.header.t_ns
            elif v == "raw_iceoryx2":
                self.listener.timed_wait(self.iox.Duration.from_secs_f64(0.05))
                sample = None
                while (newer := self.sub.receive()) is not None:
                    sample = newer
                if sample is not None:
                    k = sample.header.number_of_elements
                    ctypes.memmove(self.dst.ctypes.data, sample.payload_ptr, k)  # one copy
                    del sample
                    return time.monotonic_ns() - int.from_bytes(self.dst[:8].tobytes(), "little")
            else:
                self._event.wait(0.05)
                if self._got:
                    sample = self._got[-1]
                    self._got.clear()
                    self._event.clear()
                    data = sample.payload.to_bytes()
                    self.dst[: len(data)] = np.frombuffer(data, np.uint8)
                    return time.monotonic_ns() - int.from_bytes(data[:8], "little")
        return None

    def close(self) -> None:
        if self.variant.startswith("zplatform"):
            self.bulk.close()
        self.session.close()


def run_bulk(count: int, period_s: float) -> dict[str, dict[str, Any]]:
    """The 4 MB bulk one-way rows (:data:`BULK_VARIANTS`): per variant an owner
    process publishing ``count`` samples every ``period_s`` to a reader in
    this process, woken per sample (an iceoryx2 event the owner notifies
    after its send for the iceoryx2 rows, zenoh's callback for the zenoh
    ones). Figures: one-way ``p50_us``/``p99_us`` (stamp before the owner's
    first copy until the sample is in the reader's array), ``lost``
    (published, not taken: superseded or dropped), ``cpu_us_per_sample``
    (both processes). Blocks about ``4 * count * period_s`` plus start-ups."""
    out: dict[str, dict[str, Any]] = {}
    for v in BULK_VARIANTS:
        intra = "zenoh" if v in ("zplatform_zenoh", "raw_zenoh") else "auto"
        text = bulk_mission(BULK_BYTES, intra)
        child = Child("bench.intrahost", ["--role", "bulk", "--variant", v], text)
        reader: _BulkReader | None = None
        try:
            reader = _BulkReader(v, text)
            child.read()
            # Warm-up: routes, every page of the segments, the reader's switch.
            child.send({"cmd": "run", "n": 20, "period": period_s})
            while reader.take(1.0) is not None:
                pass
            child.read()
            samples: list[int] = []
            c0 = _cpu_s()
            child.send({"cmd": "run", "n": count, "period": period_s})
            while len(samples) < count and (t := reader.take(1.0)) is not None:
                samples.append(t)
            theirs = child.read()
            cpu = _cpu_s() - c0 + theirs["cpu_s"]
            fig = summarize(samples)
            fig["lost"] = count - len(samples)
            fig["cpu_us_per_sample"] = round(cpu / max(1, count) * 1e6, 1)
            fig["bytes"] = BULK_BYTES
            if v.startswith("zplatform"):
                fig["counters"] = reader.bulk.counters()
            out[f"bulk_{v}_4MB"] = fig
        finally:
            if reader is not None:
                reader.close()
            child.close()
    _clean_up()
    return out


def _own_files() -> list[str]:
    import glob

    return glob.glob(f"/dev/shm/{PREFIX}*") + glob.glob(
        f"/tmp/iceoryx2/**/{PREFIX}*", recursive=True
    )


def argparse_hidden() -> str:
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    main()
