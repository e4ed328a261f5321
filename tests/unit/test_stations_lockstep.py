"""Lockstep: the flight mission with a ``ground:`` section, flown in process
with several stations' requests (each framed by its own signed
:class:`~zplatform.control.uplink.Uplink` and delivered to the CN beside
the ground's): a refused viewer, a handover from the pad to the control
room, a two-person LAUNCH refused with one operator and accepted with a
second's approval, the control room going silent mid-flight and the pad
taking the lock once the lease ran out."""

from __future__ import annotations

import re
from pathlib import Path

from zplatform import decode_mission
from zplatform.config import Mission
from zplatform.control.uplink import Uplink, operator_number
from zplatform.security.identities import sim_signer
from zplatform.sim.lockstep import LockstepRunner, sim_keys

FLIGHT = Path(__file__).resolve().parents[2] / "configs" / "flight.yaml"

GROUND = """
ground:
  lease_s: 2
  stations:
    - {name: pad}
    - {name: room}
    - {name: lounge, may: view}
  operators:
    - {name: pat, roles: [operator]}
    - {name: fd, roles: [flight_director]}
    - {name: rso, roles: [range_safety]}
    - {name: vic, roles: [viewer]}
  two_person: [LAUNCH]
"""


def _long_lease_runner() -> LockstepRunner:
    """The flight with the ground section, its lease 5 s (it outlasts a
    takeover or a restart), in lockstep."""
    return LockstepRunner(
        decode_mission(
            FLIGHT.read_text() + GROUND.replace("lease_s: 2", "lease_s: 5"),
            source=str(FLIGHT),
            base_dir=FLIGHT.parent,
        )
    )


def flight_with_ground() -> Mission:
    return decode_mission(FLIGHT.read_text() + GROUND, source=str(FLIGHT), base_dir=FLIGHT.parent)


class Stations:
    """Every station's uplink, numbering as a ground does (above every number
    the CN showed, refused ones too: GroundLogic), its verdicts read from the
    CN's vector."""

    def __init__(self, runner: LockstepRunner) -> None:
        self.r = runner
        self.m = runner.mission
        keys = sim_keys(self.m)
        assert keys is not None
        self._keys = keys
        self._ups: dict[str, Uplink] = {}

    def send(
        self, who: str, command: str, element: int = 0, ref: int = 0, seq: int | None = None
    ) -> str:
        """``who`` (``op@station``) sends ``command`` numbered ``seq`` (None:
        the CN's last number plus one); one loop; its verdict."""
        if who not in self._ups:
            op, st = who.split("@")
            signer = sim_signer(self._keys, self.m, op, st)
            self._ups[who] = Uplink(self.m, self._keys.for_node("gn"), signer=signer)
        dv = self.r.control.dv
        if seq is None:
            shown = max(dv.get("cn_cmd_seq"), dv.get("cn_cmd_reject_seq"))
            seq = max(self.r.control.commands.last_seq, int(shown)) + 1
        frame = self._ups[who].frame(
            command, seq, element, 0.0, self.r.clock.now_ns(), dv.get("cn_epoch"), ref=ref
        )
        rejects = dv.get("cn_cmd_rejects")
        self.r.uplink(frame)
        self.r.step()
        if dv.get("cn_cmd_rejects") != rejects:
            assert dv.get("cn_cmd_reject_seq") == seq
            return dv.get_name("cn_cmd_reject_status")
        assert dv.get("cn_cmd_seq") == seq
        return dv.get_name("cn_cmd_status")

    @property
    def holder(self) -> str:
        dv = self.r.control.dv
        return f"{dv.get_name('cn_lock_holder')}@{dv.get_name('cn_lock_station')}"


def test_a_flight_with_stations_hand_over_two_person_launch_and_lease_expiry() -> None:
    r = LockstepRunner(flight_with_ground())
    s = Stations(r)
    r.run(0.5)
    assert s.send("vic@lounge", "NOOP") == "REJECTED_VIEW_ONLY"
    assert s.send("pat@pad", "LOCK") == "ACCEPTED"
    assert s.holder == "pat@pad"
    assert s.send("fd@room", "NOOP") == "REJECTED_NOT_HOLDER"
    # The pad hands the lock to the control room.
    assert s.send("pat@pad", "HANDOVER", element=operator_number(r.mission, "fd")) == "ACCEPTED"
    assert s.send("fd@room", "NOOP") == "ACCEPTED"
    assert s.holder == "fd@room"
    # LAUNCH is two-person: its ARM needs a second operator's approval.
    assert s.send("fd@room", "ARM") == "ACCEPTED"
    assert s.send("fd@room", "LAUNCH") == "REJECTED_NOT_APPROVED"
    assert r.control.dv.get_name("cn_state") == "SAFE"
    assert s.send("fd@room", "ARM") == "ACCEPTED"
    arm = r.control.commands.last_seq
    # An operator is no approver: refused without a verdict, its number (which
    # the CN's intake admitted) between the ARM and its command breaks nothing.
    assert s.send("pat@pad", "APPROVE", ref=arm) == "REJECTED_ROLE"
    assert s.send("rso@lounge", "APPROVE", ref=arm) == "ACCEPTED"
    assert s.send("fd@room", "LAUNCH") == "ACCEPTED"
    assert r.control.dv.get_name("cn_state") == "ARMED"
    # The control room goes silent mid-flight: the pad cannot take the lock
    # until the lease ran out, then can.
    r.run(1.0)
    assert s.holder == "fd@room"
    assert s.send("pat@pad", "LOCK") == "REJECTED_NOT_HOLDER"
    r.run(1.2)
    assert s.holder == "NONE@NONE"
    assert s.send("pat@pad", "LOCK") == "ACCEPTED"
    assert s.holder == "pat@pad"
    res = r.run(20.0)
    assert res.states[:5] == ["SAFE", "ARMED", "BOOST", "COAST", "DROGUE"]
    assert "ABORTED" not in res.states
    lock = [e.text for e in res.events if e.node == "cn" and e.id == "cmd_lock"]
    assert lock == [
        "command lock granted: pat@pad holds the command lock",
        "command lock handed: pat@pad handed the command lock to fd",
        "command lock granted: fd@room took up the handed-over lock",
        f"command lock approved: rso@lounge approved ARM #{arm}",
        "command lock expired: fd@room's command lock expired (no request in its lease)",
        "command lock granted: pat@pad holds the command lock",
        "command lock expired: pat@pad's command lock expired (no request in its lease)",
    ]
    assert r.control.dv.get("cn_auth_refused") == 4


def test_a_refused_station_never_displaces_the_holders_request_in_a_loop() -> None:
    """Two requests in one loop, the viewer's numbered higher: the CN refuses
    the viewer's before it picks (no number consumed) and takes the holder's."""
    r = LockstepRunner(flight_with_ground())
    s = Stations(r)
    r.run(0.5)
    assert s.send("pat@pad", "LOCK") == "ACCEPTED"
    dv = r.control.dv
    seq = r.control.commands.last_seq + 1
    keys = sim_keys(r.mission)
    assert keys is not None
    for who, n in (("pat@pad", seq), ("vic@lounge", seq + 1)):
        op, st = who.split("@")
        up = Uplink(r.mission, keys.for_node("gn"), signer=sim_signer(keys, r.mission, op, st))
        r.uplink(up.frame("NOOP", n, 0, 0.0, r.clock.now_ns(), dv.get("cn_epoch")))
    r.step()
    assert dv.get("cn_cmd_seq") == seq and dv.get_name("cn_cmd_status") == "ACCEPTED"
    assert dv.get("cn_cmd_reject_seq") == seq + 1
    assert dv.get_name("cn_cmd_reject_status") == "REJECTED_VIEW_ONLY"
    assert dv.get("cn_cmd_dropped") == 0


def test_range_safety_aborts_the_flight_from_a_view_station() -> None:
    r = LockstepRunner(flight_with_ground())
    s = Stations(r)
    r.run(0.5)
    s.send("fd@room", "LOCK")
    s.send("fd@room", "ARM")
    s.send("rso@lounge", "APPROVE", ref=r.control.commands.last_seq)
    assert s.send("fd@room", "LAUNCH") == "ACCEPTED"
    r.run(0.5)
    assert r.control.dv.get_name("cn_state") == "ARMED"
    assert s.send("vic@lounge", "ABORT") == "REJECTED_VIEW_ONLY"
    assert s.send("rso@lounge", "ABORT") == "ACCEPTED"
    r.step()
    assert r.control.dv.get_name("cn_state") == "ABORTED"
    assert s.holder == "fd@room"  # the abort left the lock where it was


def test_a_number_reused_after_an_authority_refusal_is_refused_as_the_live_cn_does() -> None:
    """A request the authority refuses consumes no number, but the CN's
    intake admitted it: the same number again is a replay, in lockstep as
    live (the runner's requests pass the live CN's RequestIntake)."""
    r = LockstepRunner(flight_with_ground())
    s = Stations(r)
    r.run(0.5)
    n = r.control.commands.last_seq + 1
    assert s.send("vic@lounge", "NOOP") == "REJECTED_VIEW_ONLY"
    assert r.control.commands.last_seq == n - 1  # no number consumed
    assert s.send("pat@pad", "LOCK", seq=n) == "REJECTED_REPLAY"  # numbered n again
    dv = r.control.dv
    assert dv.get("cn_cmd_reject_seq") == n and dv.get("cn_cmd_seq") == n - 1
    assert s.holder == "NONE@NONE"
    assert s.send("pat@pad", "LOCK", seq=n + 1) == "ACCEPTED"
    assert s.holder == "pat@pad"


def test_a_standby_takeover_keeps_the_lock_the_open_arm_and_its_approvals() -> None:
    """The commander dies with an ARM open for approvals and one approval
    given: the standby takes command from the mirrored vector and resumes
    the authority's state: the lock's holder, the ARM, its approval (the
    same approver is refused as approving twice); a second approver's
    APPROVE is accepted and the two-person LAUNCH is accepted by the new
    commander."""
    text = FLIGHT.read_text() + GROUND.replace(
        "    - {name: vic, roles: [viewer]}\n",
        "    - {name: vic, roles: [viewer]}\n    - {name: flo, roles: [flight_director]}\n",
    ).replace("lease_s: 2", "lease_s: 5")
    r = LockstepRunner(decode_mission(text, source=str(FLIGHT), base_dir=FLIGHT.parent))
    s = Stations(r)
    r.run(0.5)
    assert s.send("pat@pad", "LOCK") == "ACCEPTED"
    assert s.send("pat@pad", "ARM") == "ACCEPTED"
    arm = r.control.commands.last_seq
    assert s.send("rso@lounge", "APPROVE", ref=arm) == "ACCEPTED"
    r.kill("cn")
    for _ in range(20):
        r.step()
    assert [(node, term) for _, node, term in r.commanders] == [("cn", 1), ("cn_b", 2)]
    assert r.control.name == "cn_b"
    dv = r.control.dv
    assert s.holder == "pat@pad" and dv.get("cn_arm_approvals") == 1
    assert s.send("fd@room", "NOOP") == "REJECTED_NOT_HOLDER"
    assert s.send("rso@lounge", "APPROVE", ref=arm) == "REJECTED_APPROVAL_SELF"
    assert s.send("flo@room", "APPROVE", ref=arm) == "ACCEPTED"
    assert dv.get("cn_arm_approvals") == 2 and dv.get("cn_arm_open") == arm
    assert s.send("pat@pad", "LAUNCH") == "ACCEPTED"
    assert dv.get_name("cn_state") == "ARMED" and s.holder == "pat@pad"


def test_a_standby_takeover_resumes_an_arm_awaiting_its_second_operator() -> None:
    """An ARM waiting for its approval when the commander dies: approved at
    the new commander, its command accepted there (not armed again)."""
    r = _long_lease_runner()
    s = Stations(r)
    r.run(0.5)
    assert s.send("fd@room", "LOCK") == "ACCEPTED"
    assert s.send("fd@room", "ARM") == "ACCEPTED"
    arm = r.control.commands.last_seq
    r.kill("cn")
    for _ in range(20):
        r.step()
    assert r.control.name == "cn_b" and s.holder == "fd@room"
    assert s.send("rso@lounge", "APPROVE", ref=arm) == "ACCEPTED"
    assert s.send("fd@room", "LAUNCH") == "ACCEPTED"
    assert r.control.dv.get_name("cn_state") == "ARMED"


def test_a_restart_in_flight_resumes_the_lock_and_the_approved_arm_from_its_recorder() -> None:
    """Both control nodes die with an approved ARM open; cn restarts and
    resumes the run from its flight recorder's newest frame, which carries
    the authority's state: the holder keeps the lock and the approved
    two-person LAUNCH is accepted without a new ARM or approval."""
    r = _long_lease_runner()
    s = Stations(r)
    r.run(0.5)
    assert s.send("fd@room", "LOCK") == "ACCEPTED"
    assert s.send("fd@room", "ARM") == "ACCEPTED"
    arm = r.control.commands.last_seq
    assert s.send("rso@lounge", "APPROVE", ref=arm) == "ACCEPTED"
    r.kill("cn_b")
    r.kill("cn")
    r.run(0.1)
    assert r.restart("cn") == "resume"
    for _ in range(3):
        r.step()
    assert r.control.name == "cn" and s.holder == "fd@room"
    assert s.send("rso@lounge", "APPROVE", ref=arm) == "REJECTED_APPROVAL_SELF"
    assert s.send("fd@room", "LAUNCH") == "ACCEPTED"
    assert r.control.dv.get_name("cn_state") == "ARMED"


def test_a_restart_without_a_standby_resumes_the_approved_arm_from_its_recorder() -> None:
    """The same without a standby: the recorder's frame carries the last ARM
    (``cn_arm_seq``, ``cn_arm_t_ns``: kept with a recorder too) beside the
    authority's state, so the approved LAUNCH follows without a new ARM."""
    text = re.sub(r"  cn_b:\n(    .*\n){3}", "", FLIGHT.read_text())
    m = decode_mission(
        text + GROUND.replace("lease_s: 2", "lease_s: 5"),
        source=str(FLIGHT),
        base_dir=FLIGHT.parent,
    )
    assert m.standby is None and m.recorder is not None
    r = LockstepRunner(m)
    s = Stations(r)
    r.run(0.5)
    assert s.send("fd@room", "LOCK") == "ACCEPTED"
    assert s.send("fd@room", "ARM") == "ACCEPTED"
    arm = r.control.commands.last_seq
    assert s.send("rso@lounge", "APPROVE", ref=arm) == "ACCEPTED"
    r.kill("cn")
    r.run(0.1)
    assert r.restart("cn") == "resume"
    for _ in range(3):
        r.step()
    assert s.holder == "fd@room"
    assert s.send("fd@room", "LAUNCH") == "ACCEPTED"
    assert r.control.dv.get_name("cn_state") == "ARMED"
