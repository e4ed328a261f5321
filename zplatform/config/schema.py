"""The mission file's types: YAML decoded into typed structs (``msgspec.Struct``).

The :class:`Mission` struct tree, every key with its description (what
:mod:`zplatform.mission.schema` turns into the mission reference), with
``forbid_unknown_fields`` so a typo fails at decode, and the size limits that
keep a mission from exhausting memory (:data:`MAX_ARRAY_COUNT`,
:data:`MAX_REGION_BYTES`, :data:`MAX_VECTOR_BYTES`). The cross-field checks
are :mod:`zplatform.config.checks`; the platform elements every mission
gets, :mod:`zplatform.config.platform`. Imports neither.
"""

from __future__ import annotations

import math
import re
import zlib
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta

from ..errors import ConfigError
from .codes import Thread
from .types import SCALAR_TYPES, ScalarType

Scalar = int | float | bool | str
Value = Scalar | list[Scalar]
THREAD_NAMES: tuple[str, ...] = tuple(t.name.lower() for t in Thread)
"""The threads whose liveness a node reports, by bit of ``<node>_threads_stalled``
(:class:`~zplatform.config.codes.Thread`, :mod:`zplatform.core.health`)."""
_DN_RE = re.compile(r"^dn([0-9]+)$")
MAX_ARRAY_COUNT = 16 * 1024 * 1024
"""Most items in one array element (16 Mi: ``u8[16777216]``, ``f64[16777216]``)."""
MAX_REGION_BYTES = 256 * 1024 * 1024
"""Most bytes in one region (256 MiB): a region travels whole in one frame per loop."""
MAX_VECTOR_BYTES = 256 * 1024 * 1024
"""Most bytes in a Data Vector (256 MiB); the CN's holds every region."""
ARCHIVE_ROW_GROUP_BYTES = 512 * 2**20
"""Most bytes of snapshots in the ground archive's open row group (held in memory)."""
ARCHIVE_QUEUE_BYTES = 256 * 2**20
"""Most bytes of snapshots the ground archive's hand-off queue holds."""
ARCHIVE_ROW_GROUP_S = 60.0
"""``archive.row_group_s`` when unset (fewer seconds for a large vector)."""
ARCHIVE_QUEUE_S = 10.0
"""``archive.queue_s`` when unset (fewer seconds for a large vector)."""
MISSION_NAME_MAX = 128
"""Longest mission name, in characters."""


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
    See zplatform.control.watchdog."""

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
    # "auto" is resolved by zplatform.core.messages.lowlatency_for.
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
    # "auto" is resolved by zplatform.core.messages.wildcard_sync_for.
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
    # Resolved per link by zplatform.runtime.sync (ShmLink) and zplatform.node.
    intra_host: Annotated[
        Literal["auto", "zenoh", "shm"],
        Meta(
            description="The path of the sync (each loop's trigger and reply) between the CN "
            "and a DN on the same host: `shm`, iceoryx2 shared memory "
            "(docs/architecture.md#intra-host); `zenoh`, always zenoh; `auto`, shared "
            "memory for each DN whose link answers over it with a reply that passes the "
            "intake (tag, run, loop), else zenoh. A link on shared memory that fails or "
            "stalls falls back to zenoh with an event and returns later. `shm` differs from "
            "`auto` only in that a DN that cannot open its end refuses to start, and a CN "
            "whose DN has no shared-memory end events it (`sync_fallback`). A redundant "
            "mission (`failover`) syncs over zenoh: `shm` is a config error there. The "
            "path each link takes: `dnX_sync_path`. Bulk channels and, to a ground node on "
            "the CN's host, telemetry take iceoryx2 too unless this is `zenoh` (telemetry "
            "still goes over zenoh as well; `shm`: a CN or ground node whose end cannot open "
            "refuses to start). Discovery, liveliness, taps, tools and other hosts stay on "
            "zenoh."
        ),
    ] = "auto"
    intra_host_links: Annotated[
        dict[str, Literal["auto", "zenoh", "shm"]],
        Meta(
            description="`intra_host` for single device nodes, by name (`{dn1: zenoh}`): "
            "overrides the mission's for that DN's link."
        ),
    ] = msgspec.field(default_factory=dict)


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
            "the drift goes to `dnX_clock_drift_ns`. Either way a genuine trigger of another "
            "run makes the node ask the control node's run (a hello) at most once a second.",
        ),
    ] = 10.0
    # zplatform.runtime.clocksync.estimator_for builds the one named here.
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
            "(built-ins: `zplatform.control.devices:DigitalOutput`, ...)."
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
    `HOLD`, `RESUME`, `ARM`, `PRM_SET`, `PRM_SAVE` (parameters: `params`), and
    with `ground:` the command lock's `LOCK`, `RELEASE`, `HANDOVER`,
    `TAKEOVER`, `APPROVE` (no whitelist refuses those: they move no vehicle
    state; their checks come first, docs/security.md#stations-and-operators). A
    request is checked in this order, the first failure giving its verdict:
    a known command, a number above the last (`REJECTED_REPLAY`), the
    state's whitelist (`REJECTED_NOT_ALLOWED`), a latched fault for the
    `refused_while_faulted` commands (`REJECTED_NOT_ALLOWED`), an ARM just before a
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
    refused_while_faulted: Annotated[
        list[str] | None,
        Meta(
            description="Commands refused while a fault is latched in `cn_fault` "
            "(`REJECTED_NOT_ALLOWED`, naming the fault): an operator clears it first "
            "(`WRITE cn_fault NONE`). Else a LAUNCH accepted on the pad with a fault latched "
            "would enter its state, drive that state's outputs for a loop, then leave on "
            "the fault (the launch output lit, then ABORTED). Never ABORT, NOOP, ARM, WRITE "
            "or a lock command. Default: the hazardous commands; `[]`: none."
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


class ArchiveConfig(_Struct):
    """The ground archive (`zplatform.archive`): the ground node keeps every
    verified snapshot and event it receives, gap-filled loops included, as
    checksummed raw segments (the flight recorder's format, the source of
    truth) and as Parquet files (one column per element, zstd) that
    `zplatform archive MISSION runs|query|events|export` reads with DuckDB.
    The receive path only copies into a bounded queue; the archive's own
    thread does the I/O, and a snapshot the queue cannot take is counted and
    evented (`archive_dropping`), never waited for. Runs (CN epochs) are kept
    apart, each loop once. On by default; `enabled: false` turns it off."""

    enabled: Annotated[
        bool, Meta(description="Whether the ground node archives what it receives.")
    ] = True
    dir: Annotated[
        str | None,
        Meta(
            description="Directory of the archive; mission `M` writes `DIR/M/`. Relative to "
            "the mission file. Default: `zplatform/archive` in the state directory "
            "(`$XDG_STATE_HOME`, else `~/.local/state`; `/var/lib` for root). The environment "
            "variable `ZPLATFORM_ARCHIVE_DIR`, when set, replaces it."
        ),
    ] = None
    max_bytes: Annotated[
        int,
        Meta(
            ge=1024 * 1024,
            le=1 << 50,
            description="Most bytes the mission's archive holds; the oldest runs are removed "
            "whole to stay within it (never the run being written, nor the newest run).",
        ),
    ] = 20 * 1024**3
    max_age_days: Annotated[
        Annotated[float, Meta(gt=0, le=36_500)] | None,
        Meta(
            description="Runs that ended longer ago than this many days are removed; `null`: "
            "kept whatever their age."
        ),
    ] = 365.0
    row_group_s: Annotated[
        Annotated[float, Meta(ge=0.1, le=3600)] | None,
        Meta(
            description="Seconds of snapshots per Parquet row group, each written as a closed "
            "file; the archive holds the open one in memory (its rows x the control node's "
            "vector, at most 512 MiB: a longer group of a large vector is refused here, naming "
            "the most that fits). `null` (the default): 60 s, or what 512 MiB holds of a "
            "larger vector. A running run is queryable up to its last row group; larger "
            "groups make fewer files and faster queries; a crash loses none of the open "
            "group's rows that reached the raw segment (they are re-decoded from it).",
        ),
    ] = None
    file_s: Annotated[
        float,
        Meta(
            ge=1,
            le=86_400,
            description="Seconds of snapshots between two passes that compact the run's "
            "row-group files of each hour into one Parquet file (also at the run's end) and "
            "apply retention (`max_bytes`, `max_age_days`).",
        ),
    ] = 600.0
    queue_s: Annotated[
        Annotated[float, Meta(ge=0.1, le=600)] | None,
        Meta(
            description="Seconds of snapshots the hand-off queue between the receive path and "
            "the archive's thread holds (at least 16 snapshots, at most 256 MiB: a longer "
            "queue of a large vector is refused here, naming the most that fits); a full queue "
            "drops, counted. `null` (the default): 10 s, or what 256 MiB holds of a larger "
            "vector.",
        ),
    ] = None
    serve_bps: Annotated[
        int,
        Meta(
            ge=10_000,
            le=1_000_000_000,
            description="Bytes per second the ground node sends when a station or tool asks its "
            "archive over zenoh (`{vehicle}/archive/query`): answered by a thread of its own, "
            "paced so that no asker can crowd out live telemetry.",
        ),
    ] = 2_000_000
    serve_max_bytes: Annotated[
        int,
        Meta(
            ge=64 * 1024,
            le=1 << 34,
            description="Most bytes of one answer over zenoh; a query whose answer is larger "
            "is refused with a reason saying so (never cut short silently).",
        ),
    ] = 64 * 1024 * 1024
    serve_per_asker: Annotated[
        int,
        Meta(
            ge=1,
            le=8,
            description="Most queries one asker (a station or tool) may have in hand at the "
            "ground node's archive at once; one more is refused with a reason saying so.",
        ),
    ] = 2
    serve_asker_bps: Annotated[
        int,
        Meta(
            ge=10_000,
            le=1_000_000_000,
            description="Bytes per second of answers one asker may take from the ground "
            "node's archive (a bucket holding `serve_max_bytes`): a query whose answer the "
            "bucket does not hold is refused with a reason saying when to ask again.",
        ),
    ] = 1_000_000


class SecurityConfig(_Struct):
    """Authentication of every frame a node takes from the network, and of
    every peer that may open a link at all."""

    auth: Annotated[
        bool,
        Meta(
            description="Every region frame, telemetry snapshot, command request, clock-sync "
            "exchange and event record carries a 32-byte tag (the run, a header tag checked "
            "before the body, and a MAC keyed per link: CN<->dnX, the ground's uplink, the "
            "telemetry downlink, each node's events, "
            "and bound to the control node's run); each host holds "
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
    `dnX_to_cn` (each DN), with limits; see zplatform.core.health. On by default
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


class MonitorConfig(_Struct):
    """A monitor (fault detection and response, as F Prime splits them): a
    condition on one element of the CN's Data Vector that, holding for
    `persistence` loops in a row, trips once and runs its response; it
    clears when the condition stops holding. Monitors run every loop on the
    CN, after the fault monitor and before the state machine, so a response
    takes effect in the loop it trips. See zplatform.control.monitors."""

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


# -- bulk channels (zplatform.runtime.bulk moves them) --------------------------------

BULK_HEADER_BYTES = 32  # see HEADER below
MAX_CHANNEL_BYTES = 1 << 30  # 1 GiB: a typo guard, not a zenoh limit
_BULK_TYPE_RE = re.compile(r"^\s*([a-z0-9]+)\s*\[\s*([0-9]+(?:\s*,\s*[0-9]+)*)\s*\]\s*$")


class BulkChannelConfig(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True):
    """One bulk channel: a large array (a camera frame, a spectrum) that its
    owner publishes outside the 2 ms sync, through iceoryx2 shared memory
    to readers on its host (`transport.intra_host` not `zenoh`), zenoh's
    across hosts and to tools (docs/architecture.md#intra-host). The
    owner's components fill `self.bulk[name]` and the runtime publishes it
    after the loop's logic; readers' components find the newest sample
    there. Per channel, counters go to telemetry
    (`bulk_<name>_published`, `_dropped` on the owner; `_iox` (iceoryx2,
    a same-host owner), `_shm` (zenoh's shared memory), `_copied`,
    `_missed`, `_bad`, `_stale` on each reader). With `security.auth`, every
    sample carries a tag per reader, under link `bulk-<name>-<reader>`
    (held by the owner and that reader only), which that reader checks
    before it takes the sample (docs/security.md).
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


OPERATOR_ROLES = ("flight_director", "range_safety", "operator", "viewer")
"""The roles an operator may hold (``ground.operators[].roles``)."""


class StationConfig(_Struct):
    """One ground station: a host (pad, control room, a viewer's laptop) that
    sends requests with its own station key (``station-<name>.keys``)."""

    name: Annotated[
        str,
        Meta(description="The station's name: `[a-z][a-z0-9_]*`, at most 32 characters."),
    ]
    may: Annotated[
        Literal["command", "view"],
        Meta(
            description="`command`: its operators may command (with the lock); `view`: it "
            "only watches, except that range safety's ABORT is taken from any station."
        ),
    ] = "command"
    key_id: Annotated[
        int,
        Meta(
            ge=1,
            le=65535,
            description="The number of the station's key: raise it (and rerun `zplatform "
            "keygen`) to replace a lost station key; the old one no longer verifies.",
        ),
    ] = 1
    connect: Annotated[
        list[str],
        Meta(
            description="Where this station's tools connect (`--station NAME`): its router's "
            "`listen`; empty: to every node, as any tool does."
        ),
    ] = msgspec.field(default_factory=list)
    start: Annotated[
        bool,
        Meta(
            description="Whether `zplatform up` starts this station on its host: a ground "
            "process (`zplatform station MISSION NAME`) that receives, logs and archives as "
            "this station in a directory of its own, and keeps `operator`'s command lock "
            "while they hold it. Off: the station runs elsewhere."
        ),
    ] = False
    operator: Annotated[
        str | None,
        Meta(
            description="The operator (`ground.operators`) the station started by `up` runs "
            "as: its requests (lock renewals) are signed with their key and the station's. "
            "None: it only watches."
        ),
    ] = None


class RouterConfig(_Struct):
    """One zenoh router between the vehicle and the stations
    (`zplatform router MISSION --name NAME`, or started by `up`): it forwards
    the stations' subscriptions, requests and queries and fans the CN's
    telemetry out, so the vehicle publishes once whatever the number of
    stations (docs/deployment.md)."""

    name: Annotated[
        str,
        Meta(description="The router's name: `[a-z][a-z0-9_]*`, at most 32 characters."),
    ]
    listen: Annotated[
        list[str],
        Meta(description="Endpoints it listens on (stations and other routers connect here)."),
    ] = msgspec.field(default_factory=list)
    connect: Annotated[
        list[str],
        Meta(
            description="Endpoints it connects to: the control node's `listen` (a pad "
            "router), or another router's (a control-room router across the WAN)."
        ),
    ] = msgspec.field(default_factory=list)
    start: Annotated[
        bool,
        Meta(description="Whether `zplatform up` starts it on this host (off: it runs elsewhere)."),
    ] = True


class OperatorConfig(_Struct):
    """One operator: a person with a key of their own (``operator-<name>.keys``)."""

    name: Annotated[
        str,
        Meta(description="The operator's name: `[a-z][a-z0-9_]*`, at most 32 characters."),
    ]
    roles: Annotated[
        list[Literal["flight_director", "range_safety", "operator", "viewer"]],
        Meta(
            description="`flight_director` (commands, may take the lock over, approves), "
            "`range_safety` (ABORT from any station, lock or not; approves), `operator` "
            "(commands with the lock), `viewer` (never commands)."
        ),
    ]
    key_id: Annotated[
        int,
        Meta(
            ge=1,
            le=65535,
            description="The number of the operator's key (part of its derivation): raise it "
            "and rerun `zplatform keygen` to replace a lost key; the old one no longer "
            "verifies. The vehicle is never re-keyed.",
        ),
    ] = 1


class GroundConfig(_Struct):
    """Stations, operators, command authority and the two-person rule
    (docs/security.md#stations-and-operators). Without this section the
    mission has one ground and whoever holds its uplink key commands."""

    stations: Annotated[
        list[StationConfig],
        Meta(description="The ground stations (at least one may command)."),
    ]
    operators: Annotated[
        list[OperatorConfig],
        Meta(description="The operators (at least one may command)."),
    ]
    lease_s: Annotated[
        float,
        Meta(
            gt=0,
            le=3600,
            description="How long the command lock lasts after its holder's last accepted "
            "request (s): a holder's station that goes silent loses the lock then.",
        ),
    ] = 10.0
    two_person: Annotated[
        list[str],
        Meta(
            description="Hazardous commands (`LAUNCH`), protected elements (a WRITE of it) "
            "or hazardous parameters (a PRM_SET of it) that also need an APPROVE of their "
            "ARM by a second operator with an approving role, inside the ARM window."
        ),
    ] = msgspec.field(default_factory=list)
    approving_roles: Annotated[
        list[Literal["flight_director", "range_safety", "operator"]],
        Meta(description="The roles whose holders may approve (two-person rule)."),
    ] = msgspec.field(default_factory=lambda: ["flight_director", "range_safety"])
    revoked: Annotated[
        list[str],
        Meta(
            description="Revoked operator keys: `NAME` (every key of that operator) or "
            "`NAME#KEY_ID` (one key). A CN-side change: the vehicle is not re-keyed."
        ),
    ] = msgspec.field(default_factory=list)
    routers: Annotated[
        list[RouterConfig],
        Meta(description="The zenoh routers between the vehicle and the stations."),
    ] = msgspec.field(default_factory=list)
    single_operator: Annotated[
        bool,
        Meta(
            description="Keep the behaviour of a mission without `ground:`: no operator "
            "identity is required, no lock, no two-person rule (the stations and "
            "operators still get their key files)."
        ),
    ] = False


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
    archive: Annotated[
        ArchiveConfig,
        Meta(
            description="The ground archive: every run the ground node receives, kept and "
            "queryable (`zplatform archive`). On by default."
        ),
    ] = msgspec.field(default_factory=ArchiveConfig)
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
            "(physics that every board's outputs change): see zplatform.world.model."
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
    ground: Annotated[
        GroundConfig | None,
        Meta(
            description="Ground stations, operators, command authority and the two-person "
            "rule (needs the ground node `gn` and `security.auth`)."
        ),
    ] = None
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
    def authority(self) -> bool:
        """Whether the CN checks operators, the command lock and the
        two-person rule (a ``ground:`` section without ``single_operator``)."""
        return self.ground is not None and not self.ground.single_operator

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
