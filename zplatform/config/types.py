"""Element types of the Data Vector (the thesis, ch. 4.1.1; docs/architecture.md#data-vector).

The thesis' eleven scalar types, their little-endian wire form, and the range
each one holds. Everything else (arrays ``f32[3]``, enums) is built on these.
This module is pure data: no numpy arrays are allocated here.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

__all__ = ["SCALAR_TYPES", "ScalarType", "parse_type"]


@dataclass(frozen=True, slots=True)
class ScalarType:
    """One of the eleven element types.

    ``numpy`` is the little-endian numpy dtype string, ``struct`` the
    ``struct`` format character (used with ``<``), ``size`` the byte width.
    ``lo``/``hi`` bound integer types; floats and bool have ``None``.
    """

    name: str
    numpy: str
    struct: str
    size: int
    kind: str  # "int" | "float" | "bool"
    lo: int | None = None
    hi: int | None = None

    def fits(self, value: object) -> bool:
        """Whether ``value`` can be stored in this type without loss or wrap."""
        if self.kind == "bool":
            return isinstance(value, bool) or (isinstance(value, int) and value in (0, 1))
        if self.kind == "int":
            if isinstance(value, bool):
                return False
            if isinstance(value, float):
                if not value.is_integer():
                    return False
                value = int(value)
            if not isinstance(value, int):
                return False
            assert self.lo is not None and self.hi is not None
            return self.lo <= value <= self.hi
        # float: any real number, including nan and +-inf; f32 must not overflow
        if isinstance(value, bool) or not isinstance(value, int | float):
            return False
        return not (self.size == 4 and math.isfinite(value) and abs(value) > 3.4028234663852886e38)


def _int(name: str, size: int, signed: bool) -> ScalarType:
    fmt = {1: "b", 2: "h", 4: "i", 8: "q"}[size]
    if not signed:
        fmt = fmt.upper()
    bits = 8 * size
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    return ScalarType(name, f"<{'i' if signed else 'u'}{size}", fmt, size, "int", lo, hi)


SCALAR_TYPES: dict[str, ScalarType] = {
    t.name: t
    for t in (
        _int("u8", 1, False),
        _int("u16", 2, False),
        _int("u32", 4, False),
        _int("u64", 8, False),
        _int("i8", 1, True),
        _int("i16", 2, True),
        _int("i32", 4, True),
        _int("i64", 8, True),
        ScalarType("f32", "<f4", "f", 4, "float"),
        ScalarType("f64", "<f8", "d", 8, "float"),
        ScalarType("bool", "|b1", "?", 1, "bool"),
    )
}

_TYPE_RE = re.compile(r"^([a-z0-9]+)(?:\[([0-9]+)\])?$")


def parse_type(text: str) -> tuple[ScalarType, int] | None:
    """Parse ``"f32"`` or ``"u8[16]"`` into ``(scalar type, count)``.

    ``count`` is 0 for a scalar, the array length otherwise. Returns ``None``
    when the text is not a valid type (the caller raises with the YAML path).
    """
    m = _TYPE_RE.match(text.strip())
    if m is None:
        return None
    scalar = SCALAR_TYPES.get(m.group(1))
    if scalar is None:
        return None
    if m.group(2) is None:
        return scalar, 0
    count = int(m.group(2))
    if count < 1:
        return None
    return scalar, count
