"""The platform elements: the wire contract every mission gets, per region.

The elements of docs/architecture.md#data-vector that :func:`platform_elements`
adds to each region before the mission's own (the CN's loop counters,
commands and verdicts, each node's health block (:data:`HEALTH_METRICS`),
the board link counters (:data:`BOARD_LINK_COUNTERS`), the bulk channels'
counters), in the order the wire carries them. Every node derives them from
the mission alone, so they agree without being sent.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import msgspec

from ..errors import ConfigError
from .codes import Command, CommandStatus, Fault, ParamLoad, ParamSave, SafedWhy
from .schema import THREAD_NAMES, BulkChannelConfig, ElementConfig, LimitsConfig, Mission
from .types import SCALAR_TYPES, ScalarType, parse_type

# Enum names of the platform elements cn_cmd/gn_cmd, cn_cmd_status and
# cn_fault, derived from the one definition of the codes (zplatform.config.codes).
CMD_NAMES: tuple[str, ...] = tuple(m.name for m in Command)
CMD_STATUS_NAMES: tuple[str, ...] = tuple(m.name for m in CommandStatus)
CONTROLLER_MODES: tuple[str, ...] = ("enabled", "safed", "manual")
FAULT_NAMES: tuple[str, ...] = tuple(m.name for m in Fault)
PRM_LOAD_NAMES: tuple[str, ...] = tuple(m.name for m in ParamLoad)
PRM_SAVE_NAMES: tuple[str, ...] = tuple(m.name for m in ParamSave)
SAFED_WHY_NAMES: tuple[str, ...] = tuple(m.name for m in SafedWhy)


class HealthMetric(msgspec.Struct, frozen=True):
    """One health element (:mod:`zplatform.core.health`): its name after
    ``<node>_``, type, meaning and default limits (``per_period``: the limits
    are in loop periods)."""

    name: str
    type: str
    doc: str
    yellow: tuple[float | None, float | None] | None = None
    red: tuple[float | None, float | None] | None = None
    per_period: bool = False


HEALTH_METRICS: tuple[HealthMetric, ...] = (
    # sampled by the health thread, in this order (zplatform.core.health.SAMPLED)
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
    # measured by the loop, in this order (zplatform.core.health.LOOP_FIELDS)
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
"""Every health element, in block order (:mod:`zplatform.core.health`)."""
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


def counter_elements(channels: Sequence[BulkChannelConfig], node: str) -> list[dict[str, Any]]:
    """The u32 Data Vector elements that carry ``node``'s bulk counters into
    telemetry, as ElementConfig-shaped dicts (``{"name", "type", "doc"}``).

    Owner of a channel: ``bulk_<ch>_published``, ``bulk_<ch>_dropped``.
    Reader: ``bulk_<ch>_iox``, ``bulk_<ch>_shm``, ``bulk_<ch>_copied``, ``bulk_<ch>_missed``,
    ``bulk_<ch>_bad``, ``bulk_<ch>_stale``. The names match :meth:`NodeBulk.counters`.
    """
    out: list[dict[str, Any]] = []
    for ch in channels:
        names: tuple[tuple[str, str], ...] = ()
        if ch.node == node:
            names = (("published", "samples sent"), ("dropped", "no free chunk in time"))
        elif node in ch.readers:
            names = (
                ("iox", "samples received through iceoryx2 (a same-host owner)"),
                ("shm", "samples received through zenoh shared memory"),
                ("copied", "samples received copied (network or shm off)"),
                ("missed", "samples superseded or lost (seq gaps)"),
                ("bad", "samples refused as malformed (size, tag or layout)"),
                ("stale", "authentic samples refused (another run's, ahead, beyond the rate)"),
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


BOARD_LINK_DRIVERS = ("serial", "gpiod")
SYNC_PATHS = ("zenoh", "shm")
"""The values of ``dnX_sync_path``, in order (zplatform.runtime.sync)."""
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
    (:class:`~zplatform.control.loop.DeviceLogic`) after each step. Pure: it reads
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
        E("cn_loop_overruns", "u32", 0, doc="periods skipped after loops that overran theirs"),
        E("cn_sync_overruns", "u32", 0, doc="loops whose sync passed the deadline"),
        E("cn_errors", "u32", 0, doc="non-critical errors counted"),
        E("cn_last_error", "u16", 0, doc="code of the last non-critical error"),
        E("cn_bad_frames", "u32", 0, doc="frames refused (shape, layout, tag)"),
        E(
            "cn_unchecked_frames",
            "u32",
            0,
            doc="of those, frames dropped after their header, their body's MAC not "
            "checked: the loop's body-MAC budget was spent (spliced headers)",
        ),
        E(
            "cn_query_recoveries",
            "u32",
            0,
            doc="queriers declared again: a live device node's queries unanswered loop "
            "after loop (a query route lost in zenoh)",
        ),
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
        # The parameters and their store's state (zplatform.control.params).
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
    # The last ARM (the number a hazardous command must follow): mirrored to
    # a standby, and kept in the flight recorder's frames, so a takeover or a
    # restart's resume takes up an ARM (and its approvals) where it was.
    arm: list[ElementConfig] = []
    if m.standby is not None or m.recorder is not None:
        arm = [
            E(
                "cn_arm_seq",
                "u64",
                0,
                doc="number of the last ARM accepted (0: none; with a standby or a recorder)",
            ),
            E("cn_arm_t_ns", "i64", 0, doc="its loop time (ns)"),
        ]
    if m.standby is None:
        cn += arm
    else:
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
            *arm,
            E("cn_holding", "bool", False, doc="a HOLD is in effect"),
            E(
                "cn_mirror_refused",
                "u32",
                0,
                doc="mirror frames refused as they arrived (size, tag, range, not newer): "
                "the commander's, and a standby's own, added when it takes command",
            ),
        ]
    for dn in m.device_nodes:
        cn += [
            E(f"cn_rx_{dn}", "u32", 0, doc=f"replies from {dn} applied"),
            E(f"cn_missed_{dn}", "u32", 0, doc=f"loops without {dn}'s reply in time"),
            E(f"cn_late_{dn}", "u32", 0, doc=f"replies from {dn} for an older loop"),
        ]
    g = m.ground
    if g is not None and m.has_ground:
        # Command authority (zplatform.control.authority): who sent the last
        # verdict's request, who holds the lock and until when.
        ops = ["NONE", *(o.name for o in g.operators)]
        cn += [
            E("cn_cmd_operator", "enum", "NONE", ops, doc="the operator of the last verdict"),
            E("cn_lock_holder", "enum", "NONE", ops, doc="the operator holding the command lock"),
            E(
                "cn_lock_station",
                "enum",
                "NONE",
                ["NONE", *(s.name for s in g.stations)],
                doc="the holder's station (NONE: not yet bound after a handover)",
            ),
            E("cn_lock_until_ns", "i64", 0, doc="the lease's end (loop time, ns; 0: no holder)"),
            E("cn_arm_approvals", "u8", 0, doc="approvals of the current ARM (two-person rule)"),
            # The ARM open for approvals, in full: a console judges an APPROVE
            # as the CN would, and a standby or a restarted CN takes it up.
            E("cn_arm_open", "u64", 0, doc="the number of the ARM open for approvals (0: none)"),
            E("cn_arm_operator", "enum", "NONE", ops, doc="the operator of that ARM"),
            E("cn_arm_open_ns", "i64", 0, doc="its loop time (ns): approvals within 10 s"),
            E(
                "cn_arm_approvers",
                "u64",
                0,
                doc="who approved it: bit i for ground.operators[i]",
            ),
            E(
                "cn_auth_refused",
                "u32",
                0,
                doc="requests refused by operator, station, lock or two-person checks",
            ),
        ]
        if m.authority:
            # When the CN last heard each station (a request whose operator and
            # station tags verified, accepted or refused): the consoles' station
            # list, with no presence key of its own (docs/operations.md).
            cn += [
                E(
                    f"cn_heard_{s.name}_ns",
                    "i64",
                    0,
                    doc=f"loop time (ns) of the last request from station {s.name} "
                    "whose tags verified (0: not heard)",
                )
                for s in g.stations
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
            E(
                f"{dn}_unchecked_frames",
                "u32",
                0,
                doc=f"of those, frames {dn} dropped after their header, their body's MAC "
                "not checked: the loop's body-MAC budget was spent (spliced headers)",
            ),
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
            E(
                f"{dn}_sync_path",
                "enum",
                "zenoh",
                list(SYNC_PATHS),
                doc=f"the path {dn}'s last trigger came by: zenoh, or shm (iceoryx2 shared "
                "memory on one host, `transport.intra_host`)",
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
        if m.ground is not None:  # codecs/FORMAT.md: the operator's identity
            out["gn_to_cn"] += [
                E("gn_cmd_operator", "u16", 0, doc="the operator (`ground.operators` index + 1)"),
                E("gn_cmd_station", "u16", 0, doc="the station (`ground.stations` index + 1)"),
                E("gn_cmd_ref", "u64", 0, doc="APPROVE: the number of the ARM approved"),
                E("gn_cmd_op_tag", "u8[16]", 0, doc="MAC of the request under the operator's key"),
                E("gn_cmd_st_tag", "u8[16]", 0, doc="MAC of the request under the station's key"),
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
    # Health, last: one contiguous block per node (zplatform.core.health), only
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
