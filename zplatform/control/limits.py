"""Element limits: yellow and red ranges for the console and the XTCE alarms.

An element may declare ``limits: {yellow: [lo, hi], red: [lo, hi]}`` in the
mission; either bound may be null (open). A value below ``lo`` or above
``hi`` of ``red`` is red, else of ``yellow`` yellow; inside both it is
nominal. Limits apply to scalar numeric elements (not enums, not arrays).

The mission's limits are ``ElementConfig.limits``
(:class:`~zplatform.config.LimitsConfig`), checked at load by
:func:`zplatform.mission.load.check_mission`.
Callers may add or override limits with a ``{name: {yellow: .., red: ..}}``
mapping (a console option, tests).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..config import Mission
from ..core.datavector import Layout
from ..errors import DataVectorError

__all__ = ["Limits", "mission_limits"]


@dataclass(frozen=True, slots=True)
class Limits:
    """Yellow and red ranges of one element; ``None`` bounds are open."""

    yellow: tuple[float | None, float | None] = (None, None)
    red: tuple[float | None, float | None] = (None, None)

    @staticmethod
    def _outside(v: float, rng: tuple[float | None, float | None]) -> bool:
        lo, hi = rng
        return (lo is not None and v < lo) or (hi is not None and v > hi)

    def level(self, value: float) -> str:
        """``"red"``, ``"yellow"`` or ``""``."""
        if self._outside(value, self.red):
            return "red"
        if self._outside(value, self.yellow):
            return "yellow"
        return ""

    @classmethod
    def parse(cls, raw: Any, where: str) -> Limits:
        """From ``{yellow: [lo, hi], red: [lo, hi]}`` (a mapping or a Struct)."""

        def rng(key: str) -> tuple[float | None, float | None]:
            v = raw.get(key) if isinstance(raw, Mapping) else getattr(raw, key, None)
            if v is None:
                return (None, None)
            try:
                lo, hi = v
                return (
                    None if lo is None else float(lo),
                    None if hi is None else float(hi),
                )
            except (TypeError, ValueError):
                raise DataVectorError(
                    f"limits.{key} of {where} must be [lo, hi] (null for open), got {v!r}"
                ) from None

        return cls(yellow=rng("yellow"), red=rng("red"))


def mission_limits(mission: Mission, extra: Mapping[str, Any] | None = None) -> dict[str, Limits]:
    """Every element's limits: the mission's, then ``extra`` over them.

    Raises DataVectorError for an unknown element in ``extra``, a malformed
    range, or limits on an enum or array element.
    """
    layout = Layout.for_node(mission, "cn")
    raw: dict[str, Any] = {}
    for region in mission.regions.values():
        for ec in region:
            if ec.limits is not None:
                raw[ec.name] = ec.limits
    raw.update(extra or {})
    out: dict[str, Limits] = {}
    for name, v in raw.items():
        spec = layout.element(name)
        if spec.count or spec.enum is not None or spec.scalar.kind == "bool":
            raise DataVectorError(f"limits on {name} ({spec.type_text}): only numbers have limits")
        out[name] = Limits.parse(v, name)
    return out
