"""Rate groups: members that run every Nth loop, F Prime RateGroupDriver style.

Pure arithmetic, no I/O, no clock: the sans-IO core (controllers, devices)
imports this module without pulling in the real-time OS code of
:mod:`zplatform.runtime.scheduler`.

:func:`rate_due` says whether a ``(divisor, phase)`` member runs on a loop;
:class:`RateGroups` precomputes, at configure time, the tuple of members due
on each loop of the hyperperiod, so :meth:`RateGroups.due` in the loop is one
modulo and one index and allocates nothing.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Generic, TypeVar

from ..errors import SchedulerError

__all__ = ["RateGroup", "RateGroups", "check_int", "rate_due"]

T = TypeVar("T")


def check_int(name: str, value: object, *, minimum: int) -> int:
    """Return ``value`` if it is an ``int`` (not a ``bool``) of at least ``minimum``.

    Raises :class:`SchedulerError` naming ``name`` otherwise (also used by
    :mod:`zplatform.runtime.scheduler` for its own arguments).
    """
    if isinstance(value, bool) or not isinstance(value, int):
        raise SchedulerError(f"{name} must be an int, got {type(value).__name__} {value!r}")
    if value < minimum:
        raise SchedulerError(f"{name} must be >= {minimum}, got {value}")
    return value


def rate_due(loop: int, divisor: int, phase: int = 0) -> bool:
    """Whether a member with ``divisor`` and ``phase`` runs on loop ``loop``.

    True when ``loop % divisor == phase``: every loop for divisor 1, every
    other loop for 2 (odd loops with phase 1), and so on. Raises
    :class:`SchedulerError` if ``divisor < 1`` or ``phase`` is not in
    ``[0, divisor)``.
    """
    if divisor < 1:
        raise SchedulerError(f"rate-group divisor must be >= 1, got {divisor}")
    if not 0 <= phase < divisor:
        raise SchedulerError(f"rate-group phase must be in [0, {divisor}), got {phase}")
    return loop % divisor == phase


@dataclass(frozen=True, slots=True)
class RateGroup(Generic[T]):
    """One rate-group member: ``member`` runs on loops where ``loop % divisor == phase``.

    Raises :class:`SchedulerError` for a divisor below 1 or a phase outside
    ``[0, divisor)``.
    """

    member: T
    divisor: int = 1
    phase: int = 0

    def __post_init__(self) -> None:
        check_int("rate-group divisor", self.divisor, minimum=1)
        check_int("rate-group phase", self.phase, minimum=0)
        if self.phase >= self.divisor:
            raise SchedulerError(
                f"rate-group phase must be in [0, {self.divisor}), got {self.phase}"
                f" (member {self.member!r})"
            )

    def due(self, loop: int) -> bool:
        """Whether this member runs on loop ``loop``."""
        return loop % self.divisor == self.phase


class RateGroups(Generic[T]):
    """Members run every Nth loop, F Prime RateGroupDriver style.

    Members are registered at configure time with :meth:`add`; each
    registration rebuilds a table over the hyperperiod (the least common
    multiple of the divisors) holding, for each loop in it, the tuple of
    members due, in registration order. :meth:`due` is then one modulo and one
    index: no allocation, no per-member test.

    If the hyperperiod exceeds ``max_table`` entries (divisors with no common
    structure, like 7, 11, 13, 17), no table is built and :meth:`due` tests
    each member and builds its tuple per call instead; choose harmonic
    divisors (1, 2, 5, 10, …) to stay on the table.
    """

    def __init__(self, members: Iterable[RateGroup[T]] = (), *, max_table: int = 65_536) -> None:
        self._max_table = check_int("max_table", max_table, minimum=1)
        self._groups: list[RateGroup[T]] = []
        self._hyperperiod = 1
        self._table: tuple[tuple[T, ...], ...] | None = ((),)
        for group in members:
            if not isinstance(group, RateGroup):
                raise SchedulerError(f"RateGroups takes RateGroup entries, got {group!r}")
            self._groups.append(group)
        self._rebuild()

    def add(self, member: T, divisor: int = 1, phase: int = 0) -> RateGroup[T]:
        """Register ``member`` to run when ``loop % divisor == phase``; return its entry.

        Raises :class:`SchedulerError` for a divisor below 1 or a phase
        outside ``[0, divisor)``.
        """
        group = RateGroup(member, divisor, phase)
        self._groups.append(group)
        self._rebuild()
        return group

    def _rebuild(self) -> None:
        hyperperiod = 1
        for group in self._groups:
            hyperperiod = math.lcm(hyperperiod, group.divisor)
        self._hyperperiod = hyperperiod
        if hyperperiod > self._max_table:
            self._table = None
            return
        self._table = tuple(
            tuple(g.member for g in self._groups if t % g.divisor == g.phase)
            for t in range(hyperperiod)
        )

    @property
    def hyperperiod(self) -> int:
        """The least common multiple of the divisors: the due pattern repeats after it."""
        return self._hyperperiod

    @property
    def tabled(self) -> bool:
        """Whether :meth:`due` answers from the precomputed table."""
        return self._table is not None

    def due(self, loop: int) -> tuple[T, ...]:
        """The members due on loop ``loop``, in registration order."""
        table = self._table
        if table is not None:
            return table[loop % self._hyperperiod]
        return tuple(g.member for g in self._groups if loop % g.divisor == g.phase)

    def __iter__(self) -> Iterator[RateGroup[T]]:
        return iter(tuple(self._groups))

    def __len__(self) -> int:
        return len(self._groups)
