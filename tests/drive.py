"""Drive the sans-IO loop from a test the way a driver does."""

from __future__ import annotations

from pathlib import Path

from zplatform import DataVector, Layout, RegionCodec
from zplatform.loop import DeviceLogic


def run_dn_loop(
    logic: DeviceLogic, loop: int, t_ns: int, cn: DataVector | None = None
) -> None:
    """One DN loop: the CN's trigger frame for ``loop`` at ``t_ns`` (its
    ``cn_to_dnX`` region from ``cn``, a CN-layout vector; initial values if
    None), then the run."""
    if cn is None:
        cn = DataVector(Layout.for_node(logic.mission, "cn"))
    reply = logic.step(RegionCodec(cn, f"cn_to_{logic.node}").encode(loop, t_ns), t_ns)
    assert reply is not None and logic.triggered == loop, logic.reject_reason


def igniter_bench_copy(dst_dir: Path) -> Path:
    """A bench copy of the igniter mission whose ARMED state also allows ARM
    and WRITE: the fault-injection set-up of the disarm scenario (the shipped
    mission allows no WRITE in flight). Returns the copy's path."""
    src = Path(__file__).resolve().parents[1] / "configs" / "recovery_igniter.yaml"
    text = src.read_text()
    flight = "    ARMED: [NOOP, ABORT]\n"
    assert flight in text, "the igniter mission's ARMED whitelist changed: update this copy"
    code = 'pythonpath: [".."]'
    assert code in text, "the igniter mission's pythonpath changed: update this copy"
    text = text.replace(code, f"pythonpath: [{str(src.parent.parent)!r}]")
    dst = dst_dir / "recovery_igniter_bench.yaml"
    dst.write_text(text.replace(flight, "    ARMED: [NOOP, ABORT, ARM, WRITE]\n"))
    return dst
