"""Loading a mission: the schema, then every semantic check, before anything runs.

:func:`load_mission` (a file) and :func:`decode_mission` (YAML text) are the
way in for every caller (the runtime, the lockstep runner, the tools, the
tests). They return a :class:`~zplatform.config.Mission` that passed the
schema and structural checks of :func:`zplatform.config.parse_mission` and
then :func:`check_mission`, every check that needs the whole Data Vector or
the mission's code, so a bad class path, a typo in a component's config or a
physics function of the wrong shape fails at load with its YAML path, never
in the first loop on the pad.

Contract: raises :class:`~zplatform.errors.ConfigError` naming the YAML path
(a component constructor that raises: :class:`~zplatform.errors.ControlError`
naming its path and class); blocks on reading the file and importing code.
``code=False`` (the ground verbs) runs the checks that need no mission code
and imports nothing of the mission's; the Data Vector layout is the same
either way; the deployment is not loaded. Sits above the control modules.

The checks in order: docs/architecture.md#the-loop (loading a mission).
"""

from __future__ import annotations

import os
from pathlib import Path

from ..config import (
    CONTROLLER_MODES,
    Mission,
    parse_mission,
    platform_elements,
    resolve_pythonpath,
)
from ..control import (
    commands,
    controllers,
    devices,
    interlocks,
    monitors,
    params,
    statemachine,
    watchdog,
)
from ..core import health
from ..core.messages import check_intra_host, check_lowlatency
from ..errors import ConfigError
from ..world import checks as world_checks

__all__ = ["check_mission", "decode_mission", "load_mission"]


def check_mission(mission: Mission, *, code: bool = True) -> None:
    """Run every semantic check on a parsed mission; raises on the first failure.

    ``mission`` comes from :func:`zplatform.config.parse_mission` (platform
    elements added). ``code=False``: import no mission code (module doc).
    Raises ConfigError naming the YAML path, or ControlError for a component
    constructor that raised. Logs unreachable states as warnings.
    """
    for i, c in enumerate(mission.controllers):
        if c.initial_mode not in CONTROLLER_MODES:
            raise ConfigError(
                f"initial_mode {c.initial_mode!r} is not one of {list(CONTROLLER_MODES)}",
                f"$.controllers[{i}].initial_mode",
            )
    statemachine.check_config(mission)
    interlocks.check_config(mission)
    commands.check_config(mission)
    params.check_config(mission)
    if code:
        _check_pythonpath(mission)
    # The world before the devices: a node's `driver: world` board is built
    # from it, so a bad world section is reported as itself.
    world_checks.check_config(mission, code=code)
    if code:
        controllers.check_config(mission)
        devices.check_config(mission)
    health.check_config(mission)
    _check_limits(mission)
    monitors.check_config(mission)
    watchdog.check_config(mission)
    _check_downlink(mission)
    check_lowlatency(mission)
    check_intra_host(mission)


def _check_pythonpath(mission: Mission) -> None:
    """Every directory the mission's code is imported from exists."""
    for i, d in enumerate(mission.pythonpath or ()):
        if not Path(d).is_dir():
            raise ConfigError(
                f"pythonpath directory {d!r} does not exist (entries are relative to the "
                "mission file)",
                f"$.pythonpath[{i}]",
            )


def _check_downlink(mission: Mission) -> None:
    """The radio downlink can be built (its packets fit, its budget holds one snapshot)."""
    if not mission.downlink.ccsds:
        return
    try:
        from ..telemetry.ccsds import CcsdsEncoder
    except ImportError:
        raise ConfigError(
            "the CCSDS downlink needs spacepackets: pip install 'zplatform[ground]'",
            "$.downlink.ccsds",
        ) from None
    d = mission.downlink
    try:
        CcsdsEncoder(mission, divisor=d.divisor, budget_bps=d.budget_bps, max_data=d.max_data)
    except ConfigError as exc:
        raise ConfigError(exc.reason, "$.downlink." + exc.path.split(".")[-1]) from exc


def _check_limits(mission: Mission) -> None:
    """Limits only on numeric scalars, each range in order (``lo <= hi``)."""
    from ..core.datavector import Layout

    layout = Layout.for_node(mission, "cn")
    platform = platform_elements(mission)
    for region, elements in mission.regions.items():
        first = len(platform.get(region, ()))  # the YAML's own list starts after them
        for i, e in enumerate(elements):
            if e.limits is None:
                continue
            w = f"$.regions.{region}[{i - first}].limits"
            spec = layout.element(e.name)
            if spec.count or spec.enum is not None or spec.scalar.kind == "bool":
                raise ConfigError(f"{e.name} is {spec.type_text}: only numbers have limits", w)
            for key in ("yellow", "red"):
                lo, hi = getattr(e.limits, key) or (None, None)
                if lo is not None and hi is not None and lo > hi:
                    raise ConfigError(f"{key} range [{lo}, {hi}] is not [lo, hi]", f"{w}.{key}")


def decode_mission(
    text: bytes | str,
    source: str = "<string>",
    *,
    code: bool = True,
    base_dir: str | Path | None = None,
) -> Mission:
    """Decode and fully check a mission from YAML text (see :func:`load_mission`).

    ``base_dir``: the directory the text's file lives in, which relative
    ``pythonpath`` entries and a relative recorder ``dir`` are relative to and which is the default
    ``pythonpath``. None: relative entries are relative to the current
    directory and the default is no directory at all (mission code is then
    imported from ``sys.path`` as it stands).
    """
    mission = parse_mission(text, source=source)
    mission.pythonpath = resolve_pythonpath(mission.pythonpath, base_dir)
    if mission.recorder is not None and mission.recorder.dir is not None:
        # Like pythonpath: relative to the mission file (the current directory without one).
        mission.recorder.dir = os.path.join(
            os.path.abspath(base_dir if base_dir is not None else os.curdir), mission.recorder.dir
        )
    if mission.archive.dir is not None:
        mission.archive.dir = os.path.join(
            os.path.abspath(base_dir if base_dir is not None else os.curdir), mission.archive.dir
        )
    check_mission(mission, code=code)
    return mission


def load_mission(path: str | Path, *, code: bool = True) -> Mission:
    """Read, decode and check a mission YAML file.

    Its ``pythonpath`` comes back absolute (default: the file's directory).
    ``code=False`` imports no mission code (module doc): for the tools that
    only need the layouts; the Data Vector layout is the same. Blocks on
    file I/O and (``code=True``) on importing the mission's modules. Raises
    :class:`ConfigError` naming the YAML path of the first bad field (see the
    module docstring for the order); never returns a partially valid mission.
    """
    p = Path(path)
    try:
        text = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read mission file {str(p)!r}: {exc.strerror}", "$") from exc
    return decode_mission(text, source=str(p), code=code, base_dir=p.parent)
