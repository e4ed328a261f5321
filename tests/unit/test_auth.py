"""Key sets, key hygiene and frame tags (zplatform.core.auth)."""

from __future__ import annotations

import hashlib
import hmac
import os
import stat
import subprocess
import sys
from pathlib import Path

import blake3
import pytest

from tests.keys import own_key_home
from zplatform import load_mission
from zplatform.core.auth import (
    KEY_ENV,
    KEY_FILE_ENV,
    MACS,
    TAG_LEN,
    AuthError,
    Channel,
    KeyError_,
    KeySet,
    Run,
    RunError,
    check_key,
    default_key_dir,
    host_roles,
    load_keys,
    new_run_epoch,
    role_links,
    write_key_set,
)
from zplatform.mission.load import decode_mission

ROOT = Path(__file__).resolve().parents[2]
MINIMAL = load_mission(ROOT / "configs" / "minimal.yaml")
IGNITER = load_mission(ROOT / "configs" / "recovery_igniter.yaml")
GOOD = bytes.fromhex("3f8a1c9e27d45b60f1e83a97c2d0456b8e19f7a3c5d2e0b4a6918f3c7e25d0b1")


@pytest.fixture
def no_env_key(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    return own_key_home(monkeypatch, tmp_path)


# -- who holds what ------------------------------------------------------------------


def test_each_host_role_holds_only_its_links() -> None:
    assert host_roles(IGNITER) == ("cn", "dn0", "dn1", "gn", "tool")
    assert role_links(IGNITER, "cn") == (
        "cn-dn0",
        "cn-dn1",
        "uplink",
        "downlink",
        "events-cn",
    )
    assert role_links(IGNITER, "dn0") == ("cn-dn0", "events-dn0")
    ev = ("events-cn", "events-dn0", "events-dn1", "events-gn")
    assert role_links(IGNITER, "gn") == ("uplink", "downlink", *ev)
    assert role_links(IGNITER, "tool") == ("downlink", *ev)
    with pytest.raises(KeyError_, match=r"no host role 'dn7'.*cn, dn0, dn1, gn, tool"):
        role_links(IGNITER, "dn7")


def test_a_key_set_is_independent_keys_shared_per_link(no_env_key: Path) -> None:
    files = write_key_set(IGNITER, no_env_key / "set")
    assert sorted(files) == ["cn", "dn0", "dn1", "gn", "tool"]
    assert stat.S_IMODE((no_env_key / "set").stat().st_mode) == 0o700
    sets = {}
    for role, p in files.items():
        assert stat.S_IMODE(p.stat().st_mode) == 0o600
        sets[role] = load_keys(IGNITER, role, p)
        assert sets[role] is not None and sets[role].links == role_links(IGNITER, role)
    cn, dn0, gn, tool = sets["cn"], sets["dn0"], sets["gn"], sets["tool"]
    # Both ends of a link hold the same key; every link's key is its own.
    assert cn.link_key("cn-dn0") == dn0.link_key("cn-dn0")
    assert cn.link_key("uplink") == gn.link_key("uplink")
    assert tool.link_key("downlink") == cn.link_key("downlink")
    everything = {k for s in sets.values() for ln in s.links for k in [s.link_key(ln)]}
    assert len(everything) == len({ln for s in sets.values() for ln in s.links})
    # A ground's file makes no trigger, a DN's no other DN's reply, a tool's no command.
    with pytest.raises(KeyError_, match="no key for link cn-dn0"):
        gn.channel("cn_to_dn0")
    with pytest.raises(KeyError_, match="no key for link cn-dn1"):
        dn0.channel("dn1_to_cn")
    with pytest.raises(KeyError_, match="no key for link uplink"):
        tool.channel("gn_to_cn")
    with pytest.raises(KeyError_, match="exists"):
        write_key_set(IGNITER, no_env_key / "set")


def test_a_node_without_its_key_fails_at_start_naming_link_and_file(no_env_key: Path) -> None:
    files = write_key_set(IGNITER, no_env_key / "set")
    with pytest.raises(KeyError_) as ei:
        load_keys(IGNITER, "dn0", files["gn"])
    msg = str(ei.value)
    assert "dn0 needs the key of link cn-dn0" in msg and str(files["gn"]) in msg
    assert "host role gn" in msg and "\n" not in msg
    with pytest.raises(KeyError_, match="cn needs the key of link cn-dn0"):
        load_keys(IGNITER, "cn", files["dn1"])


def test_missing_keys_say_how_to_make_them(no_env_key: Path) -> None:
    with pytest.raises(KeyError_) as ei:
        load_keys(MINIMAL, "dn0")
    msg = str(ei.value)
    assert "zplatform keygen" in msg and str(default_key_dir(MINIMAL) / "dn0.keys") in msg


def test_create_makes_the_set_once(no_env_key: Path) -> None:
    keys = load_keys(MINIMAL, "cn", create=True)
    d = default_key_dir(MINIMAL)
    assert keys is not None and sorted(p.name for p in d.iterdir()) == [
        "cn.keys",
        "dn0.keys",
        "gn.keys",
        "tool.keys",
    ]
    again = load_keys(MINIMAL, "cn", create=True)
    assert again is not None and again.link_key("downlink") == keys.link_key("downlink")


def test_lookup_order(no_env_key: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    a = write_key_set(MINIMAL, no_env_key / "a")
    b = write_key_set(MINIMAL, no_env_key / "b")
    default = write_key_set(MINIMAL, default_key_dir(MINIMAL))

    def uplink(*args: object) -> bytes:
        ks = load_keys(MINIMAL, "gn", *args)  # type: ignore[arg-type]
        assert ks is not None
        return ks.link_key("uplink")

    def key_of(files: dict[str, Path]) -> bytes:
        ks = load_keys(MINIMAL, "gn", files["gn"])
        assert ks is not None
        return ks.link_key("uplink")

    assert uplink() == key_of(default)
    monkeypatch.setenv(KEY_ENV, GOOD.hex())
    master = KeySet.from_master(MINIMAL, GOOD).link_key("uplink")
    assert uplink() == master
    monkeypatch.setenv(KEY_FILE_ENV, str(a["gn"]))
    assert uplink() == key_of(a)
    monkeypatch.setenv(KEY_FILE_ENV, str(no_env_key / "b"))  # a set directory: the role's file
    assert uplink() == key_of(b)
    assert uplink(a["gn"]) == key_of(a)  # explicit wins
    # A read-only tool in a set directory without tool.keys takes the ground's.
    a["tool"].unlink()
    tool = load_keys(MINIMAL, "tool", no_env_key / "a")
    assert tool is not None and tool.links == role_links(MINIMAL, "tool")


def test_a_mission_may_turn_authentication_off(no_env_key: Path) -> None:
    text = (ROOT / "configs" / "minimal.yaml").read_text() + "security: {auth: false}\n"
    assert load_keys(decode_mission(text), "cn") is None


# -- hygiene -------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", [0o644, 0o666, 0o640, 0o604, 0o620, 0o660])
def test_key_files_open_to_others_are_refused(no_env_key: Path, mode: int) -> None:
    p = write_key_set(MINIMAL, no_env_key / "set")["dn0"]
    os.chmod(p, mode)
    with pytest.raises(KeyError_) as ei:
        load_keys(MINIMAL, "dn0", p)
    msg = str(ei.value)
    assert f"mode {mode:04o}" in msg and f"chmod 600 {p}" in msg and "\n" not in msg
    os.chmod(p, 0o400)  # read-only for its owner is fine
    assert load_keys(MINIMAL, "dn0", p) is not None


WEAK = {
    "short": "ab" * 16 + "cd",  # 17 bytes
    "zero": "00" * 32,
    "one byte": "11" * 32,
    "pattern": "deadbeef" * 8,
    "counting": bytes(range(32)).hex(),
    "counting down": bytes(range(255, 223, -1)).hex(),
    "text": b"correct horse battery staple!!!!".hex(),
    "BLAKE3's test key": b"whats the Elvish word for friend".hex(),
    "golden vectors": "5a9c4e1f0b7d3a6e82c5f19d4b07e3a8c6d2f5910e8b4a7c3d6f1e0b9a5c8d27",
}


@pytest.mark.parametrize("name", list(WEAK))
def test_weak_keys_are_refused_from_the_environment_and_from_files(
    no_env_key: Path, monkeypatch: pytest.MonkeyPatch, name: str
) -> None:
    monkeypatch.setenv(KEY_ENV, WEAK[name])
    with pytest.raises(KeyError_, match=KEY_ENV):
        load_keys(MINIMAL, "dn0")
    monkeypatch.delenv(KEY_ENV)
    p = no_env_key / "dn0.keys"
    p.write_text(f"mission minimal\nrole dn0\ncn-dn0 {WEAK[name]}\nevents-dn0 {GOOD.hex()}\n")
    os.chmod(p, 0o600)
    with pytest.raises(KeyError_, match=f"{p}:3 \\(cn-dn0\\)"):
        load_keys(MINIMAL, "dn0", p)


def test_check_key_takes_random_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    for _ in range(200):
        key = os.urandom(32)
        assert check_key(key, "x") == key
    monkeypatch.setenv(KEY_ENV, "not hex")
    with pytest.raises(KeyError_, match="must be hex"):
        load_keys(MINIMAL, "cn")


def test_malformed_and_foreign_key_files(no_env_key: Path) -> None:
    p = no_env_key / "k.keys"

    def refused(text: str, says: str) -> None:
        p.write_text(text)
        os.chmod(p, 0o600)
        with pytest.raises(KeyError_, match=says):
            load_keys(MINIMAL, "dn0", p)

    refused("mission led_test\n", "key file of mission 'led_test', not of 'minimal'")
    refused(f"cn-dn5 {GOOD.hex()}\n", "'cn-dn5' is no link of mission 'minimal'")
    refused("cn-dn0\n", r"k.keys:1: expected `LINK HEXKEY`")
    refused(GOOD.hex() + "\n", "a single mission key .* make a key set")
    p.write_bytes(b"\xff\xfe")
    with pytest.raises(KeyError_, match="not ASCII"):
        load_keys(MINIMAL, "dn0", p)


def test_a_fifo_is_refused_without_reading_it(no_env_key: Path) -> None:
    p = no_env_key / "fifo.keys"
    os.mkfifo(p, 0o600)
    with pytest.raises(KeyError_, match="not a regular file"):
        load_keys(MINIMAL, "dn0", p)


# -- tags ------------------------------------------------------------------------------


@pytest.mark.parametrize("mac", MACS)
def test_seal_and_open(mac: str) -> None:
    ch = Channel(GOOD, "rocket", "telemetry", mac)
    sealed = bytes(ch.seal(b"hello"))
    assert len(sealed) == 5 + TAG_LEN and bytes(ch.open(sealed)) == b"hello"
    for bad in (sealed[:-1] + bytes([sealed[-1] ^ 1]), b"x" * 5, b"", sealed[1:]):
        with pytest.raises(AuthError):
            ch.open(bad)
    for other in (
        Channel(GOOD, "other_vehicle", "telemetry", mac),
        Channel(GOOD, "rocket", "gn_to_cn", mac),
        Channel(bytes(reversed(GOOD)), "rocket", "telemetry", mac),
    ):
        with pytest.raises(AuthError):
            other.open(sealed)


@pytest.mark.parametrize("mac", MACS)
def test_a_twin_channel_tags_alike_with_state_of_its_own(mac: str) -> None:
    """Channel is not thread-safe: a second thread takes a twin (the archive
    server's zenoh thread, which checks asks while the serving thread seals
    replies). Same tags, same run; no hasher, buffer or key cache shared."""
    ch = Channel(GOOD, "rocket", "telemetry", mac, Run(7))
    tw = ch.twin()
    frame = b"x" * 100
    assert bytes(tw.seal(frame)) == bytes(ch.seal(frame)) and tw.run is ch.run
    assert bytes(tw.open(bytes(ch.seal(frame)))) == frame
    assert tw._main is not ch._main and tw._other is not ch._other and tw._buf is not ch._buf


def test_peers_with_another_mac_refuse_each_other_saying_so() -> None:
    b3 = Channel(GOOD, "rocket", "telemetry", "blake3")
    hm = Channel(GOOD, "rocket", "telemetry", "hmac-sha256")
    with pytest.raises(AuthError, match=r"another security\.mac; this node's is hmac-sha256"):
        hm.open(bytes(b3.seal(b"frame")))
    with pytest.raises(AuthError, match=r"wrong key, forged, or a peer with another security\.mac"):
        b3.open(bytes(hm.seal(b"frame")))


def test_the_tags_are_what_format_md_says() -> None:
    """codecs/FORMAT.md §6.1, computed by hand: a peer in another language
    can implement it from the document."""
    master = GOOD
    link = hmac.new(master, b"zplatform/2/link/rocket/downlink", hashlib.sha256).digest()
    ks = KeySet.from_master(MINIMAL, master)
    assert ks.link_key("downlink") == link
    for mac in MACS:
        ctx = f"zplatform/2/rocket/{mac}/telemetry".encode()
        ch_key = hmac.new(link, ctx, hashlib.sha256).digest()
        for epoch, frame in (
            (0, b"\x94\xce\x00\x00\x00\x01" + b"rest of a frame"),  # shorter than 40
            (0x0123456789ABCDEF, bytes(range(256)) * 3),  # longer: its first 40 bytes
        ):
            word = epoch.to_bytes(8, "little")
            k_run = hmac.new(ch_key, b"zplatform/2/run/" + word, hashlib.sha256).digest()
            k_head = hmac.new(ch_key, b"zplatform/3/header/" + word, hashlib.sha256).digest()
            head = word + len(frame).to_bytes(4, "little") + frame[:40]
            if mac == "blake3":
                htag = blake3.blake3(head, key=k_head).digest()[:8]
                mac_ = blake3.blake3(frame, key=k_run).digest()[:16]
            else:
                htag = hmac.new(k_head, head, hashlib.sha256).digest()[:8]
                mac_ = hmac.new(k_run, frame, hashlib.sha256).digest()[:16]
            ch = Channel(link, "rocket", "telemetry", mac, Run(epoch) if epoch else None)
            assert bytes(ch.seal(frame)) == frame + word + htag + mac_


def test_a_frame_of_another_run_never_verifies() -> None:
    """Keys bound to the run (codecs/FORMAT.md §6.1): a receiver bound to a
    run refuses another run's frame, and any frame before it knows its run,
    as RunError, before the MAC; an unbound one (the ground) takes every
    run's genuine frame; a frame whose run word was rewritten fails its MAC."""
    old, new = Run(1000), Run(2000)
    send_old = Channel(GOOD, "rocket", "cn_to_dn0", run=old)
    send_new = Channel(GOOD, "rocket", "cn_to_dn0", run=new)
    bound = Channel(GOOD, "rocket", "cn_to_dn0", run=Run(2000))
    unbound = Channel(GOOD, "rocket", "cn_to_dn0")
    f_old, f_new = bytes(send_old.seal(b"frame")), bytes(send_new.seal(b"frame"))
    assert bytes(bound.open(f_new)) == b"frame"
    with pytest.raises(RunError, match=r"a frame of run 1000, not of this run \(2000\)"):
        bound.open(f_old)
    with pytest.raises(RunError, match=r"before this node knows its run"):
        Channel(GOOD, "rocket", "cn_to_dn0", run=Run()).open(f_new)
    assert bytes(unbound.open(f_old)) == bytes(unbound.open(f_new)) == b"frame"
    assert Channel.run_of(f_old) == 1000 and bound.run_of(f_new) == 2000
    # The old frame relabelled with the new run: its MAC is the old run's key's.
    forged = f_old[:5] + (2000).to_bytes(8, "little") + f_old[13:]
    with pytest.raises(AuthError, match="bad authentication tag") as exc:
        bound.open(forged)
    assert not isinstance(exc.value, RunError)
    # The run re-keys the channel once it changes, on both ends.
    new.set(3000)
    bound.run.set(3000)  # type: ignore[union-attr]
    f3 = bytes(send_new.seal(b"frame"))
    assert bytes(bound.open(f3)) == b"frame"
    with pytest.raises(RunError):
        bound.open(f_new)


def test_a_new_run_is_random_in_its_low_bits_and_keeps_the_clock_order() -> None:
    t = 1_700_000_000_123_456_789
    runs = {new_run_epoch(t) for _ in range(64)}
    assert len(runs) > 60  # 24 random bits
    assert all(r >> 24 == t >> 24 for r in runs)
    assert min(new_run_epoch(t + (1 << 24)) for _ in range(16)) > max(runs)
    assert new_run_epoch(0) != 0


def test_the_mission_chooses_the_mac() -> None:
    text = (ROOT / "configs" / "minimal.yaml").read_text()
    hm = decode_mission(text + "security: {mac: hmac-sha256}\n")
    assert MINIMAL.security.mac == "blake3" and hm.security.mac == "hmac-sha256"
    assert KeySet.from_master(hm, GOOD).channel("telemetry").mac == "hmac-sha256"
    with pytest.raises(Exception, match=r"security.mac"):
        decode_mission(text + "security: {mac: md5}\n")


# -- the verb --------------------------------------------------------------------------


def test_keygen_verb(no_env_key: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in (KEY_ENV, KEY_FILE_ENV)}
    env["XDG_CONFIG_HOME"] = str(no_env_key)
    mission = str(ROOT / "configs" / "recovery_igniter.yaml")
    cmd = [sys.executable, "-m", "zplatform", "keygen", mission]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60)
    d = no_env_key / "zplatform" / "keys" / "recovery_igniter"
    assert r.returncode == 0, r.stderr
    assert f"wrote the key set of mission 'recovery_igniter' to {d}/" in r.stdout
    for role, host in (
        ("cn", "the control node's host"),
        ("dn0", "dn0's host"),
        ("dn1", "dn1's host"),
        ("gn", "the ground station"),
        ("tool", "read-only tools"),
    ):
        line = next(x for x in r.stdout.splitlines() if x.strip().startswith(f"{role}.keys"))
        assert host in line and ", ".join(role_links(IGNITER, role)) in line
        assert stat.S_IMODE((d / f"{role}.keys").stat().st_mode) == 0o600
    # Again (as after `up`, which makes the set on first use): kept, said so, exit 0.
    before = (d / "cn.keys").read_bytes()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 0 and "already" in r.stdout and "--rotate" in r.stdout, r
    assert (d / "cn.keys").read_bytes() == before
    # --rotate replaces every file with new keys, 0600 still.
    r = subprocess.run([*cmd, "--rotate"], capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 0, r.stderr
    assert (d / "cn.keys").read_bytes() != before
    assert stat.S_IMODE((d / "cn.keys").stat().st_mode) == 0o600
    assert not list(d.glob("*.new"))
    out = no_env_key / "elsewhere"
    r = subprocess.run([*cmd, "--out", str(out)], capture_output=True, text=True, env=env)
    assert r.returncode == 0 and (out / "dn1.keys").exists()


def test_keygen_needs_the_mission_s_nodes(
    no_env_key: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A bare name says nothing of the nodes, whose links the set is made of:
    one error line."""
    from zplatform.cli.main import main

    monkeypatch.chdir(tmp_path)
    for bad in ("led_test", "missions/nope.yaml"):
        assert main(["keygen", bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("zplatform: error: ") and err.count("\n") == 1, err
