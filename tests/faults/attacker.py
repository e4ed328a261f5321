"""A keyless attacker on a mission's network, as a process of its own.

The flood cases (``tests/faults/floods.py``) run it beside the mission's
node processes, so a flood competes for the CPU as a real one would. It
holds no key (its environment is stripped of ``ZPLATFORM_KEY*`` by
:func:`attacker_env`); it opens a zenoh peer connected to every node, as any
tool on the network can, and uses only what that gives it: the mission
file, the taps the nodes publish (``{vehicle}/cn/to_dnX``: the CN's
triggers; ``{vehicle}/dnX/to_cn``: dnX's replies) and the command requests
on ``{vehicle}/gn/to_cn``, all readable without a key::

    python -m tests.faults.attacker MISSION MODE [--dn dn0] [--rate 6000] [--duration 3]

Modes:

* ``query-junk``: gets on ``{vehicle}/DN/to_cn`` with junk payloads: half
  random sizes (0-2000 bytes), half exactly a trigger's size (so each one
  costs the DN a tag check, the expensive refusal);
* ``query-replay``: the same gets, each carrying one authentic trigger
  captured from the CN's tap;
* ``query-mixed``: both, alternately;
* ``reply-junk`` / ``reply-replay`` / ``reply-mixed``: a rogue queryable on
  ``{vehicle}/DN/to_cn`` that answers the CN's sync queries at ``--rate``
  replies per second in all (junk as above, of a reply's size; DN's own
  replies captured from its tap; both, alternately);
* ``tm-junk`` / ``tm-replay`` / ``tm-mixed``: puts on ``{vehicle}/cn/telemetry``
  (junk, half of a snapshot's size; the CN's own snapshots captured from
  that key; both, alternately): the ground node is the victim;
* ``declare-denied`` / ``declare-allowed``: a declaration flood: the
  attacker declares, at ``--rate`` declarations per second, round robin,
  ``--hold`` of each kind and then keeps replacing its oldest (undeclare,
  declare anew: each one a message every node it reaches takes in).
  ``denied``: subscribers on the whole key space ``{vehicle}/**`` and
  queryables on ``{vehicle}/DN/to_cn``, which the access control denies a
  ``tool`` cert; ``allowed``: subscribers on ``{vehicle}/cn/telemetry`` and
  ``{vehicle}/*/events`` and liveliness subscribers on ``{vehicle}/*/alive``,
  which it allows one (``--deployment``: the deployment whose ``tool``
  identity it presents; without one, keyless, as on plain TCP);
  ``--distinct``: each declaration on a key of its own (``{vehicle}/**/xN``,
  ``{vehicle}/DN/to_cn/xN``; ``{vehicle}/xN/events``, ``{vehicle}/xN/alive``,
  which ``*`` in an allowed rule still covers), a new resource each;
  ``declare-keyexpr``: only key expressions (``session.declare_keyexpr``,
  ``{vehicle}/xN`` with ``--distinct``): zenoh's own subscriber and
  queryable declarations send one for each new non-wild key prefix, and
  zenoh's access control filters none (zenoh 1.10);
  ``--connect EP``: reach only ``EP`` (gossip off), not every node;
* ``cmd-replay``: publishes command request frames on ``{vehicle}/gn/to_cn``,
  round robin: the operator's own, captured on the wire (a zenoh peer cannot
  subscribe to another tool's puts: tools listen nowhere) and given on
  stdin as one line ``frames HEX HEX...`` before ``ready``;
* ``key-get`` / ``key-put`` / ``key-answer``: the same three attacks on any
  key ``--key`` (the generated suite of ``tests/faults/keyfloods.py``, one
  per key space row): gets carrying, puts of, or a rogue queryable's
  answers to the queries on ``--key`` with junk (half random sizes, half
  exactly ``--size`` bytes, the row's longest frame) alternating with
  genuine frames captured from ``--capture KEY`` (a tap or the key itself,
  as any peer subscribes) or given on stdin (``--frames-stdin``: one line
  ``frames HEX...``, as for ``cmd-replay``); junk only without either.
  Gets and puts use congestion control BLOCK: every frame sent reaches the
  node, so the node's refusal counter can be held to it exactly. The JSON
  line adds ``genuine`` (frames captured) and ``right_size`` (frames sent
  of exactly ``--size`` bytes).

Insider mode (``--insider KEYFILE``, key-* modes): the attacker holds one
host role's key file (``zplatform keygen``'s format) and tags every frame
it sends, junk or replayed, with the channels that role holds, round robin,
in the run the captured frames name (:func:`insider_tagged`): the floods of
``tests/faults/test_insider_live.py``.

Protocol: prints ``ready`` once connected and armed (replay modes: once it
captured what it replays; reply modes: once the CN's queries reach its
queryable), waits for a line ``go`` on stdin, attacks for ``--duration``
seconds (or until a line ``stop``) at ``--rate`` per second, prints one JSON line (``sent``,
``seconds``, ``rate``; query modes: ``answered``, the replies its queries
got) and exits. It asks for niceness -10 (where the user may): a real attacker has a
machine of its own, this one must keep its rate beside a CPU hog.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import threading
import time
from collections import deque
from contextlib import suppress
from functools import partial
from typing import Any

import zenoh

from tests.waits import poll_until
from zplatform.core.auth import TAG_LEN, Channel
from zplatform.core.codec import frame_overhead
from zplatform.core.datavector import Layout
from zplatform.mission.load import load_mission
from zplatform.runtime.transport import KeySpace, open_session, zenoh_config
from zplatform.security.deploy import load_deployment

MODES = (
    *(f"{k}-{p}" for k in ("query", "reply", "tm") for p in ("junk", "replay", "mixed")),
    "declare-denied",
    "declare-allowed",
    "declare-keyexpr",
    "cmd-replay",
    "key-get",
    "key-put",
    "key-answer",
)
TICK_S = 0.002  # pacing granularity: rate * TICK_S frames per tick


def attacker_env() -> dict[str, str]:
    """The environment of an attacker process: the test's, without any key."""
    return {k: v for k, v in os.environ.items() if not k.startswith("ZPLATFORM_KEY")}


class Capture:
    """The newest ``keep`` samples on a key (zenoh's thread appends)."""

    def __init__(self, session: zenoh.Session, key: str, keep: int) -> None:
        self.frames: deque[bytes] = deque(maxlen=keep)
        self.seen = threading.Event()
        self._sub = session.declare_subscriber(
            key, zenoh.handlers.Callback(self._on, indirect=False)
        )

    def _on(self, sample: zenoh.Sample) -> None:
        self.frames.append(sample.payload.to_bytes())
        self.seen.set()

    def wait(self, n: int, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while len(self.frames) < n:
            if time.monotonic() > deadline:
                raise SystemExit(f"captured {len(self.frames)} of {n} frames in {timeout_s} s")
            self.seen.wait(0.1)
            self.seen.clear()

    def close(self) -> None:
        self._sub.undeclare()


def _mix(a: list[bytes], b: list[bytes]) -> list[bytes]:
    """``a`` and ``b`` interleaved (either may be empty)."""
    out = [x for pair in zip(a, b, strict=False) for x in pair]
    n = min(len(a), len(b))
    return out + a[n:] + b[n:]


def paced(rate: float, duration_s: float, send: Any, stop: threading.Event) -> tuple[int, float]:
    """Call ``send()`` ``rate`` times a second for ``duration_s`` or until
    ``stop`` is set; returns (calls, seconds taken)."""
    per_tick = rate * TICK_S
    t0 = time.monotonic()
    sent = 0
    owed = 0.0
    nxt = t0
    while (now := time.monotonic()) - t0 < duration_s and not stop.is_set():
        owed += per_tick
        while owed >= 1.0:
            send()
            sent += 1
            owed -= 1.0
        nxt += TICK_S
        if nxt > now:
            time.sleep(nxt - now)  # stimulus: the flood's pace
        else:
            nxt = now  # behind: do not burst to catch up
    return sent, time.monotonic() - t0


class Rogue:
    """A queryable on a DN's key that keeps the newest query the CN sent
    and answers it from another thread, at a rate."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.key = key
        self.latest: zenoh.Query | None = None
        self.queries = 0
        self.seen = threading.Event()
        self._qbl = session.declare_queryable(
            key, zenoh.handlers.Callback(self._on, indirect=False)
        )

    def _on(self, query: zenoh.Query) -> None:
        self.latest = query  # the older one is dropped: zenoh finalises it
        self.queries += 1
        self.seen.set()

    def reply(self, payload: bytes) -> None:
        q = self.latest
        if q is not None:
            try:
                q.reply(self.key, payload)
            except Exception:  # the query was finalised meanwhile: next one
                pass

    def close(self) -> None:
        self._qbl.undeclare()
        self.latest = None


def insider_tagged(
    m: Any, key_file: str, payloads: list[bytes], genuine: list[bytes]
) -> list[bytes]:
    """``payloads`` re-tagged by an insider (``--insider``): each frame's body
    (all but its last TAG_LEN bytes) tagged anew with the channels the key
    file's role holds, round robin, in the run the genuine frames name (the
    run word of their tags: what any holder of a key learns); a payload too
    short to carry a tag is kept."""
    from tests.faults.insider import channels_of
    from zplatform.core.auth import Run, read_key_file

    ks = read_key_file(key_file, m)
    assert ks.role is not None, f"{key_file} names no role"
    run = Run(Channel.run_of(genuine[0])) if genuine else None
    chans = [ks.channel(c, run) for c in channels_of(m, ks.role)]
    out = []
    for i, p in enumerate(payloads):
        if len(p) <= TAG_LEN:
            out.append(p)
            continue
        out.append(bytes(chans[i % len(chans)].seal(p[:-TAG_LEN])))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.faults.attacker")
    p.add_argument("mission")
    p.add_argument("mode", choices=MODES)
    p.add_argument("--dn", default="dn0")
    p.add_argument("--rate", type=float, default=6000.0)
    p.add_argument("--duration", type=float, default=3.0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--hold", type=int, default=2000, help="declare modes: held per kind")
    p.add_argument("--deployment", help="present this deployment's tool identity (mTLS)")
    p.add_argument("--distinct", action="store_true", help="declare modes: a key each")
    p.add_argument("--connect", help="connect only to this endpoint, gossip off")
    p.add_argument("--key", help="key-* modes: the key attacked")
    p.add_argument("--size", type=int, default=0, help="key-* modes: the row's frame size")
    p.add_argument("--capture", help="key-* modes: replay genuine frames seen on this key")
    p.add_argument("--frames-stdin", action="store_true", help="key-* modes: frames on stdin")
    p.add_argument("--capture-wait", type=float, default=3.0, help="key-* modes: seconds")
    p.add_argument("--insider", help="key-* modes: an insider's key file (module doc)")
    a = p.parse_args(argv)
    # A real attacker has a machine of its own: here it must keep its rate
    # beside the nodes and whatever else loads the box (a CPU hog).
    with suppress(OSError):
        os.nice(-10)
    m = load_mission(a.mission)
    keys = KeySpace(m.vehicle)
    rng = random.Random(a.seed)
    lay = Layout.for_node(m, "cn")
    tag = TAG_LEN if m.security.auth else 0
    trigger_len = (
        frame_overhead(lay.region(f"cn_to_{a.dn}").size) + lay.region(f"cn_to_{a.dn}").size + tag
    )
    reply_len = (
        frame_overhead(lay.region(f"{a.dn}_to_cn").size) + lay.region(f"{a.dn}_to_cn").size + tag
    )
    dep = load_deployment(a.deployment, m) if a.deployment else None
    cfg = zenoh_config(m, None, deployment=dep)
    if a.connect:
        cfg.insert_json5("connect/endpoints", json.dumps([a.connect]))
        cfg.insert_json5("scouting/gossip/enabled", "false")
        cfg.insert_json5("scouting/multicast/enabled", "false")
    session = open_session(cfg)
    dn_key = keys.dn_to_cn(a.dn)
    tm_len = frame_overhead(lay.size) + lay.size + tag
    exact = {"query": trigger_len, "reply": reply_len, "tm": tm_len}.get(a.mode.split("-")[0], 0)
    junk = [rng.randbytes(rng.randrange(0, 2000)) for _ in range(64)]
    junk += [rng.randbytes(exact) for _ in range(64)]
    rng.shuffle(junk)
    send: Any
    cleanup: list[Any] = []
    k = [0]
    answered = [0]  # query modes: replies (or error replies) the DN sent back
    gets = [0]  # query modes: gets sent ...
    finished: deque[None] = deque()  # ... and finalized by zenoh (answered or timed out)
    on_finished = partial(finished.append, None)  # zenoh's thread: append is atomic
    right_size = [0]  # key modes: frames sent of exactly --size bytes
    kind, _, what = a.mode.partition("-")
    if kind == "query":
        payloads = []
        if what != "junk":
            cap = Capture(session, keys.cn_to_dn(a.dn), keep=1)
            cap.wait(1, 60)
            cap.close()
            payloads = [cap.frames[-1]] * len(junk)
        payloads = _mix(junk if what != "replay" else [], payloads)

        def on_reply(r: zenoh.Reply) -> None:  # what the DN answered (zenoh's own timeouts aside)
            err = r.err
            if r.ok is not None or (err is not None and err.payload.to_bytes() != b"Timeout"):
                answered[0] += 1

        handler = zenoh.handlers.Callback(on_reply, on_finished, indirect=False)

        def send() -> None:
            k[0] += 1
            gets[0] += 1
            session.get(dn_key, handler, payload=payloads[k[0] % len(payloads)], timeout=0.05)

    elif kind == "reply":
        payloads = []
        if what != "junk":
            cap = Capture(session, dn_key, keep=len(junk))
            cap.wait(50, 60)
            cap.close()
            payloads = list(cap.frames)
        payloads = _mix(junk if what != "replay" else [], payloads)
        rogue = Rogue(session, dn_key)
        cleanup.append(rogue.close)
        rogue.seen.wait(60)

        def send() -> None:
            k[0] += 1
            rogue.reply(payloads[k[0] % len(payloads)])

    elif kind == "tm":
        payloads = []
        if what != "junk":
            cap = Capture(session, keys.telemetry, keep=len(junk))
            cap.wait(50, 60)
            cap.close()
            payloads = list(cap.frames)
        payloads = _mix(junk if what != "replay" else [], payloads)
        tm_pub = session.declare_publisher(keys.telemetry)
        cleanup.append(tm_pub.undeclare)

        def send() -> None:
            k[0] += 1
            tm_pub.put(payloads[k[0] % len(payloads)])

    elif kind == "declare":
        v = m.vehicle
        noop = zenoh.handlers.Callback(lambda _: None, indirect=False)
        kinds: list[Any]
        # --distinct: each declaration on a key of its own (a new resource
        # in every routing table that takes it in), else all on one key.
        x = (lambda: f"x{k[0]}") if a.distinct else (lambda: "")
        if what == "keyexpr":  # only key expressions: no subscriber, no queryable

            class _Ke:
                def __init__(self, ke: zenoh.KeyExpr) -> None:
                    self.ke = ke

                def undeclare(self) -> None:
                    session.undeclare(self.ke)

            kinds = [lambda: _Ke(session.declare_keyexpr(f"{v}/{x() or 'x'}"))]
        elif what == "denied":
            kinds = [
                lambda: session.declare_subscriber(f"{v}/**" + (f"/{x()}" if x() else ""), noop),
                lambda: session.declare_queryable(dn_key + (f"/{x()}" if x() else ""), noop),
            ]
        else:
            kinds = [
                lambda: session.declare_subscriber(keys.telemetry, noop),
                lambda: session.declare_subscriber(f"{v}/{x() or '*'}/events", noop),
                lambda: session.liveliness().declare_subscriber(f"{v}/{x() or '*'}/alive", noop),
            ]
        held: list[deque[Any]] = [deque() for _ in kinds]

        def send() -> None:
            i = k[0] % len(kinds)
            k[0] += 1
            if len(held[i]) >= a.hold:
                held[i].popleft().undeclare()
            held[i].append(kinds[i]())

        def undeclare_all() -> None:
            for h in held:
                while h:
                    h.popleft().undeclare()

        cleanup.append(undeclare_all)

    elif kind == "key":
        if not a.key:
            raise SystemExit(f"{a.mode}: --key is required")
        junk = [rng.randbytes(rng.randrange(0, 2000)) for _ in range(64)]
        junk += [rng.randbytes(a.size) for _ in range(64)]
        rng.shuffle(junk)
        genuine: list[bytes] = []
        if a.frames_stdin:
            words = sys.stdin.readline().split()
            if not words or words[0] != "frames":
                raise SystemExit(f"{a.mode}: expected a line `frames HEX...` on stdin")
            genuine = [bytes.fromhex(w) for w in words[1:]]
        elif a.capture:
            # What the key carries now and then (events) may not come within
            # the wait: then the flood is junk only (``genuine`` says so).
            cap = Capture(session, a.capture, keep=len(junk))
            with suppress(SystemExit):
                cap.wait(len(junk), a.capture_wait)
            cap.close()
            genuine = list(cap.frames)
        # Junk and genuine frames alternately, as many of each (a frame
        # replayed many times over is refused each time as stale).
        payloads = _mix(junk, (genuine * len(junk))[: len(junk)] if genuine else [])
        if a.insider:
            payloads = insider_tagged(m, a.insider, payloads, genuine)
        right = [len(x) == a.size for x in payloads]
        block = zenoh.CongestionControl.BLOCK
        if what == "get":

            def on_key_reply(r: zenoh.Reply) -> None:
                err = r.err
                if r.ok is not None or (err is not None and err.payload.to_bytes() != b"Timeout"):
                    answered[0] += 1

            key_handler = zenoh.handlers.Callback(on_key_reply, on_finished, indirect=False)
            key = a.key

            def send() -> None:
                k[0] += 1
                gets[0] += 1
                right_size[0] += right[k[0] % len(payloads)]
                session.get(
                    key,
                    key_handler,
                    payload=payloads[k[0] % len(payloads)],
                    timeout=0.05,
                    congestion_control=block,
                )

        elif what == "put":
            key_pub = session.declare_publisher(a.key, congestion_control=block)
            cleanup.append(key_pub.undeclare)

            def send() -> None:
                k[0] += 1
                right_size[0] += right[k[0] % len(payloads)]
                key_pub.put(payloads[k[0] % len(payloads)])

        else:  # answer: a rogue queryable, answering the newest query
            key_rogue = Rogue(session, a.key)
            cleanup.append(key_rogue.close)
            if not key_rogue.seen.wait(60):
                raise SystemExit(f"{a.mode}: no query on {a.key} in 60 s")

            def send() -> None:
                k[0] += 1
                right_size[0] += right[k[0] % len(payloads)]
                key_rogue.reply(payloads[k[0] % len(payloads)])

    else:  # cmd-replay: the frames come on stdin, captured on the wire
        words = sys.stdin.readline().split()
        if not words or words[0] != "frames" or len(words) < 2:
            raise SystemExit("cmd-replay: expected a line `frames HEX...` on stdin")
        payloads = [bytes.fromhex(w) for w in words[1:]]
        pub = session.declare_publisher(keys.gn_to_cn)
        cleanup.append(pub.undeclare)

        def send() -> None:
            k[0] += 1
            pub.put(payloads[k[0] % len(payloads)])

    print("ready", flush=True)
    if sys.stdin.readline().strip() != "go":
        return 0
    stop = threading.Event()

    def until_stop() -> None:  # a line `stop` (or stdin's end) ends the attack early
        sys.stdin.readline()
        stop.set()

    threading.Thread(target=until_stop, daemon=True).start()
    sent, seconds = paced(a.rate, a.duration, send, stop)
    # The last gets' answers, if any, come in: zenoh finalizes each get
    # (its handler's drop) once answered or at its 50 ms timeout.
    poll_until(lambda: len(finished) >= gets[0], 10.0)
    for c in cleanup:
        c()
    session.close()
    result: dict[str, Any] = {"sent": sent, "seconds": round(seconds, 3), "rate": sent / seconds}
    if kind == "query" or a.mode == "key-get":
        result["answered"] = answered[0]
    if kind == "key":
        result["genuine"] = len(genuine)
        result["right_size"] = right_size[0]
        if a.insider:  # the run the insider tagged in: the captured frames'
            result["insider_run"] = Channel.run_of(genuine[0]) if genuine else 0
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
