"""The ground tools an operator runs: ``zplatform cmd`` and the line prompt.

Each is one function over a :class:`~.link.GroundLink` (the CLI only parses
arguments and prints). Both refuse before anything is sent: an unknown
command or element, a value that does not fit, and a hazardous command or a
WRITE of a protected element that is not armed (:func:`~.logic.needs_arm`):
those go as ARM n, then the command n+1, in one step (``cmd ... --arm``,
``armed COMMAND [ARGS]`` at the prompt).
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections.abc import Iterable
from typing import TextIO

from ..config import Mission
from ..errors import CommandError, ZPlatformError
from ..uplink import validate_command
from .link import GroundLink
from .logic import needs_arm
from .records import CommandOutcome, EventRecord, format_outcome
from .status import RateMeter, status_line

__all__ = ["PROMPT_HELP", "check_command", "format_result", "run_prompt", "send_command"]

PROMPT_HELP = (
    "commands: launch | abort | noop | hold | resume | arm | write ELEMENT VALUE |\n"
    "          armed COMMAND [ARGS] (ARM n, then COMMAND n+1) | quit"
)


def check_command(
    mission: Mission, command: str, args: list[str], *, armed: bool, arm_hint: str
) -> tuple[str | None, str | None]:
    """``(element, value)`` of a command line, refused (CommandError) before
    anything is sent: bad arguments, and a command that needs ARM first
    without ``armed`` (``arm_hint`` says how to arm it in this tool)."""
    if len(args) > 2:
        raise CommandError(f"too many arguments: {args}")
    element = args[0] if args else None
    value = args[1] if len(args) > 1 else None
    cmd, _, _ = validate_command(mission, command, element, value)
    if armed and cmd == "ARM":
        raise CommandError("ARM is the confirmation itself: send it alone")
    why = needs_arm(mission, cmd, element)
    if why is not None and not armed:
        raise CommandError(f"{why}: send it as ARM n, then {cmd} n+1 ({arm_hint})")
    return element, value


def _steps(command: str, armed: bool) -> list[str]:
    return ["ARM", command.upper()] if armed else [command.upper()]


def format_result(outcomes: list[CommandOutcome], steps: list[str]) -> list[str]:
    """The lines that report one command: each outcome, then the steps not sent."""
    lines = [format_outcome(o) for o in outcomes]
    for cmd in steps[len(outcomes) :]:
        lines.append(f"{cmd}: not sent ({outcomes[-1].command} was not accepted)")
    return lines


def send_command(
    mission: Mission,
    command: str,
    args: list[str],
    *,
    armed: bool = False,
    timeout_s: float = 10.0,
    key_file: str | None = None,
) -> tuple[list[CommandOutcome], list[str]]:
    """Send one operator command and wait for its verdict(s) (``zplatform cmd``).

    Returns the outcomes and the steps the command meant to send (``["ARM",
    "LAUNCH"]`` armed). Refuses before opening a session (CommandError) what
    :func:`check_command` refuses; CommandError when telemetry, the CN or a
    verdict does not come within ``timeout_s`` (saying why).
    """
    element, value = check_command(mission, command, args, armed=armed, arm_hint="--arm")
    link = GroundLink(mission, key_file=key_file, commands=True)
    try:
        outcomes = link.command(command, element, value, armed=armed, timeout_s=timeout_s)
        return outcomes, _steps(command, armed)
    finally:
        link.close()


def _print_event(out: TextIO, rec: EventRecord) -> None:
    mark = " (unverified)" if rec.verified is False else ""
    print(f"EVENT{mark} {rec.node} {rec.severity} {rec.id}: {rec.text}", file=out, flush=True)


def run_prompt(
    mission: Mission,
    *,
    watch: Iterable[str] = (),
    interval_s: float = 1.0,
    timeout_s: float = 10.0,
    lines: Iterable[str] = sys.stdin,
    out: TextIO = sys.stdout,
) -> int:
    """The line prompt: a status line every ``interval_s`` (:func:`status_line`
    with ``watch``'s elements), every event as it comes, one command per
    line (``armed COMMAND [ARGS]`` for ARM n, then COMMAND n+1), until
    ``quit``, the end of ``lines`` or Ctrl-C. Blocks; returns 0.

    A reader thread only queues lines; this thread owns the link. Unknown
    ``watch`` elements fail at once (DataVectorError naming them).
    """
    watch = list(watch)
    link = GroundLink(mission, commands=True, on_event=lambda rec: _print_event(out, rec))
    try:
        for name in watch:
            link.dv.layout.element(name)
        queued: queue.SimpleQueue[str | None] = queue.SimpleQueue()

        def reader() -> None:
            for line in lines:
                queued.put(line)
            queued.put(None)

        threading.Thread(target=reader, name="prompt", daemon=True).start()
        print(PROMPT_HELP, file=out, flush=True)
        rate = RateMeter()
        last = 0.0
        while True:
            try:
                line = queued.get_nowait()
            except queue.Empty:
                line = ""
            if line is None:
                return 0
            words = line.split()
            if words and words[0] in ("quit", "exit"):
                return 0
            if words:
                _prompt_command(mission, link, words, timeout_s, out)
            if link.next(0.05) is None:
                continue
            rate.add_snapshot(link.dv)
            now = time.monotonic()
            if now - last >= interval_s:
                print(status_line(mission, link.dv, rate.hz, watch), file=out, flush=True)
                last = now
    except KeyboardInterrupt:
        return 0
    finally:
        link.close()


def _prompt_command(
    mission: Mission, link: GroundLink, words: list[str], timeout_s: float, out: TextIO
) -> None:
    armed = words[0].lower() == "armed"
    if armed:
        words = words[1:]
        if not words:
            print("refused: armed needs a COMMAND (armed launch)", file=out, flush=True)
            return
    try:
        element, value = check_command(
            mission, words[0], words[1:], armed=armed, arm_hint=f"armed {' '.join(words)}"
        )
    except ZPlatformError as exc:
        print(f"refused: {exc}", file=out, flush=True)
        return
    try:
        outcomes = link.command(words[0], element, value, armed=armed, timeout_s=timeout_s)
    except ZPlatformError as exc:
        print(f"error: {exc}", file=out, flush=True)
        return
    for text in format_result(outcomes, _steps(words[0], armed)):
        print(text, file=out, flush=True)
