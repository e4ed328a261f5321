"""Error handling after start (the thesis, ch. 4.11.1), sans-IO.

The thesis' split: a **critical** error sets a flag the state machine reads
(``cn_fault``, an enum of :class:`~zplatform.config.codes.Fault`), so a configured
transition (``cn_fault != NONE``) takes the vehicle to a safe state; a
**non-critical** one is counted (``cn_errors``, its code in ``cn_last_error``)
and evented, and the loop keeps its rate. :class:`FaultMonitor` decides which
is which from the ``faults`` section: a symptom (DN_LOST, CONTROLLER_FAILED,
SYNC_OVERRUNS, LOOP_OVERRUNS, CLOCK_DRIFT, DN_SAFED) becomes critical when it
persists for its count of consecutive loops; the mission's monitors latch
theirs through :meth:`FaultMonitor.raise_fault`.

Contract: runs on the CN's loop thread in ``ControlLogic.finish``, first of the
logic; never blocks, never raises for a symptom. Only the first fault
latches, and it stays until written back to ``NONE`` (or, with
``faults.dn_rejoin_clears``, DN_LOST clears when every device node answers
again); a raised fault emits one WARNING_HI ``fault`` event.

The symptoms, their counts and what is no fault: docs/architecture.md#errors-and-faults.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..config.codes import ErrorCode, Fault, SafedWhy
from ..core.events import EV, EventLog

if TYPE_CHECKING:
    from ..config import Mission
    from ..core.datavector import DataVector, Handle

__all__ = ["ErrorCode", "Fault", "FaultMonitor"]


class _Watch:
    """A counter element and how many consecutive loops it has grown."""

    __slots__ = ("fault", "get", "last", "limit", "run", "text", "who")

    def __init__(self, h: Handle, fault: Fault, limit: int, text: str, who: str = "") -> None:
        self.who = who
        self.get = h.get
        self.last: int = h.get()
        self.fault = fault
        self.limit = limit
        self.run = 0
        self.text = text


class FaultMonitor:
    """Turns persistent symptoms into the ``cn_fault`` flag (module doc).

    ``dv`` is the CN's Data Vector. The runtime calls :meth:`step` once per
    loop after the sync step (so this loop's ``cn_missed_dnX`` and received
    ``dnX_errors`` are in), before the state machine. Counters that are
    present at construction are the baseline. Everything is resolved at
    construction; a step reads the watched counters and compares integers.
    Not thread-safe (the CN loop thread only). No method raises.
    """

    def __init__(self, mission: Mission, dv: DataVector, events: EventLog) -> None:
        f = mission.faults
        self._events = events
        self._h_fault = dv.handle("cn_fault")
        self._h_errors = dv.handle("cn_errors")
        self._h_last = dv.handle("cn_last_error")
        self._controller_limit = f.controller_fail_loops
        watches: list[_Watch] = []
        dns = mission.device_nodes
        if f.dn_lost_loops > 0:
            for dn in dns:
                watches.append(
                    _Watch(
                        dv.handle(f"cn_missed_{dn}"),
                        Fault.DN_LOST,
                        f.dn_lost_loops,
                        f"{dn} missed {f.dn_lost_loops} syncs in a row",
                        dn,
                    )
                )
        if f.controller_fail_loops > 0:
            for dn in dns:
                watches.append(
                    _Watch(
                        dv.handle(f"{dn}_errors"),
                        Fault.CONTROLLER_FAILED,
                        f.controller_fail_loops,
                        f"{dn} reported errors in {f.controller_fail_loops} loops in a row",
                    )
                )
        if f.sync_overrun_loops > 0:
            watches.append(
                _Watch(
                    dv.handle("cn_sync_overruns"),
                    Fault.SYNC_OVERRUNS,
                    f.sync_overrun_loops,
                    f"sync overran in {f.sync_overrun_loops} loops in a row",
                )
            )
        if f.loop_overrun_loops > 0:
            watches.append(
                _Watch(
                    dv.handle("cn_loop_overruns"),
                    Fault.LOOP_OVERRUNS,
                    f.loop_overrun_loops,
                    f"loop overran in {f.loop_overrun_loops} loops in a row",
                )
            )
        self._watches = tuple(watches)
        # faults.dn_rejoin_clears: DN_LOST clears once every device node has
        # answered again for dn_reenable_loops loops in a row.
        self._rejoin = f.dn_rejoin_clears and f.dn_lost_loops > 0 and bool(dns)
        self._rejoin_after = f.dn_reenable_loops
        self._lost = tuple(w for w in watches if w.fault == Fault.DN_LOST)
        self._answered = 0  # loops in a row in which every device node answered
        self._lost_names: list[str] = []
        # The clock bound (thesis 4.9) holds for the whole run: the DNs'
        # periodic re-sync measures what is left after the start-up
        # correction (dnX_clock_drift_ns).
        self._clock_bound = round(mission.clock.offset_bound_ms * 1e6)
        self._drift = tuple((dn, dv.handle(f"{dn}_clock_drift_ns")) for dn in dns)
        self._safed_why = tuple((dn, dv.handle(f"{dn}_safed_why")) for dn in dns)

    @property
    def fault(self) -> str:
        """The current ``cn_fault`` value's name."""
        v = self._h_fault.get()
        return Fault(v).name if v < len(Fault) else str(v)

    def step(self, t_ns: int) -> None:
        """Update the consecutive-growth runs; raise the first fault due.

        Watches are checked in order DN_LOST, CONTROLLER_FAILED,
        SYNC_OVERRUNS, LOOP_OVERRUNS, CLOCK_DRIFT, then DN_SAFED; every run
        is updated every loop.
        """
        for w in self._watches:
            v = w.get()
            if v > w.last:
                w.run += 1
            else:
                w.run = 0
            w.last = v
            if w.run >= w.limit and self.raise_fault(w.fault, w.text, t_ns) and w.who:
                self._lost_names.append(w.who)
        if self._rejoin:
            self._clear_on_rejoin(t_ns)
        bound = self._clock_bound
        for dn, h in self._drift:
            d = h.get()
            if d > bound or d < -bound:
                self.raise_fault(
                    Fault.CLOCK_DRIFT,
                    f"{dn}'s clock drifted {d / 1e6:+.3f} ms from the CN's, beyond the "
                    f"bound of {bound / 1e6:g} ms",
                    t_ns,
                )
        for dn, h in self._safed_why:
            if h.get() == SafedWhy.CANNOT_RUN:
                self.raise_fault(
                    Fault.DN_SAFED,
                    f"{dn} safed itself: it answers the triggers but none can run (its "
                    "clock off? see its dn_safed event)",
                    t_ns,
                )

    def _clear_on_rejoin(self, t_ns: int) -> None:
        """``faults.dn_rejoin_clears``: a latched DN_LOST clears once every
        device node has answered again (none missed) for ``dn_reenable_loops``
        loops in a row, with a ``dn_fault_cleared`` event."""
        if any(w.run for w in self._lost):
            self._answered = 0
            return
        self._answered += 1
        if self._answered < self._rejoin_after or self._h_fault.get() != Fault.DN_LOST:
            return
        self._h_fault.set(int(Fault.NONE))
        who = ", ".join(self._lost_names) or "the lost device node"
        self._lost_names.clear()
        self._events.emit(
            EV.DN_FAULT_CLEARED, t_ns, dn=who, n=self._answered, fault=Fault.DN_LOST.name
        )

    def adopt(self) -> None:
        """Take up the watched counters as they stand (a takeover,
        :meth:`zplatform.control.loop.ControlLogic.adopt`): their growth runs start
        over, so a symptom must persist for its whole count from here."""
        for w in self._watches:
            w.last = w.get()
            w.run = 0

    def report_controller_failure(self, name: str, consecutive: int, t_ns: int) -> None:
        """A CN controller raised in ``consecutive`` loops in a row (the
        controller runner calls this every loop one raises). Raises
        CONTROLLER_FAILED when ``consecutive >= faults.controller_fail_loops``
        (and that is > 0). Does not count the error in ``cn_errors``: the
        runner reports it with :meth:`error` too."""
        limit = self._controller_limit
        if limit > 0 and consecutive >= limit:
            self.raise_fault(
                Fault.CONTROLLER_FAILED,
                f"controller {name} failed in {consecutive} loops in a row",
                t_ns,
            )

    def raise_fault(self, fault: Fault, text: str, t_ns: int) -> bool:
        """Set ``cn_fault`` unless a fault is already latched.

        Returns True and emits a WARNING_HI ``fault`` event when it was set;
        False (silently) when another fault was latched already.
        """
        if self._h_fault.get() != Fault.NONE or fault == Fault.NONE:
            return False
        self._h_fault.set(int(fault))
        self._events.emit(EV.FAULT, t_ns, fault=fault.name, text=text)
        return True

    def error(self, code: int, text: str, t_ns: int) -> None:
        """A non-critical error: ``cn_errors += 1`` (saturating),
        ``cn_last_error = code`` (clamped to 0..65535), a WARNING_LO ``error`` event."""
        self._h_errors.bump()
        self._h_last.set(min(max(int(code), 0), 0xFFFF))
        self._events.emit(EV.ERROR, t_ns, text=text)
