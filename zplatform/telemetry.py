"""Telemetry logs: the CSV format of DESIGN.md §6.

:class:`CsvLogger` writes one header row and one row per telemetry snapshot:

* the header is ``rx_time_ns`` then every element of the layout in buffer
  order; an array of at most :data:`MAX_ARRAY_COLUMNS` values becomes one
  column per value (``accel[0]``, ``accel[1]``, ...), a longer one is left out;
* enums are written by name (the number if the value has no name), bools as
  ``0``/``1``, integers in decimal, ``f64`` with ``repr`` and ``f32`` with the
  shortest text that reads back as the same ``f32``: every float round-trips
  exactly; ``nan``, ``inf`` and ``-inf`` are spelled so;
* lines end in ``\\n``, the file is ASCII; no quoting is ever needed (names are
  identifiers and no value contains a comma).

The same snapshots give the same bytes: nothing in a row depends on the
wall clock, dict or set order, or the platform (the lockstep runner's
byte-identical logs rely on it).

Writing a row is one ``struct.unpack_from`` over the whole vector (a format
precomputed from the layout, pad bytes over the left-out arrays) and one
formatter per column, chosen at construction.
"""

from __future__ import annotations

import csv
import struct
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any, TextIO

import numpy as np

from .datavector import DataVector, ElementSpec, Layout
from .errors import DataVectorError

__all__ = ["MAX_ARRAY_COLUMNS", "CsvLogger", "csv_columns", "read_csv"]

MAX_ARRAY_COLUMNS = 16

Formatter = Callable[[Any], str]


def _fmt_bool(v: Any) -> str:
    return "1" if v else "0"


_INF = float("inf")


def _fmt_f32(v: float) -> str:
    # numpy prints the shortest decimal that reads back as the same f32
    # (Dragon4, unique=True); repr of the widened double would print up to
    # 17 digits (0.1f -> 0.10000000149011612).
    if v != v or v == _INF or v == -_INF:
        return repr(v)
    a = abs(v)
    if a == 0.0 or 1e-4 <= a < 1e16:
        return np.format_float_positional(np.float32(v), unique=True, trim="0")
    return np.format_float_scientific(np.float32(v), unique=True, trim="0")


def _enum_formatter(names: tuple[str, ...]) -> Formatter:
    n = len(names)

    def fmt(v: int) -> str:
        return names[v] if 0 <= v < n else str(v)

    return fmt


def _formatter(spec: ElementSpec) -> Formatter:
    if spec.enum is not None:
        return _enum_formatter(spec.enum)
    kind = spec.scalar.kind
    if kind == "bool":
        return _fmt_bool
    if kind == "int":
        return str
    if spec.scalar.size == 4:
        return _fmt_f32
    return repr


def csv_columns(layout: Layout) -> list[str]:
    """The CSV header of ``layout``: ``rx_time_ns`` and every element column."""
    cols = ["rx_time_ns"]
    for e in layout.elements.values():
        if e.count == 0:
            cols.append(e.name)
        elif e.count <= MAX_ARRAY_COLUMNS:
            cols.extend(f"{e.name}[{i}]" for i in range(e.count))
    return cols


class CsvLogger:
    """Writes telemetry snapshots of one layout as CSV (see the module doc).

    ``target`` is a path (opened for writing, truncated) or an open text
    stream (not closed by :meth:`close`). The header is written at
    construction. :meth:`write` raises DataVectorError when the vector's
    layout is not the logger's (another mission config).
    """

    def __init__(self, target: str | Path | TextIO, layout: Layout) -> None:
        if isinstance(target, str | Path):
            self._f: TextIO = open(target, "w", encoding="ascii", newline="")  # noqa: SIM115
            self._owned = True
        else:
            self._f = target
            self._owned = False
        self.layout = layout
        self.rows = 0
        fmt = ["<"]
        pos = 0
        formatters: list[Formatter] = []
        # Layout.elements is in buffer order, as csv_columns lists them.
        for e in layout.elements.values():
            if e.count > MAX_ARRAY_COLUMNS:
                continue
            if e.offset > pos:
                fmt.append(f"{e.offset - pos}x")
            n = max(e.count, 1)
            fmt.append(f"{n}{e.scalar.struct}")
            formatters.extend([_formatter(e)] * n)
            pos = e.offset + e.size
        self._struct = struct.Struct("".join(fmt))
        self._formatters = tuple(formatters)
        self._columns = csv_columns(layout)
        assert len(self._columns) == len(formatters) + 1
        self._f.write(",".join(self._columns) + "\n")

    @property
    def columns(self) -> list[str]:
        """The header, as written."""
        return list(self._columns)

    def write(self, rx_time_ns: int, dv: DataVector) -> None:
        """Append one row: ``rx_time_ns`` and ``dv``'s current values."""
        if dv.layout is not self.layout and dv.layout.layout_id != self.layout.layout_id:
            raise DataVectorError(
                f"vector layout {dv.layout.layout_id:#010x} is not the logger's "
                f"{self.layout.layout_id:#010x}"
            )
        values = self._struct.unpack_from(dv.buf, 0)
        self._f.write(
            str(rx_time_ns)
            + ","
            + ",".join([f(v) for f, v in zip(self._formatters, values, strict=True)])
            + "\n"
        )
        self.rows += 1

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        """Flush; close the file if the logger opened it. Idempotent."""
        if self._f.closed:
            return
        self._f.flush()
        if self._owned:
            self._f.close()

    def __enter__(self) -> CsvLogger:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def read_csv(source: str | Path | TextIO) -> list[dict[str, str]]:
    """Read a telemetry CSV into one dict per row (column -> text). For tests and tools."""
    if isinstance(source, str | Path):
        with open(source, encoding="ascii", newline="") as f:
            return list(csv.DictReader(f))
    return list(csv.DictReader(source))
