"""The ground's status line and loop-rate meter, defined once.

``up`` prints :func:`status_line` every second, the line prompt every
``--interval``; the console draws the same facts (its header). The loop rate
comes from the CN's own numbers, ``cn_loop`` over ``cn_time_ns`` between
snapshots, not from when the ground happened to receive them, and it is
unknown (``-``) until two snapshots of one run give it: never a made-up
``0.0 Hz``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

from ..config import Mission
from ..core.datavector import DataVector

__all__ = ["RateMeter", "status_line"]


class RateMeter:
    """The CN's loop rate from ``(cn_time_ns, cn_loop)`` samples.

    :meth:`add` keeps a sample at most every ``min_step_ns`` of CN time, in
    a window of ``window`` samples; a sample going back in time (a restarted
    CN) starts the window afresh. :attr:`hz` is None until two samples span
    some time. Allocates nothing per call once the window is full.
    """

    def __init__(self, *, window: int = 64, min_step_ns: int = 50_000_000) -> None:
        self._samples: deque[tuple[int, int]] = deque(maxlen=window)
        self._step = min_step_ns

    def add(self, t_ns: int, loop: int) -> None:
        s = self._samples
        if s and (t_ns < s[-1][0] or loop < s[-1][1]):
            s.clear()
        if not s or t_ns - s[-1][0] >= self._step:
            s.append((t_ns, loop))

    def add_snapshot(self, dv: DataVector) -> None:
        """:meth:`add` with a snapshot's ``cn_time_ns`` and ``cn_loop``."""
        self.add(int(dv.get("cn_time_ns")), int(dv.get("cn_loop")))

    @property
    def hz(self) -> float | None:
        s = self._samples
        if len(s) < 2:
            return None
        (t0, l0), (t1, l1) = s[0], s[-1]
        return (l1 - l0) * 1e9 / (t1 - t0) if t1 > t0 else None


def _value(dv: DataVector, name: str) -> str:
    spec = dv.layout.element(name)
    return dv.get_name(name) if spec.enum is not None else str(dv.get(name))


def status_line(
    mission: Mission, dv: DataVector, hz: float | None, watch: Sequence[str] = ()
) -> str:
    """One line: loop, rate, state, fault, misses per DN, overruns, the last
    verdict, a redundant mission's commander, term and standby, then
    ``watch``'s elements (``name=value``)."""
    misses = " ".join(f"{dn}={int(dv.get(f'cn_missed_{dn}'))}" for dn in mission.device_nodes)
    rate = "-" if hz is None else f"{hz:.1f}"
    line = (
        f"loop {int(dv.get('cn_loop')):>8}  {rate:>6} Hz  state {dv.get_name('cn_state')}  "
        f"fault {dv.get_name('cn_fault')}  missed {misses or '-'}  overruns "
        f"{int(dv.get('cn_loop_overruns'))}/{int(dv.get('cn_sync_overruns'))}  "
        f"cmd #{int(dv.get('cn_cmd_seq'))} {dv.get_name('cn_cmd_status')}"
    )
    if mission.standby is not None:  # who commands, in which term, and the standby
        ready = "standby ready" if dv.get("cn_standby_ready") else "NO STANDBY"
        line += f"  {dv.get_name('cn_commander')} commands (term {int(dv.get('cn_term'))}, {ready})"
    if watch:
        line += "  " + " ".join(f"{n}={_value(dv, n)}" for n in watch)
    return line
