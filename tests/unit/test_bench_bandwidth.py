"""bench.bandwidth's bookkeeping without a cluster: ``--macs`` names and ``--merge``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import bandwidth


def test_macs_short_and_mission_names() -> None:
    assert bandwidth.parse_macs("blake3,hmac") == ["blake3", "hmac-sha256"]
    assert bandwidth.parse_macs("hmac-sha256, blake3,hmac") == ["hmac-sha256", "blake3"]


@pytest.mark.parametrize("text", ["md5", "blake3,", ""])
def test_unknown_mac_is_a_cli_error(text: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        bandwidth.main(["--macs", text, "--json", "unused.json"])
    assert exc.value.code == 2
    assert "--macs: unknown MAC" in capsys.readouterr().err


def _zp(elements: int, n_dn: int, size: int, **more: object) -> dict[str, object]:
    return {"elements": elements, "n_dn": n_dn, "rate_hz": 100.0, "frame_bytes_max": size, **more}


def test_merge_replaces_the_same_point_and_drops_orphan_floors(tmp_path: Path) -> None:
    path = tmp_path / "bandwidth.json"
    earlier = {
        "zp_10el_1dn": _zp(10, 1, 100, p50_us=700.0),  # before the MAC was recorded
        "raw_zenoh_1x100B": {"p50_us": 500.0},
        "zp_100el_1dn": _zp(100, 1, 200, p50_us=710.0),
        "raw_zenoh_1x200B": {"p50_us": 520.0},
        "raw_udp_1x200B": {"p50_us": 90.0},
        "zp_10el_3dn_hmac": _zp(10, 3, 116, mac="hmac-sha256", p50_us=800.0),
        "zp_10el_3dn_blake3": _zp(10, 3, 116, mac="blake3", p50_us=790.0),
    }
    machine = {"time_utc": "2026-01-01T00:00:00Z", "cpu_model": "Old CPU"}
    doc = {"bench": "bandwidth", "machine": machine, "params": {}, "variants": earlier}
    path.write_text(json.dumps(doc))
    now = {
        "zp_10el_1dn_blake3": _zp(10, 1, 116, mac="blake3", run_utc="now"),
        "raw_zenoh_1x116B": {"p50_us": 505.0, "run_utc": "now"},
        "zp_10el_3dn_b3": _zp(10, 3, 116, mac="blake3", run_utc="now"),
    }
    merged = bandwidth.merge_previous(path, now)
    # The 10-element point was measured again: its earlier variant (no MAC
    # recorded: any MAC's run replaces it) and its floor go.
    assert "zp_10el_1dn" not in merged and "raw_zenoh_1x100B" not in merged
    # A point measured with one MAC replaces that MAC's variant only.
    assert "zp_10el_3dn_blake3" not in merged and merged["zp_10el_3dn_hmac"]["p50_us"] == 800.0
    assert merged["zp_10el_1dn_blake3"] == now["zp_10el_1dn_blake3"]
    # Another point stays, with its floors, stamped with its own run.
    assert merged["zp_100el_1dn"]["run_utc"] == "2026-01-01T00:00:00Z"
    assert merged["zp_100el_1dn"]["run_cpu"] == "Old CPU"
    assert {"raw_zenoh_1x200B", "raw_udp_1x200B", "raw_zenoh_1x116B"} <= set(merged)
    bandwidth.add_floor_ratios(merged)
    assert merged["zp_100el_1dn"]["vs_raw_zenoh_p50"] == round(710.0 / 520.0, 3)


def test_merge_without_a_file_or_of_another_bench_adds_nothing(tmp_path: Path) -> None:
    now = {"zp_10el_1dn_hmac": _zp(10, 1, 116, mac="hmac-sha256")}
    assert bandwidth.merge_previous(tmp_path / "none.json", now) == now
    other = tmp_path / "sync.json"
    other.write_text(json.dumps({"bench": "sync", "variants": {"x": {}}}))
    assert bandwidth.merge_previous(other, now) == now
