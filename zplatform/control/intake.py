"""The intake of frames from the network: refused in constant time, handed
off bounded, the newest valid frame first.

One intake per key a node takes frames on (:class:`TriggerIntake`,
:class:`ProbeIntake`, :class:`MirrorIntake`, :class:`RequestIntake`,
:class:`TelemetryIntake`, and :class:`ReplyCheck` for the CN's sync
replies), run in the zenoh callback. Its checks, the first failure
winning: size (unread), one copy (none for :meth:`Intake.check_view`),
the header tag, freshness from the header, the body-MAC budget
(:data:`MAC_SPARE`), the body's MAC, the rest of freshness, a per-asker
rate bound (:class:`ProbeIntake`): junk and replays never cost a body MAC
nor spend a bound (issue 25). A refused frame is only counted. :meth:`Intake.admit`
puts an admitted one (its bytes) in a bounded :class:`~.handoff.Mailbox`
whose last item is the newest valid frame; :meth:`Intake.check` only
checks. Never blocks beyond two short locks, never raises for what
arrives; the loop thread takes the items and, once per loop, the counts
(:meth:`Intake.take_counts`), and events them (:class:`RefusalLog`).
Detail: docs/architecture.md#the-intake; per key: docs/keyspace.md;
the stamps' offsets: codecs/FORMAT.md §2.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Generic, Protocol, TypeVar, cast

from ..config import Mission
from ..config.codes import CommandStatus
from ..core.auth import NO_RUN, TAG_LEN, Channel, RunError
from ..core.codec import (
    bundle_entry,
    bundle_size,
    fixed_stamp,
    frame_data,
    frame_stamp,
    is_bundle,
    max_frame_length,
)
from ..core.datavector import Layout
from ..core.messages import wildcard_sync_for
from ..errors import CodecError
from .commands import RequestNumber, request_refusal
from .fencing import LOOP_MAX, TERM_MAX, any_run, ask_size, ask_stamp
from .handoff import Mailbox, Waker

__all__ = [
    "BACKLOG",
    "CN_REFUSALS",
    "DEDUPE_WINDOW",
    "EVENT_PERIOD_NS",
    "INBOX",
    "IOX",
    "MAC_SPARE",
    "MIRRORS",
    "PROBES",
    "PROBE_BURST",
    "ZENOH",
    "CnRefusals",
    "Dedupe",
    "Intake",
    "MirrorIntake",
    "Payload",
    "ProbeIntake",
    "RefusalLog",
    "ReplyCheck",
    "RequestIntake",
    "TelemetryIntake",
    "TriggerIntake",
    "ahead_bound_ns",
    "max_frame_len",
]

BACKLOG = 4
"""Valid triggers a DN keeps while its loop thread is busy: older ones are
for loops the CN has closed, so the oldest is let go past this."""
INBOX = 16
"""Command request frames a CN keeps between two loops (the newest ones):
only authentic requests of this run, numbered above every number seen, get
this far (:class:`RequestIntake`'s mailbox, in every CN driver)."""
PROBES = 2
"""Probe questions a DN keeps while its loop thread is busy."""
PROBE_BURST = 8
"""Probe questions one control node may ask a DN at once; then one a loop
period (:class:`ProbeIntake`'s rate bound: a standby's round is one STATUS,
one ASK and one RELEASE, at most one round a period)."""
MIRRORS = 4
"""Mirror frames a control node keeps between two beats (the newest ones)."""
MAC_SPARE = 2
"""Wasted body MACs an intake computes between two :meth:`Intake.take_counts`
(its consumer's loop): for frames whose header looks new, those that fail
(a genuine header spliced onto another body: the header is authentic,
so only a peer that saw it, a man in the middle, can); and as many, apart,
for frames whose header can tell neither new nor stale
(:meth:`Intake._fresh_header`), those that admit nothing (failed, or a
genuine frame refused by freshness after it: a replay). A body MAC that
admits its frame, or that a new-looking genuine frame passes, is not
charged (a genuine sender's frames, each newer than the last). Once a
budget is spent, what passes the header into it is dropped unread until
the next loop: counted bad (a header that looked new: spliced junk, or a
genuine frame after it, which such a peer could as well have dropped) or
stale (one that looked old)."""
EVENT_PERIOD_NS = 1_000_000_000
"""At most one refusal event per intake in this much loop time (:class:`RefusalLog`)."""

T = TypeVar("T")
H = TypeVar("H")


class Payload(Protocol):
    """What an intake reads a frame from: ``zenoh.ZBytes`` (its length is
    free, ``to_bytes`` copies)."""

    def __len__(self) -> int: ...

    def to_bytes(self) -> bytes: ...


def ahead_bound_ns(mission: Mission) -> int:
    """How far ahead of a vehicle node's corrected clock a genuine stamp of
    the CN's may be: the clock bound (``clock.offset_bound_ms``) and a
    period, as :class:`~zplatform.control.loop.DeviceLogic` believes a trigger."""
    return round(mission.clock.offset_bound_ms * 1e6) + mission.period_ns


def max_frame_len(size: int, channel: Channel | None) -> int:
    """The longest valid frame of a region of ``size`` bytes as it travels
    (:func:`zplatform.core.codec.max_frame_length`), with its tag."""
    return max_frame_length(size) + (TAG_LEN if channel is not None else 0)


_NO_VIEW = memoryview(b"")

ZENOH, IOX = 1, 2
"""The paths a frame can come by (:meth:`Intake.admit`'s ``path``): zenoh,
or iceoryx2 shared memory (a telemetry frame to a ground on the CN's host)."""
DEDUPE_WINDOW = 64
"""Frames a two-path intake remembers (:class:`Dedupe`): a frame the other
path brings this many frames late is no longer told from a replay."""


class Dedupe:
    """The frames a two-path intake admitted lately (:data:`DEDUPE_WINDOW`,
    a ring by loop number), each with the path it came by: a frame that
    arrives again, the very same (fixed-width header: loop number, stamp,
    length, and its last :data:`~zplatform.core.auth.TAG_LEN` bytes: its
    tag), by the *other* path is the copy that path carries (the same
    telemetry over iceoryx2 and zenoh), dropped as a duplicate: not taken
    twice, and not counted as refused. Only once per frame and path: a
    further copy (a replay on either path) goes through the intake, which
    refuses it as not fresh. Nothing is ever admitted by it, so a forged
    copy costs nothing; a frame without the fixed-width header is never
    a duplicate. Not thread-safe: the intake's lock. Preallocated; a check
    allocates two small slices at most."""

    __slots__ = ("_lens", "_paths", "_seqs", "_stamps", "_tags")

    def __init__(self) -> None:
        k = DEDUPE_WINDOW
        self._seqs = [-1] * k
        self._stamps = [0] * k
        self._lens = [0] * k
        self._paths = [0] * k
        self._tags = bytearray(k * TAG_LEN)

    def repeat(self, frame: bytes | memoryview, path: int) -> bool:
        """Whether ``frame`` is a frame admitted by another path, coming by
        ``path`` for the first time (then noted: a second copy is not)."""
        n = len(frame)
        stamp = fixed_stamp(frame) if n > TAG_LEN else None
        if stamp is None:
            return False
        seq, t_ns = stamp
        i = seq % DEDUPE_WINDOW
        if self._seqs[i] != seq or self._stamps[i] != t_ns or self._lens[i] != n:
            return False
        if self._paths[i] & path:
            return False  # this path brought it already: a replay
        at = i * TAG_LEN
        if memoryview(self._tags)[at : at + TAG_LEN] != memoryview(frame)[n - TAG_LEN :]:
            return False
        self._paths[i] |= path
        return True

    def note(self, frame: bytes | memoryview, path: int) -> None:
        """Remember ``frame``, admitted by ``path``."""
        n = len(frame)
        stamp = fixed_stamp(frame) if n > TAG_LEN else None
        if stamp is None:
            return
        seq, t_ns = stamp
        i = seq % DEDUPE_WINDOW
        at = i * TAG_LEN
        tag = memoryview(frame)[n - TAG_LEN :]
        if (
            self._seqs[i] == seq
            and self._stamps[i] == t_ns
            and self._lens[i] == n
            and memoryview(self._tags)[at : at + TAG_LEN] == tag
        ):
            self._paths[i] |= path  # admitted again (no keys: no freshness)
            return
        self._seqs[i], self._stamps[i], self._lens[i], self._paths[i] = seq, t_ns, n, path
        self._tags[at : at + TAG_LEN] = tag


class _InPlace:
    """A :class:`Payload` whose ``to_bytes`` is the view itself (no copy):
    :meth:`Intake.check_view`. Every use of the frame in ``_check`` (the
    tag, the frame's header) reads a buffer, which a view is."""

    __slots__ = ("view",)

    def __init__(self, view: memoryview) -> None:
        self.view = view

    def __len__(self) -> int:
        return len(self.view)

    def to_bytes(self) -> bytes:
        return cast(bytes, self.view)


class Intake(ABC, Generic[H]):
    """One key's intake (module doc): size, tag, freshness, and, for a key
    whose frames a loop takes later, a bounded mailbox of
    ``(handle, frame bytes)``.

    ``max_len``/``min_len``: the frame lengths the key can carry;
    ``channel``: the intake's own channel for the key (None: the mission
    does not authenticate); ``capacity``: the mailbox's (0: no mailbox,
    :meth:`check` only). Subclasses say what a key's frame is
    (:meth:`_frame`) and when it is fresh (:meth:`_fresh`, called with the
    intake's lock held).

    Thread-safe: :meth:`check` and :meth:`admit` from any of zenoh's
    threads; :attr:`box` and :meth:`take_counts` from the consumer.
    """

    def __init__(
        self,
        name: str,
        max_len: int,
        channel: Channel | None,
        capacity: int = 0,
        *,
        waker: Waker | None = None,
    ) -> None:
        self.name = name
        self.max_len = max_len
        self._min = TAG_LEN + 1 if channel is not None else 1
        self._open = channel
        self._lock = threading.Lock()
        self._in_place = _InPlace(_NO_VIEW)
        self.box: Mailbox[tuple[H, bytes]] | None = Mailbox(capacity, waker) if capacity else None
        self.size = 0
        self.bad = 0
        self.stale = 0
        # Body MACs that admitted nothing since the last take_counts: of
        # headers that looked new, and of headers that could not tell.
        self._macs = 0
        self._unsure = 0
        self.unchecked = 0
        """Frames dropped after their header for want of budget (also in
        ``bad`` or ``stale``) since the last :meth:`take_counts`; the count
        the last one took is :attr:`took_unchecked`."""
        self.took_unchecked = 0
        self.on_other_run: Callable[[], None] | None = None
        """Called (on zenoh's thread: it must not block) for each genuine
        frame of another run (zplatform.core.auth.RunError): a device node's cue
        to ask its clock exchange for the run now (the control node may
        have started a new one)."""

    @property
    def authenticates(self) -> bool:
        """Whether this intake checks tags: then every frame it passes has
        an authentic tag, and its consumer need not check it again
        (:meth:`zplatform.control.loop.DeviceLogic.trigger`'s ``authentic``)."""
        return self._open is not None

    dedupe: Dedupe | None = None
    """Set on an intake that takes one sender's frames by two paths (the
    ground's telemetry over iceoryx2 and zenoh): the other path's copy of a
    frame admitted is dropped as a duplicate (:class:`Dedupe`), counted in
    :attr:`duplicates`, never as a refusal. None: one path."""
    duplicates = 0
    """Frames dropped as the other path's copy of one admitted (never reset)."""
    taken_iox = 0
    """Frames :meth:`admit_view` (or :meth:`admit`) admitted by path
    :data:`IOX` (never reset; under the lock, whatever thread admits)."""
    taken_zenoh = 0
    """Frames admitted by path :data:`ZENOH` (never reset)."""

    def check(self, payload: Payload, handle: H) -> bytes | None:
        """The frame's bytes when it passes every check, else None (counted)."""
        with self._lock:
            return self._check(payload, handle)

    def check_view(self, view: memoryview, handle: H) -> memoryview | None:
        """:meth:`check` over a frame read in place (a loaned sample in
        shared memory, :mod:`zplatform.runtime.intrahost`): the same checks
        in the same order (size, tag, freshness), with no copy; returns
        ``view`` itself when it passes. The caller keeps the memory under
        ``view`` alive, and its bytes as checked, until it has copied what it
        needs (docs/architecture.md#intra-host: why a writer of that memory
        gains nothing). Thread-safe as :meth:`check`."""
        with self._lock:
            # _check's one copy is the payload's to_bytes: here the view
            # (one holder per intake, reused under the lock: no allocation).
            held = self._in_place
            held.view = view
            try:
                return cast("memoryview | None", self._check(held, handle))
            finally:
                held.view = _NO_VIEW

    def admit(self, payload: Payload, handle: H, path: int = ZENOH) -> bool:
        """Check ``payload``; put ``(handle, its bytes)`` in the mailbox when
        it passes (returns True), else count why (False). ``path``: the path
        it came by (:data:`ZENOH`, :data:`IOX`), for :attr:`dedupe`."""
        box = self.box
        assert box is not None, "an intake without a mailbox only checks"
        with self._lock:
            data = self._check(payload, handle, path)
            if data is None:
                return False
            box.put((handle, data))  # under the lock: admission order is mailbox order
            self._count(path)
            return True

    def _count(self, path: int) -> None:
        if path == IOX:
            self.taken_iox += 1
        else:
            self.taken_zenoh += 1

    def admit_view(self, view: memoryview, handle: H, path: int = IOX) -> bool:
        """:meth:`admit` of a frame read in place (a sample in shared memory,
        as :meth:`check_view`): every check on ``view`` itself, then one copy
        (``bytes``) into the mailbox, only of a frame that passed. The
        caller keeps ``view`` alive until this returns."""
        box = self.box
        assert box is not None, "an intake without a mailbox only checks"
        with self._lock:
            held = self._in_place
            held.view = view
            try:
                data = self._check(held, handle, path)
            finally:
                held.view = _NO_VIEW
            if data is None:
                return False
            box.put((handle, bytes(data)))  # the frame's one copy, after its checks
            self._count(path)
            return True

    def _check(self, payload: Payload, handle: H, path: int = ZENOH) -> bytes | None:
        n = len(payload)
        if not self._min <= n <= self.max_len:
            self.size += 1
            return None
        if not self._within_rate():
            return None
        data = payload.to_bytes()
        dedupe = self.dedupe
        if dedupe is not None:
            if dedupe.repeat(data, path):  # the other path's copy of one taken
                self.duplicates += 1
                return None
            checked = self._checked(data, handle)
            if checked is not None:
                dedupe.note(checked, path)
            return checked
        return self._checked(data, handle)

    def _checked(self, data: bytes, handle: H) -> bytes | None:
        """The tag and freshness of ``data`` (what :meth:`_check` read)."""
        ch = self._open
        if ch is None:
            return data
        try:
            frame = self._frame(data)
            body = ch.open_header(frame, any_run=self._any_run(frame))
            new = self._fresh_header(body, handle)
            if new is False:  # a replay, by its authentic header: no body MAC
                self.stale += 1
                return None
            if (self._macs if new else self._unsure) >= MAC_SPARE:
                # This loop's budget of wasted body MACs is spent: unread.
                self.unchecked += 1
                if new:
                    self.bad += 1
                else:
                    self.stale += 1
                return None
            if not new:
                self._unsure += 1  # charged unless admitted: a replay the header could not tell
            try:
                ch.check_body(frame)
            except CodecError:
                if new:  # a genuine header on another body (or its bit flipped)
                    self._macs += 1
                raise
            fresh = self._fresh(body, handle)
            if fresh and not new:
                self._unsure -= 1
        except RunError:  # another run's genuine frame (an earlier run's replay): stale
            if self._other_run():
                self.stale += 1
            if self.on_other_run is not None:
                self.on_other_run()
            return None
        except CodecError:  # a bad tag (AuthError), or an authentic frame that is none
            self.bad += 1
            return None
        if not fresh:
            if fresh is not None:  # None: refused and counted by the subclass
                self.stale += 1
            return None
        return data

    def _frame(self, data: bytes) -> bytes | memoryview:
        """The tagged frame in what arrived (CodecError if there is none)."""
        return data

    def _any_run(self, frame: bytes | memoryview) -> bool:
        """Whether ``frame`` may be of any run (zplatform.core.auth.Run): none, by
        default; a probe's STATUS question (zplatform.control.fencing.any_run)."""
        return False

    def _other_run(self) -> bool:
        """Whether a genuine frame of another run counts as ``stale`` (with
        the lock held): it does, by default."""
        return True

    def _within_rate(self) -> bool:
        """Whether a frame of the right size may be read now (before any
        copy; with the lock held): a key with a rate bound and no tag (a
        mission that does not authenticate) counts and refuses the excess
        here. Never for an authenticated key: a bound before the tag is one
        junk can spend (module doc). Every frame, by default."""
        return True

    def _fresh_header(self, body: memoryview, handle: H) -> bool | None:
        """Freshness as far as the frame's header tells it, before its body's
        MAC (with the lock held): ``body``'s first
        :data:`~zplatform.core.auth.HEADER_LEN` bytes (a region frame's
        header: seq, t_ns) are authentic, the rest not yet, and must not be
        read. False: stale (refused, counted stale; records nothing); True:
        new as far as the header tells; None: it cannot tell (a smaller
        budget of body MACs, :data:`MAC_SPARE`). CodecError if the header
        is unreadable. True by default."""
        return True

    @abstractmethod
    def _fresh(self, body: memoryview, handle: H) -> bool | None:
        """Whether the authentic frame ``body`` (with ``handle``) is newer
        than every admitted one; records it as the newest when it is.
        CodecError if unreadable; None: refused for another reason, which
        the subclass counted."""

    def take_counts(self) -> tuple[int, int, int]:
        """``(size, bad, stale)`` refusals since the last call (then zeroed)."""
        with self._lock:
            counts = (self.size, self.bad, self.stale)
            self.size = self.bad = self.stale = 0
            self._macs = self._unsure = 0
            self.took_unchecked, self.unchecked = self.unchecked, 0
            self._took()
        return counts

    def _took(self) -> None:
        """What else :meth:`take_counts` zeroes (with the lock held)."""


class _StampIntake(Intake[H]):
    """Fresh: stamped (``t_ns``, the sender's clock) later than every frame
    admitted so far, and no further ahead of the receiver's clock than its
    bound (:meth:`_ahead`). A sender's stamps grow with its loop, and a
    restarted sender's start after its last run's, so only a replay (or a
    duplicate) is not later; a stamp is authentic, so nobody without the
    key can push it ahead, and the bound ahead keeps a key holder's (or a
    stepped clock's) stamp at the end of time from becoming the newest,
    which would refuse every genuine frame after it."""

    newest_t = -(1 << 63)
    """The stamp of the newest admitted frame."""

    def _fresh_header(self, body: memoryview, handle: H) -> bool | None:
        # The stamp is in the header: the whole rule, before the body's MAC.
        _, t_ns = frame_stamp(body)
        return not self._ahead(t_ns, handle) and t_ns > self.newest_t

    def _fresh(self, body: memoryview, handle: H) -> bool:
        _, t_ns = frame_stamp(body)
        if self._ahead(t_ns, handle):
            return False
        if t_ns <= self.newest_t:
            self._replayed(t_ns, handle)
            return False
        self.newest_t = t_ns
        return True

    def _ahead(self, t_ns: int, handle: H) -> bool:
        """Whether ``t_ns`` is further ahead of the receiver's clock than
        any sender's clock may be (counted by the caller as stale)."""
        return False

    def _replayed(self, t_ns: int, handle: H) -> None:
        """Note a frame refused as not newer (with the lock held)."""


class TriggerIntake(_StampIntake[H]):
    """A DN's sync queries (``{vehicle}/dnX/to_cn``): the CN's trigger for
    the node, alone or in a sync bundle (``transport.sync_query``
    wildcard). Fresh: stamped later than any trigger admitted before, so a
    replayed trigger, however authentic, is refused (and never answered),
    and no further ahead of ``now_ns`` (the node's corrected clock, the
    CN's time) than the clock bound and a period
    (``clock.offset_bound_ms``, as :class:`~zplatform.control.loop.DeviceLogic`
    believes a trigger). Its mailbox keeps :data:`BACKLOG` triggers.

    In a mission with a standby control node a loop's trigger (loop > 0) is
    fresh in its own term (``dnX_term``, read after the body's MAC):
    stamped later than every one admitted of that term, of the newest term
    or the one before it; of an older term, later than every one admitted
    (the rule without terms, which holds for every term).
    So a new commander's first triggers are taken even when stamped before
    a trigger of the old commander that came meanwhile (a stalled commander
    still sending as the standby takes over: the old term's trigger,
    admitted here, is fenced and answered by the logic,
    :mod:`zplatform.control.fencing`); by one global stamp, the new term's
    first loops were refused as replays and the device node went without
    a trigger past its watchdog. A replay is still refused (not newer in its
    term); a header not newer than the newest stamp cannot tell, so it
    costs at most :data:`MAC_SPARE` body MACs a loop, as elsewhere."""

    def __init__(
        self,
        mission: Mission,
        node: str,
        channel: Channel | None,
        now_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        lay = Layout.for_node(mission, "cn")
        dns = mission.device_nodes
        lens = [max_frame_len(lay.region(f"cn_to_{dn}").size, channel) for dn in dns]
        self._index = mission.device_nodes.index(node)
        own = lens[self._index]
        longest = max(own, bundle_size(lens)) if wildcard_sync_for(mission) else own
        self._now = now_ns
        self._max_ahead = ahead_bound_ns(mission)
        # Terms (class doc): where the term sits in the trigger's data; the
        # newest term and the one before it, each with its newest stamp.
        self._term_at = -1
        self._data_len = 0
        if mission.standby is not None:
            region = lay.region(f"cn_to_{node}")
            self._term_at = lay.element(f"{node}_term").offset - region.offset
            self._data_len = region.size
        self._term_hi, self._t_hi = -1, -(1 << 63)
        self._term_lo, self._t_lo = -1, -(1 << 63)
        super().__init__(f"{node}'s sync query", longest, channel, BACKLOG)

    def _fresh_header(self, body: memoryview, handle: H) -> bool | None:
        seq, t_ns = frame_stamp(body)
        if self._ahead(t_ns, handle):
            return False
        if t_ns > self.newest_t:
            return True
        # Not newer than the newest: a replay, or a new term's (class doc).
        return None if self._term_at >= 0 and seq > 0 else False

    def _fresh(self, body: memoryview, handle: H) -> bool:
        seq, t_ns = frame_stamp(body)
        if self._term_at < 0 or seq == 0:  # no terms; or a warm-up, of any term
            return super()._fresh(body, handle)
        if self._ahead(t_ns, handle):
            return False
        at = self._term_at
        term = int.from_bytes(frame_data(body, self._data_len)[at : at + 4], "little")
        if term > TERM_MAX:  # no commander runs it; the newest, it would fence them all
            return False
        if term > self._term_hi:
            self._term_lo, self._t_lo = self._term_hi, self._t_hi
            self._term_hi, self._t_hi = term, t_ns
        elif term == self._term_hi and t_ns > self._t_hi:
            self._t_hi = t_ns
        elif term == self._term_lo and t_ns > self._t_lo:
            self._t_lo = t_ns
        elif term in (self._term_hi, self._term_lo) or t_ns <= self.newest_t:
            # Not newer in its term; or an older term's, not newer than every
            # trigger admitted (the rule without terms, which always holds):
            # a term pushed out by two newer ones (a standby's takeovers the
            # device nodes leased while the commander still drives them) is
            # still taken while its stamps lead, for the logic to run or fence.
            self._replayed(t_ns, handle)
            return False
        self.newest_t = max(self.newest_t, t_ns)
        return True

    def _frame(self, data: bytes) -> bytes | memoryview:
        return bundle_entry(data, self._index) if is_bundle(data) else data

    def _any_run(self, frame: bytes | memoryview) -> bool:
        # The warm-up (loop 0: answered, never run) of any run: a restarted
        # control node warms up before it knows whether it resumes the run.
        # DeviceLogic.trigger refuses any other loop of another run.
        return frame_stamp(frame)[0] == 0

    def _ahead(self, t_ns: int, handle: H) -> bool:
        return t_ns - self._now() > self._max_ahead


class ProbeIntake(Intake[H]):
    """A device node's probe questions (``{vehicle}/dnX/probe``, a redundant
    mission's control nodes asking which term it runs, :mod:`zplatform.control.fencing`).
    Fresh: stamped later than any question admitted from the same control
    node, so a replayed question is refused unanswered, and no further
    ahead of ``clock_ns`` (the node's corrected clock, the CN's time) than
    the clock bound and a period (``bound_ns``), so a question stamped at
    the end of time never locks its asker out. Its mailbox keeps
    :data:`PROBES` questions (``waker``: the trigger mailbox's, so the node's
    loop wakes for either).

    **Rate bound** (``now_ns``: the clock it runs on; ``period_ns``: the
    mission's loop period): a token bucket kept as one integer (GCRA:
    constant time, no allocation) per asker, once the tag proved who asks
    and the question is fresh: at most :data:`PROBE_BURST` at once, then
    one a period; what exceeds it is refused unanswered and counted in
    :attr:`excess`. So a flood reaches the loop thread with a few answers
    a period at most, and only a key holder's questions spend a bound:
    junk (a bad header tag) is refused for the cost of the tag, and a
    replay by its stamp, neither spending any asker's bound, so a genuine
    question sent during a keyless flood is answered (issue 25: a bound
    per channel before the tag let such a flood refuse the standby's
    questions, delaying a takeover). Without authentication the asker
    cannot be told: one bound per channel, before any copy, of ``askers``
    * :data:`PROBE_BURST` questions at once, then ``askers`` a period."""

    def __init__(
        self,
        node: str,
        channel: Channel | None,
        waker: Waker,
        *,
        period_ns: int,
        askers: int = 2,
        now_ns: Callable[[], int] = time.monotonic_ns,
        clock_ns: Callable[[], int] = time.time_ns,
        bound_ns: int = 0,
    ) -> None:
        super().__init__(
            f"{node}'s probe", ask_size(channel is not None), channel, PROBES, waker=waker
        )
        self._askers = askers
        self._newest = [-(1 << 63)] * askers
        self._now = now_ns
        self._clock = clock_ns
        self._max_ahead = bound_ns + period_ns
        self._every = max(period_ns, 1)
        self._tau = (PROBE_BURST - 1) * self._every  # one asker's burst
        self._every_all = max(self._every // askers, 1)
        self._tau_all = (askers * PROBE_BURST - 1) * self._every_all
        self._tat = [-(1 << 63)] * askers  # per asker: the theoretical arrival time
        self._tat_all = -(1 << 63)
        self._excess = 0
        self.excess = 0
        """Questions refused beyond a rate bound, among those counted by the
        last :meth:`take_counts`."""

    def _other_run(self) -> bool:
        """Whether a genuine frame of another run counts as ``stale`` (with
        the lock held): it does, by default."""
        return True

    def _within_rate(self) -> bool:
        if self._open is not None:
            return True  # authenticated: the asker's bound, after its tag (class doc)
        now = self._now()
        tat = max(self._tat_all, now)
        if tat - now > self._tau_all:
            self._excess += 1
            return False
        self._tat_all = tat + self._every_all
        return True

    def _any_run(self, frame: bytes | memoryview) -> bool:
        return any_run(frame)

    def _fresh_header(self, body: memoryview, handle: H) -> bool | None:
        # A question is shorter than HEADER_LEN: the header tag covered it all.
        asker, t_ns = ask_stamp(body, self._askers)  # CodecError: no such asker (bad)
        return not (t_ns <= self._newest[asker] or t_ns - self._clock() > self._max_ahead)

    def _fresh(self, body: memoryview, handle: H) -> bool | None:
        asker, t_ns = ask_stamp(body, self._askers)  # CodecError: no such asker (bad)
        if t_ns <= self._newest[asker] or t_ns - self._clock() > self._max_ahead:
            return False
        # After freshness: a replay of the asker's questions uses none of its bound.
        now = self._now()
        tat = max(self._tat[asker], now)
        if tat - now > self._tau:
            self._excess += 1
            return None
        self._tat[asker] = tat + self._every
        self._newest[asker] = t_ns
        return True

    def _took(self) -> None:
        self.excess, self._excess = self._excess, 0


class MirrorIntake(Intake[None]):
    """A control node's mirror frames (``{vehicle}/cn/mirror``, the
    commander's whole vector for the standby, :mod:`zplatform.control.failover`),
    for ``node``. Fresh: authentic, from the *other* control node
    (``cn_commander``), with a term and a loop in range
    (:data:`~zplatform.control.fencing.TERM_MAX`, :data:`~zplatform.control.fencing.LOOP_MAX`),
    and newer in (``cn_term``, loop) order than every mirror admitted
    before. So junk never reaches the mailbox, and a replayed mirror of
    this run (an older loop, an older term), however authentic, neither
    displaces a genuine one nor reaches a commander's check for a newer
    term: it cannot make a commander stand down. (A mirror recorded in an
    earlier run of the same keys is another matter: its term and loop may
    be above this run's: the channel is bound to the run, zplatform.core.auth.Run,
    and refuses it as stale.)
    Its mailbox keeps :data:`MIRRORS` frames."""

    def __init__(self, mission: Mission, node: str, channel: Channel | None) -> None:
        lay = Layout.for_node(mission, "cn")
        self._size = lay.size
        self._term_at = lay.element("cn_term").offset
        self._who_at = lay.element("cn_commander").offset
        self._index = mission.control_nodes.index(node)
        self._nodes = len(mission.control_nodes)
        self.newest = (0, 0)
        """``(term, loop)`` of the newest admitted mirror."""
        super().__init__("mirror", max_frame_len(self._size, channel), channel, MIRRORS)

    def _fresh_header(self, body: memoryview, handle: None) -> bool | None:
        # The term is in the data: a loop above the newest's is new (or a
        # lower term's, refused after the MAC); one not above cannot tell (a
        # replay, or a new term's: a takeover may go back in loops).
        seq, _ = frame_stamp(body)
        if not 1 <= seq <= LOOP_MAX:
            raise CodecError(f"a mirror of loop {seq}: out of range")
        return True if seq > self.newest[1] else None

    def _fresh(self, body: memoryview, handle: None) -> bool:
        seq, _ = frame_stamp(body)
        data = frame_data(body, self._size)
        at = self._term_at
        term = int.from_bytes(data[at : at + 4], "little")
        who = data[self._who_at]
        if not (1 <= term <= TERM_MAX and who < self._nodes and 1 <= seq <= LOOP_MAX):
            raise CodecError(f"a mirror of term {term}, loop {seq}, from node {who}: out of range")
        if who == self._index or (term, seq) <= self.newest:
            return False  # its own, or not newer: a replay (or a duplicate)
        self.newest = (term, seq)
        return True


class TelemetryIntake(_StampIntake[int]):
    """The ground's telemetry (``{vehicle}/cn/telemetry``); the handle is the
    receive time on the ground's clock. Fresh: newer, in (run, term, stamp)
    order, than any snapshot admitted before, as
    :class:`~zplatform.ground.logic.GroundLogic` orders them, and stamped no
    further than ``max_age_ns`` (the freshness bound) ahead of its arrival.
    The run (``cn_epoch``) and, in a redundant mission, the term
    (``cn_term``) are read from the tagged snapshot; a new run or term is
    taken only from a snapshot stamped within ``max_age_ns`` of its arrival
    (either side), so a replay of an earlier run, whatever its term, never
    displaces a new snapshot nor raises the newest term (after a takeover
    the new commander's snapshots are fresh even when the old one, not yet
    stood down, stamped a later loop: zplatform.control.failover). An older run is
    taken again, as the logic follows it, only once the newest admitted
    snapshot is older than ``max_age_ns``. The logic checks the rest (its
    clock bound both ways, the jumps). Of the refused snapshots, those
    stamped more than ``max_age_ns`` before they arrived, or of another run
    than ``channel``'s (a ground bound to a run; before it knows its run,
    they are only counted in :attr:`waiting`), are also counted in
    :attr:`aged`, those stamped beyond it after in :attr:`ahead` (what the
    logic calls ``stale`` and ``ahead``). ``capacity``: snapshots kept while
    the consumer is busy. ``dedupe``: the snapshots come by two paths (a
    ground on the CN's host: iceoryx2 and zenoh, :meth:`Intake.admit_view`
    and :meth:`Intake.admit`), each taken once (:class:`Dedupe`)."""

    def __init__(
        self,
        mission: Mission,
        channel: Channel | None,
        capacity: int,
        max_age_ns: int,
        waker: Waker | None = None,
        *,
        dedupe: bool = False,
    ) -> None:
        if dedupe:  # two paths: iceoryx2 and zenoh (zplatform.ground.link)
            self.dedupe = Dedupe()
        lay = Layout.for_node(mission, "cn")
        size = lay.size
        self._max_age = max_age_ns
        self._aged = 0
        self.aged = 0
        """Replays beyond the freshness bound among those counted by the last
        :meth:`take_counts`."""
        self._ahead_n = 0
        self.ahead = 0
        """Snapshots stamped beyond the freshness bound ahead of their arrival
        among those counted by the last :meth:`take_counts`."""
        self._size = size
        self._epoch_at = lay.element("cn_epoch").offset
        self._term_at = lay.element("cn_term").offset if mission.standby is not None else -1
        self._newest_epoch = -1
        self._newest_term = 0
        self._run = channel.run if channel is not None else None
        self.waiting = 0
        """Authentic snapshots let go because the run was not learned yet
        (a ground bound to a run: zplatform.ground.link); not counted as refused."""
        super().__init__("telemetry", max_frame_len(size, channel), channel, capacity, waker=waker)

    def _fresh_header(self, body: memoryview, handle: int) -> bool | None:
        # The run and the term are in the data; the stamp alone refuses what
        # every rule of _fresh would: stamped beyond the bound ahead, or
        # older than the freshness bound and not newer than the newest (of
        # the same run and term: not newer; of another: not of now).
        _, t_ns = frame_stamp(body)
        age = handle - t_ns
        if -age > self._max_age:
            self._ahead_n += 1
            return False
        if t_ns > self.newest_t:
            return True
        if age > self._max_age:
            self._aged += 1
            return False
        return None  # a recent stamp, not newer: a new term's, or a replay

    def _fresh(self, body: memoryview, handle: int) -> bool:
        _, t_ns = frame_stamp(body)
        age = handle - t_ns
        if -age > self._max_age:
            self._ahead_n += 1
            return False
        data = frame_data(body, self._size)
        at = self._epoch_at
        epoch = int.from_bytes(data[at : at + 8], "little")
        at = self._term_at
        term = int.from_bytes(data[at : at + 4], "little") if at >= 0 else 0
        if epoch == self._newest_epoch and term == self._newest_term:
            return super()._fresh(body, handle)
        # A new run or a new term: only from a snapshot of now.
        if age > self._max_age:
            self._aged += 1
            return False
        if epoch == self._newest_epoch:
            if term < self._newest_term:
                return False  # a term that stood down (or a replay of it)
        elif epoch < self._newest_epoch and handle - self.newest_t <= self._max_age:
            return False  # an older run while this one speaks
        self._newest_epoch = epoch
        self._newest_term = term
        self.newest_t = t_ns
        return True

    def _replayed(self, t_ns: int, handle: int) -> None:
        if handle - t_ns > self._max_age:
            self._aged += 1

    def _other_run(self) -> bool:
        # A ground bound to a run (zplatform.ground.link): another run's
        # snapshot is counted stale; one before the run is learned only in
        # `waiting` (not a replay: the ground does not know the run yet).
        run = self._run
        if run is not None and not run.known:
            self.waiting += 1
            return False
        self._aged += 1
        return True

    def _took(self) -> None:
        self.aged, self._aged = self._aged, 0
        self.ahead, self._ahead_n = self._ahead_n, 0


class RequestIntake(Intake[None]):
    """The CN's command requests (``{vehicle}/gn/to_cn``). ``channel`` bound
    to the CN's run: a request tagged in another run is refused before any
    decode (stale); one tagged in none is taken to the next check. Fresh: for this
    CN run and numbered above every number seen, by the rules of
    :func:`zplatform.control.commands.request_refusal` (``last_seq()``: the command
    handler's highest number; the intake's own highest admitted counts
    too). A refused request is counted in ``stale``; the one with the
    highest number is reported with its status (:attr:`reported`), as the
    CN's ``cn_cmd_reject_seq`` shows it."""

    def __init__(
        self,
        mission: Mission,
        channel: Channel | None,
        cn_epoch: int,
        last_seq: Callable[[], int],
        capacity: int,
    ) -> None:
        lay = Layout.for_node(mission, "cn")
        self._size = lay.region("gn_to_cn").size
        self._number = RequestNumber(lay)
        self._epoch = cn_epoch
        self._last_seq = last_seq
        self._highest = 0
        self._reported = (0, 0)
        self.reported = (0, 0)
        """``(status, seq)`` of the refused request with the highest number
        among those counted by the last :meth:`take_counts` (``(0, 0)``: none)."""
        super().__init__("command request", max_frame_len(self._size, channel), channel, capacity)

    def _any_run(self, frame: bytes | memoryview) -> bool:
        # A request tagged in no run (a ground bound to none) is opened under
        # the run-0 key: its data names its run, checked in _fresh. One tagged
        # in another run is refused before any decode (RunError: stale).
        return Channel.run_of(frame) == NO_RUN

    def _fresh_header(self, body: memoryview, handle: None) -> bool | None:
        # The frame's seq is the request's number (zplatform.control.uplink);
        # its epoch is in the data: a number above every one seen is new as
        # far as the header tells, any other cannot tell (the rules of
        # request_refusal, after the MAC, name its refusal).
        seq, _ = frame_stamp(body)
        return True if seq > max(self._last_seq(), self._highest) else None

    def _fresh(self, body: memoryview, handle: None) -> bool:
        epoch, seq = self._number.read(frame_data(body, self._size))
        status = request_refusal(epoch, seq, self._epoch, max(self._last_seq(), self._highest))
        if status:
            if self._reported[0] == 0 or seq >= self._reported[1]:
                self._reported = (status, seq)
            return False
        self._highest = seq
        return True

    def follow(self, cn_epoch: int) -> None:
        """Admit requests of CN run ``cn_epoch`` from now on (a control node
        that resumed a run it had recorded)."""
        with self._lock:
            self._epoch = cn_epoch

    def _took(self) -> None:
        self.reported, self._reported = self._reported, (0, 0)

    def take_refusals(self, out: CnRefusals) -> None:
        """Put what this intake refused since the last call into ``out``'s
        command fields (:class:`CnRefusals`: ``cmd_size``, ``cmd_bad``,
        ``cmd_stale``, ``cmd_unchecked`` and the refusal to report: the stale one with the
        highest number, else ``REJECTED_AUTH``/0 for bad tags alone), then
        zero the counts. The one way every CN driver (the live node, the
        lockstep runner) reads its request intake. Allocates nothing."""
        out.cmd_size, out.cmd_bad, out.cmd_stale = self.take_counts()
        out.cmd_unchecked = self.took_unchecked
        if out.cmd_stale:
            out.cmd_status, out.cmd_seq = self.reported
        elif out.cmd_bad:
            out.cmd_status, out.cmd_seq = CommandStatus.REJECTED_AUTH, 0
        else:
            out.cmd_status = out.cmd_seq = 0


class ReplyCheck(Intake[None]):
    """Checks a sync reply that does not come from the zenoh session known
    to answer for the DN (:class:`zplatform.runtime.sync.ControlSync`): a restarted
    DN, or someone else. Fresh: for the loop the CN is asking
    (:meth:`expect`), stamped within the clock bound plus a period of the
    query. No mailbox: the caller hands a reply that passes to the loop."""

    def __init__(self, mission: Mission, dn: str, channel: Channel | None) -> None:
        size = Layout.for_node(mission, "cn").region(f"{dn}_to_cn").size
        super().__init__(f"{dn}'s sync reply", max_frame_len(size, channel), channel)
        self._window = round(mission.clock.offset_bound_ms * 1e6) + mission.period_ns
        self.loop = -1
        self.t_ns = 0

    def expect(self, loop: int, t_ns: int) -> None:
        """From now on, a reply is fresh only for ``loop``, asked at ``t_ns``
        (the loop thread, before the queries go out)."""
        self.loop, self.t_ns = loop, t_ns

    def _fresh_header(self, body: memoryview, handle: None) -> bool:
        return self._fresh(body, handle)  # seq and t_ns: the header says it all

    def _fresh(self, body: memoryview, handle: None) -> bool:
        seq, t_ns = frame_stamp(body)
        return seq == self.loop and abs(t_ns - self.t_ns) <= self._window


class CnRefusals:
    """What a CN driver's intakes refused during one loop: an input of
    :meth:`zplatform.control.loop.ControlLogic.finish`, recorded like every other.
    Preallocated; the driver overwrites it each loop (:meth:`clear`).

    Sync replies (every DN's): ``reply_size`` of a wrong size, ``reply_bad``
    with a bad tag, ``reply_stale`` authentic but not for the loop asked (a
    replay), ``reply_foreign`` from a replier that is no DN's. Command
    requests: ``cmd_size``, ``cmd_bad``, ``cmd_stale`` (epoch or number), and
    ``cmd_status``/``cmd_seq`` of the refusal to report (the stale one with
    the highest number; ``REJECTED_AUTH``/0 when only bad tags came). Not a
    refusal, but the sync's count of the loop too (so a replay counts it):
    ``query_recovered``, the device nodes whose querier was declared again
    (:class:`~zplatform.runtime.queries.Unanswered`; not in :attr:`total`).
    Of the refused, those dropped after their header for want of body-MAC
    budget (:attr:`Intake.took_unchecked`, :data:`MAC_SPARE`; already in
    the counts above, so not in :attr:`total`): ``reply_unchecked``,
    ``cmd_unchecked``. Mirror frames the node's :class:`MirrorIntake`
    refused (a redundant mission; not in :attr:`total`, they are counted
    apart: ``cn_mirror_refused``): ``mirror_refused``."""

    __slots__ = (
        "cmd_bad",
        "cmd_seq",
        "cmd_size",
        "cmd_stale",
        "cmd_status",
        "cmd_unchecked",
        "mirror_refused",
        "query_recovered",
        "reply_bad",
        "reply_foreign",
        "reply_size",
        "reply_stale",
        "reply_unchecked",
    )  # CN_REFUSALS: their recorded order

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self.reply_size = self.reply_bad = self.reply_stale = self.reply_foreign = 0
        self.cmd_size = self.cmd_bad = self.cmd_stale = 0
        self.cmd_status = self.cmd_seq = 0
        self.query_recovered = 0
        self.reply_unchecked = self.cmd_unchecked = 0
        self.mirror_refused = 0

    @property
    def total(self) -> int:
        return (
            self.reply_size
            + self.reply_bad
            + self.reply_stale
            + self.reply_foreign
            + self.cmd_size
            + self.cmd_bad
            + self.cmd_stale
        )

    def fields(self) -> tuple[int, ...]:
        """Every count, in :data:`CN_REFUSALS` order (for a recorder)."""
        return tuple(getattr(self, k) for k in CN_REFUSALS)

    def set_fields(self, values: tuple[int, ...]) -> CnRefusals:
        """The inverse of :meth:`fields`; returns self."""
        for k, v in zip(CN_REFUSALS, values, strict=True):
            setattr(self, k, v)
        return self


CN_REFUSALS = (
    "reply_size",
    "reply_bad",
    "reply_stale",
    "reply_foreign",
    "cmd_size",
    "cmd_bad",
    "cmd_stale",
    "cmd_status",
    "cmd_seq",
    "query_recovered",
    "reply_unchecked",
    "cmd_unchecked",
    "mirror_refused",
)
""":class:`CnRefusals`' fields in their recorded order."""


class RefusalLog:
    """Turns refusal counts into events a flood cannot multiply.

    :meth:`add` accumulates counts and returns them, to be evented, when
    :data:`EVENT_PERIOD_NS` of loop time has passed since the last event
    (or there was none yet): the first refusal after a quiet period is
    evented at once, a flood costs one event a period with its counts, and
    counts left at its end go out at most one period later (:meth:`add`
    with zeros, every loop). Sans-IO and deterministic: loop time only."""

    __slots__ = ("_last", "_n", "_period")

    def __init__(self, fields: int, period_ns: int = EVENT_PERIOD_NS) -> None:
        self._n = [0] * fields
        self._last: int | None = None
        self._period = period_ns

    def add(self, t_ns: int, *counts: int) -> list[int] | None:
        n = self._n
        for i, c in enumerate(counts):
            n[i] += c
        if not any(n) or (self._last is not None and t_ns - self._last < self._period):
            return None
        self._last = t_ns
        self._n = [0] * len(n)
        return n
