"""Telemetry logs: the CSV format of docs/architecture.md#files.

:class:`CsvLogger` writes one header row (``rx_time_ns`` then every element of
the layout in buffer order; an array of at most :data:`MAX_ARRAY_COLUMNS`
values as one column per value, ``accel[0]``, a longer one left out) and one
row per telemetry snapshot: enums by name, bools as ``0``/``1``, integers in
decimal, floats in the shortest text that reads back exactly; ASCII, one
newline per row, never quoted. Also here: the events JSONL beside it
(:class:`EventWriter`, :func:`events_path`), :func:`read_csv` and the plot
(:func:`plot_telemetry`, :func:`plot_markers`). With ``append`` (a station's
logs) what is there is kept: rows go under the file's header when it is
theirs, else to the first ``NAME.N.csv`` that is (a CSV has one header),
after a torn last line is cut off (said in the log).

Contract: the same snapshots give the same bytes: nothing in a row depends on
the wall clock, dict or set order, or the platform (the lockstep runner's
byte-identical logs rely on it). Writing a row is one ``struct.unpack_from``
over the whole vector (a format precomputed from the layout) and one
formatter per column, chosen at construction; it blocks on the file write.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import struct
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple, TextIO

import msgspec
import numpy as np

from ..core.datavector import DataVector, ElementSpec, Layout
from ..errors import DataVectorError
from .records import EventRecord

__all__ = [
    "MAX_ARRAY_COLUMNS",
    "CsvLogger",
    "EventWriter",
    "Marker",
    "csv_columns",
    "events_path",
    "plot_markers",
    "plot_telemetry",
    "read_csv",
]

log = logging.getLogger("zplatform.telemetry")

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


def f32_value(v: float) -> float:
    """``v``, an f32 element's value, as the shortest float that reads back as
    the same f32: what the element holds, without the widened double's
    noise (0.7f is 0.7, not 0.699999988079071). NaN and infinities pass."""
    if v != v or v == _INF or v == -_INF:
        return float(v)
    return float(np.format_float_positional(np.float32(v), unique=True, trim="0"))


def _enum_formatter(names: tuple[str, ...]) -> Formatter:
    n = len(names)

    def fmt(v: int) -> str:
        return names[v] if 0 <= v < n else str(v)

    return fmt


def formatter(spec: ElementSpec) -> Formatter:
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
    construction. With ``append`` (a path only), a log already there is
    kept and the rows go after it (module doc: its header must be this
    layout's, else they go to ``NAME.N.csv``; :attr:`path` says where).
    :meth:`write` raises DataVectorError when the vector's layout is not the
    logger's (another mission config).
    """

    def __init__(
        self, target: str | Path | TextIO, layout: Layout, *, append: bool = False
    ) -> None:
        self.path: Path | None = None
        """The file written (None for a stream)."""
        header = ",".join(csv_columns(layout)) + "\n"
        if isinstance(target, str | Path):
            self.path = _csv_to_append(Path(target), header) if append else Path(target)
            self._f: TextIO = open(  # noqa: SIM115
                self.path, "a" if append else "w", encoding="ascii", newline=""
            )
            self._owned = True
            # The header goes into an empty file only (one appended to has it).
            fresh = os.fstat(self._f.fileno()).st_size == 0
        else:
            self._f = target
            self._owned = False
            fresh = True
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
            formatters.extend([formatter(e)] * n)
            pos = e.offset + e.size
        self._struct = struct.Struct("".join(fmt))
        self._formatters = tuple(formatters)
        self._columns = csv_columns(layout)
        assert len(self._columns) == len(formatters) + 1
        if fresh:
            self._f.write(header)

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


def _csv_to_append(path: Path, header: str) -> Path:
    """Where a log of ``header`` appends (module doc): ``path`` when it is
    absent, empty or starts with ``header`` (its torn last row cut off),
    else the first of ``NAME.1.csv``, ``NAME.2.csv``... that is. A file
    holding only part of the header (torn) is emptied. Files of another
    header are never changed."""
    want = header.encode("ascii")
    p, n = path, 0
    while not _takes(p, want):
        n += 1
        p = path.with_name(f"{path.stem}.{n}{path.suffix}")
    if p != path:
        log.warning("%s holds another layout's columns: the rows go to %s", path, p)
    return p


def _takes(p: Path, header: bytes) -> bool:
    """Whether rows under ``header`` may be appended to ``p`` (made ready
    for them: a torn last row cut off, a torn header emptied)."""
    try:
        with open(p, "rb") as f:
            head = f.read(len(header))
    except FileNotFoundError:
        return True
    if head == header:
        _cut_torn_tail(p)
        return True
    if not header.startswith(head) or len(head) != p.stat().st_size:
        return False  # another layout's log
    if head:  # a header cut short: no row was ever under it
        log.warning("%s: its header was cut short (%d bytes): rewritten", p, len(head))
        os.truncate(p, 0)
    return True


def _cut_torn_tail(path: Path) -> int:
    """Cut off ``path``'s last line when it has no newline (a process killed
    mid-write left it: no whole row or event), saying so in the log; return
    the bytes cut (0: the file ends with a newline, or is empty)."""
    with open(path, "r+b") as f:
        end = pos = f.seek(0, os.SEEK_END)
        while pos > 0:
            step = min(pos, 65536)
            f.seek(pos - step)
            chunk = f.read(step)
            if pos == end and chunk.endswith(b"\n"):
                return 0
            i = chunk.rfind(b"\n")
            if i >= 0:
                pos = pos - step + i + 1
                break
            pos -= step
        f.truncate(pos)
    log.warning("%s: its last line was cut short (%d bytes, no newline): removed", path, end - pos)
    return end - pos


def read_csv(source: str | Path | TextIO) -> list[dict[str, str]]:
    """Read a telemetry CSV into one dict per row (column -> text). For tests and tools."""
    if isinstance(source, str | Path):
        with open(source, encoding="ascii", newline="") as f:
            return list(csv.DictReader(f))
    return list(csv.DictReader(source))


# ---------------------------------------------------------------- events


def events_path(csv_path: str | Path) -> Path:
    """Where the events of a telemetry log go: ``tm.csv`` -> ``tm.events.jsonl``.

    A path that ends in ``.csv`` loses that suffix; any other gets
    ``.events.jsonl`` appended.
    """
    p = Path(csv_path)
    base = p.name[: -len(".csv")] if p.name.lower().endswith(".csv") else p.name
    return p.with_name(base + ".events.jsonl")


class EventWriter:
    """Writes event records as JSON lines, one object per event, in arrival order.

    Each line is a :class:`~zplatform.telemetry.records.EventRecord`:
    ``rx_time_ns`` (the receiver's clock, as in the CSV), then the event's
    ``node``, ``seq``, ``t_ns``, ``severity`` (its name), ``id`` and
    ``text``. Flushed after each event: events are rare and an operator may
    ``tail -f`` the file. The file is truncated at construction; with
    ``append``, the events go after those already there (module doc).
    :attr:`count` counts this writer's own.
    """

    def __init__(self, target: str | Path, *, append: bool = False) -> None:
        self.path = Path(target)
        if append and self.path.exists():
            _cut_torn_tail(self.path)
        self._f: TextIO = open(self.path, "a" if append else "w", encoding="utf-8")  # noqa: SIM115
        self.count = 0

    def write(self, rec: EventRecord) -> None:
        self._f.write(json.dumps(msgspec.to_builtins(rec), ensure_ascii=False) + "\n")
        self._f.flush()
        self.count += 1

    def close(self) -> None:
        """Close the file. Idempotent."""
        if not self._f.closed:
            self._f.close()

    def __enter__(self) -> EventWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------- plots


class Marker(NamedTuple):
    """A vertical line on a plot: ``t_s`` since the first row, its ``label``, its ``kind``."""

    t_s: float
    label: str
    kind: str  # "state" or "command"


def plot_markers(rows: list[dict[str, str]]) -> list[Marker]:
    """State changes and command verdicts found in a telemetry log.

    A state change is a row whose ``cn_state`` differs from the row before
    (label: the new state). A command is a row whose ``cn_cmd_seq`` differs
    from the row before (label: ``cn_cmd`` and ``cn_cmd_status``, e.g.
    ``LAUNCH ACCEPTED``). Columns that are missing give no markers.
    """
    if not rows or "rx_time_ns" not in rows[0]:
        return []
    t0 = int(rows[0]["rx_time_ns"])
    out: list[Marker] = []
    prev: dict[str, str] | None = None
    for r in rows:
        t = (int(r["rx_time_ns"]) - t0) / 1e9
        if prev is not None:
            if "cn_state" in r and r["cn_state"] != prev["cn_state"]:
                out.append(Marker(t, r["cn_state"], "state"))
            if "cn_cmd_seq" in r and r["cn_cmd_seq"] != prev["cn_cmd_seq"]:
                what = " ".join(x for x in (r.get("cn_cmd"), r.get("cn_cmd_status")) if x)
                out.append(Marker(t, what or f"command #{r['cn_cmd_seq']}", "command"))
        prev = r
    return out


def _as_numbers(raw: list[str]) -> list[float] | None:
    try:
        return [float(v) for v in raw]
    except ValueError:
        return None


#: Markers closer than this share of the run share one label.
_NEAR = 0.02
#: A shared label names at most this many markers, then "(+N more)".
_MAX_LINES = 5
#: Label text size and the gaps (points) around and between labels.
_LABEL_PT, _LABEL_GAP_PT = 7.0, 2.0


def _marker_groups(markers: list[Marker], span_s: float) -> list[list[Marker]]:
    """Markers in time order, in groups: those within :data:`_NEAR` of the run share a label."""
    near = _NEAR * (span_s if span_s > 0 else 1.0)
    groups: list[list[Marker]] = []
    for m in markers:
        if groups and m.t_s - groups[-1][0].t_s <= near:
            groups[-1].append(m)
        else:
            groups.append([m])
    return groups


def _group_text(group: list[Marker]) -> str:
    lines = [m.label for m in group]
    if len(lines) > _MAX_LINES:
        lines = [*lines[: _MAX_LINES - 1], f"(+{len(lines) - _MAX_LINES + 1} more)"]
    return "\n".join(lines)


def _stack_labels(fig: Any, ax: Any, labels: list[Any]) -> float:
    """Place marker labels above ``ax`` so that no two overlap; returns their height (pixels).

    Each label (an annotation at its marker's time on the top edge of
    ``ax``) is measured with the figure's renderer: its text and its
    background box. In time order, a label goes at the lowest height above
    the axes where it overlaps no label placed before it (a skyline: the
    candidates are the axes' edge and the top of every placed label). A
    label that would run past the axes' right edge is set to the left of its
    marker instead. The layout must be final in x: call after
    ``tight_layout``.
    """
    from matplotlib.transforms import Bbox

    renderer = fig.canvas.get_renderer()
    px_per_pt = renderer.points_to_pixels(1.0)
    gap = _LABEL_GAP_PT * px_per_pt
    right = ax.get_window_extent(renderer).x1

    def extent(label: Any) -> Any:
        label.update_positions(renderer)
        boxes = [label.get_window_extent(renderer)]
        patch = label.get_bbox_patch()
        if patch is not None:
            label.update_bbox_position_size(renderer)
            boxes.append(patch.get_window_extent(renderer))
        return Bbox.union(boxes)

    placed: list[Any] = []
    for label in labels:
        label.set_horizontalalignment("left")
        label.xyann = (_LABEL_GAP_PT, _LABEL_GAP_PT)
        box = extent(label)
        if box.x1 > right:  # no room on the right: the text ends at its marker
            label.set_horizontalalignment("right")
            label.xyann = (-_LABEL_GAP_PT, _LABEL_GAP_PT)
            box = extent(label)
        # Each box widened by a gap either side: neighbours on a line stay two gaps apart.
        wide = Bbox.from_extents(box.x0 - gap, box.y0, box.x1 + gap, box.y1)
        rise = 0.0
        for up in sorted({0.0, *(p.y1 + gap - box.y0 for p in placed)}):
            if up < 0:
                continue
            moved = wide.translated(0, up)
            if not any(moved.overlaps(p) for p in placed):
                rise = up
                break
        label.xyann = (label.xyann[0], _LABEL_GAP_PT + rise / px_per_pt)
        placed.append(wide.translated(0, rise))
    if not placed:
        return 0.0
    return max(p.y1 for p in placed) - ax.get_window_extent(renderer).y1 + gap


def plot_telemetry(
    rows: list[dict[str, str]],
    elements: list[str],
    out: str | Path,
    *,
    title: str | None = None,
) -> list[Marker]:
    """Draw ``elements`` of a telemetry log against time into ``out`` (PNG, ...).

    Numbers are lines; booleans (columns holding only ``0``/``1``) and enums
    (names) are steps with labelled levels (``False``/``True``, the enum
    names in order of first appearance). State changes and commands
    (:func:`plot_markers`) are vertical lines on every axis, named above the
    top one: markers within 2 % of the run share a label, and labels are
    stacked so that none overlaps another (:func:`_stack_labels`); the
    figure grows by their height. Needs matplotlib (the ``plot`` extra);
    uses the Agg backend. Returns the markers drawn.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    t0 = int(rows[0]["rx_time_ns"])
    t = [(int(r["rx_time_ns"]) - t0) / 1e9 for r in rows]
    markers = plot_markers(rows)
    height_in = 1.5 + 2.0 * len(elements)
    fig, axes = plt.subplots(
        len(elements), 1, sharex=True, squeeze=False, figsize=(10, height_in), dpi=100
    )
    try:
        for ax, name in zip(axes[:, 0], elements, strict=True):
            raw = [r[name] for r in rows]
            nums = _as_numbers(raw)
            if nums is not None and set(raw) <= {"0", "1"}:
                ax.step(t, nums, where="post")
                ax.set_yticks([0, 1], ["False", "True"])
                ax.set_ylim(-0.2, 1.2)
            elif nums is not None:
                ax.plot(t, nums)
                if all(v.lstrip("-").isdigit() for v in raw):
                    # An integer element: whole-number ticks only (a counter
                    # between 3 and 4 has no 3.5).
                    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
            else:  # an enum written by name: its levels in order of appearance
                names = sorted(set(raw), key=raw.index)
                ax.step(t, [names.index(v) for v in raw], where="post")
                ax.set_yticks(range(len(names)), names)
                ax.set_ylim(-0.5, len(names) - 0.5)
            ax.set_ylabel(name)
            ax.grid(True, alpha=0.3)
            for m in markers:
                ax.axvline(
                    m.t_s,
                    color="tab:red" if m.kind == "state" else "tab:green",
                    linestyle="--" if m.kind == "state" else ":",
                    linewidth=1,
                    label=m.label,
                )
        top = axes[0, 0]
        labels = []
        for g in _marker_groups(markers, t[-1] - t[0]):
            at = (g[0].t_s, 1.0)
            state = g[0].kind == "state"
            # The marker's line, on from the axes' edge up to its label, beneath every label.
            top.annotate(
                "",
                xy=at,
                xycoords=("data", "axes fraction"),
                xytext=(0, 0),
                textcoords="offset points",
                arrowprops={
                    "arrowstyle": "-",
                    "color": "tab:red" if state else "tab:green",
                    "linestyle": "--" if state else ":",
                    "lw": 1,
                    "shrinkA": 0,
                    "shrinkB": 0,
                },
                annotation_clip=False,
                zorder=2.5,
            ).set_in_layout(False)
            labels.append(
                top.annotate(
                    _group_text(g),
                    xy=at,
                    xycoords=("data", "axes fraction"),
                    xytext=(_LABEL_GAP_PT, _LABEL_GAP_PT),
                    textcoords="offset points",
                    va="bottom",
                    ha="left",
                    fontsize=_LABEL_PT,
                    bbox={"boxstyle": "square,pad=0.1", "fc": "white", "ec": "none"},
                    color="tab:red" if all(m.kind == "state" for m in g) else "black",
                    annotation_clip=False,
                    zorder=3,
                )
            )
        leaders = [a for a in top.texts if not a.get_text()]
        axes[-1, 0].set_xlabel("time since first snapshot (s)")
        fig.suptitle(title or ", ".join(elements))
        # The labels' height depends on where the layout puts the axes, and the
        # layout on the labels' height: settle it (the x scale barely moves).
        for attempt in range(4):
            fig.tight_layout()
            stack_in = _stack_labels(fig, top, labels) / fig.dpi
            want = height_in + stack_in
            if attempt == 3 or abs(fig.get_figheight() - want) < 0.02:
                break
            fig.set_figheight(want)
        for leader, label in zip(leaders, labels, strict=True):
            leader.xyann = (0.0, label.xyann[1])
        fig.savefig(Path(out), dpi=100)
    finally:
        plt.close(fig)
    return markers
