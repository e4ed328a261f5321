"""bench.archive runs (a smoke test: it measures, the test only checks shape)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from bench import archive


def test_archive_bench_quick(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(archive, "QUICK_S", 20)
    monkeypatch.setattr(archive, "CAPTURE", 300)
    monkeypatch.setattr(archive, "QUERY_ROUNDS", 1)
    out = tmp_path / "archive.json"
    monkeypatch.setattr(sys, "argv", ["bench.archive", "--quick", "--json", str(out)])
    archive.main()
    v = json.loads(out.read_text())["variants"]
    ingest = v["ingest_snapshot_call"]
    assert (ingest["snapshots"], ingest["archived"], ingest["dropped"]) == (2000, 2000, 0)
    assert 0 < v["size"]["parquet_bytes_per_hour"] < v["size"]["csv_bytes_per_hour"]
    assert v["query_one_element_hour"]["msgs"] == 1
