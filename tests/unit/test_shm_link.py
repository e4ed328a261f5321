"""The CN's choice of path per intra-host link (zplatform.runtime.sync.ShmLink),
loop by loop: probation, fallback, return with hysteresis, the events queued;
``transport.intra_host`` on a redundant mission; the path in ``up``'s status."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import msgspec
import pytest
import yaml

from zplatform.cli import supervisor
from zplatform.config import relocate_mission
from zplatform.core.datavector import DataVector, Layout
from zplatform.errors import ConfigError
from zplatform.mission.load import load_mission
from zplatform.runtime import sync as sync_mod
from zplatform.runtime.intrahost import intra_host_mode
from zplatform.runtime.sync import RETRY_LOOPS, ShmLink

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


class _Client:
    def close(self) -> None:
        pass


@pytest.fixture(autouse=True)
def _no_scan(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sync_mod, "remove_stale", lambda: 0)


def _link(pinned: bool = False) -> ShmLink:
    client: Any = _Client()
    return ShmLink("dn0", client, pinned=pinned)


def _tries(link: ShmLink, loops: int) -> list[int]:
    """The loops (1-based from now) on which the link is tried, each failing."""
    out = []
    for k in range(1, loops + 1):
        if link.try_shm():
            out.append(k)
            link.missed("no reply within the deadline")
    return out


def test_a_verified_link_carries_every_loop_until_it_misses() -> None:
    link = _link()
    assert link.try_shm()  # the first loop tries (probation)
    link.took()
    assert link.on_shm and link.changes == [("shm", "its reply passed the intake")]
    link.changes.clear()
    assert all(link.try_shm() for _ in range(500))
    link.missed("a reply the intake refused")
    assert not link.on_shm and link.fallbacks == 1
    assert link.changes == [("zenoh", "a reply the intake refused")]
    # Back on zenoh: the next try comes RETRY_LOOPS loops later.
    assert _tries(link, RETRY_LOOPS)[0] == RETRY_LOOPS


def test_a_verified_link_falls_back_on_the_second_timeout_in_a_row() -> None:
    """One late reply is the box's scheduling: the link stays; a reply in
    between starts the count again; FALL_AFTER in a row is a stall."""
    assert sync_mod.FALL_AFTER == 2
    link = _link()
    link.try_shm()
    link.took()
    link.changes.clear()
    for _ in range(5):  # late, answered, late, answered...
        assert link.try_shm()
        link.missed("no reply within the deadline", timeout=True)
        assert link.on_shm and link.changes == []
        assert link.try_shm()
        link.took()
    assert link.try_shm()
    link.missed("no reply within the deadline", timeout=True)
    assert link.try_shm()  # still on shared memory for the second try
    link.missed("no reply within the deadline", timeout=True)
    assert not link.on_shm and link.fallbacks == 1
    assert link.changes == [("zenoh", "no reply within the deadline, 2 loops in a row")]
    assert _tries(link, RETRY_LOOPS)[0] == RETRY_LOOPS
    # Returned, then a timeout and no server: no server falls back at once.
    link.took()
    link.changes.clear()
    link.try_shm()
    link.missed("no reply within the deadline", timeout=True)
    link.try_shm()
    link.no_peer("no shared-memory server")
    assert link.changes == [("zenoh", "no shared-memory server")] and link.fallbacks == 2


def test_failed_tries_back_off_doubling_up_to_the_bound() -> None:
    link = _link()
    assert link.try_shm()
    link.missed("a reply the intake refused")  # never verified: no change to tell
    tries = _tries(link, 4000)
    gaps = [b - a for a, b in zip([0, *tries], tries, strict=False)]
    assert gaps[:4] == [RETRY_LOOPS, 2 * RETRY_LOOPS, 4 * RETRY_LOOPS, 8 * RETRY_LOOPS]
    assert max(gaps) == sync_mod.RETRY_MAX_LOOPS
    assert link.changes == [] and link.fallbacks == 0


def test_no_peer_costs_no_loop_and_no_backoff() -> None:
    link = _link()
    link.try_shm()
    link.took()
    link.changes.clear()
    link.try_shm()
    link.no_peer("no shared-memory server")  # zenoh carries this loop
    assert link.changes == [("zenoh", "no shared-memory server")]
    link.changes.clear()
    for _ in range(3):  # still no server: a try every RETRY_LOOPS, no doubling
        assert not any(link.try_shm() for _ in range(RETRY_LOOPS - 1))
        assert link.try_shm()
        link.no_peer("no shared-memory server")
    assert link.changes == []


def test_pinned_shm_without_a_peer_is_told_once() -> None:
    link = _link(pinned=True)
    for _ in range(3):
        while not link.try_shm():
            pass
        link.no_peer("no shared-memory server")
    assert link.changes == [("zenoh", "pinned to shm, but no shared-memory server")]


def test_pinned_shm_on_a_redundant_mission_is_a_config_error(tmp_path: Path) -> None:
    raw = yaml.safe_load((CONFIGS / "flight.yaml").read_text())
    relocate_mission(raw, CONFIGS / "flight.yaml")
    assert "cn_b" in raw["nodes"]
    raw.setdefault("transport", {})["intra_host"] = "shm"
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(ConfigError) as err:
        load_mission(path)
    assert err.value.path == "$.transport.intra_host"
    # `auto` on it resolves to zenoh: failover syncs over zenoh.
    raw["transport"]["intra_host"] = "auto"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    assert intra_host_mode(load_mission(path)) == "zenoh"


def test_up_shows_each_links_path_unless_the_mission_pins_zenoh() -> None:
    m = load_mission(CONFIGS / "led_test.yaml")
    dv = DataVector(Layout.for_node(m, "cn"))
    dv.set("dn1_sync_path", 1)
    assert supervisor.sync_paths(m, dv) == "  sync dn0=zenoh dn1=shm dn2=zenoh"
    zenoh_only = msgspec.structs.replace(
        m, transport=msgspec.structs.replace(m.transport, intra_host="zenoh")
    )
    assert supervisor.sync_paths(zenoh_only, dv) == ""


def test_up_shows_each_bulk_channels_path_from_its_readers_counters() -> None:
    """``up``'s status line names, per bulk channel, the path its reader's
    samples took lately: the counter (``bulk_<ch>_iox``, ``_shm``,
    ``_copied``) that grew most since the last line (one that fell: a
    restarted reader, counting from zero); ``-`` before any grew; the last
    path seen while a slow channel's counters stand still."""
    m = load_mission(CONFIGS / "camera.yaml")
    dv = DataVector(Layout.for_node(m, "cn"))
    paths = supervisor.BulkPaths(m)
    assert paths.line(dv) == "  bulk frame=- flat_field=-"
    dv.set("bulk_frame_iox", 100)  # the CN reads frame over iceoryx2
    dv.set("bulk_flat_field_copied", 10)  # dn0 reads flat_field copied off zenoh
    assert paths.line(dv) == "  bulk frame=iox flat_field=zenoh"
    dv.set("bulk_frame_iox", 101)  # fell back meanwhile: zenoh's shared memory wins
    dv.set("bulk_frame_shm", 99)
    assert paths.line(dv) == "  bulk frame=zenoh-shm flat_field=zenoh"
    assert paths.line(dv) == "  bulk frame=zenoh-shm flat_field=zenoh"  # nothing moved
    dv.set("bulk_frame_iox", 5)  # the CN restarted: its counters start again
    dv.set("bulk_frame_shm", 0)
    assert paths.line(dv).startswith("  bulk frame=iox ")
    no_bulk = load_mission(CONFIGS / "led_test.yaml")
    assert supervisor.BulkPaths(no_bulk).line(DataVector(Layout.for_node(no_bulk, "cn"))) == ""


def test_a_link_entry_overrides_the_missions_path_and_names_a_device_node(
    tmp_path: Path,
) -> None:
    raw = yaml.safe_load((CONFIGS / "led_test.yaml").read_text())
    relocate_mission(raw, CONFIGS / "led_test.yaml")
    raw.setdefault("transport", {})["intra_host"] = "zenoh"
    raw["transport"]["intra_host_links"] = {"dn1": "shm"}
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    m = load_mission(path)
    assert [intra_host_mode(m, dn) for dn in m.device_nodes] == ["zenoh", "shm", "zenoh"]
    assert intra_host_mode(m) == "shm"  # some link may take shared memory
    raw["transport"]["intra_host_links"] = {"dn7": "shm"}
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(ConfigError) as err:
        load_mission(path)
    assert err.value.path == "$.transport.intra_host_links.dn7"
