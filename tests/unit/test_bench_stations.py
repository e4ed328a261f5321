"""bench.stations measures what issue 29 asks: the control room and the
lounge two routers away across a WAN relay (bench/wan.py), and its result
holds the rows and targets of the issue's benchmark. The quick run starts
node, router and relay processes (about a minute): slow suite."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import stations
from zplatform.mission.load import load_mission


def test_the_control_room_and_the_lounge_are_two_routers_and_the_wan_away(
    tmp_path: Path,
) -> None:
    path = tmp_path / "mission.yaml"
    path.write_text(stations._mission(7001, 7002, 7003, 7004, 7005))
    m = load_mission(path, code=False)
    assert m.ground is not None
    routers = {r.name: r for r in m.ground.routers}
    assert list(routers["r1"].connect) == ["tcp/127.0.0.1:7001"]  # the CN
    assert list(routers["r2"].connect) == ["tcp/127.0.0.1:7005"]  # the relay, not r1
    st = {s.name: s for s in m.ground.stations}
    assert list(st["room"].connect) == list(st["lounge"].connect) == ["tcp/127.0.0.1:7004"]
    assert st["lounge"].may == "view"


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_quick_run_has_issue_29s_rows_and_targets(tmp_path: Path) -> None:
    out = tmp_path / "stations.json"
    assert stations.main(["--quick", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    v, p = doc["variants"], doc["params"]
    rows = {f"{k}_{h}" for k in ("rtt", "raw") for h in (0, 1, 2)}
    rows |= {f"fanout_{k}_{n}" for k in ("direct", "router") for n in (1, 4, 10)}
    rows |= {f"tm_{k}_{n}" for k in ("direct", "wan") for n in (1, 10)}
    assert set(v) == rows
    assert p["wan"]["delay_ms_each_way"] == stations.WAN_DELAY_MS and p["wan"]["loss"] == 0
    assert v["tm_wan_1"]["wan_one_way_ms_subtracted"] == stations.WAN_DELAY_MS
    assert v["tm_direct_1"]["wan_one_way_ms_subtracted"] == 0
    for n in (1, 4, 10):
        row = v[f"fanout_router_{n}"]
        assert len(row["snapshots_per_subscriber"]) == n
        assert all(c > 0 for c in row["snapshots_per_subscriber"])
        assert {"cn_late_max_ms_p50", "cn_late_max_ms_max", "cn_overruns"} <= set(row)
    assert set(p["ratios_10_over_1"]) == {
        f"{k}_{w}" for k in ("direct", "router") for w in ("cn_cpu_pct", "cn_late_max_ms_p50")
    }
    assert [t["value"] for t in p["targets"]] == [
        v["tm_wan_1"]["added_ms"],
        v["tm_wan_10"]["added_ms"],
        v["rtt_2"]["added_ms"],
    ]
