"""Which term drove each loop, from the device nodes' own flight recorders.

The oracle of the failover tests and of ``bench.failover``: every device
node records the reply frame of every loop it runs (zplatform.recorder), and
a redundant mission's reply carries ``dnX_term_seen``, the term whose
trigger the node ran. Read back for the node's latest run, they say, loop by
loop, which term drove which node: no loop may show two.
"""

from __future__ import annotations

from pathlib import Path

from zplatform.config import Mission
from zplatform.core.auth import TAG_LEN
from zplatform.core.codec import RegionCodec
from zplatform.core.datavector import DataVector, Layout
from zplatform.recorder import RecorderReader, recorder_dir
from zplatform.recorder.format import FRAME

__all__ = ["driven_terms", "two_term_loops"]


def _node_terms(mission: Mission, dn: str, directory: Path) -> dict[int, int]:
    region = f"{dn}_to_cn"
    dv = DataVector(Layout.for_regions(mission, [region]))
    codec = RegionCodec(dv, region)
    tag = TAG_LEN if mission.security.auth else 0
    by_run: dict[int, dict[int, int]] = {}
    for head, rec in RecorderReader(directory).records():
        if rec.type != FRAME:
            continue
        frame = codec.apply(rec.payload[: len(rec.payload) - tag])
        by_run.setdefault(head.run, {})[frame.seq] = int(dv.get(f"{dn}_term_seen"))
    return by_run[max(by_run)] if by_run else {}


def driven_terms(mission: Mission, root: Path | None = None) -> dict[int, dict[str, int]]:
    """Per loop, the term each device node ran it under (its latest run's
    record; ``root``: the recorder directory the nodes were given, else
    where the mission records)."""
    out: dict[int, dict[str, int]] = {}
    for dn in mission.device_nodes:
        d = root / mission.mission / dn if root is not None else recorder_dir(mission, dn)
        for loop, term in _node_terms(mission, dn, d).items():
            out.setdefault(loop, {})[dn] = term
    return out


def two_term_loops(driven: dict[int, dict[str, int]]) -> list[tuple[int, dict[str, int]]]:
    """The loops that device nodes ran under more than one term."""
    return [(n, by) for n, by in sorted(driven.items()) if len(set(by.values())) > 1]
