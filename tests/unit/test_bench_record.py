"""bench.record runs (a smoke test: it measures, the test only checks shape)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from bench import record


def test_record_bench_quick(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "record.json"
    monkeypatch.setattr(sys, "argv", ["bench.record", "--quick", "--json", str(out)])
    record.main()
    doc = json.loads(out.read_text())
    rec = doc["variants"]["cn_loop_recording"]
    assert rec["dropped_loops"] == 0 and rec["bytes_per_loop"] > 0
    assert doc["variants"]["cn_loop"]["msgs"] == rec["msgs"]
