"""The insider plan: for each host role of a mission (each device node, the
ground, a tool, the control nodes), every tagged frame of the key space
outside that role's rights, and what the role's own keys can make of it.

Generated from the key-space table (zplatform/security/keyspace.py: who puts,
declares, queries each key, and which node's intake takes each frame) and
from the links each role holds (:func:`zplatform.core.auth.role_links`),
never hand-listed. A role's *rights* on a frame: it is in the row's column
for that kind of frame (a query's ``queries``, a reply's ``declares``, a
sample's ``puts``) and it holds the frame's key (a read-only tool is in
``gn_to_cn``'s ``puts``, for a tool that may command, but holds no uplink
key). For every tagged frame a node takes that the role has no right to
send, the verdict is one of

* ``refused``: the role holds no key of the frame's channel; the insider's
  best forgery is the frame tagged with each channel it does hold (in the
  run it knows), which the receiving intake refuses, counted once as bad
  (tests/faults/test_insider.py feeds them);
* ``own node``: the role holds the channel (both ends of a link hold its
  key), and the only node that takes the frame is the role's own (a device
  node can forge triggers, probe questions and clock replies to itself);
* ``grounds only``: the role holds the channel, and only grounds and tools
  take the frame (the shared downlink and event keys: an insider can lie to
  other grounds, never to the vehicle; docs/architecture.md "Who holds which
  key");
* ``commands``: a control node's, which holds every vehicle link by design
  (a standby may command);
* ``REACHES``: none of these: the role's key reaches a vehicle node past its
  role. The suite fails on it.

``python -m tests.faults.insider`` prints the table for the shipped missions.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from zplatform.config import Mission
from zplatform.core.auth import host_roles, link_of, role_links
from zplatform.mission.load import load_mission
from zplatform.security.keyspace import ExpandedKey, KeyFrames, expand_keys

ROOT = Path(__file__).resolve().parents[2]
MISSION_NAMES = ("flight", "recovery_igniter")

REFUSED = "refused"
OWN_NODE = "own node"
GROUNDS_ONLY = "grounds only"
COMMANDS = "commands"
REACHES = "REACHES"
GROUND_SIDE = frozenset({"gn", "tool"})


@dataclass(frozen=True)
class InsiderCase:
    """One (row, role, frame) of the plan (module doc): the expanded key,
    the frame's index in its row, the roles that take it (``receivers``),
    the channels the insider forges with (``forge``: every channel it
    holds, for ``refused``; none otherwise) and the verdict."""

    mission: str
    role: str
    key: ExpandedKey
    frame: int
    receivers: frozenset[str]
    forge: tuple[str, ...]
    verdict: str

    @property
    def f(self) -> KeyFrames:
        return self.key.row.frames[self.frame]

    @property
    def channel(self) -> str:
        return self.key.channels[self.frame]

    @property
    def id(self) -> str:
        kind = self.f.kind
        if self.channel.startswith("run_"):
            kind += ":" + self.channel
        return f"{self.mission}-{self.role}-{self.key.id}-{kind}"


def _resolve(m: Mission, k: ExpandedKey, who: str) -> set[str]:
    """The host roles one entry of a who-column (or an intake's node) names."""
    params = dict(k.params)
    if who in ("commander", "control"):
        return set(m.control_nodes)
    if who.startswith("{"):
        name = params.get(who.strip("{}"))
        if name is None:
            return set()
        return set(m.control_nodes) if name == "peer" else {name}
    if who == "gn":
        return {"gn"} if m.has_ground else set()
    if who == "tool":
        return {"tool"}
    if who == "any":
        return set(host_roles(m))
    return set()  # "self": local to a session


def senders(m: Mission, k: ExpandedKey, j: int) -> set[str]:
    """The roles with the right to send frame ``j`` of ``k`` (module doc). A
    row that is only a subscription (``all_events``) has the senders of the
    node whose channel tags the frame."""
    f = k.row.frames[j]
    col = {"query": k.row.queries, "reply": k.row.declares, "sample": k.row.puts}[f.kind]
    if f.kind == "sample" and not col and "node" in dict(k.params):
        col = ("{node}",)
    out: set[str] = set()
    for w in col:
        out |= _resolve(m, k, w)
    return out


def receivers(m: Mission, k: ExpandedKey, j: int) -> frozenset[str]:
    """The roles whose intake takes frame ``j`` of ``k`` (its row's intake node)."""
    node = k.row.frames[j].intake.rsplit(" ", 1)[-1]
    return frozenset(_resolve(m, k, node))


def channels_of(m: Mission, role: str) -> tuple[str, ...]:
    """Every auth channel of the mission that ``role``'s links key, in table order."""
    held = set(role_links(m, role))
    seen: dict[str, None] = {}
    for k in expand_keys(m):
        for c in k.channels:
            if c and link_of(c) in held:
                seen[c] = None
    return tuple(seen)


def plan(name: str, m: Mission) -> list[InsiderCase]:
    """Every (row, role, frame) of ``m`` outside the role's rights (module doc)."""
    out: list[InsiderCase] = []
    for role in host_roles(m):
        mine = channels_of(m, role)
        for k in expand_keys(m):
            for j, f in enumerate(k.row.frames):
                if not f.tagged or f.intake == "none":
                    continue
                ch = k.channels[j]
                if role in senders(m, k, j) and ch in mine:
                    continue  # its right (a tool that may not command holds no uplink)
                rx = receivers(m, k, j)
                if ch not in mine:
                    verdict, forge = REFUSED, mine
                elif role in m.control_nodes:
                    verdict, forge = COMMANDS, ()
                elif rx <= GROUND_SIDE:
                    verdict, forge = GROUNDS_ONLY, ()
                elif rx <= {role}:
                    verdict, forge = OWN_NODE, ()
                else:
                    verdict, forge = REACHES, ()
                out.append(InsiderCase(name, role, k, j, rx, forge, verdict))
    return out


def shipped() -> dict[str, Mission]:
    return {n: load_mission(ROOT / "configs" / f"{n}.yaml") for n in MISSION_NAMES}


def markdown(cases: list[InsiderCase]) -> str:
    """The plan as a table: mission, role, row, frame, channel, receivers, verdict."""
    lines = [
        "| mission | role | key | frame | channel | taken by | verdict |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in cases:
        forged = f" ({len(c.forge)} forgeries)" if c.forge else ""
        lines.append(
            f"| {c.mission} | {c.role} | {c.key.id} | {c.f.kind} | `{c.channel}` | "
            f"{', '.join(sorted(c.receivers))} | {c.verdict}{forged} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.stdout.write(markdown([c for n, m in shipped().items() for c in plan(n, m)]))
