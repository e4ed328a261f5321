"""The ground node takes no shared memory from its peers (issue 25).

zenoh maps a same-host peer's whole shared-memory pool (16 MiB) the first
time that peer sends a payload over 3 KiB, and keeps it mapped after the
peer has gone: a keyless peer that connected to the ground node, put 4 KiB
of junk on an event key (the fault suite's event rows) and left grew the
ground by about 19 MB each time, for good. The ground node's session now
has shared memory off (``zenoh_config``), whatever the mission says; a
vehicle node has it only where it helps (a bulk channel, a region frame over
zenoh's 3 KiB threshold: ``core.messages.shared_memory_for``).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import yaml

from zplatform.mission.load import load_mission
from zplatform.runtime.transport import rewrite_endpoints, zenoh_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _mission(tmp: Path) -> Path:
    path = tmp / "minimal.yaml"
    rewrite_endpoints(CONFIGS / "minimal.yaml", path)
    raw = yaml.safe_load(path.read_text())
    raw.setdefault("security", {})["transport"] = "plain"  # a keyless peer's reach
    assert raw.get("transport", {}).get("shared_memory", True)  # the mission has it on
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def test_the_ground_nodes_session_has_no_shared_memory(tmp_path: Path) -> None:
    m = load_mission(_mission(tmp_path))
    shm = "transport/shared_memory/enabled"
    assert json.loads(zenoh_config(m, "gn").get_json(shm)) is False
    assert json.loads(zenoh_config(m, "gn", shared_memory=True).get_json(shm)) is False
    # minimal's device node has small regions and no bulk channel: nothing to gain.
    assert json.loads(zenoh_config(m, "dn0").get_json(shm)) is False
    assert json.loads(zenoh_config(m, "dn0", shared_memory=True).get_json(shm)) is True


def test_a_vehicle_node_has_shared_memory_only_where_it_helps() -> None:
    from zplatform.core.messages import shared_memory_for

    camera = load_mission(CONFIGS / "camera.yaml")  # a bulk channel dn0 -> cn
    owners = {ch.node for ch in camera.bulk} | {r for ch in camera.bulk for r in ch.readers}
    assert owners and all(shared_memory_for(camera, n) for n in owners)
    assert not shared_memory_for(camera, "gn")
    assert shared_memory_for(camera, None)  # a tool: `tap` shows a bulk sample's path
    minimal = load_mission(CONFIGS / "minimal.yaml")
    assert not any(shared_memory_for(minimal, n) for n in minimal.nodes)


def test_a_flooding_peer_that_leaves_leaves_no_memory_behind() -> None:
    """The ground node as a process; three keyless peers in turn connect,
    flood 4 KiB junk events for 1 s and leave (bench.ground_memory). Before:
    about +16 to +19 MB of RSS per peer, never returned."""
    from bench.ground_memory import run_variant

    with tempfile.TemporaryDirectory() as tmp:
        res = run_variant(_mission(Path(tmp)), "as_is", 3, 3000.0, 1.0)
    assert res["refused"] == sum(res["sent"])  # every junk record reached the ground
    rss = res["rss_mb"]
    # The first peer warms the ground's allocator; the next two add nothing
    # lasting (a bound well under one mapped pool, 16 MiB).
    assert rss[-1] - rss[1] < 4.0, rss
