"""Drive the sans-IO loop from a test the way a driver does."""

from __future__ import annotations

from pathlib import Path

from zplatform import DataVector, Layout, RegionCodec
from zplatform.control.commands import CommandHandler, RequestNumber
from zplatform.control.loop import DeviceLogic


def run_dn_loop(logic: DeviceLogic, loop: int, t_ns: int, cn: DataVector | None = None) -> None:
    """One DN loop: the CN's trigger frame for ``loop`` at ``t_ns`` (its
    ``cn_to_dnX`` region from ``cn``, a CN-layout vector; initial values if
    None), then the run."""
    if cn is None:
        cn = DataVector(Layout.for_node(logic.mission, "cn"))
    reply = logic.step(RegionCodec(cn, f"cn_to_{logic.node}").encode(loop, t_ns), t_ns)
    assert reply is not None and logic.triggered == loop, logic.reject_reason


def step_request(ch: CommandHandler, dv: DataVector, new_request: bool, t_ns: int) -> None:
    """One :meth:`CommandHandler.step` as the CN's loop makes it: the request
    applied to ``dv``'s ``gn_to_cn`` region (``new_request``) is admitted
    first (:meth:`CommandHandler.admit`: its run and number), then stepped."""
    if new_request:
        base = dv.layout.region("gn_to_cn").offset
        data = memoryview(dv.buf)[base:]
        number = RequestNumber(dv.layout)
        epoch, seq = number.read(data)
        new_request = ch.admit(epoch, seq, t_ns, number.command(data), data)
    ch.step(new_request, t_ns)


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


# The recovery igniter's flight, quicker: apogee (320 m) 4 s after LAUNCH
# instead of 8.2 s (326 m), and down to the deploy altitude (250 m) under a
# 60 m/s drogue instead of 30: DEPLOYED 5.9 s into the run instead of 11.4 s
# (configs/recovery_igniter.commands, in sim). The same states, rules,
# firing window (50-400 m) and limits: only the simulated world is quicker.
QUICK_FLIGHT = {"v0_mps": 160.0, "g_mps2": 40.0, "drogue_mps": 60.0}


def igniter_quick_flight(dst: Path, src: Path | None = None) -> Path:
    """A copy of the recovery igniter mission (``src``: a copy of it; the
    shipped file by default) at ``dst`` whose vehicle world flies
    :data:`QUICK_FLIGHT`, for live tests that wait for the whole flight.
    Returns ``dst``."""
    import yaml

    from zplatform.config import relocate_mission

    src = src or Path(__file__).resolve().parents[1] / "configs" / "recovery_igniter.yaml"
    raw = yaml.safe_load(src.read_text())
    relocate_mission(raw, src)  # its code found from wherever dst is
    raw["world"]["params"].update(QUICK_FLIGHT)
    dst.write_text(yaml.safe_dump(raw, sort_keys=False))
    return dst


# The LED platform's walk, quicker: state C lights dn1's five LEDs 0.25 s
# apart instead of 1 s (C lasts 1 s, not 4), and D flashes at 0.4 s instead
# of 1 s. A (until LAUNCH), B's 3 s and E are the shipped mission's.
QUICK_LEDS = {"seq_leds": {"step_s": 0.25}, "flasher": {"period_s": 0.4}}


def led_quick(dst: Path) -> Path:
    """A copy of configs/led_test.yaml at ``dst`` with :data:`QUICK_LEDS`, for
    the live walk. Returns ``dst``."""
    import yaml

    from zplatform.config import relocate_mission

    src = Path(__file__).resolve().parents[1] / "configs" / "led_test.yaml"
    raw = yaml.safe_load(src.read_text())
    relocate_mission(raw, src)
    for c in raw["controllers"]:
        c.setdefault("config", {}).update(QUICK_LEDS.get(c["name"], {}))
    assert all(any(c["name"] == n for c in raw["controllers"]) for n in QUICK_LEDS)
    dst.write_text(yaml.safe_dump(raw, sort_keys=False))
    return dst
