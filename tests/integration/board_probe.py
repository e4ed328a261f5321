"""A device for live tests that watch a board's link (not collected: no ``test_`` prefix).

The platform keeps a board's health counters (:class:`~zplatform.boards.BoardHealth`:
frames sent and received, timeouts, late replies, bad frames, device
errors, reconnects) inside the device node's process: no telemetry element
and no summary carries them. ``tests.integration.board_probe:BoardCounters``
copies them into Data Vector elements of the node's region every loop, so a
test reads them in the CN's telemetry like any element. It only reads the
board (``board_health``): the loop, the board and the link are unchanged.
:func:`with_probe` adds it, and its elements, to a mission file.
"""

from __future__ import annotations

from pathlib import Path

import msgspec
import yaml

from zplatform.boards import board_health
from zplatform.datavector import DataVector
from zplatform.devices import Sensor

COUNTERS = (
    "frames_sent",
    "frames_received",
    "timeouts",
    "late_replies",
    "bad_frames",
    "device_errors",
    "reconnects",
    "errors",
)


class BoardCounters(Sensor):
    """``prefix`` + each of :data:`COUNTERS`: the board's counter, every loop."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        prefix: str

    config: Config

    def bind(self, dv: DataVector) -> None:
        p = self.config.prefix
        self._out = [(n, self.output(p + n, "prefix", kinds=("int",))) for n in COUNTERS]

    def run(self, t_ns: int) -> None:
        h = board_health(self.board)
        for name, out in self._out:
            out.set(getattr(h, name))


def with_probe(src: Path, dst: Path, node: str, root: Path) -> str:
    """Copy mission ``src`` to ``dst`` with a :class:`BoardCounters` on
    ``node`` (elements ``{node}_board_*`` in ``{node}_to_cn``); the copy's
    ``pythonpath`` is ``root`` (where ``nodes`` and ``tests`` are). Returns
    the prefix."""
    raw = yaml.safe_load(src.read_text())
    raw["pythonpath"] = [str(root)]
    prefix = f"{node}_board_"
    raw["regions"][f"{node}_to_cn"] += [{"name": prefix + n, "type": "u32"} for n in COUNTERS]
    raw["devices"].append(
        {
            "name": "board_probe",
            "class": "tests.integration.board_probe:BoardCounters",
            "node": node,
            "config": {"prefix": prefix},
        }
    )
    dst.write_text(yaml.safe_dump(raw, sort_keys=False))
    return prefix
