"""Argument checks shared by the ``zplatform`` verbs.

Everything here turns a user mistake into a one-line message before any
process is spawned or any file is half-written: argparse ``type=`` functions
for numbers (``--duration -1`` is refused by argparse, exit 2) and
:func:`check_output` / :func:`check_ports` for paths and endpoints
(:class:`~zplatform.errors.CommandError`, exit 2).
"""

from __future__ import annotations

import argparse
import errno
import os
import socket
from pathlib import Path

from ..config import Mission
from ..control.authority import Signer
from ..errors import CommandError

__all__ = [
    "MISSION_HELP",
    "check_output",
    "check_ports",
    "identity_options",
    "mission_verb",
    "nonnegative_float",
    "positive_float",
    "positive_int",
    "signer_of",
    "timeout_option",
]


MISSION_HELP = "mission YAML file, or the name of a running mission (`zplatform ps`)"


def mission_verb(
    sub: argparse._SubParsersAction[argparse.ArgumentParser],
    name: str,
    *,
    help: str,
    description: str | None = None,
) -> argparse.ArgumentParser:
    """A verb's parser whose first argument is MISSION (a file or a running
    mission's name)."""
    p = sub.add_parser(name, help=help, description=description)
    p.add_argument("mission", help=MISSION_HELP)
    return p


def identity_options(p: argparse.ArgumentParser) -> None:
    """``--operator NAME --station NAME``: who commands, from where (a
    mission with ``ground:``; their key files come from the key directory)."""
    p.add_argument(
        "--operator",
        metavar="NAME",
        help="the operator who commands (ground.operators; key file operator-NAME.keys)",
    )
    p.add_argument(
        "--station",
        metavar="NAME",
        help="the station commanded from (ground.stations; key file station-NAME.keys)",
    )


def signer_of(
    mission: Mission, args: argparse.Namespace, *, commands: bool = True
) -> Signer | None:
    """The signer of ``args.operator``/``args.station``
    (:func:`zplatform.ground.identity.station_signer`): CommandError or
    KeyError_ (one line) before anything starts. ``commands`` False: a
    ground that sends nothing needs no operator (None without the flags)."""
    from ..ground.identity import station_signer

    operator, station = getattr(args, "operator", None), getattr(args, "station", None)
    if not commands and operator is None and station is None:
        return None
    return station_signer(mission, operator, station)


def timeout_option(p: argparse.ArgumentParser, what: str, default: float = 10.0) -> None:
    """``--timeout S`` (> 0, ``default`` seconds): how long to wait for ``what``."""
    p.add_argument(
        "--timeout",
        type=positive_float,
        default=default,
        metavar="S",
        help=f"seconds to wait for {what} (default {default:g})",
    )


def _seconds(text: str, *, zero_ok: bool) -> float:
    """A finite number of seconds, > 0 (>= 0 when ``zero_ok``); NaN is
    refused too. Raises ArgumentTypeError saying which."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not (v >= 0 if zero_ok else v > 0) or v == float("inf"):
        raise argparse.ArgumentTypeError(f"must be {'>=' if zero_ok else '>'} 0, got {text}")
    return v


def positive_float(text: str) -> float:
    """argparse type: a number > 0."""
    return _seconds(text, zero_ok=False)


def nonnegative_float(text: str) -> float:
    """argparse type: a number >= 0."""
    return _seconds(text, zero_ok=True)


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return v


def check_output(path: str | os.PathLike[str], what: str) -> None:
    """Refuse an output file that cannot be written (CommandError naming it).

    Checks without creating anything: the parent is an existing directory we
    may write in, and the path itself is not a directory or a read-only file.
    """
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise CommandError(f"cannot write {what} {str(p)!r}: it is a directory")
    if not parent.exists():
        raise CommandError(f"cannot write {what} {str(p)!r}: no directory {str(parent)!r}")
    if not parent.is_dir():
        raise CommandError(f"cannot write {what} {str(p)!r}: {str(parent)!r} is not a directory")
    if p.exists() and not os.access(p, os.W_OK):
        raise CommandError(f"cannot write {what} {str(p)!r}: permission denied")
    if not p.exists() and not os.access(parent, os.W_OK | os.X_OK):
        raise CommandError(f"cannot write {what} {str(p)!r}: permission denied in {str(parent)!r}")


def _tcp_host_port(endpoint: str) -> tuple[str, int] | None:
    """``tcp/HOST:PORT`` or ``tls/HOST:PORT`` -> (host, port); None for other
    protocols or shapes."""
    proto, _, rest = endpoint.partition("/")
    if proto not in ("tcp", "tls"):
        return None
    rest = rest.split("#", 1)[0]
    host, sep, port = rest.rpartition(":")
    if not sep or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def check_ports(mission: Mission) -> None:
    """Refuse to start when a node's TCP listen port (or the vehicle world's UDP port) is taken.

    Binds each port once (and lets go): a busy port means another ``up`` of
    this mission, or another program, holds it. Only "address in use" is
    reported; any other bind error is zenoh's to report.
    """
    if mission.world is not None:  # the vehicle world's UDP port
        host, _, port_text = mission.world.listen.rpartition(":")
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            try:
                s.bind((host.strip("[]"), int(port_text)))
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    raise CommandError(
                        f"port {port_text} (the vehicle world's UDP listen) is in use: is this "
                        "mission already running? see `zplatform ps`; use --free-ports to run "
                        "beside it"
                    ) from None
    for name, node in mission.nodes.items():
        for ep in node.listen:
            hp = _tcp_host_port(ep)
            if hp is None or hp[1] == 0:
                continue
            host, port = hp
            family = socket.AF_INET6 if ":" in host else socket.AF_INET
            with socket.socket(family, socket.SOCK_STREAM) as s:
                # SO_REUSEADDR: a port in TIME_WAIT after the last run is free.
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                try:
                    s.bind((host, port))
                except OSError as exc:
                    if exc.errno == errno.EADDRINUSE:
                        raise CommandError(
                            f"port {port} ({name}'s listen endpoint {ep}) is in use: is this "
                            "mission already running? see `zplatform ps`; use --free-ports "
                            "to run beside it"
                        ) from None
                    continue
