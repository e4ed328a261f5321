"""The wildcard sync query live (led_test's 3 DNs with ``sync_query:
wildcard``: one bundle query per loop): every DN runs from it; a foreign
queryable on ``{vehicle}/*/to_cn`` is counted, never applied; a malformed
bundle is refused by every DN as it arrives, counted, and never answered; a
rogue's error replies in a DN's name are foreign, not the DN's; a dead DN is
missed while the others run on."""

from __future__ import annotations

import queue
from pathlib import Path

import yaml
import zenoh

from tests.budget import assert_kept_syncing, sync_counts
from zplatform.config import relocate_mission
from zplatform.core.auth import load_keys
from zplatform.core.events import EventReader
from zplatform.core.messages import wildcard_sync_for

from .harness import CONFIGS, Cluster


def test_one_query_runs_every_dn_and_foreign_replies_are_counted(tmp_path: Path) -> None:
    src = tmp_path / "led_wild.yaml"
    doc = yaml.safe_load((CONFIGS / "led_test.yaml").read_text())
    relocate_mission(doc, CONFIGS / "led_test.yaml")
    # Over zenoh: on one host the syncs would take shared memory (intra_host: auto).
    doc["transport"] = {"sync_query": "wildcard", "intra_host": "zenoh"}
    src.write_text(yaml.safe_dump(doc, sort_keys=False))
    with Cluster(src, tmp_path) as c:
        assert wildcard_sync_for(c.mission)
        dns = c.mission.device_nodes
        for dn in dns:
            c.spawn(dn)
        c.spawn("cn")
        c.advance(30)
        before = sync_counts(c.tm, dns)
        bad0 = int(c.tm.get("cn_bad_frames"))
        v = c.mission.vehicle
        answered: queue.SimpleQueue[int] = queue.SimpleQueue()

        def rogue(q: zenoh.Query) -> None:
            with q:
                q.reply(f"{v}/evil/to_cn", b"\x94junk")
            answered.put(1)

        qbl = c.session.declare_queryable(f"{v}/evil/to_cn", rogue)
        try:
            c.wait_for(lambda dv: int(dv.get("cn_bad_frames")) >= bad0 + 20, 60, "foreign counted")
        finally:
            qbl.undeclare()
        c.advance(30)
        # Every DN kept syncing through it; nothing of the rogue's was applied.
        assert_kept_syncing(before, sync_counts(c.tm, dns), dns)
        assert answered.qsize() >= 20
        # A malformed bundle to every DN at once: each refuses it unanswered
        # (a forged trigger gets no reply, zplatform.control.intake) and counts it.
        answers = list(c.session.get(f"{v}/*/to_cn", payload=b"ZB\x01\x01\xff\xff", timeout=2.0))
        assert [r for r in answers if r.ok is not None or r.err is not None] == [], answers
        c.wait_for(
            lambda dv: all(int(dv.get(f"{dn}_bad_frames")) >= 1 for dn in dns),
            60,
            "every DN counted the bad bundle",
        )
        # A rogue answering with errors in dn0's name: foreign bad frames.
        texts: queue.SimpleQueue[str] = queue.SimpleQueue()
        reader = EventReader(c.mission, load_keys(c.mission, "tool"))
        sub = c.session.declare_subscriber(
            f"{v}/cn/events",
            lambda s: texts.put(reader.read(str(s.key_expr), s.payload.to_bytes())[0].text),
        )

        def liar(q: zenoh.Query) -> None:
            with q:
                q.reply_err(b"dn0: forged by a rogue")

        bad1 = int(c.tm.get("cn_bad_frames"))
        before = sync_counts(c.tm, ("dn0",))
        qbl = c.session.declare_queryable(f"{v}/evil/to_cn", liar)
        seen: list[str] = []
        try:
            try:
                c.wait_for(
                    lambda dv: int(dv.get("cn_bad_frames")) >= bad1 + 20, 60, "rogue counted"
                )
            finally:
                qbl.undeclare()
            # Counted together as replies from no device node (evented at
            # most once a second), never as dn0's.
            while not any("from no device node" in t for t in seen):
                seen.append(texts.get(timeout=60))
        finally:
            sub.undeclare()
        assert not any(t.startswith("frame from dn0 rejected") for t in seen), seen[:5]
        assert_kept_syncing(before, sync_counts(c.tm, ("dn0",)), ("dn0",))
        # A dead DN: missed loop after loop, the others run on.
        missed0 = int(c.tm.get("cn_missed_dn2"))
        before = sync_counts(c.tm, ("dn0", "dn1"))
        c.kill("dn2")
        c.wait_for(lambda dv: int(dv.get("cn_missed_dn2")) >= missed0 + 50, 60, "dn2 missed")
        assert_kept_syncing(before, sync_counts(c.tm, ("dn0", "dn1")), ("dn0", "dn1"))
