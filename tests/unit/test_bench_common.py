"""bench.common's child-process plumbing shared by bench.shm and bench.intrahost:
the two-node mission they load, and the tagged JSON line a child says."""

from __future__ import annotations

import json

import pytest

from bench.common import TAG, say, two_node_mission
from zplatform.mission.load import decode_mission


def test_two_node_mission_decodes() -> None:
    m = decode_mission(two_node_mission("bench_x", 7001, 7002))
    assert m.mission == "bench_x"
    assert set(m.nodes) == {"cn", "dn0"}
    assert m.nodes["dn0"].connect == ["tcp/127.0.0.1:7001"]


def test_say_writes_one_tagged_line(capsys: pytest.CaptureFixture[str]) -> None:
    say({"ready": True, "n": 3})
    out = capsys.readouterr().out
    assert out.startswith(TAG) and out.endswith("\n") and out.count("\n") == 1
    assert json.loads(out[len(TAG) :]) == {"ready": True, "n": 3}
