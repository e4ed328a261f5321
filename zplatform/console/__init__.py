"""The ground console (``zplatform ground MISSION [--web PORT]``).

* :mod:`.model`: :class:`ConsoleModel`, the console's state, sans-IO;
* :mod:`.link`: :class:`Link`, a thread over the ground link feeding the model
  and sending commands;
* :mod:`.app`: :class:`ConsoleApp`, the textual screen (terminal, or a browser);
* :mod:`.history`: where history comes from (the ground archive on this host,
  or the ground node's over zenoh); :mod:`.historyview`: its screens (an
  element over a time range, the run picker);
* :mod:`.web`: the web server that gives each operator's browser session its
  own console process; :mod:`.webdriver`: that process's textual driver.

The screen needs ``textual`` (a dependency of zplatform); the model does
not, so the screen and the link are imported on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .model import ConsoleModel, Limits, LogLine, Status

if TYPE_CHECKING:
    from ..control.authority import Signer
    from .app import ConfirmScreen, ConsoleApp
    from .link import Link

__all__ = [
    "ConfirmScreen",
    "ConsoleApp",
    "ConsoleModel",
    "Limits",
    "Link",
    "LogLine",
    "Status",
    "run_console",
    "serve_console",
]


def __getattr__(name: str) -> Any:
    if name in ("ConfirmScreen", "ConsoleApp"):
        from . import app

        return getattr(app, name)
    if name == "Link":
        from .link import Link

        return Link
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def run_console(
    mission_path: str,
    *,
    timeout_s: float = 10.0,
    los_s: float = 0.3,
    limits: dict[str, object] | None = None,
    history_min: float | None = None,
    plot: list[str] | None = None,
    signer: Signer | None = None,
) -> int:
    """Run the console in this terminal until the operator quits. Blocks.

    ``limits``: extra element limits (:mod:`zplatform.control.limits`) over the mission's;
    ``history_min``: minutes of history to open with (None: the default,
    :data:`~.history.DEFAULT_HISTORY_MIN`; 0: none); ``plot``: elements
    plotted from the start (their history filled too); ``signer``: the
    operator and station its commands are signed as (None: it only watches;
    :func:`zplatform.ground.identity.station_signer`). Raises CommandError
    for an element ``plot`` cannot plot.
    """
    from ..mission.load import load_mission
    from .app import ConsoleApp
    from .history import DEFAULT_HISTORY_MIN, history_source
    from .link import Link

    mission = load_mission(mission_path, code=False)
    minutes = DEFAULT_HISTORY_MIN if history_min is None else history_min
    model = ConsoleModel(mission, los_s=los_s, limits=limits, history_s=minutes * 60)
    if plot:
        model.set_plot(plot)
    link = Link(model, timeout_s=timeout_s, signer=signer)
    app = ConsoleApp(model, link, history=history_source(mission))
    return app.run() or 0


def serve_console(
    mission_path: str,
    port: int,
    *,
    host: str = "127.0.0.1",
    timeout_s: float = 10.0,
    los_s: float = 0.3,
    limits_path: str | None = None,
    history_min: float | None = None,
    plot: list[str] | None = None,
    operator: str | None = None,
    station: str | None = None,
) -> None:
    """Serve the console to the operator's browser on ``http://host:port`` until Ctrl-C. Blocks.

    Prints the address to open, with its one-time token; every browser
    session is its own ``zplatform ground MISSION --console`` process, which
    ends with the session and with the server (:mod:`.web`); with
    ``operator`` and ``station``, each signs its commands as them.
    """
    import sys
    from pathlib import Path

    from ..mission.load import load_mission
    from ..runtime.process import setup_logging
    from .web import WebConsole

    mission = load_mission(mission_path, code=False)  # fail here, not in every browser tab
    argv = [
        sys.executable,
        "-m",
        "zplatform",
        "ground",
        str(Path(mission_path).resolve()),
        "--console",
        "--timeout",
        str(timeout_s),
        "--los",
        str(los_s),
        *(["--limits", str(Path(limits_path).resolve())] if limits_path else []),
        *(["--history", str(history_min)] if history_min is not None else []),
        *(["--plot", *plot] if plot else []),
        *(["--operator", operator] if operator else []),
        *(["--station", station] if station else []),
    ]
    setup_logging()
    WebConsole(argv, host=host, port=port, title=f"zplatform ground - {mission.mission}").serve()
