"""XTCE export of a mission: the CCSDS downlink and the operator commands.

:func:`mission_xtce` describes, with ``yamcs-pymdb``, exactly the packets
:mod:`zplatform.telemetry.ccsds` sends, so Yamcs (or any XTCE ground system) decodes
them without zplatform: the CCSDS primary header, our secondary header, and
one container per packet of :func:`zplatform.telemetry.ccsds.packet_plan` holding one
parameter per Data Vector element at its bit position, with the element's
limits as alarms. An element that straddles two segments of a segmented
region is declared but placed in no container (:attr:`XtceExport.unplaced`).
Commands: one meta-command per operator command on the ``gn_to_cn`` layout;
the mission's hazardous commands are CRITICAL.

Contract: a pure function of the mission (loaded with ``code=False`` is
enough); it needs the ``ground`` extra (``yamcs-pymdb``). ARM-then-fire and
the frame's tag stay zplatform's own uplink's: XTCE does not describe them.

The containers, types and commands in full: docs/operations.md#radio-downlink.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from yamcs.pymdb import (
    ArrayParameter,
    BooleanDataType,
    BooleanParameter,
    Command,
    CommandLevel,
    Container,
    DataType,
    EnumeratedArgument,
    EnumeratedDataType,
    EnumeratedParameter,
    FloatArgument,
    FloatDataType,
    FloatEncoding,
    FloatParameter,
    IntegerArgument,
    IntegerDataType,
    IntegerEncoding,
    IntegerEncodingScheme,
    IntegerParameter,
    Parameter,
    ParameterEntry,
    System,
    ThresholdAlarm,
    ccsds,
    eq,
)
from yamcs.pymdb.commands import ArgumentEntry
from yamcs.pymdb.expressions import all_of

from ..config import CMD_NAMES, Mission
from ..control.commands import writable_elements
from ..control.limits import Limits, mission_limits
from ..core.datavector import ElementSpec, Layout
from ..errors import ConfigError
from ..telemetry.ccsds import APID_BASE, MAX_DATA, SECONDARY_HEADER, packet_plan

__all__ = ["HEADER_BITS", "XtceExport", "mission_xtce", "write_xtce"]

#: Bits before the first region byte of a packet (primary + secondary header).
HEADER_BITS = (6 + SECONDARY_HEADER.size) * 8
SECONDARY_NAMES = ("ccsds_loop", "ccsds_time_ns", "ccsds_segment_offset")


@dataclass
class XtceExport:
    """The generated XTCE and what could not be placed."""

    xml: str
    unplaced: list[str] = field(default_factory=list)


def _int_encoding(bits: int, signed: bool, little: bool = True) -> IntegerEncoding:
    scheme = IntegerEncodingScheme.TWOS_COMPLEMENT if signed else IntegerEncodingScheme.UNSIGNED
    return IntegerEncoding(bits=bits, little_endian=little, scheme=scheme)


def _element_type(spec: ElementSpec) -> DataType:
    """The XTCE data type of one value of ``spec`` (an array's item type)."""
    st = spec.scalar
    bits = st.size * 8
    if spec.enum is not None:
        return EnumeratedDataType(
            choices=list(enumerate(spec.enum)), encoding=_int_encoding(bits, False)
        )
    if st.kind == "bool":
        return BooleanDataType(encoding=_int_encoding(8, False))
    if st.kind == "float":
        return FloatDataType(
            bits=32 if bits == 32 else 64, encoding=FloatEncoding(bits=bits, little_endian=True)
        )
    signed = st.name.startswith("i")
    return IntegerDataType(signed=signed, bits=bits, encoding=_int_encoding(bits, signed))


def _alarm(lim: Limits | None) -> ThresholdAlarm | None:
    """Yellow -> XTCE warning range, red -> critical range (bounds inclusive, as ours)."""
    if lim is None:
        return None
    return ThresholdAlarm(
        warning_low=lim.yellow[0],
        warning_high=lim.yellow[1],
        critical_low=lim.red[0],
        critical_high=lim.red[1],
    )


def _parameter(
    system: System, spec: ElementSpec, doc: str, limits: Limits | None = None
) -> Parameter:
    st = spec.scalar
    bits = st.size * 8
    desc = doc or None
    if spec.count:
        return ArrayParameter(
            system=system,
            name=spec.name,
            data_type=_element_type(spec),
            length=spec.count,
            short_description=desc,
        )
    if spec.enum is not None:
        return EnumeratedParameter(
            system=system,
            name=spec.name,
            choices=list(enumerate(spec.enum)),
            encoding=_int_encoding(bits, False),
            short_description=desc,
        )
    if st.kind == "bool":
        return BooleanParameter(
            system=system, name=spec.name, encoding=_int_encoding(8, False), short_description=desc
        )
    if st.kind == "float":
        return FloatParameter(
            system=system,
            name=spec.name,
            bits=32 if bits == 32 else 64,
            encoding=FloatEncoding(bits=bits, little_endian=True),
            short_description=desc,
            alarm=_alarm(limits),
        )
    signed = st.name.startswith("i")
    return IntegerParameter(
        system=system,
        name=spec.name,
        signed=signed,
        bits=bits,
        encoding=_int_encoding(bits, signed),
        short_description=desc,
        alarm=_alarm(limits),
    )


def mission_xtce(
    mission: Mission,
    *,
    apid_base: int = APID_BASE,
    max_data: int = MAX_DATA,
    limits: dict[str, object] | None = None,
) -> XtceExport:
    """The mission's telemetry packets and commands as an XTCE 1.2 document.

    ``apid_base`` and ``max_data`` must be those of the downlink's
    :class:`~zplatform.telemetry.ccsds.CcsdsEncoder`. Element limits (the mission's,
    and ``limits`` over them; :mod:`zplatform.control.limits`) become threshold
    alarms: yellow the warning range, red the critical one. Raises
    ConfigError when an element name clashes with a name the export uses.
    """
    layout = Layout.for_node(mission, "cn")
    clash = sorted(set(layout.elements) & {*SECONDARY_NAMES, "zplatform_packet"})
    if clash:
        raise ConfigError(f"element names {clash} are reserved by the XTCE export", "$.regions")
    docs = {e.name: e.doc for r in mission.regions.values() for e in r}
    system = System(mission.mission)
    system.short_description = f"zplatform mission {mission.mission} (vehicle {mission.vehicle})"
    header = ccsds.add_ccsds_header(system)

    sec = [
        IntegerParameter(
            system=system,
            name="ccsds_loop",
            signed=False,
            bits=64,
            encoding=_int_encoding(64, False, little=False),
            short_description="CN loop number of the snapshot",
        ),
        IntegerParameter(
            system=system,
            name="ccsds_time_ns",
            signed=True,
            bits=64,
            units="ns",
            encoding=_int_encoding(64, True, little=False),
            short_description="CN time of the snapshot (ns since the epoch)",
        ),
        IntegerParameter(
            system=system,
            name="ccsds_segment_offset",
            signed=False,
            bits=32,
            units="bytes",
            encoding=_int_encoding(32, False, little=False),
            short_description="offset of this packet's bytes inside its region",
        ),
    ]
    base = Container(
        system=system,
        name="zplatform_packet",
        base=header.tm_container,
        abstract=True,
        short_description="zplatform telemetry packet: CCSDS header + loop, time, offset",
        entries=[ParameterEntry(p, bitpos=48 + 64 * i) for i, p in enumerate(sec)],
    )

    lims = mission_limits(mission, limits)
    params = {
        spec.name: _parameter(system, spec, docs.get(spec.name, ""), lims.get(spec.name))
        for spec in layout.elements.values()
    }
    plan = packet_plan(mission, apid_base=apid_base, max_data=max_data)
    segmented = {p.region for p in plan if p.offset}
    placed: set[str] = set()
    period_s = mission.telemetry_divisor / mission.loop_hz
    for p in plan:
        region = layout.region(p.region)
        lo, hi = p.offset, p.offset + p.length
        entries = []
        for spec in region.elements:
            rel = spec.offset - region.offset
            if lo <= rel and rel + spec.size <= hi:
                entries.append(
                    ParameterEntry(params[spec.name], bitpos=HEADER_BITS + (rel - lo) * 8)
                )
                placed.add(spec.name)
        cond = eq(header.tm_apid, p.apid)
        name = p.region
        if p.region in segmented:
            name = f"{p.region}_seg{p.offset}"
            cond = all_of(cond, eq(sec[2], p.offset))
        Container(
            system=system,
            name=name,
            base=base,
            condition=cond,
            entries=entries,
            bits=p.packet_size * 8,
            rate=period_s,
            short_description=f"region {p.region} bytes {lo}..{hi} (APID {p.apid:#x})",
        )
    unplaced = [n for n in layout.elements if n not in placed and layout.element(n).size]
    _add_commands(system, mission, layout, header, apid_base)
    return XtceExport(system.dumps(), unplaced)


def _add_commands(
    system: System, mission: Mission, layout: Layout, header: ccsds.CcsdsHeader, apid_base: int
) -> None:
    if not mission.has_ground:
        return
    gn = layout.region("gn_to_cn")
    names = mission.region_names()
    apid = apid_base + names.index("gn_to_cn")

    def spec(name: str) -> ElementSpec:
        return layout.element(name)

    cmd_arg = EnumeratedArgument(
        name="gn_cmd",
        choices=list(enumerate(CMD_NAMES)),
        encoding=_int_encoding(spec("gn_cmd").scalar.size * 8, False),
    )
    seq_arg = IntegerArgument(
        name="gn_cmd_seq",
        signed=False,
        bits=32,
        encoding=_int_encoding(spec("gn_cmd_seq").scalar.size * 8, False),
        short_description="command number: one more than the CN's last verdict",
    )
    # WRITE's elements (the list the CN accepts: the platform's one rule),
    # then PRM_SET's parameters (never WRITE's: the CN refuses them).
    names = writable_elements(mission) + [p.name for p in mission.params]
    targets = [layout.element(n) for n in names]
    el_arg = EnumeratedArgument(
        name="gn_cmd_element",
        choices=[(0, "none")] + [(e.index, e.name) for e in targets if e.index],
        default="none",
        encoding=_int_encoding(spec("gn_cmd_element").scalar.size * 8, False),
    )
    val_arg = FloatArgument(
        name="gn_cmd_value",
        bits=64,
        default=0.0,
        encoding=FloatEncoding(bits=64, little_endian=True),
    )
    bitpos = {e.name: 48 + (e.offset - gn.offset) * 8 for e in gn.elements}
    request = Command(
        system=system,
        name="zplatform_request",
        base=header.tc_command,
        abstract=True,
        assignments={header.tc_apid.name: apid, header.tc_secondary_header.name: False},
        arguments=[cmd_arg, seq_arg, el_arg, val_arg],
        entries=[
            ArgumentEntry(a, bitpos=bitpos[a.name]) for a in (cmd_arg, seq_arg, el_arg, val_arg)
        ],
        short_description="one operator command: the gn_to_cn region",
    )
    hazardous = {c.upper() for c in mission.commands.hazardous}
    for cmd in CMD_NAMES[1:]:
        assign: dict[str, object] = {"gn_cmd": cmd}
        if cmd not in ("WRITE", "PRM_SET"):
            assign.update(gn_cmd_element="none", gn_cmd_value=0.0)
        Command(
            system=system,
            name=cmd,
            base=request,
            assignments=assign,
            level=CommandLevel.CRITICAL if cmd in hazardous else CommandLevel.NORMAL,
            warning_message=(
                f"{cmd} is hazardous: zplatform sends ARM first" if cmd in hazardous else None
            ),
        )


def write_xtce(mission: Mission, out: str | Path) -> XtceExport:
    """Write :func:`mission_xtce` to ``out``; returns the export."""
    x = mission_xtce(mission)
    Path(out).write_text(x.xml, encoding="utf-8")
    return x
