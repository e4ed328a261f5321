"""The ground console (``zplatform ground MISSION [--web PORT]``).

* :mod:`.model`: :class:`ConsoleModel`, the console's state, sans-IO;
* :mod:`.link`: :class:`Link`, a thread over the ground link feeding the model
  and sending commands;
* :mod:`.app`: :class:`ConsoleApp`, the textual screen (terminal, or a browser
  through ``textual-serve``).

The screen needs ``textual`` (a dependency of zplatform); the model does
not, so the screen and the link are imported on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .model import ConsoleModel, Limits, LogLine, Status

if TYPE_CHECKING:
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
) -> int:
    """Run the console in this terminal until the operator quits. Blocks.

    ``limits``: extra element limits (:mod:`zplatform.limits`) over the mission's.
    """
    from ..mission import load_mission
    from .app import ConsoleApp
    from .link import Link

    mission = load_mission(mission_path)
    model = ConsoleModel(mission, los_s=los_s, limits=limits)
    app = ConsoleApp(model, Link(model, timeout_s=timeout_s))
    return app.run() or 0


def serve_console(
    mission_path: str,
    port: int,
    *,
    host: str = "127.0.0.1",
    timeout_s: float = 10.0,
    limits_path: str | None = None,
) -> None:
    """Serve the console to browsers on ``http://host:port`` until Ctrl-C. Blocks.

    ``textual-serve`` starts one console process per browser tab (the same
    ``zplatform ground MISSION`` command), so each viewer has its own session.
    """
    import shlex
    import sys
    from pathlib import Path

    from textual_serve.server import Server

    from ..mission import load_mission

    mission = load_mission(mission_path)  # fail here, not in every browser tab
    cmd = " ".join(
        shlex.quote(a)
        for a in (
            sys.executable,
            "-m",
            "zplatform",
            "ground",
            str(Path(mission_path).resolve()),
            "--console",
            "--timeout",
            str(timeout_s),
            *(["--limits", str(Path(limits_path).resolve())] if limits_path else []),
        )
    )
    Server(cmd, host=host, port=port, title=f"zplatform ground - {mission.mission}").serve()
