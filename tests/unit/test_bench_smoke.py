"""Smoke tests of the bandwidth, reliability, telemetry-latency, clock, failover and
intra-host benches.

Each runs its bench's ``main`` briefly (realtime scheduling off, so the test
process is never put in SCHED_FIFO) and checks the result file's shape and
that :mod:`bench.report` renders it: they prove the benches run, not what
they measure. They start node processes and take 3-45 s each, so the whole
module is in the slow suite (``./scripts/test.sh -m slow``), with the
``--quick`` runs as shipped.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import (
    bandwidth,
    clock,
    failover,
    intrahost,
    levers,
    reliability,
    report,
    telemetry_latency,
)

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]


def _doc(path: Path, bench: str) -> dict:  # type: ignore[type-arg]
    doc = json.loads(path.read_text())
    assert doc["bench"] == bench
    assert doc["variants"] and doc["machine"]
    return doc  # type: ignore[no-any-return]


def _renders(tmp_path: Path) -> str:
    out = tmp_path / "REPORT.md"
    return report.build_report(tmp_path, out, None)


def test_bandwidth_smoke(tmp_path: Path) -> None:
    out = tmp_path / "bandwidth.json"
    bandwidth.main(
        [
            "--counts",
            "10",
            "--splits",
            "1",
            "--regions",
            "",
            "--no-rates",
            "--seconds",
            "1",
            "--no-plot",
            "--priority",
            "0",
            "--json",
            str(out),
        ]
    )
    doc = _doc(out, "bandwidth")
    assert doc["params"]["macs"] == ["blake3", "hmac-sha256"]  # both by default
    v, h = doc["variants"]["zp_10el_1dn_blake3"], doc["variants"]["zp_10el_1dn_hmac"]
    assert v["elements"] == 10 and v["bytes_per_loop"] > 0 and v["p50_us"] is not None
    assert (v["mac"], h["mac"]) == ("blake3", "hmac-sha256")
    assert v["bad_frames"] == h["bad_frames"] == 0
    assert h["frame_bytes_max"] == v["frame_bytes_max"]  # both tags are 16 B: one floor
    assert "raw_zenoh_1x" + str(v["frame_bytes_max"]) + "B" in doc["variants"]
    assert v["vs_raw_zenoh_p50"] > 0 and h["vs_raw_zenoh_p50"] > 0
    assert "**Sweep**" in _renders(tmp_path)

    # One MAC again, merged: it replaces its own variant and keeps the other's.
    bandwidth.main(
        [
            *("--counts", "10", "--splits", "1", "--regions", "", "--no-rates"),
            *("--seconds", "1", "--no-plot", "--priority", "0", "--no-floors"),
            *("--macs", "blake3", "--merge", "--json", str(out)),
        ]
    )
    merged = _doc(out, "bandwidth")["variants"]
    assert merged["zp_10el_1dn_hmac"] == h
    assert merged["zp_10el_1dn_blake3"]["mac"] == "blake3"
    assert "raw_zenoh_1x" + str(v["frame_bytes_max"]) + "B" in merged


def test_reliability_smoke(tmp_path: Path) -> None:
    out = tmp_path / "reliability.json"
    reliability.main(["--minutes", "0.05", "--priority", "0", "--json", str(out)])
    doc = _doc(out, "reliability")
    zp = doc["variants"]["zplatform_led_test"]
    raw = doc["variants"]["raw_zenoh_replica"]
    assert zp["messages"] == raw["messages"] > 0
    assert zp["tm_received"] > 0 and zp["tm_latency_p50_us"] is not None
    assert "ratio_to_floor" in doc["params"]
    assert "**Reliability**" in _renders(tmp_path)


def test_telemetry_latency_smoke(tmp_path: Path) -> None:
    src = Path(telemetry_latency.REPO_ROOT) / "configs" / "led_test.yaml"
    fig = telemetry_latency.run_mission(
        telemetry_latency.mission_copy(src, tmp_path / "led.yaml"), 1.0, 0
    )
    assert fig["msgs"] > 50 and fig["p99_us"] is not None and fig["lost"] <= 2


def test_clock_smoke(tmp_path: Path) -> None:
    out = tmp_path / "clock.json"
    clock.main(["--quick", "--json", str(out)])
    doc = _doc(out, "clock")
    assert set(doc["params"]["abs_err_p50_us"]) == {"node_clock", "zenoh_ts"}
    assert doc["params"]["more_accurate"] in ("node_clock", "zenoh_ts")
    assert "Residual error" in _renders(tmp_path)


def test_intrahost_smoke(tmp_path: Path) -> None:
    out = tmp_path / "intrahost.json"
    intrahost.main(["--quick", "--priority", "0", "--json", str(out)])
    doc = _doc(out, "intrahost")
    paced = {f"{v}_{s}" for v in intrahost.VARIANTS for s in intrahost.SIZES}
    unpaced = {f"{v}_unpaced_256B" for v in intrahost.UNPACED}
    assert paced | unpaced == set(doc["variants"])
    assert all(v["msgs"] + v["lost"] == 120 for v in doc["variants"].values())
    assert "intrahost" in _renders(tmp_path)


@pytest.mark.slow
@pytest.mark.timeout(420)  # bandwidth's --quick runs every point once per MAC: about 3 min
@pytest.mark.parametrize("bench", ["bandwidth", "reliability", "telemetry_latency", "clock"])
def test_quick_as_shipped(bench: str, tmp_path: Path) -> None:
    mod = {
        "bandwidth": bandwidth,
        "reliability": reliability,
        "telemetry_latency": telemetry_latency,
        "clock": clock,
    }[bench]
    out = tmp_path / f"{bench}.json"
    args = ["--quick", "--json", str(out)]
    if bench != "clock":
        args += ["--priority", "0"]
    if bench == "bandwidth":
        args.append("--no-plot")  # the repository's plot is the full run's
    mod.main(args)
    _doc(out, bench)


def test_levers_and_sync_trace_smoke(tmp_path: Path) -> None:
    out = tmp_path / "levers.json"
    args = ["--rounds", "1", "--seconds", "1", "--only", "shipped,wildcard"]
    levers.main([*args, "--priority", "0", "--json", str(out)])
    doc = _doc(out, "levers")
    for name in ("shipped", "wildcard"):
        v = doc["variants"][name]
        assert v["p50_us"] > 0 and v["hop_issued->arrive_p50_us"] > 0, v
    assert "wildcard/shipped" in doc["params"]["ratios_p50"]
    assert "levers" in _renders(tmp_path)


def test_failover_smoke(tmp_path: Path) -> None:
    """``bench.failover --quick`` as shipped (about 20 s): two kill -9 and two
    SIGSTOPs of the commanding control node on the flight mission, each
    answered by a takeover in a new term; no loop driven by two terms (the
    fencing's guarantee, whatever the load); the report renders the cases."""
    out = tmp_path / "failover.json"
    failover.main(["--quick", "--json", str(out)])
    doc = _doc(out, "failover")
    assert set(doc["variants"]) == {"kill9", "sigstop"}
    assert doc["params"]["faults_per_case"] == 2 and doc["params"]["targets"]
    for case, v in doc["variants"].items():
        assert "error" not in v, (case, v["error"])
        assert v["faults"] == len(v["each"]) == 2
        assert v["takeovers"] >= 2 and v["loops_recorded"] > 0
        for t in v["each"]:
            assert t["new_term"] > t["old_term"] and t["commander"] != t["victim"], t
            assert t["loops"] == t["term_loop"] - t["fault_loop"] > 0, t
            assert set(t["dn_untriggered"]) == {"dn0", "dn1"}, t
        for k in ("takeover_loops_p50", "takeover_loops_max", "takeover_ms_p50",
                  "dn_untriggered_max", "dn_safed_events", "final_state"):  # fmt: skip
            assert v[k] is not None, k
        for k in ("met_p50", "met_max", "met_no_safings", "met_no_two_term_loops"):
            assert isinstance(v[k], bool), k
        assert v["two_term_loops"] == 0 and v["met_no_two_term_loops"]
    assert "**Takeovers**" in _renders(tmp_path)
