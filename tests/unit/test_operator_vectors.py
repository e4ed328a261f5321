"""The operator-tag golden vectors of codecs/vectors/operators/ (FORMAT.md
§6.7, §8.2): every key and tag from the formulas alone, and the platform
makes each request again byte for byte and takes it."""

from __future__ import annotations

import hashlib
import hmac
import json
from pathlib import Path

import blake3
import pytest

from zplatform.control.authority import Authority, Identity
from zplatform.control.uplink import Uplink
from zplatform.core.auth import KeySet
from zplatform.mission.load import load_mission
from zplatform.security.identities import sim_signer

OPERATORS = Path(__file__).resolve().parents[2] / "codecs" / "vectors" / "operators"
NAMES = sorted(p.stem for p in OPERATORS.glob("*.json"))


def test_operator_vectors_present() -> None:
    assert sorted(p.stem for p in OPERATORS.glob("*.bin")) == NAMES
    assert (
        sorted(f"{m}_{w}" for m in ("blake3", "hmac-sha256") for w in ("lock", "approve")) == NAMES
    )


def _mac(mac: str, key: bytes, body: bytes) -> bytes:
    if mac == "blake3":
        return blake3.blake3(body, key=key).digest(16)
    return hmac.new(key, body, hashlib.sha256).digest()[:16]


@pytest.mark.parametrize("name", NAMES)
def test_operator_vector_by_hand(name: str) -> None:
    meta = json.loads((OPERATORS / f"{name}.json").read_text())
    frame = (OPERATORS / f"{name}.bin").read_bytes()
    master = bytes.fromhex(meta["master_hex"])
    base = hmac.new(master, meta["operators_context"].encode(), hashlib.sha256).digest()
    assert base.hex() == meta["operators_key_hex"]
    v = meta["vehicle"]
    for kind in ("operator", "station"):
        ctx = f"zplatform/2/{v}/{kind}/{meta[kind]}/1"
        assert meta[f"{kind}_context"] == ctx
        key = hmac.new(base, ctx.encode(), hashlib.sha256).digest()
        assert key.hex() == meta[f"{kind}_key_hex"]
        body = bytes.fromhex(meta["covered_hex"])
        assert _mac(meta["mac"], key, body).hex() == meta[f"{kind}_tag_hex"]
    at = meta["data_offset"]
    data = frame[at:]
    n = meta["covered_size"]
    assert data[:n].hex() == meta["covered_hex"]
    assert data[n : n + 16].hex() == meta["operator_tag_hex"]
    assert data[n + 16 : n + 32].hex() == meta["station_tag_hex"]


@pytest.mark.parametrize("name", NAMES)
def test_operator_vector_by_the_platform(name: str) -> None:
    meta = json.loads((OPERATORS / f"{name}.json").read_text())
    frame = (OPERATORS / f"{name}.bin").read_bytes()
    m = load_mission(OPERATORS / "mission.yaml")
    m.security.mac = meta["mac"]
    keys = KeySet.from_master(m, bytes.fromhex(meta["master_hex"]))
    up = Uplink(m, signer=sim_signer(keys, m, meta["operator"], meta["station"]))
    made = up.frame(
        meta["command"], meta["seq"], 0, 0.0, meta["t_ns"], meta["run"], ref=meta["ref"]
    )
    assert bytes(made) == frame
    assert m.ground is not None
    auth = Authority(m.ground, m.vehicle, m.security.mac, keys.link_key("operators"))
    data = memoryview(frame)[meta["data_offset"] :]
    n = meta["covered_size"]
    who = auth.identify(
        meta["operator_number"], meta["station_number"], data[:n], data[n : n + 16], data[n + 16 :]
    )
    assert who == Identity(meta["operator_number"] - 1, meta["station_number"] - 1)
