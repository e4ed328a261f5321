"""Operator and station key files (zplatform.security.identities) and
`zplatform keygen` for a mission with ``ground:``: one file per operator and
per station, 0600, derived from the control node's ``operators`` key; a
revocation or a new key id changes no vehicle key file."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from tests.keys import AUTH_VEHICLE
from tests.unit.test_authority import Rig
from zplatform.cli.main import main
from zplatform.control.authority import identity_key
from zplatform.control.uplink import Uplink
from zplatform.core.auth import KeyError_, read_key_file
from zplatform.mission.load import load_mission
from zplatform.security.identities import load_signer, read_identity_file

MISSION = (
    "mission: idtest\n"
    + AUTH_VEHICLE
    + """\
ground:
  stations:
    - {name: pad}
    - {name: lounge, may: view}
  operators:
    - {name: alice, roles: [operator]}
    - {name: bob, roles: [operator]}
"""
)

VEHICLE_FILES = ("cn.keys", "dn0.keys", "gn.keys", "tool.keys")


def keygen(tmp_path: Path, text: str, out: Path) -> Path:
    path = tmp_path / "idtest.yaml"
    path.write_text(text)
    assert main(["keygen", str(path), "--out", str(out)]) == 0
    return path


def test_keygen_writes_one_private_file_per_operator_and_station(
    keydir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = keygen(tmp_path, MISSION, keydir)
    out = capsys.readouterr().out
    m = load_mission(path, code=False)
    names = ["operator-alice", "operator-bob", "station-pad", "station-lounge"]
    for name in names:
        p = keydir / f"{name}.keys"
        assert stat.S_IMODE(p.stat().st_mode) == 0o600
        assert f"{name}.keys" in out
    cn = read_key_file(keydir / "cn.keys", m)
    assert cn.has("operators")
    assert not read_key_file(keydir / "gn.keys", m).has("operators")
    alice = read_identity_file(keydir / "operator-alice.keys", m)
    assert alice.key == identity_key(cn.link_key("operators"), "rocket", "operator", "alice", 1)


def test_a_cn_with_cn_keys_takes_a_request_signed_with_the_files(
    keydir: Path, tmp_path: Path
) -> None:
    path = keygen(tmp_path, MISSION, keydir)
    m = load_mission(path, code=False)
    base = read_key_file(keydir / "cn.keys", m).link_key("operators")
    r = Rig(m, key=base)
    signer = load_signer(m, keydir / "operator-alice.keys", keydir / "station-pad.keys")
    assert r.send("x@y", "LOCK", up=Uplink(m, signer=signer)) == "ACCEPTED"
    assert r.holder == "alice@pad"


def test_revoking_an_operator_rekeys_nothing(keydir: Path, tmp_path: Path) -> None:
    keygen(tmp_path, MISSION, keydir)
    before = {f: (keydir / f).read_bytes() for f in os.listdir(keydir)}
    path = keygen(tmp_path, MISSION + "  revoked: [alice]\n", keydir)
    after = {f: (keydir / f).read_bytes() for f in os.listdir(keydir)}
    assert after == before  # no file written: the mission file is the change
    m = load_mission(path, code=False)
    r = Rig(m, key=read_key_file(keydir / "cn.keys", m).link_key("operators"))
    alice = load_signer(m, keydir / "operator-alice.keys", keydir / "station-pad.keys")
    bob = load_signer(m, keydir / "operator-bob.keys", keydir / "station-pad.keys")
    assert r.send("x@y", "LOCK", up=Uplink(m, signer=alice)) == "REJECTED_OPERATOR_REVOKED"
    assert r.send("x@y", "LOCK", up=Uplink(m, signer=bob)) == "ACCEPTED"


def test_a_new_key_id_rewrites_only_that_operators_file(keydir: Path, tmp_path: Path) -> None:
    path = keygen(tmp_path, MISSION, keydir)
    m1 = load_mission(path, code=False)
    old = load_signer(m1, keydir / "operator-alice.keys", keydir / "station-pad.keys")
    before = {f: (keydir / f).read_bytes() for f in os.listdir(keydir)}
    text = MISSION.replace(
        "{name: alice, roles: [operator]}", "{name: alice, roles: [operator], key_id: 2}"
    )
    path = keygen(tmp_path, text, keydir)
    after = {f: (keydir / f).read_bytes() for f in os.listdir(keydir)}
    assert {f for f in after if after[f] != before.get(f)} == {"operator-alice.keys"}
    assert all(after[f] == before[f] for f in VEHICLE_FILES)
    m2 = load_mission(path, code=False)
    r = Rig(m2, key=read_key_file(keydir / "cn.keys", m2).link_key("operators"))
    assert r.send("x@y", "LOCK", up=Uplink(m2, signer=old)) == "REJECTED_OPERATOR_AUTH"
    new = load_signer(m2, keydir / "operator-alice.keys", keydir / "station-pad.keys")
    assert r.send("x@y", "LOCK", up=Uplink(m2, signer=new)) == "ACCEPTED"


def test_identity_files_are_refused_when_open_foreign_unknown_or_old(
    keydir: Path, tmp_path: Path
) -> None:
    path = keygen(tmp_path, MISSION, keydir)
    m = load_mission(path, code=False)
    p = keydir / "operator-alice.keys"
    os.chmod(p, 0o644)
    with pytest.raises(KeyError_, match="chmod 600"):
        read_identity_file(p, m)
    os.chmod(p, 0o600)
    text = p.read_text()
    for old, new, match in (
        ("mission idtest", "mission other", "mission 'other'"),
        ("operator alice", "operator eve", "no operator 'eve'"),
        ("key_id 1", "key_id 2", "an old key"),
        ("key_id 1", "role cn", "expected"),
    ):
        p.write_text(text.replace(old, new))
        with pytest.raises(KeyError_, match=match):
            read_identity_file(p, m)
    p.write_text(text)
    with pytest.raises(KeyError_, match="operator's then a station's"):
        load_signer(m, keydir / "station-pad.keys", p)
