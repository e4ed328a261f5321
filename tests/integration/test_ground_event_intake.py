"""The ground's event intake under a flood of forged records (the generated
flood suite, tests/faults/keyfloods.py, floods ``{vehicle}/<node>/events``
with junk at 6,000 records/s): a record whose tag fails is refused in
zenoh's callback, before it is queued, and counted. Before, every record
was copied into the bounded mailbox unchecked: a flood held EVENT_BACKLOG
copies of up to EVENT_MAX bytes and let the oldest go, so a genuine record
queued before the flood was lost.

In process: one GroundLink (a tool's session, no peer) fed samples directly
through its callback, as zenoh's thread would."""

from __future__ import annotations

import os
import time
from pathlib import Path

from zplatform.core.auth import KEY_ENV, KeySet, Run, channel
from zplatform.core.events import Event, encode_event
from zplatform.ground.link import EVENT_BACKLOG, EVENT_MAX, GroundLink
from zplatform.mission.load import load_mission
from zplatform.runtime.transport import rewrite_endpoints

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


class _Payload:
    def __init__(self, b: bytes) -> None:
        self._b = b

    def __len__(self) -> int:
        return len(self._b)

    def to_bytes(self) -> bytes:
        return self._b


class _Sample:
    def __init__(self, key: str, b: bytes) -> None:
        self.key_expr = key
        self.payload = _Payload(b)


def test_forged_event_records_are_refused_before_they_are_queued(tmp_path: Path) -> None:
    path = tmp_path / "m.yaml"
    rewrite_endpoints(CONFIGS / "minimal.yaml", path)
    m = load_mission(path)
    keys = KeySet.from_master(m, bytes.fromhex(os.environ[KEY_ENV]))
    got: list[object] = []
    link = GroundLink(m, keys=keys, telemetry=False, on_event=got.append)
    try:
        run = time.time_ns()
        link.run.set(run)  # as if learned by its run hello (no control node here)
        seal = channel(keys, "events_dn0", Run(run))
        assert seal is not None
        rec = encode_event(Event("dn0", 1, time.time_ns(), 2, "bad_frame", "x"))
        link._on_event(_Sample("rocket/dn0/events", bytes(seal.seal(rec))))  # type: ignore[arg-type]
        n = EVENT_BACKLOG + 1000
        junk = bytes((i * 131 + 7) & 0xFF for i in range(EVENT_MAX))
        for i in range(n):  # forged: of every length up to the longest read
            link._on_event(_Sample("rocket/dn0/events", junk[: 1 + i % EVENT_MAX]))  # type: ignore[arg-type]
        # Nothing forged holds memory in the mailbox, and the genuine record
        # queued before the flood is still there.
        assert len(link._ev_box) == 1
        link.next(0.0)
        assert [e.seq for e in got] == [1]  # type: ignore[attr-defined]
        assert link.logic.counters.bad_events == n
    finally:
        link.close()
