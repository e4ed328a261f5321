"""Per-link keys and the authenticated clock on real node processes, on the
recovery igniter mission (cn, dn0, dn1 and the ground node playing ARM +
LAUNCH as separate processes).

* A peer holding only the ground's key file forges triggers that would fire
  both igniters: every one is refused, the vehicle stays SAFE and nothing
  fires; the same triggers under the CN's key file do fire (the forgery is
  real: with one mission key, the ground's key was the CN's).
* A rogue clock server without the key answers the DNs' clock queries with
  the CN's time +30 ms and +5 s (one queryable declared ``complete``, one
  not): the DNs refuse and count its replies, run their loops, and the
  flight (the quick one of tests/drive.py) deploys.
* The same rogue on a mission that does not authenticate (a closed bench)
  does move the DNs' clocks: then every trigger is stale, and a DN that
  cannot run safes itself and the CN latches DN_SAFED (ABORTED, visibly),
  instead of the flight ending ARMED with a link that looks healthy.

The mission runs on plain links (``security.transport: plain``): under its
default mutual TLS the attacker, holding no node's certificate, would get no
session (tests/integration/test_secure_transport.py) and the keys behind it
would go untested.

Waits are on telemetry predicates; every process and the rogue's session
end with the test (``Cluster.close``).
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from tests.budget import LINK_ALIVE
from tests.drive import igniter_quick_flight
from tests.integration.harness import CONFIGS, Cluster
from tests.waits import wait_until
from zplatform.core.auth import KEY_FILE_ENV, Channel, KeySet, Run, load_keys, write_key_set
from zplatform.core.codec import RegionCodec
from zplatform.core.datavector import DataVector, Layout
from zplatform.mission.load import load_mission
from zplatform.runtime.timebase import NodeClock

pytestmark = pytest.mark.timeout(240)

MISSION = CONFIGS / "recovery_igniter.yaml"
SCRIPT = CONFIGS / "recovery_igniter.commands"
MS = 1_000_000
_QUERY = struct.Struct("<2sBB16sq")
_REPLY = struct.Struct("<2sBB16sqqq")


def _get(dv: DataVector, k: str) -> Any:
    spec = dv.layout.element(k)
    return dv.get_name(k) if spec.enum is not None else dv.get(k)


def _fire_trigger(c: Cluster, dn: str, seq: int, t_ns: int, state: str = "FIRE") -> bytes:
    """A ``cn_to_dnX`` frame that would fire dnX's igniter (armed, commanded
    in this very loop, its safety controller enabled), stamped with
    ``state`` (``dnX_state``, which the DN's interlock reads: FIRE is a
    state the igniter may fire in)."""
    dv = DataVector(Layout.for_node(c.mission, "cn"))
    dv.set(f"{dn}_state", state)
    dv.set(f"{dn}_ign_armed", True)
    dv.set(f"{dn}_ign_cmd", True)
    dv.set(f"{dn}_ign_cmd_loop", seq)
    dv.set(f"safety{dn[2:]}_mode", "enabled")
    return bytes(RegionCodec(dv, f"cn_to_{dn}").encode(seq, t_ns))


def _next_loop(c: Cluster, clock: NodeClock) -> int:
    """The CN's next loop number: its newest snapshot's loop, advanced by the
    periods since that snapshot's stamp (on a loaded box the snapshot may be
    several loops old, and a trigger for a loop the DN has already run does
    not run; one too far ahead of the DN's last loop is unbelievable)."""
    loop, t = int(c.tm.get("cn_loop")), int(c.tm.get("cn_time_ns"))
    return loop + max(0, clock.now_ns() - t) // c.mission.period_ns + 1


def _query(c: Cluster, dn: str, payload: bytes) -> None:
    c.session.get(
        f"{c.mission.vehicle}/{dn}/to_cn",
        zenoh.handlers.Callback(lambda _r: None, indirect=False),
        payload=payload,
        timeout=0.05,
    )


def test_a_ground_key_cannot_fire_the_igniter(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The barometers read 150 m, inside the igniter's window (50-400 m),
    # while the vehicle sits in SAFE (the flight itself starts only at
    # LAUNCH): what a forged trigger needs to fire.
    raw = yaml.safe_load(MISSION.read_text())
    raw["world"]["params"]["stuck_m"] = {"dn0": 150.0, "dn1": 150.0}
    raw["pythonpath"] = [str(MISSION.parent / p) for p in raw.get("pythonpath") or ["."]]
    mission = tmp_path / "recovery_igniter_at_150m.yaml"
    mission.write_text(yaml.safe_dump(raw, sort_keys=False))
    with Cluster(mission, tmp_path, transport="plain") as c:
        keys = tmp_path / "keys"
        files = write_key_set(c.mission, keys)
        env = {KEY_FILE_ENV: str(keys)}  # each node takes its own file from the set
        monkeypatch.setenv(KEY_FILE_ENV, str(keys))  # this process: a read-only tool
        for node in ("dn0", "dn1", "cn"):
            c.spawn(node, env=env)
        c.wait_for(lambda dv: float(dv.get("dn0_alt_m")) > 60.0, 60, "dn0 above 60 m")
        ground = load_keys(c.mission, "gn", files["gn"])
        assert ground is not None
        # Every key in the ground's file, as the link key of a trigger under
        # either MAC, and as a master deriving a whole set.
        seals: list[Callable[[bytes], bytes]] = [lambda f: f, lambda f: f + bytes(16)]
        for link in ground.links:
            k = ground.link_key(link)
            for dn in ("dn0", "dn1"):
                for mac in ("blake3", "hmac-sha256"):
                    ch = Channel(k, c.mission.vehicle, f"cn_to_{dn}", mac)
                    seals.append(lambda f, ch=ch: bytes(ch.seal(f)))
                as_master = KeySet.from_master(c.mission, k).channel(f"cn_to_{dn}")
                seals.append(lambda f, ch=as_master: bytes(ch.seal(f)))
        clock = NodeClock()
        bad0 = {dn: int(c.tm.get(f"{dn}_bad_frames")) for dn in ("dn0", "dn1")}
        sent = 0
        # Every way five times over (a count, not a time: however slowly
        # the box runs the loop below, each way is tried as often).
        while sent < 5 * len(seals):
            seq = _next_loop(c, clock)
            for dn in ("dn0", "dn1"):
                _query(c, dn, seals[sent % len(seals)](_fire_trigger(c, dn, seq, clock.now_ns())))
            sent += 1
            c.rx.next(0.01)
            assert c.tm.get("igniter_fired") is False, "a ground key fired the igniter"
        c.wait_for(
            lambda dv: all(int(dv.get(f"{dn}_bad_frames")) >= bad0[dn] + sent for dn in bad0),
            20,
            "every forged trigger refused",
        )
        c.advance(20)
        assert sent >= len(seals)  # every way was tried, at least once per DN
        assert c.tm.get_name("cn_state") == "SAFE" and c.tm.get("igniter_fired") is False
        assert c.tm.get_name("cn_fault") == "NONE"
        # The control: the CN's own key file makes the same triggers fire both
        # igniters, with the vehicle in SAFE (what the ground's key did with
        # one mission key for every link), once they claim a state the
        # igniter may fire in.
        cn = load_keys(c.mission, "cn", files["cn"])
        assert cn is not None
        # In the CN's run (zplatform.core.auth.Run): what an insider holding its
        # key can do in the current run (an earlier run's frames never verify).
        run = Run(int(c.tm.get("cn_epoch")))
        seal = {dn: cn.channel(f"cn_to_{dn}", run) for dn in ("dn0", "dn1")}
        # First stamped with the vehicle's state, SAFE: each device node's
        # interlock drives its igniter safe instead, and counts it.
        deadline = time.monotonic() + 20
        while not (c.tm.get("dn0_interlocked") and c.tm.get("dn1_interlocked")):
            assert time.monotonic() < deadline, "the interlocks counted nothing"
            seq = _next_loop(c, clock)
            for dn in ("dn0", "dn1"):
                frame = _fire_trigger(c, dn, seq, clock.now_ns(), state="SAFE")
                _query(c, dn, bytes(seal[dn].seal(frame)))
            c.rx.next(0.05)
        assert c.tm.get("igniter_fired") is False
        assert not c.tm.get("dn0_ign_out") and not c.tm.get("dn1_ign_out")
        deadline = time.monotonic() + 20
        while not c.tm.get("igniter_fired"):
            assert time.monotonic() < deadline, "the CN's key did not fire the igniter"
            seq = _next_loop(c, clock)
            for dn in ("dn0", "dn1"):
                frame = _fire_trigger(c, dn, seq, clock.now_ns())
                _query(c, dn, bytes(seal[dn].seal(frame)))
            c.rx.next(0.05)
        assert c.tm.get_name("cn_state") == "SAFE"


BOTH = ((30 * MS, True), (5_000 * MS, False))


@contextmanager
def rogue_clock(
    c: Cluster, tagged: bool, shifts: tuple[tuple[int, bool], ...] = BOTH
) -> Iterator[dict[str, int]]:
    """A peer without the key answering ``{vehicle}/cn/clock``: one
    queryable per ``(shift_ns, complete)``, by default +30 ms on one
    declared ``complete`` and +5 s on one not. Each reply echoes the
    query's nonce and claims the server took the whole round trip (t2 and
    t3 half a second either side), so that NTP's fastest-exchange filter
    prefers it; ``tagged``: with a made-up tag, as the mission's frames
    carry one. Yields the count of replies sent."""
    clock = NodeClock()
    sent = {"replies": 0}
    lock = threading.Lock()

    def answering(shift_ns: int) -> Callable[[zenoh.Query], None]:
        def answer(q: zenoh.Query) -> None:
            with q:
                raw = q.payload.to_bytes() if q.payload is not None else b""
                if len(raw) < _QUERY.size:
                    return
                _, _, dn, nonce, t1 = _QUERY.unpack_from(raw)
                t = clock.now_ns() + shift_ns
                body = _REPLY.pack(b"ZR", 1, dn, nonce, t1, t - 500 * MS, t + 500 * MS)
                q.reply(q.key_expr, body + (bytes(16) if tagged else b""))
                with lock:
                    sent["replies"] += 1

        return answer

    key = f"{c.mission.vehicle}/cn/clock"
    qs = [
        c.session.declare_queryable(key, answering(shift), complete=complete)
        for shift, complete in shifts
    ]
    try:
        yield sent
    finally:
        for q in qs:
            q.undeclare()


def _fly(c: Cluster) -> None:
    """Every node of the flight, the ground playing ARM + LAUNCH. The CN
    starts last, once this process's session (the rogue's) is connected to
    dn0, dn1 and gn: a DN syncs its clock only after the CN is alive, so
    the rogue is on the clock key for the DNs from their first exchange."""
    for node in ("dn0", "dn1"):
        c.spawn(node)
    c.spawn("gn", "--commands", str(SCRIPT), "--log", str(c.tmp / "gn.csv"))

    def linked() -> bool:  # zenoh's view of this session's links; a node that died fails
        for name, p in c.procs.items():
            assert p.poll() is None, f"{name} exited:\n{c.log(name)[-2000:]}"
        return len(list(c.session.info.peers_zid())) >= 3

    wait_until(linked, 60, "the test's session to reach dn0, dn1 and gn")
    c.spawn("cn")


def test_a_rogue_clock_is_refused_and_the_flight_deploys(tmp_path: Path) -> None:
    # The quick flight (tests/drive.py): DEPLOYED 6 s after start, not 11 s.
    quick = igniter_quick_flight(tmp_path / "recovery_igniter_quick.yaml")
    with Cluster(quick, tmp_path, transport="plain") as c:
        with rogue_clock(c, tagged=True) as rogue:
            _fly(c)
            c.wait_for(
                lambda dv: dv.get_name("cn_state") in ("DEPLOYED", "NO_FIRE", "ABORTED"),
                90,
                "the flight's end",
            )
        tm = c.tm
        values = {k: _get(tm, k) for k in ("cn_state", "cn_fault", "igniter_fired")}
        assert values == {"cn_state": "DEPLOYED", "cn_fault": "NONE", "igniter_fired": True}
        assert rogue["replies"] > 0
        for dn in ("dn0", "dn1"):
            # The rogue's replies reached the DN and were refused, counted.
            assert int(tm.get(f"{dn}_clock_refused")) > 0, dn
            # Corrected to the CN (same host), not by +30 ms or +5 s.
            assert abs(int(tm.get(f"{dn}_clock_offset_ns"))) < 5 * MS, dn
            assert tm.get_name(f"{dn}_safed_why") != "CANNOT_RUN", dn
        # The DNs answered their syncs all flight (the quick flight deploys
        # at loop ~585 of the CN's loop time): links alive by tests/budget.py's
        # rule, a fraction of the loops, not a rate of the box.
        loops = int(tm.get("cn_loop"))
        assert loops > 500, loops
        for dn in ("dn0", "dn1"):
            assert int(tm.get(f"cn_rx_{dn}")) >= LINK_ALIVE * loops, (dn, loops)


def test_a_dn_that_cannot_run_safes_and_the_cn_faults(tmp_path: Path) -> None:
    """Without authentication (a closed bench) the rogue (+30 ms, complete)
    does move the DNs' clocks: every real trigger is then stale. Before, the
    DNs answered each one and ran none, never safed, and the flight ended
    ARMED with no fault. Now a DN safes, the CN latches DN_SAFED, and the
    LAUNCH is refused for it (or, if it came first, the fault aborts).
    (With +30 ms and +5 s answering together the DNs' corrections disagree
    with their residuals and the CN refuses to start, which was visible
    already.)"""
    with Cluster(MISSION, tmp_path, transport="plain") as c:
        raw = yaml.safe_load(c.path.read_text())
        raw["security"]["auth"] = False
        c.path.write_text(yaml.safe_dump(raw, sort_keys=False))
        c.mission = load_mission(c.path)
        with rogue_clock(c, tagged=False, shifts=((30 * MS, True),)):
            _fly(c)
            c.wait_for(lambda dv: dv.get_name("cn_fault") != "NONE", 60, "a fault")
            # The script's ARM + LAUNCH: after the fault latched, the LAUNCH is
            # refused for it (commands.refused_while_faulted); before, it is
            # accepted and the fault aborts the flight.
            c.wait_for(lambda dv: int(dv.get("cn_cmd_seq")) == 2, 30, "the LAUNCH's verdict")
            if c.tm.get_name("cn_cmd_status") == "ACCEPTED":
                c.wait_for(lambda dv: dv.get_name("cn_state") == "ABORTED", 30, "ABORTED")
            else:
                assert c.tm.get_name("cn_cmd_status") == "REJECTED_NOT_ALLOWED"
                assert c.tm.get_name("cn_state") == "SAFE"
        tm = c.tm
        assert tm.get_name("cn_fault") == "DN_SAFED"
        safed = [dn for dn in ("dn0", "dn1") if tm.get_name(f"{dn}_safed_why") == "CANNOT_RUN"]
        assert safed, {dn: tm.get_name(f"{dn}_safed_why") for dn in ("dn0", "dn1")}
        assert tm.get("igniter_fired") is False
        log = "".join(c.log(dn) for dn in safed)
        assert "none could run" in log and "clock off" in log
