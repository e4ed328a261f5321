"""The standby control node: it mirrors the commander and takes over when it falls silent.

Holds :class:`Standby` (a control node that does not command), the mirror
frame's reader (:class:`MirrorReader`) and :class:`Decision`. The commander
sends its whole Data Vector each loop as a mirror; the standby writes every
fresh one into its own vector and keeps the commander's schedule. When the
commander falls silent it probes the device nodes (STATUS, then ASK for the
next term, :mod:`zplatform.control.fencing`) and takes command only when more than
half of them granted and none refused; a standby whose last mirror is older
than :attr:`Standby.max_age` loops (``2 * takeover_loops + lease_loops``) is
blind and never takes command from it.

Contract: sans-IO like the loop (:mod:`zplatform.control.loop`): reads no clock, opens
nothing, starts no thread; one :class:`~zplatform.control.role.ControlRole` drives it
for both drivers, on the node's loop thread (not thread-safe). It never raises
for what arrives: refused mirrors and probe replies are counted
(:attr:`Standby.bad`, :attr:`Standby.bad_replies`), evented at most once a second.

The whole story and the driver's call order: docs/architecture.md#failover.
"""

from __future__ import annotations

import enum
import struct

from ..config import Mission
from ..core.auth import KeySet, channel
from ..core.codec import Frame, RegionCodec
from ..core.events import EV
from ..errors import CodecError
from .fencing import (
    ASK,
    LOOP_MAX,
    RELEASE,
    STATUS,
    TERM_JUMP,
    TERM_MAX,
    ProbeReply,
    ask_frame,
    attested_term,
    new_nonce,
    next_term,
    read_reply,
)
from .intake import RefusalLog
from .loop import ControlLogic
from .params import encode_params

__all__ = ["Decision", "MirrorReader", "Standby", "probe_wait_ns"]

_U32 = struct.Struct("<I")


def probe_wait_ns(mission: Mission) -> int:
    """How long a control node's probe round waits for the device nodes'
    answers (:class:`~zplatform.runtime.sync.ProbeSync`): a whole period.
    A round ends as soon as every device node answered, so this costs only
    when an answer is late; a standby has nothing else to do meanwhile, and
    an answer it gives up on costs a round at the next slot. (It was the
    larger of the sync timeout and a quarter period, 2.5 ms at 100 Hz: a
    busy host's device nodes answered in 3 to 17 ms, and each round without
    them held a takeover back, issue 25.)"""
    return mission.period_ns


class Decision(enum.IntEnum):
    """What :meth:`Standby.decide` concluded from a probe round."""

    WAIT = 0
    TAKE = 1


class MirrorReader:
    """Checks mirror frames for a control node (tag, layout, shape, and the
    range of every integer the failover reads from them: a term from 1 to
    :data:`~zplatform.control.fencing.TERM_MAX`, a commander that is one of the
    mission's control nodes, a loop from 1 to
    :data:`~zplatform.control.fencing.LOOP_MAX`) and reads their term and commander,
    writing nothing. A commander keeps one to hear a newer term's mirror
    (:meth:`newer_term`); a :class:`Standby` reads the mirrors it applies
    with one. Not thread-safe."""

    def __init__(self, logic: ControlLogic, keys: KeySet | None) -> None:
        dv = logic.dv
        self.logic = logic
        self.index = logic.mission.control_nodes.index(logic.name)
        # Bound to the logic's run: a mirror of another run never verifies.
        self._open = channel(keys, "mirror", logic.auth_run)
        self.codec = RegionCodec(dv)
        self._term_at = dv.layout.element("cn_term").offset
        self._commander_at = dv.layout.element("cn_commander").offset
        self._nodes = len(logic.mission.control_nodes)
        self.bad = 0
        """Frames refused: a bad tag, another layout, malformed, out of range."""

    def read(self, payload: bytes | bytearray | memoryview) -> Frame | None:
        """The checked frame, or None (counted in :attr:`bad`)."""
        try:
            frame = self.codec.check(self._open.open(payload) if self._open else payload)
        except CodecError:
            self.bad += 1
            return None
        term, who = self.stamp(frame)
        if not (1 <= term <= TERM_MAX and who < self._nodes and 1 <= frame.seq <= LOOP_MAX):
            self.bad += 1  # authentic, but a vector no commander can have sent
            return None
        return frame

    def stamp(self, frame: Frame) -> tuple[int, int]:
        """``(term, commander index)`` of a checked frame."""
        data = frame.data
        return int(_U32.unpack_from(data, self._term_at)[0]), int(data[self._commander_at])

    def newer_term(self, payload: bytes | bytearray | memoryview) -> tuple[int, int]:
        """``(term, commander)`` of an authentic mirror from the other control
        node with a term above this logic's, else ``(0, -1)``: a commander
        that hears one stands down."""
        frame = self.read(payload)
        if frame is None:
            return 0, -1
        term, who = self.stamp(frame)
        if who == self.index or term <= self.logic.term:
            return 0, -1
        return term, who


class Standby:
    """A control node that does not command (module doc), sans-IO.

    ``logic``: the :class:`~zplatform.control.loop.ControlLogic` it will run when it
    takes command; its Data Vector is where mirrors go. ``keys``: the
    node's keys (the mirror's link, each device node's probe channels).
    Not thread-safe: the node's loop thread. Never raises for what arrives
    (refused frames are counted: :attr:`bad`, :attr:`bad_replies`).
    """

    def __init__(self, mission: Mission, logic: ControlLogic, keys: KeySet | None) -> None:
        if mission.standby is None:
            raise ValueError("a mission without a standby control node has no standby")
        self.mission = mission
        self.logic = logic
        self.name = logic.name
        self.index = mission.control_nodes.index(logic.name)
        self.events = logic.events
        dv = logic.dv
        self._reader = MirrorReader(logic, keys)
        self._period = mission.period_ns
        # How far ahead of this node's (corrected) clock a commander's stamp
        # may be: the clock bound and a period, as a device node believes one.
        self._max_ahead = round(mission.clock.offset_bound_ms * 1e6) + mission.period_ns
        self._takeover = mission.takeover.takeover_loops
        self._lease = mission.takeover.lease_loops * mission.period_ns
        dns = mission.device_nodes
        self.dns = tuple(dns)
        # The run: the commander's, which a standby's clock exchange with it
        # learned (logic.auth_run); a device node answers only questions of it.
        self._ask_ch = tuple(channel(keys, f"probe_cn_to_{dn}", logic.auth_run) for dn in dns)
        self._reply_ch = tuple(channel(keys, f"probe_{dn}_to_cn", logic.auth_run) for dn in dns)
        self._nonces = [b""] * len(dns)
        self.answers: list[ProbeReply | None] = [None] * len(dns)
        """The replies of the current probe round, per device node."""
        self.releases: list[bytes | None] = [None] * len(dns)
        """After a round that did not take command: the RELEASE question to
        send to each device node that granted (None: nothing to release)."""
        self.mirrored = 0
        """The loop of the last mirror applied (0: none yet)."""
        self.following = False
        """A mirror from the commander was applied (since this node stood down,
        if it did): the standby is ready to take over."""
        self.mirrored_t = 0
        self.term = 0
        """The newest term known: the (authenticated) mirror's, its own, or
        one more than half of the device nodes attest
        (:func:`~zplatform.control.fencing.attested_term`), never one a lone
        device node reported: its insider could name any."""
        self.reach = 0
        """The highest term the last round's answers named above :attr:`term`,
        cut to ``term +`` :data:`~zplatform.control.fencing.TERM_JUMP` (0:
        none): the next round asks past it, so that a device node fenced a
        little above the others grants; the round after forgets it."""
        self.commander = -1
        """The index of the control node the last mirror came from (-1: none)."""
        self.origin: int | None = None
        """The commander's schedule: the time of loop 1 (loop n runs at
        ``origin + (n - 1) * period``); None before the first mirror."""
        self.bad_replies = 0
        """Probe replies refused: a bad tag, another question's, malformed,
        out of range, a grant of a term not asked for."""
        # Refused mirrors and replies, evented at most once a second (tick).
        self._refusals = RefusalLog(2)
        self._counted = (0, 0)
        self._asked = 0  # the term the current round asks for
        self._kind = ASK
        self._next_ask = 0  # the first slot a new round may start in
        self._held = False  # a cn_takeover_held event was given for this silence
        self.max_age = 2 * self._takeover + mission.takeover.lease_loops
        """The oldest mirror (in loops) this standby takes command from."""
        self._blind = False  # a cn_takeover_held event said the mirror is too old
        # Whether the commander still reaches the device nodes, from the
        # mirrors: cn_rx_dnX grows for each reply it applied.
        self._rx = tuple(dv.handle(f"cn_rx_{dn}") for dn in dns)
        self._rx_last = [0] * len(dns)
        self.cut = 0
        """Mirrored loops in a row in which the commander applied the replies of
        at most half of the device nodes (it is alive but cut off from them)."""
        self._finals = tuple(dv.handle(f"{dn}_final") for dn in dns)
        self.ended = False
        """The last mirror was of the commander's final loop (its run ended as
        planned: ``dnX_final``); nothing is to be taken over."""
        self._save_seq = 0
        self._save: tuple[int, bytes] | None = None
        self._params = bool(mission.params)
        if self._params:
            self._h_save_seq = dv.handle("cn_prm_save_seq")
            self._h_save = dv.handle("cn_prm_save_status")

    @property
    def bad(self) -> int:
        """Mirror frames refused."""
        return self._reader.bad

    # -- following --------------------------------------------------------
    def mirror(self, payload: bytes | bytearray | memoryview, now_ns: int) -> bool:
        """Take one mirror frame: applied (True) when it is authentic, of
        this mission's layout, from the other control node, and newer (a
        newer term, or a later loop of the same term) than the last one.
        One stamped further ahead of ``now_ns`` (this node's clock) than
        the clock bound and a period is refused and counted in :attr:`bad`:
        no commander's clock makes it, and taken it would set the schedule
        the standby follows and takes over on (:attr:`origin`)."""
        frame = self._reader.read(payload)
        if frame is None:
            return False
        if frame.t_ns - now_ns > self._max_ahead:
            self._reader.bad += 1
            return False
        term, commander = self._reader.stamp(frame)
        if commander == self.index:  # its own, from before it stood down
            return False
        if (term, frame.seq) <= (self.term, self.mirrored):
            return False
        self._reader.codec.write(frame)
        first = not self.following
        self.following = True
        got = 0
        for i, h in enumerate(self._rx):
            rx = h.get()
            got += rx != self._rx_last[i]
            self._rx_last[i] = rx
        self.cut = (
            0
            if first or 2 * got > len(self._rx) or frame.seq != self.mirrored + 1
            else (self.cut + 1)
        )
        self.mirrored, self.mirrored_t = frame.seq, frame.t_ns
        self.term, self.commander = term, commander
        self.origin = frame.t_ns - (frame.seq - 1) * self._period
        self.ended = any(h.get() for h in self._finals)
        self._held = self._blind = False
        if first:
            self.events.emit(
                EV.CN_FOLLOWING,
                now_ns,
                node=self.name,
                commander=self.mission.control_nodes[commander],
                term=term,
                loop=frame.seq,
            )
        if self._params:
            self._follow_save(now_ns)
        return True

    def _follow_save(self, now_ns: int) -> None:
        """A PRM_SAVE the commander accepted is saved here too, to this node's
        own file, with the values the mirror holds: both control nodes keep
        the same parameters (the driver writes :meth:`take_save`)."""
        seq = int(self._h_save_seq.get())
        if seq and seq != self._save_seq:
            self._save_seq = seq
            values = self.logic.params.values()
            self._save = (seq, encode_params(self.mission, values, seq=seq, saved_ns=now_ns))

    def take_save(self) -> tuple[int, bytes] | None:
        """A parameter save to write to this node's file, once (None: none)."""
        save, self._save = self._save, None
        return save

    # -- deciding ------------------------------------------------------------
    def slot(self, now_ns: int) -> int:
        """The loop of the commander's schedule running at ``now_ns`` (0
        before the first mirror)."""
        if self.origin is None:
            return 0
        return (now_ns - self.origin) // self._period + 1

    def missing(self, slot: int) -> int:
        """Loops up to ``slot`` whose mirror has not come (the driver ticks
        when the mirror of ``slot``'s own loop is due: half a period in)."""
        return max(slot - self.mirrored, 0)

    def blind(self, slot: int) -> bool:
        """Whether the last mirror is too old to take command from in
        ``slot`` (more than :attr:`max_age` loops missing; module doc). A
        node that never had a mirror is blind too."""
        return self.origin is None or self.missing(slot) > self.max_age

    def tick(self, slot: int) -> bool:
        """Whether to probe the device nodes in ``slot`` (called once per slot,
        half a period in): no mirror for ``takeover_loops`` loops, or mirrors
        that show the commander without most device nodes' replies for as
        many loops (:attr:`cut`); and no round asked in the last
        ``takeover_loops`` slots; and the mirror not too old (:meth:`blind`:
        a ``cn_takeover_held`` event says so, once per silence); and a next
        term to ask for (none after :data:`~zplatform.control.fencing.TERM_MAX`).
        Refused mirrors and probe replies are evented here, at most once a
        second."""
        self._event_refusals(slot)
        if (
            self.origin is None
            or self.ended
            or (self.missing(slot) < self._takeover and self.cut < self._takeover)
        ):
            self._next_ask = 0
            return False
        if self.blind(slot):
            if not self._blind:
                self._blind = True
                self._held_event(
                    self.origin + (slot - 1) * self._period,
                    f"the last mirror, of loop {self.mirrored}, is {self.missing(slot)} "
                    f"loops old (a takeover needs one at most {self.max_age} old): taking "
                    "command from it would turn the vehicle's state back; following again "
                    "from the next mirror",
                )
            return False
        if not next_term(self.term):
            if not self._held:
                self._held = True
                self._held_event(
                    self.origin + (slot - 1) * self._period,
                    f"term {self.term} is the last a node can run: there is no next "
                    "term to ask for",
                )
            return False
        return slot >= self._next_ask

    def _held_event(self, t_ns: int, why: str) -> None:
        """The ``cn_takeover_held`` event at ``t_ns`` saying ``why`` (the
        callers keep it to once per cause)."""
        self.events.emit(
            EV.CN_TAKEOVER_HELD,
            t_ns,
            node=self.name,
            loop=self.mirrored,
            why=why,
        )

    def _event_refusals(self, slot: int) -> None:
        """Mirrors and probe replies refused since the last slot, as one
        ``bad_frame`` event at most once a second (of the schedule's time)."""
        counted = (self._reader.bad, self.bad_replies)
        new = (counted[0] - self._counted[0], counted[1] - self._counted[1])
        self._counted = counted
        t = self.origin + (slot - 1) * self._period if self.origin is not None else 0
        ev = self._refusals.add(t, *new)
        if ev is not None:
            self.events.emit(
                EV.BAD_FRAME,
                t,
                source=f"{sum(ev)} failover frame(s)",
                reason=f"refused by {self.name}: {ev[0]} mirror(s), {ev[1]} probe "
                "answer(s) (a bad tag, malformed, out of range, or another question's)",
            )

    def ask(self, slot: int, now_ns: int, *, kind: int = ASK) -> list[bytes]:
        """The probe questions of a new round, one per device node: ASK for
        the term after every term known (``kind``: STATUS, a question that
        asks for nothing; a STATUS too when there is no next term,
        :func:`~zplatform.control.fencing.next_term`)."""
        self._asked = next_term(max(self.term, self.reach)) if kind == ASK else 0
        if not self._asked:
            kind = STATUS
        self._kind = kind
        out = []
        for i in range(len(self.dns)):
            self.answers[i] = None
            self.releases[i] = None
            nonce = self._nonces[i] = new_nonce()
            out.append(ask_frame(self._ask_ch[i], kind, i, self.index, self._asked, nonce, now_ns))
        self._next_ask = slot + self._takeover
        return out

    def answer(self, i: int, payload: bytes | bytearray | memoryview) -> bool:
        """Take device node ``i``'s reply to this round (True when it is one)."""
        try:
            r = read_reply(self._reply_ch[i], payload, i, self._nonces[i])
        except CodecError:
            self.bad_replies += 1
            return False
        if r.granted and (self._kind != ASK or r.promised != self._asked):
            self.bad_replies += 1  # a grant of a term this round did not ask for
            return False
        self.answers[i] = r
        return True

    def silent(self, slot: int, now_ns: int) -> bool:
        """A STATUS round is over (``ask(slot, now, kind=STATUS)``, asking
        nothing): whether the device nodes' answers show the commander
        silent too, so that an ASK may follow in the same slot. True when
        more than half of them answered and none ran a trigger within the
        lease or holds a promise (to either control node). Otherwise no
        term is asked for, so no promise can fence a commander that still
        drives some device node (a busy host's late triggers included); the
        next round comes when the lease may have run out (as after a refused
        ASK), or at the next slot when no answer showed a driven device node
        (too few came in time), with a ``cn_takeover_held`` event (once per
        silence). Learns a newer term from the answers: the one more than
        half of the device nodes attest, and, for the next round only, one a
        single device node named, up to ``TERM_JUMP`` above it
        (:attr:`reach`)."""
        answered = [a for a in self.answers if a is not None]
        driven = [a for a in answered if 0 <= a.quiet_ns < self._lease or a.promised]
        # Too few answers and none driven: a busy host's late answers, not a
        # commander at work. Asking nothing, the next STATUS round may come at
        # the next slot (one question a period: within every device node's
        # rate bound); waiting takeover_loops here would push a takeover past
        # the device nodes' watchdog after two such rounds, and past the
        # blind standby's limit after three (issue 25).
        retry = self._retry_in(driven) if driven else 1
        self._learn(False)
        if 2 * len(answered) > len(self.dns) and not driven:
            return True
        self._next_ask = slot + retry
        if not self._held:
            self._held = True
            self._held_event(now_ns, self._why_held(answered, answered, driven))
        return False

    def decide(self, slot: int, now_ns: int) -> Decision:
        """The round is over: TAKE when every device node that answered
        granted the term and they are more than half of all; else WAIT, with
        :attr:`releases` to send and a ``cn_takeover_held`` event (once per
        silence of the commander). Learns a newer term the device nodes
        reported as :meth:`silent` does."""
        answered = [a for a in self.answers if a is not None]
        granted = [a for a in answered if a.granted]
        self._learn(True)
        majority = 2 * len(granted) > len(self.dns)
        if self._kind == ASK and answered and len(granted) == len(answered) and majority:
            return Decision.TAKE
        # Every device node asked gets the RELEASE, not only those whose grant
        # came back in time: a late answer may have carried a promise, which
        # would fence the commander for the lease.
        if self._kind == ASK:
            for i in range(len(self.dns)):
                self.releases[i] = ask_frame(
                    self._ask_ch[i], RELEASE, i, self.index, self._asked, new_nonce(), now_ns
                )
            self._next_ask = slot + self._retry_in(answered)
        if self._kind == ASK and not self._held:
            self._held = True
            self._held_event(
                now_ns, self._why_held(answered, granted, [a for a in answered if not a.granted])
            )
        return Decision.WAIT

    def _learn(self, asked: bool) -> None:
        """Learn from this round's answers (``asked``: an ASK's, whose grants
        name the term asked, not one a node holds): :attr:`term` rises to
        the term more than half of the device nodes attest; :attr:`reach`
        becomes the highest any one named, cut to ``term + TERM_JUMP``
        (issue 25: a device node's insider naming TERM_MAX left the
        standby no next term for good; docs/architecture.md#failover)."""
        terms = [0] * len(self.dns)
        for a in self.answers:
            if a is not None:
                terms[a.dn] = max(a.term, 0 if (asked and a.granted) else a.promised)
        self.term = max(self.term, attested_term(terms, len(self.dns)))
        top = max(terms)
        self.reach = min(top, self.term + TERM_JUMP) if top > self.term else 0

    def _retry_in(self, answered: list[ProbeReply]) -> int:
        """Slots until the next round: when the device nodes refused only
        because their lease had not yet run out (they last ran a trigger just
        before the commander fell silent), as soon as it will have, else
        ``takeover_loops`` (a commander still driving them)."""
        refusing = [a for a in answered if not a.granted]
        if not refusing or any(a.term > self.term or a.quiet_ns < 0 for a in refusing):
            return self._takeover
        left = self._lease - min(a.quiet_ns for a in refusing)
        return max(1, min(self._takeover, -(-left // self._period)))

    def _why_held(
        self, answered: list[ProbeReply], counted: list[ProbeReply], refusing: list[ProbeReply]
    ) -> str:
        """Why a round ends without a takeover: no answer; ``refusing``, the
        device nodes still driven (or refusing); else too few of them
        (``counted``: those that answered as a takeover needs)."""
        if not answered:
            return "no device node answered its question"
        busy = [
            f"{self.dns[a.dn]} ran loop {a.last_loop} of term {a.term} "
            f"{a.quiet_ns / 1e6:.0f} ms ago"
            + (f" and promised term {a.promised}" if a.promised else "")
            for a in refusing
        ]
        if busy:
            return "the commander still drives " + "; ".join(busy)
        return (
            f"only {len(counted)} of {len(self.dns)} device nodes answered: a takeover needs "
            "more than half"
        )

    def take(self, loop: int) -> ControlLogic:
        """Take command from ``loop`` on (after a TAKE): the logic adopts the
        mirror (:meth:`~zplatform.control.loop.ControlLogic.adopt`), enters the term it
        asked for, and is returned for the driver to run; ``cn_took_command``."""
        logic = self.logic
        logic.adopt()
        logic.take_command(self._asked, loop)
        nodes = self.mission.control_nodes
        was = nodes[self.commander] if self.commander >= 0 else "no control node"
        t = self.origin + (loop - 1) * self._period if self.origin is not None else 0
        what = (
            f"silent since loop {self.mirrored}"
            if self.cut < self._takeover
            else f"cut off from the device nodes for {self.cut} loops"
        )
        self.events.emit(
            EV.CN_TOOK_COMMAND,
            t,
            node=self.name,
            term=self._asked,
            loop=loop,
            why=f"{was} (term {self.term}) {what}; "
            f"{sum(1 for a in self.answers if a is not None and a.granted)} of "
            f"{len(self.dns)} device nodes granted the term; continuing from the mirror of "
            f"loop {self.mirrored}",
        )
        return logic

    # -- standing down -----------------------------------------------------------
    @classmethod
    def stand_down(
        cls, mission: Mission, logic: ControlLogic, keys: KeySet | None, why: str
    ) -> Standby:
        """A commander that learned of a newer term becomes the standby: its
        logic (and vector) are kept, to be overwritten by the new
        commander's mirrors; ``cn_stood_down``."""
        sb = cls(mission, logic, keys)
        # Its own schedule and vector until the new commander's mirrors come:
        # loop numbers follow time, so the schedule is the same.
        sb.term = max(logic.term, logic.superseded)
        sb.mirrored, sb.mirrored_t = logic.loop, logic.t_ns
        sb.commander = sb.index
        sb.origin = logic.t_ns - (logic.loop - 1) * mission.period_ns if logic.loop else None
        sb.following = False  # until the new commander's mirror comes
        logic.events.emit(
            EV.CN_STOOD_DOWN,
            logic.t_ns,
            node=logic.name,
            loop=logic.loop,
            term=sb.term,
            why=why,
        )
        return sb
