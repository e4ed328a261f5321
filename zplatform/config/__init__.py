"""The mission configuration: YAML decoded into typed, structurally checked structs.

A package of three rooms that import downwards only (``schema`` <-
``platform`` <- ``checks``): :mod:`zplatform.config.schema`, the
:class:`Mission` struct tree (``msgspec.Struct`` with ``forbid_unknown_fields``,
every key with its description) and the size limits (:data:`MAX_ARRAY_COUNT`,
:data:`MAX_REGION_BYTES`, :data:`MAX_VECTOR_BYTES`);
:mod:`zplatform.config.platform`, the platform elements every mission gets
(docs/architecture.md#data-vector); :mod:`zplatform.config.checks`, the
structural checks and :func:`parse_mission`. This package re-exports every
public name of the three: ``from zplatform.config import X`` is the way in.

Contract: :func:`parse_mission` raises :class:`~zplatform.errors.ConfigError`
naming the YAML path of the bad field and what was expected. It imports none
of the modules that give the sections their meaning (they import it), so a
mission that only passed it is not fit to fly: the semantic checks run in
:func:`zplatform.mission.load.load_mission`. A loaded :class:`Mission` is immutable.

Loading, in order: docs/architecture.md#the-loop (loading a mission).
"""

from __future__ import annotations

from .checks import (
    check_bulk_channels as check_bulk_channels,
)
from .checks import (
    check_mission_name as check_mission_name,
)
from .checks import (
    parse_mission as parse_mission,
)
from .checks import (
    relocate_mission as relocate_mission,
)
from .checks import (
    resolve_pythonpath as resolve_pythonpath,
)
from .checks import (
    transport_reason as transport_reason,
)
from .platform import (
    BOARD_LINK_COUNTERS as BOARD_LINK_COUNTERS,
)
from .platform import (
    BOARD_LINK_DRIVERS as BOARD_LINK_DRIVERS,
)
from .platform import (
    CMD_NAMES as CMD_NAMES,
)
from .platform import (
    CMD_STATUS_NAMES as CMD_STATUS_NAMES,
)
from .platform import (
    CONTROLLER_MODES as CONTROLLER_MODES,
)
from .platform import (
    FAULT_NAMES as FAULT_NAMES,
)
from .platform import (
    HEALTH_METRICS as HEALTH_METRICS,
)
from .platform import (
    PRM_LOAD_NAMES as PRM_LOAD_NAMES,
)
from .platform import (
    PRM_SAVE_NAMES as PRM_SAVE_NAMES,
)
from .platform import (
    SAFED_WHY_NAMES as SAFED_WHY_NAMES,
)
from .platform import (
    HealthMetric as HealthMetric,
)
from .platform import (
    board_link_elements as board_link_elements,
)
from .platform import (
    counter_elements as counter_elements,
)
from .platform import (
    counter_region as counter_region,
)
from .platform import (
    element_spec as element_spec,
)
from .platform import (
    health_elements as health_elements,
)
from .platform import (
    interlocked_nodes as interlocked_nodes,
)
from .platform import (
    platform_elements as platform_elements,
)
from .schema import (
    BULK_HEADER_BYTES as BULK_HEADER_BYTES,
)
from .schema import (
    MAX_ARRAY_COUNT as MAX_ARRAY_COUNT,
)
from .schema import (
    MAX_CHANNEL_BYTES as MAX_CHANNEL_BYTES,
)
from .schema import (
    MAX_REGION_BYTES as MAX_REGION_BYTES,
)
from .schema import (
    MAX_VECTOR_BYTES as MAX_VECTOR_BYTES,
)
from .schema import (
    MISSION_NAME_MAX as MISSION_NAME_MAX,
)
from .schema import (
    OPERATOR_ROLES as OPERATOR_ROLES,
)
from .schema import (
    STANDBY as STANDBY,
)
from .schema import (
    THREAD_NAMES as THREAD_NAMES,
)
from .schema import (
    ActionConfig as ActionConfig,
)
from .schema import (
    ArchiveConfig as ArchiveConfig,
)
from .schema import (
    BulkChannelConfig as BulkChannelConfig,
)
from .schema import (
    ClockConfig as ClockConfig,
)
from .schema import (
    CommandsConfig as CommandsConfig,
)
from .schema import (
    ComponentConfig as ComponentConfig,
)
from .schema import (
    DownlinkConfig as DownlinkConfig,
)
from .schema import (
    ElementConfig as ElementConfig,
)
from .schema import (
    FailoverConfig as FailoverConfig,
)
from .schema import (
    FaultsConfig as FaultsConfig,
)
from .schema import (
    GroundConfig as GroundConfig,
)
from .schema import (
    HazardousOutputConfig as HazardousOutputConfig,
)
from .schema import (
    HealthConfig as HealthConfig,
)
from .schema import (
    LimitsConfig as LimitsConfig,
)
from .schema import (
    Mission as Mission,
)
from .schema import (
    MonitorConfig as MonitorConfig,
)
from .schema import (
    NodeConfig as NodeConfig,
)
from .schema import (
    OperatorConfig as OperatorConfig,
)
from .schema import (
    ParamConfig as ParamConfig,
)
from .schema import (
    RecorderConfig as RecorderConfig,
)
from .schema import (
    RouterConfig as RouterConfig,
)
from .schema import (
    Scalar as Scalar,
)
from .schema import (
    SecurityConfig as SecurityConfig,
)
from .schema import (
    StateConfig as StateConfig,
)
from .schema import (
    StateMachineConfig as StateMachineConfig,
)
from .schema import (
    StationConfig as StationConfig,
)
from .schema import (
    TransitionConfig as TransitionConfig,
)
from .schema import (
    TransportConfig as TransportConfig,
)
from .schema import (
    Value as Value,
)
from .schema import (
    WatchdogConfig as WatchdogConfig,
)
from .schema import (
    WorldBoardConfig as WorldBoardConfig,
)
from .schema import (
    WorldConfig as WorldConfig,
)
from .schema import (
    parse_bulk_type as parse_bulk_type,
)

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
    "OPERATOR_ROLES",
    "PRM_LOAD_NAMES",
    "PRM_SAVE_NAMES",
    "SAFED_WHY_NAMES",
    "THREAD_NAMES",
    "ActionConfig",
    "ArchiveConfig",
    "ClockConfig",
    "CommandsConfig",
    "ComponentConfig",
    "ElementConfig",
    "FaultsConfig",
    "GroundConfig",
    "HazardousOutputConfig",
    "HealthConfig",
    "HealthMetric",
    "Mission",
    "MonitorConfig",
    "NodeConfig",
    "OperatorConfig",
    "ParamConfig",
    "RecorderConfig",
    "RouterConfig",
    "StateConfig",
    "StateMachineConfig",
    "StationConfig",
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
