"""Terms and fencing: which control node may drive a device node (docs/architecture.md#failover).

A mission with a standby control node numbers its commanders' reigns: the
**term** (1 for the first commander, one more per takeover), carried in every
trigger (``dnX_term``) and in telemetry (``cn_term``). :class:`TermGuard`
(used by :class:`~zplatform.control.loop.DeviceLogic`) is a device node's rule: run a
trigger only of the highest term it ran or promised (a lower term's is
answered, never run), follow a higher term only on a promise or after its
own term's lease ran out, never run two triggers of one loop. The probe
(``STATUS``, ``ASK`` a term, ``RELEASE`` it) is a control node's question to
a device node before it takes command: :func:`ask_frame`, :func:`read_ask`,
:func:`reply_frame`, :func:`read_reply`, :func:`next_term`.

Contract: sans-IO; :class:`TermGuard` allocates nothing per trigger. Every
integer a frame carries is range-checked where it is read (a term at most
:data:`TERM_MAX`, a loop at most :data:`LOOP_MAX`, an asker a control node, a
flag 0 or 1): a frame outside them raises CodecError, counted like a forged one.

The probe byte by byte and the ranges: codecs/FORMAT.md (section 6.6).
"""

from __future__ import annotations

import secrets
import struct
from typing import NamedTuple

from ..core.auth import TAG_LEN, AuthError, Channel
from ..errors import CodecError

__all__ = [
    "ASK",
    "LOOP_MAX",
    "NONCE_LEN",
    "RELEASE",
    "STATUS",
    "TERM_JUMP",
    "TERM_MAX",
    "ProbeAsk",
    "ProbeReply",
    "TermGuard",
    "Verdict",
    "ask_frame",
    "ask_nonce",
    "ask_size",
    "ask_stamp",
    "attested_term",
    "next_term",
    "read_ask",
    "read_reply",
    "reply_frame",
    "screen_reply",
]

VERSION = 1
NONCE_LEN = 16
ASK, STATUS, RELEASE = 1, 2, 3
"""The kinds of probe question (module doc)."""
_KINDS = (ASK, STATUS, RELEASE)
TERM_MAX = 0xFFFF_FFFE
"""The highest term a node may run, ask for or adopt (module doc): one below
the largest ``u32``, so ``term + 1`` of a valid term is always representable
and a node at :data:`TERM_MAX` asks for nothing more."""
TERM_JUMP = 8
"""How far above the term it knows (its mirror's, or one most device nodes
attest: :func:`attested_term`) a control node asks past a term one device
node alone reports (docs/architecture.md#failover): enough for an honest
device node fenced a few takeovers ahead of the others (each takeover is one
term; a promise held past it lapses within the lease), while a device node's
insider naming :data:`TERM_MAX` burns at most this many terms per takeover
instead of the whole term space."""
LOOP_MAX = (1 << 63) - 1
"""The highest loop number taken from a failover frame (a mirror's ``seq``,
a probe answer's ``last_loop``): schedule arithmetic on it stays within the
``u64``/``i64`` fields it is written back to."""
MAX_ASKERS = 2
"""Control nodes a mission can have (``cn``, ``cn_b``): a question's
``asker`` is below this."""
# magic "ZP", version, kind, device node index, the asker (its index among the
# mission's control nodes), term, nonce, the asker's stamp
_ASK = struct.Struct(f"<2sBBBBI{NONCE_LEN}sq")
# magic "ZA", version, device node index, nonce echo, term run, term promised,
# granted, safed_why, quiet (ns since the last trigger ran; -1: none yet),
# that trigger's loop and its stamp (the commander's clock)
_REPLY = struct.Struct(f"<2sBB{NONCE_LEN}sIIBBqQq")
_A_MAGIC = b"ZP"
_R_MAGIC = b"ZA"


class ProbeAsk(NamedTuple):
    """A probe question, as a device node reads it."""

    kind: int
    dn: int
    asker: int
    term: int
    nonce: bytes
    t_ns: int


class ProbeReply(NamedTuple):
    """A device node's answer to a probe (module doc)."""

    dn: int
    nonce: bytes
    term: int
    promised: int
    granted: bool
    safed_why: int
    quiet_ns: int
    last_loop: int
    last_t_ns: int


def ask_size(authenticated: bool) -> int:
    """Bytes of a probe question on the wire."""
    return _ASK.size + (TAG_LEN if authenticated else 0)


def reply_size(authenticated: bool) -> int:
    """Bytes of a probe reply on the wire."""
    return _REPLY.size + (TAG_LEN if authenticated else 0)


def new_nonce() -> bytes:
    return secrets.token_bytes(NONCE_LEN)


def next_term(term: int) -> int:
    """The term to ask for after ``term`` (every term known): ``term + 1``,
    or 0 when ``term`` is :data:`TERM_MAX` already, or out of range (there
    is no next term: the asker asks for nothing)."""
    return term + 1 if 0 <= term < TERM_MAX else 0


def attested_term(terms: list[int], nodes: int) -> int:
    """The highest term more than half of ``nodes`` device nodes report:
    the ``nodes // 2 + 1``-th largest of ``terms`` (one per device node that
    answered, or 0 for one that did not; 0 when fewer than that many are
    given). No minority (one device node's insider) can raise it above what
    an honest device node reports (docs/architecture.md#failover); one that
    lowers it only makes its asker ask too low a term, which is refused.
    Allocates (a sorted copy): for probe rounds and a stand-down, never per
    trigger."""
    k = nodes // 2 + 1
    if len(terms) < k:
        return 0
    return sorted(terms, reverse=True)[k - 1]


def ask_stamp(body: bytes | memoryview, askers: int = MAX_ASKERS) -> tuple[int, int]:
    """``(asker, stamp)`` of a probe question's checked body (fixed offsets;
    CodecError for a body of another size, or an asker that is not one of
    ``askers`` control nodes)."""
    if len(body) != _ASK.size:
        raise CodecError(f"{len(body)} bytes: not a probe question")
    asker = body[5]
    if asker >= askers:
        raise CodecError(f"a probe question from control node {asker}: there are {askers}")
    return asker, int.from_bytes(body[_ASK.size - 8 :], "little", signed=True)


def any_run(payload: bytes | bytearray | memoryview) -> bool:
    """Whether a device node answers the probe question ``payload`` whatever
    run it names (its tag still checked under that run's key): a STATUS,
    which changes nothing and whose answer is bound to the asker's nonce, so
    a control node that has not learned the run yet (restarted, it asks
    before it knows who commands) gets its answer. An ASK or a RELEASE
    moves a device node's term: only of its run."""
    return len(payload) > 3 and payload[3] == STATUS  # byte 3: the question's kind


def ask_frame(
    ch: Channel | None, kind: int, index: int, asker: int, term: int, nonce: bytes, t_ns: int
) -> bytes:
    """A probe question for device node ``index`` from control node number
    ``asker`` (tagged with ``ch``, the node's ``probe_cn_to_dnX`` channel,
    when the mission authenticates)."""
    body = _ASK.pack(_A_MAGIC, VERSION, kind, index, asker, term, nonce, t_ns)
    return bytes(ch.seal(body)) if ch is not None else body


def read_ask(
    ch: Channel | None,
    payload: bytes | bytearray | memoryview,
    index: int,
    askers: int = MAX_ASKERS,
) -> ProbeAsk:
    """Check and read a probe question for device node ``index`` from one of
    ``askers`` control nodes; CodecError (AuthError for a bad tag) for
    anything else, a value out of range included (module doc): an ASK or a
    RELEASE names a term from 1 to :data:`TERM_MAX`, a STATUS none (0).
    With ``ch`` bound to a run (zplatform.core.auth.Run), an ASK or a RELEASE
    must be of that run (RunError: an earlier run's, replayed); a STATUS may
    be of any (:func:`any_run`)."""
    body = ch.open(payload, any_run=any_run(payload)) if ch is not None else memoryview(payload)
    if len(body) != _ASK.size:
        raise CodecError(f"{len(body)} bytes: not a probe question")
    magic, version, kind, i, asker, term, nonce, t_ns = _ASK.unpack(body)
    if magic != _A_MAGIC or version != VERSION or kind not in _KINDS:
        raise CodecError("not a probe question of version 1")
    if i != index:
        raise CodecError(f"a probe question for device node {i}, not {index}")
    if asker >= askers:
        raise CodecError(f"a probe question from control node {asker}: there are {askers}")
    if (term != 0) if kind == STATUS else not 1 <= term <= TERM_MAX:
        raise CodecError(f"a probe question for term {term}: out of range for its kind {kind}")
    return ProbeAsk(kind, i, asker, term, nonce, t_ns)


def reply_frame(ch: Channel | None, r: ProbeReply) -> bytes:
    """A device node's reply (tagged with its ``probe_dnX_to_cn`` channel)."""
    body = _REPLY.pack(
        _R_MAGIC,
        VERSION,
        r.dn,
        r.nonce,
        r.term,
        r.promised,
        int(r.granted),
        r.safed_why,
        r.quiet_ns,
        r.last_loop,
        r.last_t_ns,
    )
    return bytes(ch.seal(body)) if ch is not None else body


_ASK_NONCE_AT = 10  # after magic, version, kind, index, asker and term (_ASK)


def ask_nonce(frame: bytes | bytearray | memoryview) -> bytes:
    """The nonce of probe question ``frame`` (as :func:`ask_frame` made it;
    read, not checked): what its reply must echo."""
    return bytes(frame[_ASK_NONCE_AT : _ASK_NONCE_AT + NONCE_LEN])


def screen_reply(
    ch: Channel, payload: bytes | bytearray | memoryview, index: int, nonce: bytes
) -> bool:
    """Whether ``payload`` may be device node ``index``'s reply to the
    question with ``nonce``: its header tag checks on ``ch`` (the node's
    ``probe_dnX_to_cn`` channel; a channel no other thread uses), and its
    magic, version, node and echoed nonce, all within the header tag's
    bytes: no MAC over the body. For zenoh's reply callback, before the
    hand-off (:class:`~zplatform.runtime.sync.ProbeSync`): junk and replies
    to other questions never take a place a genuine reply needs.
    :func:`read_reply` decides. Never raises."""
    try:
        body = ch.open_header(payload)
    except CodecError:
        return False
    return (
        len(body) == _REPLY.size
        and body[:2] == _R_MAGIC
        and body[2] == VERSION
        and body[3] == index
        and body[4 : 4 + NONCE_LEN] == nonce
    )


def read_reply(
    ch: Channel | None, payload: bytes | bytearray | memoryview, index: int, nonce: bytes
) -> ProbeReply:
    """Check and read device node ``index``'s reply to the question with
    ``nonce``; CodecError (AuthError: a bad tag) for anything else, a reply
    to another question included."""
    body = ch.open(payload) if ch is not None else memoryview(payload)
    if len(body) != _REPLY.size:
        raise CodecError(f"{len(body)} bytes: not a probe reply")
    magic, version, i, echo, term, promised, granted, why, quiet, loop, t = _REPLY.unpack(body)
    if magic != _R_MAGIC or version != VERSION or i != index:
        raise AuthError(f"not device node {index}'s probe reply")
    if echo != nonce:
        raise CodecError("a probe reply to another question (a replay, or late)")
    if term > TERM_MAX or promised > TERM_MAX:
        raise CodecError(f"a probe reply naming term {max(term, promised)}: above {TERM_MAX}")
    if granted > 1 or (granted and not promised):
        raise CodecError(f"a probe reply granting {granted} for term {promised}: malformed")
    if quiet < -1 or loop > LOOP_MAX:
        raise CodecError(f"a probe reply quiet for {quiet} ns since loop {loop}: out of range")
    return ProbeReply(i, echo, term, promised, bool(granted), why, quiet, loop, t)


class Verdict:
    """What :meth:`TermGuard.admit` says of a trigger's term."""

    SAME = 0
    """The term the node runs: run it (if it is otherwise new)."""
    NEW = 1
    """A higher term the node may follow (promised to it, its lease out, or
    its first trigger ever): run it, then follow that term."""
    FENCED = 2
    """Below a term the node runs or has promised: answer, never run."""
    LEASED = 3
    """A higher term, but a trigger of the current term ran within the
    lease: the current commander is alive; answer, never run."""


class TermGuard:
    """A device node's term fencing (module doc), sans-IO.

    ``lease_ns``: ``failover.lease_loops`` periods. The caller tells it when
    a trigger's term is to be judged (:meth:`admit`, with the local time of
    the last trigger that ran) and when a trigger of a term ran
    (:meth:`ran`); it answers probe questions (:meth:`answer`). Not
    thread-safe: the node's loop thread.
    """

    __slots__ = ("_asker", "_given", "_lease", "_promise", "_until", "term")

    def __init__(self, lease_ns: int) -> None:
        self._lease = lease_ns
        self.term = 0
        """The highest term whose trigger this node ran (0: none yet)."""
        self._promise = 0
        self._asker = -1
        self._given = 0
        self._until = 0

    def promised(self, now_ns: int) -> int:
        """The term promised and not lapsed at ``now_ns`` (0: none)."""
        return self._promise if self._promise and now_ns < self._until else 0

    def seen(self, now_ns: int) -> int:
        """The term this node reports (``dnX_term_seen``): the highest it
        runs or has promised."""
        return max(self.term, self.promised(now_ns))

    def _quiet(self, now_ns: int, last_run_ns: int | None) -> bool:
        """No trigger ran, and no promise was given, for the lease: a fresh
        promise is a commander about to drive, as much as a trigger is."""
        if self.promised(now_ns) and now_ns - self._given < self._lease:
            return False
        return last_run_ns is None or now_ns - last_run_ns >= self._lease

    def admit(self, term: int, now_ns: int, last_run_ns: int | None) -> int:
        """The :class:`Verdict` on a trigger of ``term`` arriving at ``now_ns``;
        ``last_run_ns``: this node's time when its last trigger ran (None: never)."""
        if term < self.seen(now_ns):
            return Verdict.FENCED
        if term == self.term:
            return Verdict.SAME
        # A higher term: promised to it, the node's first, or the lease is out.
        if term == self.promised(now_ns) or self.term == 0 or self._quiet(now_ns, last_run_ns):
            return Verdict.NEW
        return Verdict.LEASED

    def ran(self, term: int) -> bool:
        """A trigger of ``term`` ran; returns whether the node now follows a
        new term (its promise, if any, is then fulfilled)."""
        if term <= self.term:
            return False
        self.term = term
        self._promise = 0
        return True

    def answer(
        self, kind: int, asker: int, term: int, now_ns: int, last_run_ns: int | None
    ) -> bool:
        """Take a probe question from control node number ``asker`` (module
        doc); returns whether an ASK was granted. A promise is to one asker:
        the other control node asking for the same term is refused."""
        if kind == ASK:
            if term > self.seen(now_ns) and self._quiet(now_ns, last_run_ns):
                self._promise = term
                self._asker = asker
                self._given = now_ns
                self._until = now_ns + self._lease
                return True
            # The same asker again, for the term already promised to it.
            return term == self.promised(now_ns) and asker == self._asker
        if kind == RELEASE and term == self._promise and asker == self._asker:
            self._promise = 0
        return False
