"""Error handling after start (the thesis, ch. 4.11.1), sans-IO.

The thesis' node mains handle an error after start in one of two ways:

* **critical**: set a flag the state machine reads, so a configured
  transition (``cn_fault != NONE -> ABORT``) takes the vehicle to a safe
  state. The flag is ``cn_fault``, an enum of
  :class:`~zplatform.codes.Fault`;
* **non-critical**: count it in the Data Vector (``cn_errors``, with the
  code in ``cn_last_error``) and publish an event; the loop keeps its rate.

:class:`FaultMonitor` decides which is which from the ``faults`` section:
a symptom becomes critical when it persists for N consecutive loops (N = 0
turns that check off):

================== ==================================== ======================
fault              symptom, per loop                    N
================== ==================================== ======================
DN_LOST            ``cn_missed_dnX`` grew (any dnX)     ``dn_lost_loops``
CONTROLLER_FAILED  ``dnX_errors`` grew (any dnX), or a  ``controller_fail_loops``
                   CN controller raised
                   (:meth:`~FaultMonitor.report_controller_failure`)
SYNC_OVERRUNS      ``cn_sync_overruns`` grew            ``sync_overrun_loops``
LOOP_OVERRUNS      ``cn_loop_overruns`` grew            ``loop_overrun_loops``
CLOCK_DRIFT        ``|dnX_clock_drift_ns|`` beyond the   1 (one reading)
                   clock bound (``clock.offset_bound_ms``)
DN_SAFED           ``dnX_safed_why`` is ``CANNOT_RUN``   1 (one reading)
                   (any dnX)
================== ==================================== ======================

``DN_SAFED`` is a device node that answers the CN's triggers yet runs none
of them (its clock off, every trigger stale): the node has safed itself
after ``faults.dn_watchdog_loops`` periods of that and says so in its
replies (:class:`~zplatform.loop.DeviceLogic`). A node safed because the CN
went quiet (``CN_LOST``) or because the run ended (``RUN_ENDED``) is no
fault here: it re-enables once the CN triggers it again, and a CN that
stops hearing it latches ``DN_LOST``. Missions answer ``DN_SAFED`` like
any fault (``cn_fault != NONE``): the shipped igniter mission aborts from
ARMED and FIRE, so a DN that cannot run ends a flight ABORTED, visibly,
instead of ARMED with a healthy-looking link.

The mission's monitors (:mod:`zplatform.monitors`) latch faults too, through
:meth:`FaultMonitor.raise_fault`: ``MONITOR`` or the fault a monitor names
(``THREAD_STALLED`` for a node's stalled thread, say).

Only the first fault latches: once ``cn_fault`` is not ``NONE`` it stays
until someone writes it back (a WRITE command of ``cn_fault = NONE``, or a
state-machine action); a symptom still present then raises it again. A
mission may let DN_LOST clear itself (``faults.dn_rejoin_clears``): once
every device node has answered again for ``faults.dn_reenable_loops`` loops
in a row (a restarted node, a healed link), with a ``dn_fault_cleared``
event; a transition the fault fired stays taken. A
raised fault emits one ``WARNING_HI`` event (``EV.FAULT``): the platform acted,
and the state machine answers it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .codes import ErrorCode, Fault, SafedWhy
from .events import EV, EventLog

if TYPE_CHECKING:
    from .config import Mission
    from .datavector import DataVector, Handle

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
        :meth:`zplatform.loop.ControlLogic.adopt`): their growth runs start
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
