"""bench.health runs (a smoke test: it measures, the test only checks shape)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from bench import health


def test_health_bench_quick(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "health.json"
    monkeypatch.setattr(sys, "argv", ["bench.health", "--quick", "--json", str(out)])
    health.main()
    doc = json.loads(out.read_text())
    assert set(doc["variants"]) == {"cn_loop", "cn_loop_health_2hz", "cn_loop_health_10hz"}
    for name in ("cn_loop_health_2hz", "cn_loop_health_10hz"):
        v = doc["variants"][name]
        assert v["health_loops"] > 0 and v["samples_taken"] > 0 and v["msgs"] > 0
        assert "added_p50_us" in v and "added_p99_us" in v
