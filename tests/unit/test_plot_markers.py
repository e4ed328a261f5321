"""Telemetry plots: markers for state changes and commands; bools and enums as steps."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import pytest

from zplatform.telemetry.logs import Marker, events_path, plot_markers, plot_telemetry


def _rows() -> list[dict[str, str]]:
    base = 1_000_000_000
    states = ["A"] * 3 + ["B"] * 4 + ["C"] * 3
    cmd = ["NONE"] * 2 + ["LAUNCH"] * 8
    seq = ["0"] * 2 + ["1"] * 8
    status = ["NONE"] * 2 + ["ACCEPTED"] * 8
    led = ["1", "1", "0", "0", "1", "1", "0", "0", "0", "1"]
    return [
        {
            "rx_time_ns": str(base + i * 100_000_000),
            "cn_state": states[i],
            "cn_cmd": cmd[i],
            "cn_cmd_seq": seq[i],
            "cn_cmd_status": status[i],
            "led": led[i],
            "alt": str(i * 1.5),
        }
        for i in range(10)
    ]


def test_markers_are_state_changes_and_command_verdicts() -> None:
    m = plot_markers(_rows())
    assert m == [
        Marker(0.2, "LAUNCH ACCEPTED", "command"),
        Marker(0.3, "B", "state"),
        Marker(0.7, "C", "state"),
    ]


def test_markers_without_the_columns_are_none() -> None:
    assert plot_markers([{"rx_time_ns": "1", "x": "2"}, {"rx_time_ns": "2", "x": "3"}]) == []
    assert plot_markers([]) == []


def test_plot_of_a_bool_an_enum_and_a_number_renders(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    out = tmp_path / "p.png"
    markers = plot_telemetry(_rows(), ["cn_state", "led", "alt"], out, title="t")
    assert len(markers) == 3
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert out.stat().st_size > 5000


def test_events_path_is_beside_the_csv() -> None:
    assert events_path("tm.csv") == Path("tm.events.jsonl")
    assert events_path("/a/b/run.CSV") == Path("/a/b/run.events.jsonl")
    assert events_path("log") == Path("log.events.jsonl")


# ------------------------------------------------- marker labels never overlap


def _timeline(
    span_s: float, states: list[tuple[float, str]], commands: list[tuple[float, str]]
) -> list[dict[str, str]]:
    """Rows at 10 Hz over ``span_s``, with state changes and command verdicts at the given times."""
    rows = []
    seq = 0
    cmd, status = "NONE", "NONE"
    for i in range(int(span_s * 10) + 1):
        t = i / 10
        state = [s for at, s in states if at <= t + 1e-9][-1]
        for at, c in commands:
            if abs(at - t) < 1e-9:
                seq += 1
                cmd, status = c.split()
        rows.append(
            {
                "rx_time_ns": str(1_000_000_000 + i * 100_000_000),
                "cn_state": state,
                "cn_cmd": cmd,
                "cn_cmd_seq": str(seq),
                "cn_cmd_status": status,
                "alt": str((t * (span_s - t)) % 997),
            }
        )
    return rows


#: The flight mission's run (configs/flight.commands): the audit's overlaps,
#: BOOST/COAST over "ARM ACCEPTED" and LANDED over "NOOP ACCEPTED".
FLIGHT = _timeline(
    60.0,
    [
        (0, "SAFE"),
        (1.0, "ARMED"),
        (3.1, "BOOST"),
        (6.0, "COAST"),
        (15.4, "DROGUE"),
        (31.0, "MAIN"),
        (47.1, "LANDED"),
    ],
    [(1.0, "ARM ACCEPTED"), (1.1, "LAUNCH ACCEPTED"), (45.0, "NOOP ACCEPTED")],
)

#: A busy run: a marker every 0.5 s to 2 % apart, long labels, some at the very end.
BUSY = _timeline(
    20.0,
    [(0, "SAFE")] + [(0.3 + 0.9 * k, f"STATE_NUMBER_{k}") for k in range(22)],
    [(0.5 * k, "WRITE_PARAMETER_SET REJECTED_NOT_WHITELISTED") for k in range(1, 41)],
)


class Drawn(NamedTuple):
    """A plot as drawn: what each label covers, the top plot's area, the figure's."""

    labels: list[tuple[str, Any]]  # (text, Bbox in pixels); the title as "(title)"
    top: Any
    figure: Any


def _draw(
    monkeypatch: pytest.MonkeyPatch, rows: list[dict[str, str]], elements: list[str], out: Path
) -> Drawn:
    """Plot ``rows`` and measure its texts with the renderer that drew them.

    A text covers its glyphs and its background box (``bbox=``), both
    measured after a draw; the title counts too.
    """
    from matplotlib.figure import Figure
    from matplotlib.transforms import Bbox

    drawn: list[Drawn] = []
    save = Figure.savefig

    def measure(fig: Figure, *a: Any, **kw: Any) -> None:
        save(fig, *a, **kw)
        fig.canvas.draw()
        r = fig.canvas.get_renderer()  # type: ignore[attr-defined]
        texts = [t for ax in fig.axes for t in ax.texts if t.get_text()]
        if fig._suptitle is not None:
            texts.append(fig._suptitle)
        labels = []
        for t in texts:
            boxes = [t.get_window_extent(r)]
            if t.get_bbox_patch() is not None:
                boxes.append(t.get_bbox_patch().get_window_extent(r))
            name = "(title)" if t is fig._suptitle else t.get_text()
            labels.append((name, Bbox.union(boxes)))
        drawn.append(Drawn(labels, fig.axes[0].get_window_extent(r), fig.bbox.frozen()))

    monkeypatch.setattr(Figure, "savefig", measure)
    plot_telemetry(rows, elements, out)
    (d,) = drawn
    return d


@pytest.mark.parametrize(
    ("rows", "elements"),
    [(FLIGHT, ["cn_state", "alt"]), (FLIGHT, ["alt"]), (BUSY, ["cn_state", "alt"])],
    ids=["flight", "flight-one-axis", "busy"],
)
def test_marker_labels_do_not_overlap(
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
    rows: list[dict[str, str]],
    elements: list[str],
) -> None:
    pytest.importorskip("matplotlib")
    d = _draw(monkeypatch, rows, elements, tmp_path / "p.png")
    drawn = "\n".join(text for text, _ in d.labels)
    assert all(m.label in drawn for m in plot_markers(rows)[:3])  # the labels are there
    for i, (a, ba) in enumerate(d.labels):
        for b, bb in d.labels[i + 1 :]:
            assert not ba.overlaps(bb), f"{a!r} at {ba.bounds} overlaps {b!r} at {bb.bounds}"
    # ...and none leaves the figure or covers the top plot's data
    for text, box in d.labels:
        assert d.figure.x0 <= box.x0 and box.x1 <= d.figure.x1, text
        assert d.figure.y0 <= box.y0 and box.y1 <= d.figure.y1, text
        if text != "(title)":
            assert box.y0 >= d.top.y1 - 1, f"{text!r} covers the plot"


def test_an_integer_element_gets_whole_number_ticks(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    pytest.importorskip("matplotlib")
    from matplotlib.figure import Figure

    rows = [{"rx_time_ns": str(i * 10**8), "misses": str(3 + (i > 4))} for i in range(10)]
    ticks: list[list[float]] = []
    save = Figure.savefig

    def measure(fig: Any, *a: Any, **kw: Any) -> None:
        save(fig, *a, **kw)
        ticks.append([float(v) for v in fig.axes[0].get_yticks()])

    monkeypatch.setattr(Figure, "savefig", measure)
    plot_telemetry(rows, ["misses"], tmp_path / "i.png")
    (drawn,) = ticks
    assert drawn and all(v.is_integer() for v in drawn), drawn


def test_the_flight_plot_reads_a_csv_and_points_its_chute_arrows_at_the_vehicle(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    pytest.importorskip("matplotlib")
    from matplotlib.figure import Figure

    from nodes.flight import plot

    # A flight mission CSV's columns, a rise and fall, the drogue at the top.
    rows = []
    for i in range(100):
        h = 100.0 - abs(i - 50) * 2.0
        rows.append(
            {
                "cn_time_ns": str(i * 10**8),
                "cn_state": "COAST" if i < 50 else "DROGUE",
                "nav_h_m": str(h),
                "apogee_target_m": "120",
                "dn1_airbrake_cmd": "0",
                "drogue_fired": "1" if i >= 50 else "0",
                "main_fired": "0",
            }
        )
    csv_path = tmp_path / "fl.csv"
    csv_path.write_text(
        ",".join(rows[0]) + "\n" + "".join(",".join(r.values()) + "\n" for r in rows)
    )
    arrows: list[tuple[float, float]] = []
    save = Figure.savefig

    def measure(fig: Any, *a: Any, **kw: Any) -> None:
        arrows.extend(t.xy for t in fig.axes[0].texts if "out" in t.get_text())
        save(fig, *a, **kw)

    monkeypatch.setattr(Figure, "savefig", measure)
    plot.main(["--csv", str(csv_path), "--out", str(tmp_path / "f.png")])
    assert arrows == [(5.0, 100.0)]  # the drogue's arrow at the apogee, not the axis
