"""Transport policy from the mission: when the lowlatency transport is safe,
how big a message gets, zenoh's receive pool, the event text cap."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from zplatform.config import parse_mission
from zplatform.core.events import EV, MAX_TEXT, EventLog, encode_event
from zplatform.core.messages import LOWLATENCY_MAX_MESSAGE, largest_message, lowlatency_for
from zplatform.errors import ConfigError
from zplatform.mission.load import decode_mission, load_mission
from zplatform.runtime.transport import zenoh_config

ROOT = Path(__file__).resolve().parents[2]

BIG = """
mission: big
nodes: {cn: {}, dn0: {}}
transport: {lowlatency: %s}
regions:
  dn0_to_cn:
    - {name: samples, type: 'f32[%d]'}
"""


def _ll(cfg: object) -> bool:
    return bool(json.loads(cfg.get_json("transport/unicast/lowlatency")))  # type: ignore[attr-defined]


def test_lowlatency_is_off_by_default_and_auto_would_take_the_small_missions() -> None:
    for name in ("led_test", "thesis_200", "minimal", "recovery_igniter"):
        m = load_mission(ROOT / "configs" / f"{name}.yaml")
        assert m.transport.lowlatency is False  # a stalled link would block the sender
        assert not lowlatency_for(m) and not _ll(zenoh_config(m, "cn"))
        assert largest_message(m) <= LOWLATENCY_MAX_MESSAGE, name
        doc = yaml.safe_load((ROOT / "configs" / f"{name}.yaml").read_text())
        doc.setdefault("transport", {})["lowlatency"] = "auto"
        auto = decode_mission(yaml.safe_dump(doc))
        assert lowlatency_for(auto), name
        assert _ll(zenoh_config(auto, "cn")) and _ll(zenoh_config(auto, None))


def test_auto_keeps_it_off_where_a_message_could_be_dropped() -> None:
    # Telemetry of 8,000 f32 is 32 KB: over the limit, so auto says no.
    m = decode_mission(BIG % ("auto", 8000))
    assert largest_message(m) > 32_000
    assert not lowlatency_for(m)
    assert not _ll(zenoh_config(m, "dn0"))
    # Bulk channels (megabyte samples) never go over lowlatency.
    cam = load_mission(ROOT / "configs" / "camera.yaml")
    assert cam.bulk and not lowlatency_for(cam)


def test_asking_for_lowlatency_where_it_cannot_carry_the_mission_names_the_field() -> None:
    with pytest.raises(ConfigError) as ei:
        decode_mission(BIG % ("true", 8000))
    assert ei.value.path == "$.transport.lowlatency"
    assert "drops bigger ones" in str(ei.value)
    with pytest.raises(ConfigError) as ei:
        doc = yaml.safe_load((ROOT / "configs" / "camera.yaml").read_text())
        doc.setdefault("transport", {})["lowlatency"] = True
        decode_mission(yaml.safe_dump(doc))
    assert ei.value.path == "$.transport.lowlatency"


def test_explicit_settings_are_kept() -> None:
    assert lowlatency_for(decode_mission(BIG % ("true", 10)))
    off = decode_mission(BIG % ("false", 10))
    assert not lowlatency_for(off) and not _ll(zenoh_config(off, "cn"))
    with pytest.raises(ConfigError) as ei:
        parse_mission(BIG % ("sometimes", 10))
    assert "transport.lowlatency" in ei.value.path


def test_the_largest_message_counts_telemetry_regions_and_the_downlink() -> None:
    small = decode_mission(BIG % ("auto", 10))
    ten_k = decode_mission(BIG % ("auto", 10_000))
    assert largest_message(ten_k) - largest_message(small) >= 4 * 10_000 - 4 * 10 - 8_704
    assert largest_message(ten_k) >= 40_000 + 16  # data + the authentication tag
    ccsds = decode_mission(BIG % ("auto", 10) + "downlink: {ccsds: true, max_data: 60000}\n")
    assert largest_message(ccsds) > 60_000 and not lowlatency_for(ccsds)


def test_event_text_is_capped_so_every_event_fits_a_small_message() -> None:
    log = EventLog("cn")
    log.emit(EV.ERROR, 0, text="x" * 100_000)
    (e,) = log.drain()
    assert len(e.text) == MAX_TEXT and e.text.endswith("...(cut)")
    assert len(encode_event(e)) < 4 * MAX_TEXT + 512
    log.emit(EV.ERROR, 0, text="short")
    assert log.drain()[0].text == "short"
