"""The mission configuration's schema: YAML decoded into typed, structurally checked structs.

This module is the schema and nothing more: the :class:`Mission` struct tree
(``msgspec.Struct`` with ``forbid_unknown_fields``, so a typo fails at
decode), the structural checks of the thesis, ch. 4.1.1 (Data Vector), 4.2.1
(network) and the topology rules of docs/architecture.md, the size limits that keep a
mission from exhausting memory (:data:`MAX_ARRAY_COUNT`,
:data:`MAX_REGION_BYTES`, :data:`MAX_VECTOR_BYTES`), and the platform
elements of docs/architecture.md#data-vector added to the regions. :func:`parse_mission` does
all of that; every failure is a :class:`~zplatform.errors.ConfigError` whose
message names the YAML path of the bad field and what was expected.

It imports none of the modules that give the sections their meaning (state
machine, commands, controllers, devices): those import *it*. The semantic
checks live with them and are run by :func:`zplatform.mission.load_mission`
/ :func:`zplatform.mission.decode_mission`, the way in for everyone else. A
mission that only passed :func:`parse_mission` is not fit to fly.

After loading, a :class:`Mission` is treated as immutable: the runtime reads
it, never writes it.
"""

from __future__ import annotations

import math
import os
import re
import unicodedata
import zlib
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta

from .codes import Command, CommandStatus, Fault, ParamLoad, ParamSave, SafedWhy, Thread
from .errors import ConfigError
from .types import SCALAR_TYPES, ScalarType, parse_type

__all__ = [
    "BOARD_LINK_COUNTERS",
    "BOARD_LINK_DRIVERS",
    "CMD_NAMES",
    "CMD_STATUS_NAMES",
    "CONTROLLER_MODES",
    "FAULT_NAMES",
    "HEALTH_METRICS",
    "MAX_ARRAY_COUNT",
    "MAX_REGION_BYTES",
    "MAX_VECTOR_BYTES",
    "MISSION_NAME_MAX",
    "PRM_LOAD_NAMES",
    "PRM_SAVE_NAMES",
    "SAFED_WHY_NAMES",
    "THREAD_NAMES",
    "ActionConfig",
    "ClockConfig",
    "CommandsConfig",
    "ComponentConfig",
    "ElementConfig",
    "FaultsConfig",
    "HazardousOutputConfig",
    "HealthConfig",
    "HealthMetric",
    "Mission",
    "MonitorConfig",
    "NodeConfig",
    "ParamConfig",
    "RecorderConfig",
    "StateConfig",
    "StateMachineConfig",
    "TransitionConfig",
    "TransportConfig",
    "WatchdogConfig",
    "WorldBoardConfig",
    "WorldConfig",
    "board_link_elements",
    "check_mission_name",
    "element_spec",
    "health_elements",
    "interlocked_nodes",
    "parse_mission",
    "platform_elements",
    "relocate_mission",
    "resolve_pythonpath",
    "transport_reason",
]

Scalar = int | float | bool | str
Value = Scalar | list[Scalar]

# Enum names of the platform elements cn_cmd/gn_cmd, cn_cmd_status and
# cn_fault, derived from the one definition of the codes (zplatform.codes).
CMD_NAMES: tuple[str, ...] = tuple(m.name for m in Command)
CMD_STATUS_NAMES: tuple[str, ...] = tuple(m.name for m in CommandStatus)
CONTROLLER_MODES: tuple[str, ...] = ("enabled", "safed", "manual")
FAULT_NAMES: tuple[str, ...] = tuple(m.name for m in Fault)
PRM_LOAD_NAMES: tuple[str, ...] = tuple(m.name for m in ParamLoad)
PRM_SAVE_NAMES: tuple[str, ...] = tuple(m.name for m in ParamSave)
SAFED_WHY_NAMES: tuple[str, ...] = tuple(m.name for m in SafedWhy)
THREAD_NAMES: tuple[str, ...] = tuple(t.name.lower() for t in Thread)
"""The threads whose liveness a node reports, by bit of ``<node>_threads_stalled``
(:class:`~zplatform.codes.Thread`, :mod:`zplatform.health`)."""

# Names checked with fullmatch, never match: `$` also matches before a
# trailing newline, so "cn_loop\n" would pass a match().
_NAME_RE = re.compile(r"^[a-z][a-z0-9_]*$")
_ENUM_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_DN_RE = re.compile(r"^dn([0-9]+)$")
MAX_ARRAY_COUNT = 16 * 1024 * 1024
"""Most items in one array element (16 Mi: ``u8[16777216]``, ``f64[16777216]``)."""
MAX_REGION_BYTES = 256 * 1024 * 1024
"""Most bytes in one region (256 MiB): a region travels whole in one frame per loop."""
MAX_VECTOR_BYTES = 256 * 1024 * 1024
"""Most bytes in a Data Vector (256 MiB); the CN's holds every region."""
MISSION_NAME_MAX = 128
"""Longest mission name, in characters."""
# Characters with a meaning in zenoh key expressions (wildcards, separators,
# the `$*` chunk syntax, `#` reserved): never part of a name that may go
# into a key or a file name.
_KEY_SPECIALS = frozenset("*$?#/")

_FLOAT_WORDS = ("nan", "inf", "+inf", "-inf", "infinity", "-infinity")
_EXP_FLOAT_RE = re.compile(r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)e[-+]?[0-9]+$")


class _Struct(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True):
    pass


class LimitsConfig(_Struct):
    """Yellow and red ranges of a numeric element, for the ground console and
    the XTCE alarms: a value outside ``yellow`` is a warning, outside ``red``
    an alarm. They are shown, never enforced on the vehicle."""

    yellow: Annotated[
        tuple[float | None, float | None] | None,
        Meta(description="`[lo, hi]`: the warning range; `null` for an open bound."),
    ] = None
    red: Annotated[
        tuple[float | None, float | None] | None,
        Meta(description="`[lo, hi]`: the alarm range; `null` for an open bound."),
    ] = None


class ElementConfig(_Struct):
    """One Data Vector element of the mission: a named, typed value that
    every node holding its region sees (`{name, type, initial, enum, doc,
    limits}`)."""

    name: Annotated[
        str,
        Meta(
            description="Unique in the whole Data Vector: a lowercase letter, then lowercase "
            "letters, digits or `_`. Platform element names are taken."
        ),
    ]
    type: Annotated[
        str,
        Meta(
            description="`u8`, `u16`, `u32`, `u64`, `i8`, `i16`, `i32`, `i64`, `f32`, `f64`, "
            "`bool`; a fixed array of one (`f32[3]`, at most 16 Mi items); or `enum`, an "
            "unsigned integer with the names in `enum` (u8 up to 256 names, else u16). "
            "Required unless `enum` names are given."
        ),
    ] = "enum"
    initial: Annotated[
        Value | None,
        Meta(
            description="Value before the first loop (default 0, `false`, or an enum's first "
            "name). An enum's may be a name; an array takes a list of its length or one "
            "value for every item; floats also take `nan`, `inf`, `-inf`."
        ),
    ] = None
    enum: Annotated[
        list[str] | None,
        Meta(description="The names of an enum's values 0, 1, 2, ... (identifiers, no repeats)."),
    ] = None
    doc: Annotated[
        str,
        Meta(description="What the element means; shown by the ground tools and in XTCE."),
    ] = ""
    limits: Annotated[
        LimitsConfig | None,
        Meta(description="Warning and alarm ranges for the ground (numeric elements)."),
    ] = None


class WatchdogConfig(_Struct):
    """A node's watchdog: the loop strokes systemd's watchdog or a watchdog
    device while every watched thread checks in, and stops the moment one
    does not (so the host is reset); strokes resume if it recovers first.
    See zplatform.watchdog."""

    kind: Annotated[
        Literal["systemd", "device"],
        Meta(
            description="`systemd`: `WATCHDOG=1` to `$NOTIFY_SOCKET` (sd_notify; the unit "
            "sets `WatchdogSec=`, and the node refuses to start without the variable); "
            "`device`: a byte to `device` (the kernel's `/dev/watchdog`)."
        ),
    ]
    device: Annotated[
        str,
        Meta(
            description="`kind: device`: the watchdog device. On a clean stop the node writes "
            "`V` (the magic close), so an orderly exit does not reset the host."
        ),
    ] = "/dev/watchdog"
    interval_ms: Annotated[
        float,
        Meta(
            ge=10,
            le=60_000,
            description="Stroke (and check the threads) every this many ms: well under the "
            "watchdog's timeout (systemd: under half of `WatchdogSec`).",
        ),
    ] = 100.0
    threads: Annotated[
        list[str] | None,
        Meta(
            description="The threads that must be alive (names of `<node>_threads_stalled`: "
            + ", ".join(f"`{n}`" for n in THREAD_NAMES)
            + "). Default: every thread the node runs."
        ),
    ] = None


class NodeConfig(_Struct):
    """A zenoh peer: where it listens and whom it connects to.

    The endpoints carry the host: a node on another host listens on that
    host's address (`tcp/10.0.0.2:7461`) and the others connect to it; the
    same file then runs on every host (`zplatform node MISSION NAME`)."""

    listen: Annotated[
        list[str],
        Meta(
            description="Endpoints this node listens on, `<proto>/<host>:<port>` (`tcp`, "
            "`udp`, `tls`, `ws`; `unixsock-stream/<path>`). An endpoint is listened on by one "
            "node only. When the mission's links run mutual TLS (`security.transport`), `tcp` "
            "runs as `tls` and only `tcp`/`tls` endpoints are allowed."
        ),
    ] = msgspec.field(default_factory=list)
    connect: Annotated[
        list[str],
        Meta(description="Endpoints this node connects to: usually the control node's `listen`."),
    ] = msgspec.field(default_factory=list)
    # Only >= 0, not < os.cpu_count(): the mission may target another host.
    cpu: Annotated[
        Annotated[int, Meta(ge=0)] | None,
        Meta(
            description="CPU to pin the node's loop thread to. Best effort: where it is not "
            "permitted, the node logs why and runs unpinned."
        ),
    ] = None
    priority: Annotated[
        Annotated[int, Meta(ge=1, le=99)] | None,
        Meta(
            description="SCHED_FIFO priority of the node's loop thread. Best effort: without "
            "the right to it, the node logs why and runs with normal scheduling."
        ),
    ] = None
    board: Annotated[
        dict[str, Any],
        Meta(
            description="Device nodes: the I/O board the devices use, `{driver: NAME, ...}` "
            "with the driver's own keys (see Boards). Default: a simulated board."
        ),
    ] = msgspec.field(default_factory=dict)
    watchdog: Annotated[
        WatchdogConfig | None,
        Meta(description="A watchdog the node's loop strokes while its threads are alive."),
    ] = None


class TransportConfig(_Struct):
    """Zenoh session settings shared by every node of the mission."""

    multicast_scouting: Annotated[
        bool,
        Meta(description="Find peers by UDP multicast; off: peers meet only through endpoints."),
    ] = False
    gossip_scouting: Annotated[
        bool,
        Meta(
            description="Peers tell each other about the peers they know over their links, "
            "so nodes that connect only to the CN (and tools) still reach each other."
        ),
    ] = True
    lease_ms: Annotated[
        int,
        Meta(
            ge=100,
            le=60_000,
            description="Zenoh link lease (ms): how soon a hung or cut-off peer is declared "
            "gone (a killed one is seen at once).",
        ),
    ] = 1000
    # "auto" is resolved by zplatform.messages.lowlatency_for.
    lowlatency: Annotated[
        bool | Literal["auto"],
        Meta(
            description="Zenoh's lowlatency transport (QoS off, no tx batching task). About "
            "10 % faster syncs here (bench/REPORT.md, sync), but off by default: it writes to "
            "the socket from the sending thread, so a cut cable froze the CN's loop for "
            "271 ms in the fault tests (off, the query is dropped and the loop runs on), and "
            "it cannot fragment (a message over about 48 KiB is dropped without a word). "
            "`auto` turns it on only when every message the mission sends fits in 16 KiB and "
            "there are no bulk channels; `true` on a mission where one may not fit is a "
            "config error."
        ),
    ] = False
    # "auto" is resolved by zplatform.messages.wildcard_sync_for.
    sync_query: Annotated[
        Literal["auto", "wildcard", "per_node"],
        Meta(
            description="How the CN queries its DNs each loop: `per_node`, one query per DN; "
            "`wildcard`, one query on `{vehicle}/*/to_cn` carrying a bundle of every DN's "
            "frame (codecs/FORMAT.md §6.2); `auto`, wildcard for two or more DNs while the "
            "bundle is at most 4 KiB. `per_node` is the default because it measured faster "
            "in zplatform (bench/REPORT.md, sync and levers), and the wildcard sends every DN "
            "every DN's frame."
        ),
    ] = "per_node"
    batching: Annotated[
        bool,
        Meta(
            description="Zenoh's tx batching (holds small messages up to 1 ms): good for "
            "throughput, bad for a 2 ms sync deadline."
        ),
    ] = False
    shared_memory: Annotated[
        bool,
        Meta(
            description="Zenoh shared memory between the processes of one host (bulk "
            "channels travel through it; large messages too)."
        ),
    ] = True


class ClockConfig(_Struct):
    """Clock synchronisation: each DN measures its clock's offset to the CN's
    over zenoh (four time points per exchange, the fastest exchanges kept),
    applies it at start-up and re-measures it in flight."""

    offset_bound_ms: Annotated[
        float,
        Meta(
            gt=0,
            description="Largest clock error (ms) left after correction: beyond it at "
            "start-up the CN refuses to start; in flight a DN whose drift exceeds it raises "
            "the CLOCK_DRIFT fault.",
        ),
    ] = 100.0
    exchanges: Annotated[
        int, Meta(ge=8, le=10_000, description="Exchanges per start-up measurement.")
    ] = 200
    keep_fraction: Annotated[
        float,
        Meta(
            gt=0,
            le=1,
            description="Fraction of the exchanges, the fastest (least delayed), that the "
            "estimate uses.",
        ),
    ] = 0.1
    resync_s: Annotated[
        float,
        Meta(
            ge=0,
            description="Re-measure the offset in flight every this many seconds (0: never); "
            "the drift goes to `dnX_clock_drift_ns`.",
        ),
    ] = 10.0
    # zplatform.clocksync.estimator_for builds the one named here.
    estimator: Annotated[
        Literal["zenoh_ts", "node_clock"],
        Meta(
            description="Where the four time points come from. `zenoh_ts`: stamped inside "
            "zenoh as the query and the reply cross it, mapped into node time; it measured "
            "more accurate (bench/REPORT.md, clock: median |error| 6.94 us vs 7.36 us, worst "
            "17.3 us vs 26.6 us) and falls back to `node_clock`, with a warning, when the CN "
            "answers without usable zenoh timestamps. `node_clock`: the node clocks alone."
        ),
    ] = "zenoh_ts"


class ActionConfig(_Struct):
    """A timed write: `at_s` seconds into the state, `element = value`. An
    action runs at most once per visit of its state; actions at 0 s run in
    the loop the state is entered, however soon it is left."""

    element: Annotated[
        str,
        Meta(
            description="An element CN logic may write: the mission's own elements of `cn` "
            "and `cn_to_dnX`, a controller's `<name>_mode`, or `cn_fault` (written `NONE` to "
            "clear a fault)."
        ),
    ]
    value: Annotated[
        Scalar,
        Meta(
            description="The value, fitting the element's type: an enum name (`enabled`, "
            "`safed`, `manual` for a mode), `true`/`false`, a number; an array element gets "
            "every item set."
        ),
    ]
    at_s: Annotated[
        float, Meta(ge=0, description="Seconds after the state was entered (a HOLD pauses it).")
    ] = 0.0


class TransitionConfig(_Struct):
    """Go to state `to` when `element op value` holds, or after `after_s`
    seconds in the state: give the three condition keys or `after_s`, not
    both. A state's transitions are tried in order (commands in
    `state_machine.priority` first), the first that holds fires, at most one
    per loop."""

    to: Annotated[str, Meta(description="The state to go to.")]
    element: Annotated[
        str | None,
        Meta(
            description="The condition's element: any scalar element of the CN's Data Vector "
            "(`cn_cmd` for commands, `cn_fault` for faults, a sensor reading, ...)."
        ),
    ] = None
    op: Annotated[
        Literal["==", "!=", "<", "<=", ">", ">="] | None,
        Meta(description="The comparison; bools and enums take only `==` and `!=`."),
    ] = None
    value: Annotated[
        Scalar | None,
        Meta(
            description="What the element is compared with: a command (`LAUNCH`), a fault "
            "(`NONE`), an enum name, `true`/`false`, a number (never `nan`)."
        ),
    ] = None
    after_s: Annotated[
        Annotated[float, Meta(ge=0)] | None,
        Meta(
            description="Fire after this many seconds in the state (a HOLD pauses the "
            "clock). `after_s: 0` transitions may not form a cycle."
        ),
    ] = None


class StateConfig(_Struct):
    """One state: what it does on a timer and how it is left."""

    actions: Annotated[
        list[ActionConfig],
        Meta(description="Timed writes, run in `at_s` order (config order for equal times)."),
    ] = msgspec.field(default_factory=list)
    transitions: Annotated[
        list[TransitionConfig],
        Meta(description="Ways out of the state, tried in order each loop."),
    ] = msgspec.field(default_factory=list)
    doc: Annotated[str, Meta(description="What the state is for.")] = ""


class StateMachineConfig(_Struct):
    """The vehicle's states (thesis: they live in the configuration, not in
    code). The current state is the platform element `cn_state`, the time
    in it `cn_time_in_state_ns`. An accepted command stays in `cn_cmd` until
    a transition takes it, or for one loop in a state that does not handle
    it."""

    initial: Annotated[str, Meta(description="The state of the first loop (`cn_state`'s initial).")]
    states: Annotated[
        dict[str, StateConfig],
        Meta(
            description="Every state by name (identifiers), in the order `cn_state` numbers them."
        ),
    ]
    priority: Annotated[
        list[str],
        Meta(
            description="Commands whose transitions are tried before every other transition "
            "of a state, in this order (ABORT-class: an ABORT wins over a timer or a data "
            "transition due in the same loop)."
        ),
    ] = msgspec.field(default_factory=lambda: ["ABORT"])


class ComponentConfig(_Struct):
    """A controller or a device: mission code placed on one node, with its
    own typed configuration."""

    name: Annotated[
        str,
        Meta(
            description="Unique among the section's names: `[a-z][a-z0-9_]*`. A controller's "
            "mode is the platform element `<name>_mode`."
        ),
    ]
    cls: Annotated[
        str,
        Meta(
            description="`package.module:ClassName`: a `zplatform.Controller` subclass for a "
            "controller, a `zplatform.Sensor` or `zplatform.Actuator` subclass for a device "
            "(built-ins: `zplatform.devices:DigitalOutput`, ...)."
        ),
    ] = msgspec.field(name="class")
    node: Annotated[
        str,
        Meta(
            description="Where it runs: `cn` or a device node for a controller, a device "
            "node for a device."
        ),
    ]
    rate_divisor: Annotated[
        int, Meta(ge=1, description="Its rate group: run every Nth loop of the node.")
    ] = 1
    rate_phase: Annotated[
        int,
        Meta(
            ge=0,
            description="Run in the loops where `loop % rate_divisor == rate_phase` (below "
            "`rate_divisor`).",
        ),
    ] = 0
    initial_mode: Annotated[
        Literal["enabled", "safed", "manual"],
        Meta(
            description="Controllers: the mode before the state machine's first action "
            "(`<name>_mode`'s initial value)."
        ),
    ] = "safed"
    config: Annotated[
        dict[str, Any],
        Meta(
            description="The class's own typed configuration, decoded into its `Config` "
            "struct: unknown keys and wrong types fail at load with their YAML path."
        ),
    ] = msgspec.field(default_factory=dict)


class CommandsConfig(_Struct):
    """Which operator commands each state accepts, which need ARM first, and
    what a WRITE may write. Commands: `NOOP`, `LAUNCH`, `ABORT`, `WRITE`,
    `HOLD`, `RESUME`, `ARM`, `PRM_SET`, `PRM_SAVE` (parameters: `params`). A
    request is checked in this order, the first failure giving its verdict:
    a known command, a number above the last (`REJECTED_REPLAY`), the
    state's whitelist (`REJECTED_NOT_ALLOWED`), an ARM just before a
    hazardous command, a protected WRITE or a hazardous parameter's PRM_SET
    (`REJECTED_NOT_ARMED`), a WRITE's element and value or a PRM_SET's
    parameter and value (`REJECTED_BAD_ARGUMENT`), a WRITE's states
    (`write_states`, `hazardous_outputs`: `REJECTED_NOT_ALLOWED`), then for PRM_SET the
    parameter's states (`REJECTED_PARAM_STATE`) and bounds
    (`REJECTED_OUT_OF_BOUNDS`), for PRM_SAVE a save still being written
    (`REJECTED_BUSY`)."""

    whitelist: Annotated[
        dict[str, list[str]],
        Meta(
            description="Per state, the commands it accepts (ARM and NOOP included); a "
            "state not listed accepts every command."
        ),
    ] = msgspec.field(default_factory=dict)
    hazardous: Annotated[
        list[str],
        Meta(
            description="Commands accepted only right after an accepted ARM numbered one "
            "less, within 10 s (`zplatform cmd MISSION launch --arm`); one ARM confirms "
            "one command."
        ),
    ] = msgspec.field(default_factory=list)
    writable: Annotated[
        list[str],
        Meta(
            description="The elements a WRITE may set; deny by default: an element not listed "
            "here is never written by a WRITE (`REJECTED_BAD_ARGUMENT`). Each is a scalar CN "
            "logic may write (the mission's own in `cn` and `cn_to_dnX`, controller modes, "
            "`cn_fault`), never a parameter (PRM_SET sets those), and never an element a "
            "transition of a state where it may be written reads (a WRITE must not fire a "
            "transition)."
        ),
    ] = msgspec.field(default_factory=list)
    write_states: Annotated[
        dict[str, list[str]],
        Meta(
            description="Per writable element, the states in which a WRITE may set it "
            "(the state's whitelist must allow WRITE too). An element not listed here may be "
            "written in every state whose whitelist allows WRITE; a hazardous output "
            "(`hazardous_outputs`) only in its own states."
        ),
    ] = msgspec.field(default_factory=dict)
    protected: Annotated[
        list[str] | None,
        Meta(
            description="Elements a WRITE may set only as a hazardous command (ARM n, then "
            "WRITE n+1). Default: every controller mode when the mission has hazardous "
            "commands, else none."
        ),
    ] = None


class HazardousOutputConfig(_Struct):
    """A hazardous output (an igniter, a motor, a valve): a scalar element a
    device node drives an actuator from, and the states in which it may be
    driven. The CN refuses a WRITE of it in any other state, and the device
    node holding it enforces the same rule on its own: it learns the
    vehicle's state from each authenticated trigger (`dnX_state`) and, in a
    state not listed, writes the output's `safe` value before its actuators
    run, counts it in `dnX_interlocked` and events it (at most once a
    second). A state-machine action may set it to anything but its safe
    value only in its states (checked at load)."""

    element: Annotated[
        str,
        Meta(
            description="The output's element: a scalar of region `cn_to_dnX` or `dnX_to_cn` "
            "of the device node that drives it (the mission's own, not a platform element)."
        ),
    ]
    states: Annotated[
        list[str],
        Meta(description="The states in which the output may be driven (unique state names)."),
    ]
    safe: Annotated[
        Scalar | None,
        Meta(
            description="The value the device node writes in every other state: fits the "
            "element. Default: `false`, 0 or the enum's first name."
        ),
    ] = None
    doc: Annotated[str, Meta(description="What the output drives.")] = ""


class ParamConfig(_Struct):
    """One mission parameter: a value the ground crew tunes without a rebuild
    (a controller gain, a target, a deployment altitude). Its value is a Data
    Vector element of region `cn` named after the parameter, so it travels in
    telemetry and is logged, recorded and replayed like any element;
    controllers read it each loop. It starts at `default`, or at the value the
    control node saved (PRM_SAVE) in its parameter file, and changes only by a
    PRM_SET command accepted in one of `states`, within `[min, max]`. A plain
    WRITE cannot change it, nor can a state-machine action."""

    name: Annotated[
        str,
        Meta(
            description="The parameter's name and its element's: `[a-z][a-z0-9_]*`, unique "
            "in the whole Data Vector (an element of that name is refused)."
        ),
    ]
    type: Annotated[
        str,
        Meta(
            description="A scalar type: `u8`, `u16`, `u32`, `u64`, `i8`, `i16`, `i32`, `i64`, "
            "`f32`, `f64`, `bool` (no arrays, no enums)."
        ),
    ]
    default: Annotated[
        int | float | bool,
        Meta(
            description="The value without a saved one (and in place of a saved one that is "
            "out of bounds): fits the type, within `[min, max]`, a finite number."
        ),
    ]
    min: Annotated[
        int | float | None,
        Meta(
            description="The lowest value PRM_SET may set; required for numbers, finite, "
            "fitting the type (not for `bool`)."
        ),
    ] = None
    max: Annotated[
        int | float | None,
        Meta(description="The highest value PRM_SET may set; as `min`, and `min <= max`."),
    ] = None
    units: Annotated[str, Meta(description="Units shown by the ground tools (`m`, `1/s`).")] = ""
    states: Annotated[
        list[str] | None,
        Meta(
            description="The states in which PRM_SET may change it (the whitelist must "
            "also allow PRM_SET there). Default: every state the whitelist allows."
        ),
    ] = None
    hazardous: Annotated[
        bool,
        Meta(
            description="PRM_SET of this parameter needs an accepted ARM numbered one less "
            "(ARM n, then PRM_SET n+1), like a hazardous command."
        ),
    ] = False
    doc: Annotated[
        str, Meta(description="What the parameter means; shown by the ground tools.")
    ] = ""


class DownlinkConfig(_Struct):
    """The radio downlink: telemetry packed into CCSDS space packets by the CN
    (APID per region, sequence counts, CRC-16), published on
    `{vehicle}/cn/downlink`; `zplatform ccsds` records and decodes them."""

    ccsds: Annotated[bool, Meta(description="Send the downlink.")] = False
    divisor: Annotated[int, Meta(ge=1, description="Downlink every Nth telemetry snapshot.")] = 10
    budget_bps: Annotated[
        Annotated[int, Meta(ge=1)] | None,
        Meta(
            description="Bytes per second the radio carries: snapshots over it are dropped "
            "whole, and counted. Default: no budget."
        ),
    ] = None
    max_data: Annotated[
        int,
        Meta(
            ge=64,
            le=65_536,
            description="Packet data field size (bytes); larger regions are segmented.",
        ),
    ] = 4096


class RecorderConfig(_Struct):
    """The on-board flight recorder (`zplatform.recorder`): each recording node
    keeps its own telemetry and events on its own storage, whatever the radio
    link does. The CN records every telemetry frame it publishes, a device node
    every reply frame it sends (its region), each with its events, in a ring of
    files under `DIR/<node>/`: when the ring is full, the oldest file is removed
    (counted in `<node>_rec_evicted`, with a `recorder_evicted` event). The loop
    only copies into a RAM buffer; a writer thread does the I/O, and a loop the
    buffer cannot take is dropped whole and counted (`<node>_rec_dropped`, a
    `recorder_dropping` event). Every record is checksummed, so a torn tail
    (kill -9, power loss) is detected and skipped by the reader, never misread.
    `zplatform log MISSION --from-recorder DIR --out CSV` reads a node's
    directory; the ground fills telemetry gaps from the CN's recorder over
    zenoh (`{vehicle}/cn/recorder`)."""

    dir: Annotated[
        str | None,
        Meta(
            description="Directory of the recorder files; node `X` writes `DIR/X/`. Relative to "
            "the mission file. Default: `zplatform/recorder/<mission>` in the state directory "
            "(`$XDG_STATE_HOME`, else `~/.local/state`; `/var/lib` for root). The environment "
            "variable `ZPLATFORM_RECORDER_DIR`, when set, replaces it (`$ZPLATFORM_RECORDER_DIR"
            "/<mission>/X/`): for tests and for a flight data partition."
        ),
    ] = None
    nodes: Annotated[
        list[str] | None,
        Meta(
            description="The nodes that record: `cn` and device nodes (the ground node has "
            "its own log). Default: the CN and every device node."
        ),
    ] = None
    max_bytes: Annotated[
        int,
        Meta(
            ge=128 * 1024,
            le=1 << 50,
            description="Most bytes a node's recorder directory holds (every file, earlier "
            "runs included); the oldest file is removed to stay within it. At least twice "
            "`file_bytes`.",
        ),
    ] = 256 * 1024 * 1024
    file_bytes: Annotated[
        int,
        Meta(
            ge=64 * 1024,
            le=1 << 30,
            description="Size of one file of the ring: a new file is started when the next "
            "record would not fit. Must hold several loops' records.",
        ),
    ] = 8 * 1024 * 1024
    fsync_ms: Annotated[
        Annotated[float, Meta(ge=0, le=3_600_000)] | None,
        Meta(
            description="Flush the file to the storage (fsync) at most this often (ms); 0: "
            "after every write; `null`: never (the operating system writes back when it "
            "wants). What was written survives a kill -9 of the node in any case; a power "
            "loss keeps everything up to the last fsync."
        ),
    ] = 1000.0
    buffer_ms: Annotated[
        float,
        Meta(
            ge=50,
            le=600_000,
            description="How long the storage may stall (ms of loops) before the recorder "
            "drops loops: sizes the RAM buffer between the loop and the writer thread.",
        ),
    ] = 2000.0
    serve_bps: Annotated[
        int,
        Meta(
            ge=10_000,
            le=1_000_000_000,
            description="Bytes per second the CN's recorder sends when the ground asks it for "
            "a telemetry gap (`{vehicle}/cn/recorder`): answered by a thread of its own, "
            "rate-limited so that no asker can starve the control loop.",
        ),
    ] = 2_000_000


class SecurityConfig(_Struct):
    """Authentication of every frame a node takes from the network, and of
    every peer that may open a link at all."""

    auth: Annotated[
        bool,
        Meta(
            description="Every region frame, telemetry snapshot, command request, clock-sync "
            "exchange and event record carries a 16-byte tag keyed per link (CN<->dnX, the "
            "ground's uplink, the telemetry downlink, each node's events); each host holds "
            "only its own links' keys, which never live in the YAML (key files from "
            "`zplatform keygen`, or the environment). Off only for benchmarks and closed "
            "test benches."
        ),
    ] = True
    transport: Annotated[
        Literal["auto", "mtls", "plain"],
        Meta(
            description="How the nodes' links are secured. `mtls`: every `tcp/` endpoint runs "
            "as `tls/` with mutual TLS and a zenoh access-control list keyed by each peer's "
            "certificate (its node name): a peer without a certificate from the mission's CA "
            "gets no session at all. The certificates live outside the mission, in a "
            "deployment file (`zplatform keygen MISSION` makes them; `up` does on first use). "
            "`plain`: unauthenticated links (frames are still tagged, `auth`); for closed "
            "benches and tests, and `zplatform check` warns when a mission with hazardous "
            "commands says so. `auto` (default): `mtls` when the mission has hazardous "
            "commands (`commands.hazardous`) or a `tls/` endpoint, else `plain`."
        ),
    ] = "auto"
    mac: Annotated[
        Literal["blake3", "hmac-sha256"],
        Meta(
            description="The tag's MAC: `blake3` (keyed BLAKE3, the default: about 3.5x "
            "faster than HMAC-SHA256 on large frames, bench/REPORT.md) or `hmac-sha256`. "
            "The name is part of every channel key (codecs/FORMAT.md §6.1), so every node "
            "of a mission must use the same one: a peer with another refuses each frame "
            "as a bad tag, saying so."
        ),
    ] = "blake3"


class FaultsConfig(_Struct):
    """Which errors after start are critical: a symptom that persists for N
    loops latches a fault in `cn_fault` (the first one only, until written
    back to `NONE`), for the state machine to answer (`cn_fault != NONE`).
    N = 0 turns a check off. Other errors are counted and reported as
    events, and the loop goes on."""

    dn_lost_loops: Annotated[
        int,
        Meta(ge=0, description="DN_LOST after a device node missed this many syncs in a row."),
    ] = 50
    controller_fail_loops: Annotated[
        int,
        Meta(
            ge=0,
            description="CONTROLLER_FAILED after a CN controller raised, or a device node's "
            "error count grew, in this many loops in a row.",
        ),
    ] = 3
    sync_overrun_loops: Annotated[
        int,
        Meta(
            ge=0,
            description="SYNC_OVERRUNS after this many loops in a row in which the sync "
            "overran its deadline.",
        ),
    ] = 10
    loop_overrun_loops: Annotated[
        int,
        Meta(
            ge=0,
            description="LOOP_OVERRUNS after this many loops in a row that overran the period.",
        ),
    ] = 0
    dn_watchdog_loops: Annotated[
        int,
        Meta(
            ge=1,
            le=1_000_000,
            description="A device node without a valid trigger for this many periods writes "
            "every actuator's safe value and the board's safe state (`dnX_safed`).",
        ),
    ] = 10
    dn_reenable_loops: Annotated[
        int,
        Meta(
            ge=1,
            le=1_000_000,
            description="A safed device node runs its devices again after this many valid "
            "triggers in a row.",
        ),
    ] = 10
    dn_rejoin_clears: Annotated[
        bool,
        Meta(
            description="Whether a latched DN_LOST clears when the lost device node answers "
            "again (a restarted node, a healed link) for `dn_reenable_loops` loops in a row, "
            "with a `dn_fault_cleared` event. A transition the fault already fired stays "
            "taken. Off (default): DN_LOST stays latched until an operator clears `cn_fault`."
        ),
    ] = False


STANDBY = "cn_b"
"""The node name of a mission's standby control node (docs/architecture.md#failover)."""


class FailoverConfig(_Struct):
    """A hot-standby control node, `cn_b` in `nodes` (docs/architecture.md#failover):
    it mirrors the commanding control node's whole Data Vector every loop and
    takes command, in a new term, when that one falls silent; each device node
    runs triggers of the highest term only. The section is optional with a
    `cn_b` node (the defaults below) and refused without one."""

    takeover_loops: Annotated[
        int,
        Meta(
            ge=1,
            le=1000,
            description="Loops without the commanding control node's mirror frame after "
            "which the standby asks the device nodes whether they still hear it (and takes "
            "command if none does). With the ask and the first loop of the new term it "
            "must end before the device nodes' watchdog: at most "
            "`faults.dn_watchdog_loops` - 3.",
        ),
    ] = 3
    lease_loops: Annotated[
        int,
        Meta(
            ge=1,
            le=1000,
            description="A device node follows a new term only after this many periods "
            "without a trigger of its current term (so a standby that is only cut off "
            "from a working control node never takes the vehicle from it). At most "
            "`takeover_loops`.",
        ),
    ] = 3


class HealthConfig(_Struct):
    """Each node's health in telemetry: CPU, memory, disk, temperature, loop
    lateness, overruns, garbage-collector pauses and the liveness of its
    threads, as platform elements `<node>_...` in `cn` (the CN) and
    `dnX_to_cn` (each DN), with limits; see zplatform.health. On by default
    at 1 Hz; `health: null` in the mission turns it off."""

    rate_hz: Annotated[
        float,
        Meta(
            ge=1,
            le=10,
            description="How often each node samples and reports its health (Hz); sampling "
            "runs on a thread of its own, the loop only copies the result.",
        ),
    ] = 2.0
    disk_path: Annotated[
        str,
        Meta(
            description="The directory whose free space is `<node>_disk_free_mb`: where the "
            "node logs (its flight recorder's directory, say). Relative paths are relative "
            "to the node's working directory."
        ),
    ] = "."
    deadlines_ms: Annotated[
        dict[str, Annotated[float, Meta(ge=10, le=600_000)]],
        Meta(
            description="Check-in deadline (ms) per thread name ("
            + ", ".join(f"`{n}`" for n in THREAD_NAMES)
            + "); a thread silent for longer is reported stalled. Defaults: `loop` 1000, "
            "`zenoh` and `health` three health periods (at least 2000), `clock` 3000, the "
            "rest 2000."
        ),
    ] = msgspec.field(default_factory=dict)
    limits: Annotated[
        dict[str, LimitsConfig],
        Meta(
            description="Yellow/red limits per health element, by its name after `<node>_` "
            "(`cpu_pct: {red: [null, 90]}`), for every node; a band given replaces the "
            "default band (`[null, null]` removes it)."
        ),
    ] = msgspec.field(default_factory=dict)


class HealthMetric(msgspec.Struct, frozen=True):
    """One health element (:mod:`zplatform.health`): its name after
    ``<node>_``, type, meaning and default limits (``per_period``: the limits
    are in loop periods)."""

    name: str
    type: str
    doc: str
    yellow: tuple[float | None, float | None] | None = None
    red: tuple[float | None, float | None] | None = None
    per_period: bool = False


HEALTH_METRICS: tuple[HealthMetric, ...] = (
    # sampled by the health thread, in this order (zplatform.health.SAMPLED)
    HealthMetric("cpu_pct", "f32", "the node process's CPU, % of one core", (None, 80), (None, 95)),
    HealthMetric("sys_cpu_pct", "f32", "the host's CPU, % of all cores", (None, 85), (None, 95)),
    HealthMetric("rss_mb", "f32", "the process's resident memory (MiB)", (None, 512), (None, 1024)),
    HealthMetric(
        "mem_free_mb", "f32", "the host's available memory (MiB)", (256, None), (64, None)
    ),
    HealthMetric(
        "disk_free_mb",
        "f32",
        "free disk where the node logs (health.disk_path, MiB)",
        (512, None),
        (64, None),
    ),
    HealthMetric(
        "cpu_temp_c",
        "f32",
        "the hottest CPU temperature (deg C); NaN: the host has no sensor",
        (None, 75),
        (None, 85),
    ),
    HealthMetric("health_seq", "u32", "samples the node's health thread has taken"),
    # measured by the loop, in this order (zplatform.health.LOOP_FIELDS)
    HealthMetric(
        "late_max_ms",
        "f32",
        "the loop's worst start lateness in the last health period (ms; default limits "
        "half a period, a period)",
        (None, 0.5),
        (None, 1.0),
        per_period=True,
    ),
    HealthMetric(
        "overruns_recent",
        "u32",
        "loops that overran their period in the last health period",
        (None, 0),
        (None, 10),
    ),
    HealthMetric(
        "gc_max_ms",
        "f32",
        "the longest garbage-collector pause in the last health period (ms)",
        (None, 2),
        (None, 5),
    ),
    HealthMetric("gc_count", "u32", "garbage collections in the last health period"),
    HealthMetric(
        "threads_stalled",
        "u16",
        "threads past their check-in deadline, bit i: "
        + ", ".join(f"{i} {n}" for i, n in enumerate(THREAD_NAMES)),
        None,
        (None, 0),
    ),
)
"""Every health element, in block order (:mod:`zplatform.health`)."""
_HEALTH_READINGS = 6  # the first six are readings: NaN until the first sample


def _health_limits(
    m: HealthMetric, period_ms: float, override: LimitsConfig | None
) -> dict[str, list[float | None]] | None:
    out: dict[str, list[float | None]] = {}
    for band in ("yellow", "red"):
        rng = getattr(override, band, None) if override is not None else None
        if rng is None:
            rng = getattr(m, band)
            if rng is not None and m.per_period:
                rng = tuple(None if x is None else x * period_ms for x in rng)
        if rng is not None and tuple(rng) != (None, None):
            out[band] = list(rng)
    return out or None


def health_elements(mission: Mission, node: str) -> list[dict[str, Any]]:
    """``node``'s health elements as ElementConfig-shaped dicts (``name``,
    ``type``, ``initial``, ``doc``, ``limits``), in block order; ``[]`` when
    the mission has no ``health:`` section. The readings start as NaN (no
    reading yet, inside every limit). Pure."""
    cfg = mission.health
    if cfg is None:
        return []
    period_ms = 1000.0 / mission.loop_hz
    out = []
    for i, m in enumerate(HEALTH_METRICS):
        e: dict[str, Any] = {"name": f"{node}_{m.name}", "type": m.type, "doc": m.doc}
        if i < _HEALTH_READINGS:
            e["initial"] = "nan"
        lim = _health_limits(m, period_ms, cfg.limits.get(m.name))
        if lim is not None:
            e["limits"] = lim
        out.append(e)
    return out


class MonitorConfig(_Struct):
    """A monitor (fault detection and response, as F Prime splits them): a
    condition on one element of the CN's Data Vector that, holding for
    `persistence` loops in a row, trips once and runs its response; it
    clears when the condition stops holding. Monitors run every loop on the
    CN, after the fault monitor and before the state machine, so a response
    takes effect in the loop it trips. See zplatform.monitors."""

    name: Annotated[str, Meta(description="Unique monitor name: `[a-z][a-z0-9_]*`.")]
    element: Annotated[
        str,
        Meta(
            description="Any scalar element of the CN's Data Vector (a DN's arrive one loop "
            "after the DN wrote them)."
        ),
    ]
    kind: Annotated[
        Literal["limit", "stale", "rate"],
        Meta(
            description="`limit`: the value is outside `[lo, hi]` or the element's `band`; "
            "`stale`: unchanged for `unchanged_loops` loops, or (a time stamp in ns, "
            "`dnX_time_ns`) older than `max_age_ms` in CN time; `rate`: its change per "
            "second over `window_loops` loops is outside `[lo, hi]`."
        ),
    ]
    lo: Annotated[
        float | None,
        Meta(description="`limit`, `rate`: the lowest value (per second for `rate`) allowed."),
    ] = None
    hi: Annotated[
        float | None,
        Meta(description="`limit`, `rate`: the highest value (per second for `rate`) allowed."),
    ] = None
    band: Annotated[
        Literal["yellow", "red"] | None,
        Meta(description="`limit`: use the element's own yellow or red limits instead of lo/hi."),
    ] = None
    unchanged_loops: Annotated[
        Annotated[int, Meta(ge=1, le=1_000_000)] | None,
        Meta(description="`stale`: trip when the value has not changed for this many loops."),
    ] = None
    max_age_ms: Annotated[
        Annotated[float, Meta(gt=0)] | None,
        Meta(
            description="`stale`: the element is a time stamp (ns, an integer); trip when it "
            "is older than this in CN time. Armed once the stamp first changes."
        ),
    ] = None
    window_loops: Annotated[
        int, Meta(ge=1, le=10_000, description="`rate`: the loops the change is taken over.")
    ] = 1
    persistence: Annotated[
        int,
        Meta(
            ge=1,
            le=1_000_000,
            description="Loops in a row the condition must hold before the monitor trips.",
        ),
    ] = 1
    states: Annotated[
        list[str] | None,
        Meta(
            description="The states in which the monitor runs (default: every state); outside "
            "them it neither trips nor clears, and its persistence count starts over."
        ),
    ] = None
    response: Annotated[
        Literal["event", "fault", "transition", "safe"],
        Meta(
            description="What tripping does (besides its event): `event` only "
            "(`monitor_warning`); `fault`: latch `fault` in `cn_fault`; `transition`: go "
            "to state `to` this loop (after a pending ABORT-class command's transition, "
            "before the state's others); `safe`: set controller `controller`'s mode to "
            "`safed`."
        ),
    ] = "event"
    fault: Annotated[
        str | None,
        Meta(description="`response: fault`: the fault to latch (default `MONITOR`)."),
    ] = None
    to: Annotated[str | None, Meta(description="`response: transition`: the target state.")] = None
    controller: Annotated[
        str | None, Meta(description="`response: safe`: the controller to safe.")
    ] = None
    doc: Annotated[str, Meta(description="What the monitor guards against.")] = ""


class WorldBoardConfig(_Struct):
    """One device node's board as the vehicle world sees it: its pin counts.

    At most 64 digital and 16 analog pins, the serial board protocol's
    limits, so any world board can also be served over the serial protocol
    for hardware in the loop (``world.serve_serial``)."""

    digital_pins: Annotated[
        int, Meta(ge=0, le=64, description="Digital pins of this node's board, from 0.")
    ] = 8
    analog_pins: Annotated[
        int, Meta(ge=0, le=16, description="Analog pins (volts) of this node's board, from 0.")
    ] = 8


class WorldConfig(_Struct):
    """The vehicle world (:mod:`zplatform.world`): one physical state that the
    boards of several device nodes read and drive.

    ``physics`` is a ``"module:function"`` called as ``function(world,
    t_ns)``; ``params`` its data (decoded into ``function.Params`` when it
    has one). ``boards``: the device nodes whose pins the world holds (a
    node uses one with ``board: {driver: world}``). Live, the world is its
    own process (``zplatform world MISSION``, started by ``up``) that
    advances on its own clock at ``rate_hz`` and sends every board its
    inputs each time, listening on ``listen`` (UDP, loopback only:
    simulation plumbing, not authenticated); a board whose newest inputs
    are older than ``stale_ms`` fails its step (the world is gone).
    ``serve_serial`` maps a node to a pty symlink path at which the world
    process plays that node's board firmware over the serial board protocol
    (hardware in the loop: the node's ``board`` is then ``driver: serial``
    with that ``port``)."""

    physics: Annotated[
        str,
        Meta(
            description="`package.module:function` called as `function(world, t_ns)`: reads "
            "every board's outputs (`world.boards[node].output_digital(pin)`) and sets what "
            "their inputs read (`inject_analog`, `inject_digital`)."
        ),
    ]
    boards: Annotated[
        dict[str, WorldBoardConfig],
        Meta(
            description="The device nodes whose pins the world holds, by node name; such a "
            "node's board is `{driver: world}` (or a serial board the world serves)."
        ),
    ]
    params: Annotated[
        dict[str, Any],
        Meta(
            description="The physics' data, read as `world.params`; decoded into the "
            "function's `Params` struct when it has one (a typo fails at load)."
        ),
    ] = msgspec.field(default_factory=dict)
    listen: Annotated[
        str,
        Meta(
            description="Loopback `host:port` (UDP) of the world process under `up`: "
            "simulation plumbing, not authenticated, so never beyond loopback."
        ),
    ] = "127.0.0.1:7479"
    rate_hz: Annotated[
        float,
        Meta(gt=0, le=10_000, description="How often the live world process advances (Hz)."),
    ] = 400.0
    stale_ms: Annotated[
        float,
        Meta(
            gt=0,
            le=10_000,
            description="A board whose newest inputs are older than this fails its step "
            "(the world process is gone).",
        ),
    ] = 100.0
    serve_serial: Annotated[
        dict[str, str],
        Meta(
            description="Node -> pty symlink path at which the world process plays that "
            "node's board firmware over the serial board protocol (hardware in the loop)."
        ),
    ] = msgspec.field(default_factory=dict)


# -- bulk channels (zplatform.bulk moves them) --------------------------------

BULK_HEADER_BYTES = 32  # see HEADER below
MAX_CHANNEL_BYTES = 1 << 30  # 1 GiB: a typo guard, not a zenoh limit
_BULK_NAME_RE = re.compile(r"^[a-z][a-z0-9_]*$")
_BULK_TYPE_RE = re.compile(r"^\s*([a-z0-9]+)\s*\[\s*([0-9]+(?:\s*,\s*[0-9]+)*)\s*\]\s*$")


class BulkChannelConfig(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True):
    """One bulk channel: a large array (a camera frame, a spectrum) that its
    owner publishes outside the 2 ms sync, through zenoh shared memory
    between the processes of one host (over the network across hosts). The
    owner's components fill `self.bulk[name]` and the runtime publishes it
    after the loop's logic; readers' components find the newest sample
    there. Per channel, counters go to telemetry
    (`bulk_<name>_published`, `_dropped` on the owner; `_shm`, `_copied`,
    `_missed`, `_bad` on each reader).
    """

    name: Annotated[str, Meta(description="Unique channel name: `[a-z][a-z0-9_]*`.")]
    node: Annotated[str, Meta(description="The node that owns (publishes) it.")]
    type: Annotated[
        str,
        Meta(
            description="A scalar type with a shape: `u8[4194304]`, `f32[1024,1024]` (at "
            "most 1 GiB)."
        ),
    ]
    readers: Annotated[
        list[str],
        Meta(description="The nodes that subscribe to it (not the owner)."),
    ] = msgspec.field(default_factory=list)
    rate_divisor: Annotated[int, Meta(ge=1, description="Publish every Nth loop of the owner.")] = 1
    rate_phase: Annotated[
        int,
        Meta(ge=0, description="Publish in the loops where `loop % rate_divisor == rate_phase`."),
    ] = 0
    alloc_timeout_ms: Annotated[
        float,
        Meta(
            ge=0,
            le=1000,
            description="How long a publish waits for a free shared-memory chunk before it "
            "counts a drop (ms).",
        ),
    ] = 1.0
    slots: Annotated[
        Annotated[int, Meta(ge=1, le=64)] | None,
        Meta(
            description="Chunks in the owner's pool for this channel. Default `1 + 2 * "
            "len(readers)`, at least 3: one being filled and, per reader, one held and one "
            "in flight."
        ),
    ] = None
    doc: Annotated[str, Meta(description="What the channel carries.")] = ""

    # -- derived (the config is checked before these are used) -------------
    @property
    def scalar(self) -> ScalarType:
        return _parse_or_raise(self.type, "$.bulk[?].type")[0]

    @property
    def shape(self) -> tuple[int, ...]:
        return _parse_or_raise(self.type, "$.bulk[?].type")[1]

    @property
    def dtype(self) -> str:
        """The little-endian numpy dtype string (``"<f4"``)."""
        return self.scalar.numpy

    @property
    def nbytes(self) -> int:
        """Array bytes (without the header)."""
        return self.scalar.size * math.prod(self.shape)

    @property
    def sample_bytes(self) -> int:
        """Bytes of one sample on the wire: header + array."""
        return BULK_HEADER_BYTES + self.nbytes

    @property
    def layout_id(self) -> int:
        """A stable hash of name, element type and shape: a reader built for
        another declaration refuses the sample instead of misreading it."""
        shape = ",".join(map(str, self.shape))
        return zlib.crc32(f"bulk:{self.name}:{self.scalar.name}[{shape}]".encode())

    @property
    def slot_count(self) -> int:
        return self.slots if self.slots is not None else max(3, 1 + 2 * len(self.readers))


def parse_bulk_type(text: str) -> tuple[ScalarType, tuple[int, ...]] | None:
    """``"f32[1024,1024]"`` -> ``(f32, (1024, 1024))``; ``None`` if invalid
    (no shape, unknown scalar, a zero dimension). Bulk arrays always have a
    shape: a scalar is a Data Vector element, not a bulk channel."""
    m = _BULK_TYPE_RE.match(text)
    if m is None:
        return None
    scalar = SCALAR_TYPES.get(m.group(1))
    if scalar is None:
        return None
    shape = tuple(int(d) for d in m.group(2).split(","))
    if any(d < 1 for d in shape):
        return None
    return scalar, shape


def _parse_or_raise(text: str, where: str) -> tuple[ScalarType, tuple[int, ...]]:
    parsed = parse_bulk_type(text)
    if parsed is None:
        raise ConfigError(
            f"bulk type {text!r} must be a scalar type with a shape, like 'u8[4194304]' "
            f"or 'f32[1024,1024]' (types: {', '.join(SCALAR_TYPES)})",
            where,
        )
    return parsed


def check_bulk_channels(
    channels: Sequence[BulkChannelConfig], nodes: Collection[str], where: str = "$.bulk"
) -> None:
    """Check the mission's ``bulk`` list against its ``nodes``.

    Raises :class:`ConfigError` naming the YAML path of the first bad field
    (``$.bulk[0].type``): a bad or duplicate name, an unknown owner or reader,
    the owner among its readers, a repeated reader, an invalid type or one
    larger than :data:`MAX_CHANNEL_BYTES`. Pure: touches no zenoh.
    """
    seen: set[str] = set()
    for i, ch in enumerate(channels):
        w = f"{where}[{i}]"
        if not _BULK_NAME_RE.match(ch.name):
            raise ConfigError(f"name {ch.name!r} must match {_BULK_NAME_RE.pattern}", f"{w}.name")
        if ch.name in seen:
            raise ConfigError(f"duplicate bulk channel name {ch.name!r}", f"{w}.name")
        seen.add(ch.name)
        if ch.node not in nodes:
            raise ConfigError(f"no node named {ch.node!r}; nodes: {sorted(nodes)}", f"{w}.node")
        scalar, shape = _parse_or_raise(ch.type, f"{w}.type")
        nbytes = scalar.size * math.prod(shape)
        if nbytes > MAX_CHANNEL_BYTES:
            raise ConfigError(
                f"{ch.type} is {nbytes} bytes; a bulk channel holds at most "
                f"{MAX_CHANNEL_BYTES} bytes",
                f"{w}.type",
            )
        if ch.rate_phase >= ch.rate_divisor:
            raise ConfigError(
                f"rate_phase {ch.rate_phase} must be below rate_divisor {ch.rate_divisor}",
                f"{w}.rate_phase",
            )
        readers: set[str] = set()
        for j, r in enumerate(ch.readers):
            if r not in nodes:
                raise ConfigError(
                    f"no node named {r!r}; nodes: {sorted(nodes)}", f"{w}.readers[{j}]"
                )
            if r == ch.node:
                raise ConfigError(
                    f"{r!r} owns channel {ch.name!r} and cannot also read it", f"{w}.readers[{j}]"
                )
            if r in readers:
                raise ConfigError(f"reader {r!r} is listed twice", f"{w}.readers[{j}]")
            readers.add(r)


def counter_elements(channels: Sequence[BulkChannelConfig], node: str) -> list[dict[str, Any]]:
    """The u32 Data Vector elements that carry ``node``'s bulk counters into
    telemetry, as ElementConfig-shaped dicts (``{"name", "type", "doc"}``).

    Owner of a channel: ``bulk_<ch>_published``, ``bulk_<ch>_dropped``.
    Reader: ``bulk_<ch>_shm``, ``bulk_<ch>_copied``, ``bulk_<ch>_missed``,
    ``bulk_<ch>_bad``. The names match :meth:`NodeBulk.counters`.
    """
    out: list[dict[str, Any]] = []
    for ch in channels:
        names: tuple[tuple[str, str], ...] = ()
        if ch.node == node:
            names = (("published", "samples sent"), ("dropped", "no free chunk in time"))
        elif node in ch.readers:
            names = (
                ("shm", "samples received through shared memory"),
                ("copied", "samples received copied (network or shm off)"),
                ("missed", "samples superseded or lost (seq gaps)"),
                ("bad", "samples refused (size or layout)"),
            )
        out += [
            {"name": f"bulk_{ch.name}_{n}", "type": "u32", "doc": f"{ch.name}: {d}"}
            for n, d in names
        ]
    return out


def counter_region(node: str) -> str | None:
    """The region that carries ``node``'s bulk counters to the CN's telemetry:
    ``cn`` for the CN, ``dnX_to_cn`` for a device node, ``None`` for the
    ground node (its counters stay local; ``zplatform tap`` shows its own)."""
    if node == "cn":
        return "cn"
    if node.startswith("dn"):
        return f"{node}_to_cn"
    return None


class Mission(_Struct):
    """A whole mission file: the nodes, the Data Vector, the state machine,
    controllers, devices and command rules. See `configs/*.yaml` for
    examples; every key below is checked at load, and an error names its
    YAML path."""

    mission: Annotated[
        str,
        Meta(
            description="The mission's name: its key set directory (`~/.config/zplatform/"
            "keys/<mission>/`, one key file per host role: `cn.keys`, `dn0.keys`, ..., "
            "`gn.keys`, `tool.keys`), its name while `up` runs (`zplatform ps`). At most 128 "
            "characters; no control characters, no `* $ ? # /`."
        ),
    ]
    nodes: Annotated[
        dict[str, NodeConfig],
        Meta(
            description="The zenoh peers by name: `cn`, the control node (required); device "
            "nodes `dn0`, `dn1`, ... numbered without gaps; `gn`, the ground node (optional); "
            "`cn_b`, a hot-standby control node (optional, `failover`)."
        ),
    ]
    regions: Annotated[
        dict[str, list[ElementConfig]],
        Meta(
            description="The mission's own Data Vector elements, per region. The nodes decide "
            "the regions: `cn` (the CN's own), `cn_to_dnX` (written by the CN, sent to dnX "
            "with each loop's trigger), `dnX_to_cn` (written by dnX, sent back in its reply), "
            "`gn_to_cn` (the ground's command requests). Every region needs at least one "
            "element. Platform elements are added; do not declare them."
        ),
    ]
    vehicle: Annotated[
        str,
        Meta(
            description="The first level of every zenoh key of the mission "
            "(`{vehicle}/cn/telemetry`): `[a-z][a-z0-9_]*`."
        ),
    ] = "rocket"
    loop_hz: Annotated[
        float,
        Meta(gt=0, le=10_000, description="The base loop rate of every node (Hz)."),
    ] = 100.0
    sync_timeout_ms: Annotated[
        float,
        Meta(
            gt=0,
            description="How long the CN waits each loop for the DNs' replies (ms), shorter "
            "than the loop period; a reply later than that is a miss (`cn_missed_dnX`).",
        ),
    ] = 2.0
    telemetry_divisor: Annotated[
        int, Meta(ge=1, description="The CN publishes telemetry every Nth loop.")
    ] = 1
    transport: TransportConfig = msgspec.field(default_factory=TransportConfig)
    clock: ClockConfig = msgspec.field(default_factory=ClockConfig)
    state_machine: Annotated[
        StateMachineConfig | None,
        Meta(description="The vehicle's states; without it the CN stays in state `IDLE`."),
    ] = None
    controllers: Annotated[
        list[ComponentConfig],
        Meta(description="The control logic: `zplatform.Controller` subclasses."),
    ] = msgspec.field(default_factory=list)
    devices: Annotated[
        list[ComponentConfig],
        Meta(description="Sensor and actuator drivers on the device nodes."),
    ] = msgspec.field(default_factory=list)
    commands: CommandsConfig = msgspec.field(default_factory=CommandsConfig)
    hazardous_outputs: Annotated[
        list[HazardousOutputConfig],
        Meta(
            description="Outputs that may be driven only in the states each names, enforced "
            "by the CN (WRITE) and by the device node holding each (its interlock)."
        ),
    ] = msgspec.field(default_factory=list)
    faults: FaultsConfig = msgspec.field(default_factory=FaultsConfig)
    security: SecurityConfig = msgspec.field(default_factory=SecurityConfig)
    downlink: DownlinkConfig = msgspec.field(default_factory=DownlinkConfig)
    recorder: Annotated[
        RecorderConfig | None,
        Meta(
            description="The on-board flight recorder: each vehicle node keeps its telemetry "
            "and events on local storage (`{}` turns it on with the defaults). Off when absent."
        ),
    ] = None
    bulk: Annotated[
        list[BulkChannelConfig],
        Meta(description="Bulk channels: large arrays moved outside the sync."),
    ] = msgspec.field(default_factory=list)
    params: Annotated[
        list[ParamConfig],
        Meta(
            description="Parameters the ground tunes without a rebuild (PRM_SET, saved by "
            "PRM_SAVE into the control node's parameter file and loaded at its start): "
            "each is an element of region `cn` named after it."
        ),
    ] = msgspec.field(default_factory=list)
    # Where the mission's own Python code is found: directories put at the
    # front of sys.path while the verbs that run flight code (check, sim, up,
    # node, replay) import its controllers, devices, boards and physics.
    pythonpath: Annotated[
        list[str] | None,
        Meta(
            description=(
                "Directories (relative to the mission file, or absolute) put at the "
                "front of Python's import path while the mission's code (controller, "
                "device, board and physics classes) is imported. Default: the mission "
                "file's own directory. Verbs that only talk to a running mission "
                "(cmd, tap, log, ground, xtce, ccsds) import no mission code."
            )
        ),
    ] = None
    world: Annotated[
        WorldConfig | None,
        Meta(
            description="One vehicle world shared by the boards of several device nodes "
            "(physics that every board's outputs change): see zplatform.world."
        ),
    ] = None
    health: Annotated[
        HealthConfig | None,
        Meta(
            description="Each node's health (CPU, memory, disk, temperature, loop timing, "
            "thread liveness) in telemetry. On by default at 1 Hz for every vehicle node; "
            "`health: null` turns it off (no health elements)."
        ),
    ] = msgspec.field(default_factory=lambda: HealthConfig(rate_hz=1.0))
    failover: Annotated[
        FailoverConfig | None,
        Meta(
            description="The hot-standby control node's takeover (only with a `cn_b` node; "
            "its defaults apply when the section is absent)."
        ),
    ] = None
    monitors: Annotated[
        list[MonitorConfig],
        Meta(description="Conditions on the CN's Data Vector and their responses."),
    ] = msgspec.field(default_factory=list)
    doc: Annotated[str, Meta(description="What the mission is for.")] = ""

    # -- derived views (cheap; computed from the checked fields) -----------
    @property
    def device_nodes(self) -> list[str]:
        """Device node names in index order (``dn0``, ``dn1``, ...)."""
        return sorted((n for n in self.nodes if _DN_RE.fullmatch(n)), key=lambda n: int(n[2:]))

    @property
    def has_ground(self) -> bool:
        return "gn" in self.nodes

    @property
    def standby(self) -> str | None:
        """The standby control node's name (``cn_b``), or None for a mission without one."""
        return STANDBY if STANDBY in self.nodes else None

    @property
    def control_nodes(self) -> list[str]:
        """The control nodes: ``cn``, then the standby ``cn_b`` if the mission has one."""
        return ["cn", STANDBY] if STANDBY in self.nodes else ["cn"]

    @property
    def takeover(self) -> FailoverConfig:
        """The failover settings (the defaults when the section is absent)."""
        return self.failover if self.failover is not None else FailoverConfig()

    @property
    def mtls(self) -> bool:
        """Whether the mission's links run mutual TLS (``security.transport``
        resolved: ``auto`` is mtls with hazardous commands or a ``tls/``
        endpoint). A loaded mission's endpoints are then all ``tls/``."""
        t = self.security.transport
        if t != "auto":
            return t == "mtls"
        return bool(self.commands.hazardous) or any(
            ep.startswith("tls/") for n in self.nodes.values() for ep in [*n.listen, *n.connect]
        )

    @property
    def recording_nodes(self) -> list[str]:
        """The nodes whose flight recorder runs (``recorder.nodes``, by default
        the CN and every device node); empty without a ``recorder`` section."""
        r = self.recorder
        if r is None:
            return []
        return list(r.nodes) if r.nodes is not None else [*self.control_nodes, *self.device_nodes]

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.loop_hz)

    @property
    def sync_timeout_ns(self) -> int:
        return round(self.sync_timeout_ms * 1e6)

    def region_names(self) -> list[str]:
        """Every region of the CN's Data Vector, in buffer order."""
        names = ["cn"]
        for dn in self.device_nodes:
            names += [f"cn_to_{dn}", f"{dn}_to_cn"]
        if self.has_ground:
            names.append("gn_to_cn")
        return names

    def node_regions(self, node: str) -> list[str]:
        """The regions held in ``node``'s Data Vector (thesis 4.3)."""
        if node == "cn" or (node == STANDBY and node in self.nodes):
            return self.region_names()
        if node == "gn":
            return ["gn_to_cn"]
        if node in self.nodes and _DN_RE.fullmatch(node):
            return [f"cn_to_{node}", f"{node}_to_cn"]
        raise ConfigError(f"no node named {node!r}; nodes: {sorted(self.nodes)}", "$.nodes")

    def element(self, name: str) -> tuple[str, ElementConfig]:
        """``(region, element config)`` of element ``name``; KeyError if absent."""
        for region, elements in self.regions.items():
            for e in elements:
                if e.name == name:
                    return region, e
        raise KeyError(name)


# ---------------------------------------------------------------------------
# loading


def parse_mission(text: bytes | str, source: str = "<string>") -> Mission:
    """Decode YAML text into a :class:`Mission`: schema, structural checks, platform elements.

    Raises :class:`ConfigError` naming the YAML path of the first bad field.
    Runs no semantic check (state machine, commands, controller and device
    classes): use :func:`zplatform.mission.decode_mission`, which calls this
    and then those, unless you are one of those checks.
    """
    try:
        raw = msgspec.yaml.decode(text)
    except msgspec.DecodeError as exc:
        raise ConfigError(f"{source}: not valid YAML: {exc}", "$") from exc
    if raw is None or raw == {}:
        raise ConfigError(f"{source}: mission config is empty", "$")
    _check_duplicate_keys(text)
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level", "$")
    try:
        mission = msgspec.convert(raw, type=Mission)
    except msgspec.ValidationError as exc:
        msg, _, where = str(exc).partition(" - at `")
        raise ConfigError(msg, _name_the_key(raw, where.rstrip("`") or "$")) from exc
    _check_mission(mission)
    # Structural checks of controllers/devices come before the platform
    # elements are added: a repeated controller name must be reported as
    # such, not as the repeated `<name>_mode` element it would create.
    _check_control_sections(mission)
    _check_recorder(mission)
    _check_params(mission)
    n_platform = _add_platform_elements(mission)
    _check_elements(mission, n_platform)
    return mission


def _keyed_sections() -> tuple[tuple[tuple[str, ...], Any], ...]:
    """The mappings of the schema keyed by user names, and their value types."""
    return (
        (("nodes",), NodeConfig),
        (("regions",), list[ElementConfig]),
        (("state_machine", "states"), StateConfig),
        (("commands", "whitelist"), list[str]),
        (("commands", "write_states"), list[str]),
    )


def _name_the_key(raw: dict[str, Any], where: str) -> str:
    """Replace msgspec's ``[...]`` (a key it does not name) with the key at fault.

    msgspec reports an error inside a ``dict`` value as ``$.nodes[...].cpu``;
    the user needs ``$.nodes.cn.cpu``. The values of that mapping are
    converted one by one, and the first that fails names the key (and the
    path inside it). Returns ``where`` unchanged when it cannot tell.
    """
    for keys, value_type in _keyed_sections():
        prefix = "$." + ".".join(keys)
        if not where.startswith(prefix + "[...]"):
            continue
        mapping: Any = raw
        for k in keys:
            mapping = mapping.get(k) if isinstance(mapping, dict) else None
        if not isinstance(mapping, dict):
            return where
        for key, value in mapping.items():
            try:
                msgspec.convert(value, type=value_type)
            except msgspec.ValidationError as exc:
                at = str(exc).partition(" - at `")[2].rstrip("`")
                return f"{prefix}.{key}{at[1:] if at.startswith('$') else ''}"
        return where
    return where


def _check_duplicate_keys(text: bytes | str) -> None:
    """Refuse a key given twice in one mapping (two regions ``cn:``, two
    ``name:`` in one element): YAML loaders silently keep the last one."""
    import yaml

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    root = yaml.compose(text, Loader=loader)  # already parsed once: no YAMLError here
    stack: list[tuple[yaml.Node, str]] = [(root, "$")] if root is not None else []
    seen_nodes: set[int] = set()  # aliases share nodes, and may even be recursive
    while stack:
        node, path = stack.pop()
        if id(node) in seen_nodes:
            continue
        seen_nodes.add(id(node))
        if isinstance(node, yaml.MappingNode):
            seen: set[object] = set()
            for k, v in node.value:
                key = k.value if isinstance(k, yaml.ScalarNode) else id(k)
                where = f"{path}.{key}"
                if key in seen:
                    raise ConfigError(
                        f"key {key!r} is given twice (line {k.start_mark.line + 1})", where
                    )
                seen.add(key)
                stack.append((v, where))
        elif isinstance(node, yaml.SequenceNode):
            stack += [(v, f"{path}[{i}]") for i, v in enumerate(node.value)]


def _unsafe_name_reason(name: str) -> str | None:
    """Why ``name`` cannot be a name (empty, control characters, key specials), or None."""
    if not name:
        return "is empty"
    for ch in name:
        if unicodedata.category(ch)[0] == "C":  # Cc control (NUL, \n), Cf, Cs, Co, Cn
            return f"contains the control character {ch!r}"
        if ch in _KEY_SPECIALS:
            return f"contains {ch!r}, which has a meaning in zenoh key expressions"
    return None


def check_mission_name(name: str) -> None:
    """Refuse a mission name that cannot name keys, files and registry
    entries (ConfigError at ``$.mission``): the rule every mission file's
    ``mission:`` obeys, for tools that take a bare name (``keygen``)."""
    why = _unsafe_name_reason(name)
    if why is not None:
        raise ConfigError(f"mission name {name!r} {why}", "$.mission")
    if len(name) > MISSION_NAME_MAX:
        raise ConfigError(
            f"mission name is {len(name)} characters long; at most {MISSION_NAME_MAX}",
            "$.mission",
        )


def resolve_pythonpath(entries: Sequence[str] | None, base_dir: str | Path | None) -> list[str]:
    """The absolute directories a mission's ``pythonpath`` names.

    Relative entries are relative to ``base_dir`` (the mission file's
    directory; None: the current directory). ``entries`` None (the key not
    given) means ``[base_dir]``, or nothing without a ``base_dir`` (a mission
    decoded from text). Pure: checks no directory.
    """
    if entries is None:
        return [] if base_dir is None else [os.path.abspath(base_dir)]
    base = os.path.abspath(base_dir if base_dir is not None else os.curdir)
    return [os.path.normpath(os.path.join(base, e)) for e in entries]


def relocate_mission(raw: dict[str, Any], source: str | Path) -> None:
    """Make a mission mapping read from file ``source`` mean the same from
    any other directory: its ``pythonpath`` (or the default, ``source``'s
    directory) and its recorder ``dir`` become absolute. For copies of a mission file (``up
    --free-ports``, a recording). A malformed ``pythonpath`` is left for the
    loader to refuse with its YAML path."""
    entries = raw.get("pythonpath")
    if entries is None or (isinstance(entries, list) and all(isinstance(e, str) for e in entries)):
        raw["pythonpath"] = resolve_pythonpath(entries, Path(source).parent)
    rec = raw.get("recorder")
    if isinstance(rec, dict) and isinstance(rec.get("dir"), str) and rec["dir"]:
        rec["dir"] = os.path.join(os.path.abspath(Path(source).parent), rec["dir"])


def _check_mission(m: Mission) -> None:
    check_mission_name(m.mission)
    for i, d in enumerate(m.pythonpath or ()):
        if not d or "\x00" in d:
            raise ConfigError(
                "a pythonpath entry must be a non-empty directory path", f"$.pythonpath[{i}]"
            )
    if not _NAME_RE.fullmatch(m.vehicle):
        raise ConfigError(
            f"vehicle key prefix must match {_NAME_RE.pattern}, got {m.vehicle!r}", "$.vehicle"
        )
    if not m.nodes:
        raise ConfigError("a mission needs at least the control node 'cn'", "$.nodes")
    if "cn" not in m.nodes:
        raise ConfigError("the control node 'cn' is missing", "$.nodes")
    for name in m.nodes:
        if name not in ("cn", "gn", STANDBY) and not _DN_RE.fullmatch(name):
            raise ConfigError(
                f"node name {name!r} is not one of cn, {STANDBY} (a standby control node), gn, "
                "dn0, dn1, ...",
                f"$.nodes.{name}",
            )
    _check_failover(m)
    dns = m.device_nodes
    if [int(d[2:]) for d in dns] != list(range(len(dns))):
        raise ConfigError(
            f"device nodes must be numbered dn0..dn{len(dns) - 1} without gaps, got {dns}",
            "$.nodes",
        )
    mtls = m.mtls  # before any endpoint is rewritten
    why = transport_reason(m)
    seen: dict[str, str] = {}
    for name, node in m.nodes.items():
        for i, ep in enumerate(node.listen):
            where = f"$.nodes.{name}.listen[{i}]"
            _check_endpoint(ep, where)
            ep = node.listen[i] = _link_endpoint(ep, mtls, why, where)
            if ep in seen:
                raise ConfigError(f"endpoint {ep!r} is also listened on by {seen[ep]}", where)
            seen[ep] = name
        for i, ep in enumerate(node.connect):
            where = f"$.nodes.{name}.connect[{i}]"
            _check_endpoint(ep, where)
            node.connect[i] = _link_endpoint(ep, mtls, why, where)
    if m.sync_timeout_ms * 1e6 >= m.period_ns:
        raise ConfigError(
            f"sync_timeout_ms {m.sync_timeout_ms} must be shorter than the loop period "
            f"({1000.0 / m.loop_hz:g} ms)",
            "$.sync_timeout_ms",
        )
    valid = set(m.region_names())
    for region, elements in m.regions.items():
        where = f"$.regions.{region}"
        if region not in valid:
            raise ConfigError(
                f"region {region!r} does not match the node topology; valid regions: "
                f"{m.region_names()}",
                where,
            )
        if not elements:
            raise ConfigError("a region must have at least one element", where)
    check_bulk_channels(m.bulk, m.nodes)


def _check_failover(m: Mission) -> None:
    """A `failover` section needs a standby; its takeover fits the DN watchdog."""
    if m.standby is None:
        if m.failover is not None:
            raise ConfigError(
                f"failover settings need a standby control node `{STANDBY}` in `nodes`",
                "$.failover",
            )
        return
    if not m.device_nodes:
        raise ConfigError(
            f"a standby control node ({STANDBY}) needs device nodes: they decide when it may "
            "take command (docs/architecture.md#failover)",
            f"$.nodes.{STANDBY}",
        )
    f = m.takeover
    if f.lease_loops > f.takeover_loops:
        raise ConfigError(
            f"lease_loops ({f.lease_loops}) must be at most takeover_loops "
            f"({f.takeover_loops}): the device nodes would refuse every takeover the standby "
            "asks for when it asks",
            "$.failover.lease_loops",
        )
    wd = m.faults.dn_watchdog_loops
    if f.takeover_loops + 3 > wd:
        raise ConfigError(
            f"takeover_loops ({f.takeover_loops}) plus the ask and the new term's first loop "
            f"must end before the device nodes' watchdog (faults.dn_watchdog_loops = {wd}): "
            f"at most {wd - 3}",
            "$.failover.takeover_loops",
        )
    if m.nodes[STANDBY].board:
        raise ConfigError("a control node has no board", f"$.nodes.{STANDBY}.board")
    for i, ch in enumerate(m.bulk):
        if ch.node in ("cn", STANDBY) or "cn" in ch.readers or STANDBY in ch.readers:
            raise ConfigError(
                f"bulk channel {ch.name!r} ends on a control node: a mission with a standby "
                "control node mirrors the Data Vector, not bulk arrays, so a takeover would "
                "lose it (keep bulk channels between device nodes)",
                f"$.bulk[{i}]",
            )


_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|unixsock-stream|ws)/(.+)$")


def _check_endpoint(ep: str, where: str) -> None:
    m = _ENDPOINT_RE.fullmatch(ep)
    if m is None:
        raise ConfigError(
            f"endpoint {ep!r} is not '<proto>/<address>' (e.g. tcp/10.0.0.1:7447)", where
        )
    if m.group(1) == "quic":
        # quic needs the same certificate settings as tls; zplatform's
        # deployment file (zplatform.deploy) is tested with tls/ only.
        raise ConfigError(
            f"endpoint {ep!r}: quic/ needs TLS certificate settings from a deployment file, "
            "which zplatform does not support for quic yet; use tcp/ (it runs as tls/ with "
            "mutual TLS under security.transport: mtls, see zplatform.deploy)",
            where,
        )
    # A tls/ endpoint is structurally fine here; its certificate settings come
    # from the deployment file, which the session reads (zplatform.deploy).
    if m.group(1) in ("tcp", "udp", "tls", "quic", "ws"):
        host, sep, port = m.group(2).rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise ConfigError(f"endpoint {ep!r} needs host:port with a port 0-65535", where)


def transport_reason(m: Mission) -> str:
    """Why the mission's links run mutual TLS, or plain (for messages):
    ``security.transport is auto and the mission has hazardous commands``."""
    if m.security.transport != "auto":
        return f"security.transport is {m.security.transport}"
    if not m.mtls:
        return "security.transport is auto and the mission has no hazardous command"
    return "security.transport is auto and the mission has " + (
        "hazardous commands" if m.commands.hazardous else "a tls/ endpoint"
    )


def _link_endpoint(ep: str, mtls: bool, why: str, where: str) -> str:
    """The endpoint a node actually uses under the mission's transport:
    ``tcp/`` runs as ``tls/`` under mtls (zplatform.deploy supplies the
    certificates); ConfigError for an endpoint that cannot (``udp/``, ``ws/``,
    a unix socket) or for ``tls/`` in a mission that says ``plain``."""
    proto = ep.partition("/")[0]
    if not mtls:
        if proto == "tls":
            raise ConfigError(
                f"endpoint {ep!r} is tls/, but security.transport is plain: say "
                "security.transport: mtls (or auto), or use tcp/",
                where,
            )
        return ep
    if proto == "tcp":
        return "tls/" + ep[4:]
    if proto == "tls":
        return ep
    raise ConfigError(
        f"endpoint {ep!r} cannot carry mutual TLS, which this mission's links run ({why}): "
        "use tcp/ (it runs as tls/), or say security.transport: plain on a closed network",
        where,
    )


BOARD_LINK_DRIVERS = ("serial", "gpiod")
"""The board drivers whose link a device node reports in ``dnX_board_*``:
the ones that talk to hardware outside the node's process (a serial port,
the kernel's GPIO lines). ``sim`` is the node's own memory, ``world`` is
simulation plumbing on loopback (and the lockstep runner swaps it for an
in-process port), and a team's ``package.module:Class`` promises no
:class:`~zplatform.boards.HealthCounters`: those add no elements, so their
missions keep their layout."""

BOARD_LINK_COUNTERS: tuple[tuple[str, str, str], ...] = (
    ("sent", "frames_sent", "frames {dn}'s board link sent (gpiod: I/O cycles)"),
    ("received", "frames_received", "frames {dn}'s board link received (gpiod: I/O cycles)"),
    ("timeouts", "timeouts", "steps of {dn}'s board that waited in vain for the inputs"),
    ("late", "late_replies", "answers from {dn}'s board after their step gave up"),
    ("bad_frames", "bad_frames", "frames from {dn}'s board refused (CRC, framing, shape)"),
    ("reconnects", "reconnects", "times {dn}'s board link was lost and opened again"),
    ("device_errors", "device_errors", "ERROR frames {dn}'s board sent (it refused a frame)"),
)
"""The ``dnX_board_<suffix>`` u32 counters: ``(suffix, HealthCounters
attribute, doc)``, in layout order after ``dnX_board_ok``. Counters a driver
does not keep (gpiod has no link to time out) stay 0."""


def board_link_elements(m: Mission, dn: str) -> list[ElementConfig]:
    """Device node ``dn``'s board link elements (``dnX_to_cn``), or ``[]``
    when its board's driver is not one of :data:`BOARD_LINK_DRIVERS`.

    ``dnX_board_ok`` (bool): the board's step succeeded in dnX's last run;
    then one u32 per :data:`BOARD_LINK_COUNTERS`, the board's own count,
    saturating at the type's maximum. Written by the node's loop
    (:class:`~zplatform.loop.DeviceLogic`) after each step. Pure: it reads
    only the mission's config, never a board."""
    if m.nodes[dn].board.get("driver", "sim") not in BOARD_LINK_DRIVERS:
        return []
    E = ElementConfig
    return [
        E(f"{dn}_board_ok", "bool", False, doc=f"{dn}'s board step succeeded in its last run"),
        *(E(f"{dn}_board_{s}", "u32", 0, doc=d.format(dn=dn)) for s, _, d in BOARD_LINK_COUNTERS),
    ]


def interlocked_nodes(m: Mission) -> list[str]:
    """The device nodes that hold a hazardous output (``hazardous_outputs``:
    an element of their ``cn_to_dnX`` or ``dnX_to_cn``), in index order:
    the ones whose triggers carry the CN's state (``dnX_state``) and that
    count what their interlock refused (``dnX_interlocked``). Pure."""
    wanted = {h.element for h in m.hazardous_outputs}
    if not wanted:
        return []
    return [
        dn
        for dn in m.device_nodes
        if any(
            e.name in wanted for r in (f"cn_to_{dn}", f"{dn}_to_cn") for e in m.regions.get(r, ())
        )
    ]


def platform_elements(m: Mission) -> dict[str, list[ElementConfig]]:
    """The elements every mission has (docs/architecture.md#data-vector), per region."""
    states = list(m.state_machine.states) if m.state_machine else ["IDLE"]
    initial = m.state_machine.initial if m.state_machine else "IDLE"
    E = ElementConfig
    cn = [
        E("cn_loop", "u64", 0, doc="loop number, from 1"),
        E("cn_time_ns", "i64", 0, doc="the loop's scheduled start, CN time (ns)"),
        E("cn_state", "enum", initial, states, doc="the state machine's state"),
        E("cn_loop_overruns", "u32", 0, doc="loops that overran their period"),
        E("cn_sync_overruns", "u32", 0, doc="loops whose sync passed the deadline"),
        E("cn_errors", "u32", 0, doc="non-critical errors counted"),
        E("cn_last_error", "u16", 0, doc="code of the last non-critical error"),
        E("cn_bad_frames", "u32", 0, doc="frames refused (shape, layout, tag)"),
        E("cn_cmd", "enum", "NONE", list(CMD_NAMES), doc="the accepted command, until taken"),
        E("cn_cmd_seq", "u64", 0, doc="number of the last request judged"),
        E("cn_cmd_status", "enum", "NONE", list(CMD_STATUS_NAMES), doc="its verdict"),
        E("cn_cmd_rejects", "u32", 0, doc="requests refused without a number"),
        E(
            "cn_cmd_reject_status",
            "enum",
            "NONE",
            list(CMD_STATUS_NAMES),
            doc="why the last of those was refused",
        ),
        E(
            "cn_cmd_reject_seq",
            "u64",
            0,
            doc="number of the last authenticated request refused that way (0: unknown)",
        ),
        E("cn_cmd_dropped", "u32", 0, doc="requests dropped by a full inbox"),
        E("cn_epoch", "u64", 0, doc="this run of the CN; requests must carry it"),
        E("cn_fault", "enum", "NONE", list(FAULT_NAMES), doc="the latched fault"),
        E("cn_time_in_state_ns", "i64", 0, doc="time in the current state (ns)"),
    ]
    if m.params:
        # The parameters and their store's state (zplatform.params).
        cn += [
            E(p.name, p.type, p.default, doc=p.doc or f"parameter {p.name}") for p in m.params
        ] + [
            E(
                "cn_prm_load_status",
                "enum",
                "DEFAULTS",
                list(PRM_LOAD_NAMES),
                doc="what the start made of the parameter file",
            ),
            E("cn_prm_save_seq", "u64", 0, doc="number of the last PRM_SAVE accepted"),
            E(
                "cn_prm_save_status",
                "enum",
                "NONE",
                list(PRM_SAVE_NAMES),
                doc="that save: pending, saved or failed",
            ),
            E("cn_prm_unsaved", "bool", False, doc="a PRM_SET since the last load or save"),
        ]
    if m.standby is not None:
        # A redundant mission (docs/architecture.md#failover): who commands in
        # which term, and the command handler's and state machine's state that
        # a standby must mirror to continue exactly where the other left off.
        cn += [
            E(
                "cn_term",
                "u32",
                1,
                doc="the term in command, raised by every takeover (with a standby, `cn_b`; "
                "so are the next six)",
            ),
            E("cn_commander", "enum", "cn", m.control_nodes, doc="the control node in command"),
            E("cn_term_loop", "u64", 0, doc="the loop this term began (0: the first term)"),
            E(
                "cn_standby_ready",
                "bool",
                False,
                doc="the other control node is alive and mirrors this one",
            ),
            E("cn_arm_seq", "u64", 0, doc="number of the last ARM accepted (0: none)"),
            E("cn_arm_t_ns", "i64", 0, doc="its loop time (ns)"),
            E("cn_holding", "bool", False, doc="a HOLD is in effect"),
        ]
    for dn in m.device_nodes:
        cn += [
            E(f"cn_rx_{dn}", "u32", 0, doc=f"replies from {dn} applied"),
            E(f"cn_missed_{dn}", "u32", 0, doc=f"loops without {dn}'s reply in time"),
            E(f"cn_late_{dn}", "u32", 0, doc=f"replies from {dn} for an older loop"),
        ]
    out: dict[str, list[ElementConfig]] = {"cn": cn}
    for dn in m.device_nodes:
        # Set by the CN in the trigger of its planned last loop: the DN then
        # safes its actuators as the run's end, not as a lost control node.
        out[f"cn_to_{dn}"] = [E(f"{dn}_final", "bool", False)]
        if m.standby is not None:  # the term of the control node that sent the trigger
            out[f"cn_to_{dn}"].append(
                E(f"{dn}_term", "u32", 1, doc="the term of the trigger (with a standby)")
            )
        interlocked = dn in interlocked_nodes(m)
        if interlocked:  # what the DN's interlock judges its hazardous outputs by
            out[f"cn_to_{dn}"].append(
                E(
                    f"{dn}_state",
                    "enum",
                    initial,
                    states,
                    doc="the CN's state when it sent the trigger (with a hazardous output)",
                )
            )
        out[f"{dn}_to_cn"] = [
            E(f"{dn}_loop", "u64", 0, doc=f"the CN loop {dn} last ran"),
            E(f"{dn}_time_ns", "i64", 0, doc=f"{dn}'s time of that loop (ns)"),
            E(f"{dn}_loop_overruns", "u32", 0, doc=f"{dn}'s loops that overran"),
            E(f"{dn}_errors", "u32", 0, doc=f"{dn}'s non-critical errors"),
            E(f"{dn}_bad_frames", "u32", 0, doc=f"triggers {dn} refused"),
            E(f"{dn}_clock_offset_ns", "i64", 0, doc=f"{dn}'s clock correction (ns)"),
            E(f"{dn}_clock_drift_ns", "i64", 0, doc=f"{dn}'s clock error at the last re-sync"),
            E(f"{dn}_safed", "bool", False, doc=f"{dn} safed its actuators (why: next)"),
            E(
                f"{dn}_safed_why",
                "enum",
                "NONE",
                list(SAFED_WHY_NAMES),
                doc=f"why {dn} safed: CN_LOST, RUN_ENDED, CANNOT_RUN (a fault), STOPPING",
            ),
            E(
                f"{dn}_clock_refused",
                "u32",
                0,
                doc=f"clock replies and estimates {dn} refused (bad tag, replayed, a jump)",
            ),
            E(
                f"{dn}_clock_timeouts",
                "u32",
                0,
                doc=f"clock exchanges of {dn} left unanswered (a silent or slow clock)",
            ),
        ]
        if m.standby is not None:
            out[f"{dn}_to_cn"].append(
                E(
                    f"{dn}_term_seen",
                    "u32",
                    0,
                    doc=f"the highest term {dn} ran or promised (with a standby)",
                )
            )
        if interlocked:
            out[f"{dn}_to_cn"].append(
                E(
                    f"{dn}_interlocked",
                    "u32",
                    0,
                    doc=f"hazardous outputs {dn} drove safe in a state not theirs "
                    "(one per output and loop)",
                )
            )
        # Its board's link, for a board that has one (BOARD_LINK_DRIVERS):
        # an operator sees timeouts and reconnects as they happen.
        out[f"{dn}_to_cn"] += board_link_elements(m, dn)
    if m.has_ground:
        out["gn_to_cn"] = [
            E("gn_cmd", "enum", "NONE", list(CMD_NAMES), doc="the requested command"),
            E("gn_cmd_seq", "u64", 0, doc="the request's number: above the last"),
            E("gn_cmd_epoch", "u64", 0, doc="the CN run it is for (`cn_epoch`)"),
            E("gn_cmd_element", "u16", 0, doc="WRITE, PRM_SET: the element's index"),
            E("gn_cmd_value", "f64", 0.0, doc="WRITE, PRM_SET: the value"),
        ]
    # A controller's mode lives where its node reads it: in `cn` for CN
    # controllers, in `cn_to_dnX` for DN controllers (the CN's state machine
    # writes it, the sync protocol carries it down).
    for i, c in enumerate(m.controllers):
        region = "cn" if c.node == "cn" else f"cn_to_{c.node}"
        if region not in out:
            raise ConfigError(
                f"controller {c.name!r} is placed on {c.node!r}, which is not a cn or device node",
                f"$.controllers[{i}].node",
            )
        out[region].append(
            E(
                f"{c.name}_mode",
                "enum",
                c.initial_mode,
                list(CONTROLLER_MODES),
                doc=f"controller {c.name}'s mode",
            )
        )
        if region == "cn" and m.standby is not None:
            # Controller.enabled_at_ns, mirrored so a takeover keeps it.
            out[region].append(
                E(
                    f"{c.name}_enabled_ns",
                    "i64",
                    0,
                    doc=f"when controller {c.name} was last enabled (ns; with a standby)",
                )
            )
    # Bulk channel counters live where their node reports them.
    for node in m.nodes:
        counters_at = counter_region(node)
        if counters_at is not None and counters_at in out:
            out[counters_at] += [msgspec.convert(e, E) for e in counter_elements(m.bulk, node)]
    # Flight recorder counters, where the recording node reports them.
    for node in m.recording_nodes:
        at = counter_region(node)
        if at is not None and at in out:
            out[at] += [
                E(f"{node}_rec_dropped", "u32", 0, doc=f"loops {node}'s recorder could not keep"),
                E(f"{node}_rec_evicted", "u32", 0, doc=f"files {node}'s recorder ring removed"),
                E(f"{node}_rec_errors", "u32", 0, doc=f"{node}'s recorder storage errors"),
            ]
    # Health, last: one contiguous block per node (zplatform.health), only
    # in a mission with a `health:` section.
    for node in ["cn", *m.device_nodes]:
        out["cn" if node == "cn" else f"{node}_to_cn"] += [
            msgspec.convert(e, E) for e in health_elements(m, node)
        ]
    return out


def _add_platform_elements(m: Mission) -> dict[str, int]:
    """Prepend the platform elements; returns how many each region got."""
    platform = platform_elements(m)
    regions: dict[str, list[ElementConfig]] = {}
    for region in m.region_names():
        regions[region] = platform.get(region, []) + list(m.regions.get(region, []))
    m.regions = regions
    return {region: len(elements) for region, elements in platform.items()}


def element_spec(e: ElementConfig) -> tuple[ScalarType, int]:
    """``(scalar type, array count)`` of a checked element (enum -> its int)."""
    if e.type == "enum":
        n = len(e.enum or ())
        return SCALAR_TYPES["u8" if n <= 256 else "u16"], 0
    parsed = parse_type(e.type)
    assert parsed is not None, "element_spec on an unchecked element"
    return parsed


def _element_path(m: Mission, region: str, i: int, n_platform: int, name: str) -> str:
    """The YAML path of the ``i``-th element of a region after platform elements
    were prepended: the index the user wrote, or where a platform element
    comes from (``cn_state`` from the state machine, ``<c>_mode`` from a
    controller, ``dnX_board_*`` from the node's board)."""
    if i >= n_platform:
        return f"$.regions.{region}[{i - n_platform}]"
    if name == "cn_state":
        return "$.state_machine"
    if any(p.name == name for p in m.params):
        return _param_path(m, name)
    dn = region.removesuffix("_to_cn")
    if dn != region and name.startswith(f"{dn}_board_"):
        return f"$.nodes.{dn}.board"
    if m.health is not None and any(name.endswith(f"_{t.name}") for t in HEALTH_METRICS):
        return "$.health"
    for j, c in enumerate(m.controllers):
        if name == f"{c.name}_mode":
            return f"$.controllers[{j}]"
    return f"$.regions.{region}"


def _param_path(m: Mission, name: str) -> str:
    """The YAML path of parameter ``name`` (``$.params[i]``)."""
    return f"$.params[{next(j for j, p in enumerate(m.params) if p.name == name)}]"


def _check_params(m: Mission) -> None:
    """Structural checks of ``params`` (each entry alone): name, a scalar
    type, bounds for numbers (finite, fitting the type, in order), a default
    that fits and lies within them. States and the whitelist are checked by
    :func:`zplatform.params.check_config`."""
    names: set[str] = set()
    for i, p in enumerate(m.params):
        w = f"$.params[{i}]"
        if not _NAME_RE.fullmatch(p.name):
            raise ConfigError(
                f"parameter name {p.name!r} must match {_NAME_RE.pattern}", f"{w}.name"
            )
        if p.name in names:
            raise ConfigError(f"duplicate parameter name {p.name!r}", f"{w}.name")
        names.add(p.name)
        st = SCALAR_TYPES.get(p.type)
        if st is None:
            raise ConfigError(
                f"parameter type {p.type!r} is not a scalar type; expected one of "
                f"{', '.join(SCALAR_TYPES)}",
                f"{w}.type",
            )
        if st.kind == "bool":
            for key in ("min", "max"):
                if getattr(p, key) is not None:
                    raise ConfigError("a bool parameter has no bounds", f"{w}.{key}")
            if not isinstance(p.default, bool):
                raise ConfigError(f"expected true or false, got {p.default!r}", f"{w}.default")
            continue
        for key in ("min", "max", "default"):
            v = getattr(p, key)
            if v is None:
                raise ConfigError(
                    f"a {p.type} parameter needs `{key}`: PRM_SET may set only values "
                    "within [min, max]",
                    f"{w}.{key}",
                )
            not_finite = isinstance(v, float) and not math.isfinite(v)
            if isinstance(v, bool) or not_finite or not st.fits(v):
                rng = f" (range {st.lo}..{st.hi})" if st.kind == "int" else ""
                raise ConfigError(f"{v!r} is not a finite {p.type}{rng}", f"{w}.{key}")
        assert p.min is not None and p.max is not None
        if p.min > p.max:
            raise ConfigError(f"min {p.min!r} is above max {p.max!r}", f"{w}.min")
        if not p.min <= p.default <= p.max:
            raise ConfigError(
                f"default {p.default!r} is outside [{p.min!r}, {p.max!r}]", f"{w}.default"
            )


def _check_elements(m: Mission, n_platform: dict[str, int]) -> None:
    seen: dict[str, tuple[str, str]] = {}
    vector_bytes = 0
    for region, elements in m.regions.items():
        n = n_platform.get(region, 0)
        region_bytes = 0
        for i, e in enumerate(elements):
            where = _element_path(m, region, i, n, e.name)
            if not _NAME_RE.fullmatch(e.name):
                raise ConfigError(
                    f"element name {e.name!r} must match {_NAME_RE.pattern}", f"{where}.name"
                )
            if e.name in seen and any(p.name == e.name for p in m.params):
                raise ConfigError(
                    f"parameter {e.name!r} has the name of an element; a parameter is an "
                    "element of its own (region cn): rename one of them",
                    f"{_param_path(m, e.name)}.name",
                )
            if e.name in seen:
                first_region, first_where = seen[e.name]
                # Blame the element the user declared: when this one is a
                # platform element, the user's earlier one is the culprit.
                culprit = first_where if i < n else where
                raise ConfigError(
                    f"duplicate element name {e.name!r} (also in region "
                    f"{first_region if culprit == where else region!r}; "
                    "platform elements are added automatically, do not declare them)",
                    f"{culprit}.name",
                )
            seen[e.name] = (region, where)
            _check_element_type(e, where)
            # Sizes before initial values: `u8[99999999999]` must fail here
            # with its path, not in a list of that many initial values.
            st, count = element_spec(e)
            size = st.size * max(count, 1)
            region_bytes += size
            vector_bytes += size
            if region_bytes > MAX_REGION_BYTES:
                raise ConfigError(
                    f"region {region!r} grows to {region_bytes} bytes with element {e.name!r}; "
                    f"a region holds at most {MAX_REGION_BYTES} bytes (256 MiB)",
                    f"{where}.type",
                )
            if vector_bytes > MAX_VECTOR_BYTES:
                raise ConfigError(
                    f"the control node's Data Vector (every region) grows to {vector_bytes} "
                    f"bytes with element {e.name!r}; at most {MAX_VECTOR_BYTES} bytes (256 MiB)",
                    f"{where}.type",
                )
            e.initial = _check_initial(e, where)


def _check_element_type(e: ElementConfig, where: str) -> None:
    if e.type == "enum" and e.enum is None:
        raise ConfigError(
            f"element {e.name!r} needs a `type` ({', '.join(SCALAR_TYPES)}, an array like "
            "'f32[3]') or a list of `enum` names",
            f"{where}.type",
        )
    if e.type == "enum" or e.enum is not None:
        if not e.enum:
            raise ConfigError("an enum needs a non-empty list of names in `enum`", f"{where}.enum")
        if e.type != "enum":
            parsed = parse_type(e.type)
            if parsed is None or parsed[0].kind != "int" or parsed[1] != 0:
                raise ConfigError(
                    f"an element with `enum` names must have type 'enum', got {e.type!r}",
                    f"{where}.type",
                )
            e.type = "enum"
        names = e.enum
        for j, n in enumerate(names):
            if not _ENUM_NAME_RE.fullmatch(n):
                raise ConfigError(f"enum name {n!r} is not an identifier", f"{where}.enum[{j}]")
        if len(set(names)) != len(names):
            raise ConfigError(f"enum names repeat: {names}", f"{where}.enum")
        if len(names) > 65536:
            raise ConfigError("an enum holds at most 65536 names", f"{where}.enum")
        return
    parsed = parse_type(e.type)
    if parsed is None:
        raise ConfigError(
            f"invalid element type {e.type!r}; expected one of "
            f"{', '.join(SCALAR_TYPES)}, an array like 'f32[3]', or 'enum'",
            f"{where}.type",
        )
    if parsed[1] > MAX_ARRAY_COUNT:
        raise ConfigError(
            f"array {e.type!r} has {parsed[1]} items; an array holds at most "
            f"{MAX_ARRAY_COUNT} (16 Mi)",
            f"{where}.type",
        )


def _coerce_scalar(st: ScalarType, v: object, where: str, enum: list[str] | None) -> Scalar:
    if enum is not None:
        if isinstance(v, str):
            if v not in enum:
                raise ConfigError(f"{v!r} is not one of the enum names {enum}", where)
            return enum.index(v)
        if isinstance(v, int) and not isinstance(v, bool) and 0 <= v < len(enum):
            return v
        raise ConfigError(f"expected one of the enum names {enum}, got {v!r}", where)
    if st.kind == "float" and isinstance(v, str):
        # YAML has no literal for nan/inf in flow style everyone writes; accept
        # the spelled-out names and nothing else (a "1.5" string is a typo).
        # PyYAML (YAML 1.1) also reads an exponent without a dot (`1e-3`) as
        # a string: accept that form too, then range-check it like a number.
        word = v.strip().lower()
        if word in _FLOAT_WORDS:
            return float(v)
        if not _EXP_FLOAT_RE.match(word):
            raise ConfigError(f"expected a number for {st.name}, got {v!r}", where)
        v = float(word)
    if not st.fits(v):
        if st.kind == "int":
            raise ConfigError(
                f"initial value {v!r} does not fit {st.name} (range {st.lo}..{st.hi})", where
            )
        raise ConfigError(f"initial value {v!r} does not fit {st.name}", where)
    if st.kind == "bool":
        return bool(v)
    if st.kind == "int":
        assert isinstance(v, int | float)
        return int(v)
    assert isinstance(v, int | float)
    return float(v)


def _check_initial(e: ElementConfig, where: str) -> Value:
    st, count = element_spec(e)
    v = e.initial
    w = f"{where}.initial"
    if v is None:
        v = 0 if e.enum else (False if st.kind == "bool" else (0.0 if st.kind == "float" else 0))
        return [v] * count if count else v
    if count == 0:
        if isinstance(v, list):
            raise ConfigError(f"a scalar {e.type} element needs a scalar initial value", w)
        return _coerce_scalar(st, v, w, e.enum)
    if isinstance(v, list):
        if len(v) != count:
            raise ConfigError(f"expected {count} initial values for {e.type}, got {len(v)}", w)
        return [_coerce_scalar(st, x, f"{w}[{j}]", None) for j, x in enumerate(v)]
    return [_coerce_scalar(st, v, w, None)] * count


def _check_recorder(m: Mission) -> None:
    """The recorder's nodes exist and record, and its ring holds two files."""
    r = m.recorder
    if r is None:
        return
    if r.dir is not None and (not r.dir or "\x00" in r.dir):
        raise ConfigError("the recorder directory must be a non-empty path", "$.recorder.dir")
    for i, n in enumerate(r.nodes or ()):
        if n not in m.nodes or n == "gn":
            raise ConfigError(
                f"{n!r} is not the control node or a device node of this mission "
                "(the ground node keeps its own log)",
                f"$.recorder.nodes[{i}]",
            )
    if r.nodes is not None and len(set(r.nodes)) != len(r.nodes):
        raise ConfigError("a node is listed twice", "$.recorder.nodes")
    if r.max_bytes < 2 * r.file_bytes:
        raise ConfigError(
            f"max_bytes ({r.max_bytes}) must hold at least two files of file_bytes "
            f"({r.file_bytes}): the ring removes the oldest file to start a new one",
            "$.recorder.max_bytes",
        )


def _check_control_sections(m: Mission) -> None:
    """Structural checks of the control sections; semantic checks that need
    the whole Data Vector are done by the owning modules' ``check_config``
    (run by :func:`zplatform.mission.check_mission` afterwards)."""
    for section in ("controllers", "devices"):
        names: set[str] = set()
        for i, c in enumerate(getattr(m, section)):
            where = f"$.{section}[{i}]"
            if not _NAME_RE.fullmatch(c.name):
                raise ConfigError(f"name {c.name!r} must match {_NAME_RE.pattern}", f"{where}.name")
            if c.name in names:
                raise ConfigError(f"duplicate {section[:-1]} name {c.name!r}", f"{where}.name")
            names.add(c.name)
            if c.node not in m.nodes or c.node in ("gn", STANDBY):
                raise ConfigError(
                    f"{section[:-1]} {c.name!r} is placed on {c.node!r}; "
                    "expected cn or a device node"
                    + (
                        " (the standby runs cn's controllers when it commands)"
                        if c.node == STANDBY
                        else ""
                    ),
                    f"{where}.node",
                )
            if section == "devices" and c.node == "cn":
                raise ConfigError("devices run on device nodes only", f"{where}.node")
            if ":" not in c.cls:
                raise ConfigError(
                    f"class {c.cls!r} must be 'package.module:ClassName'", f"{where}.class"
                )
