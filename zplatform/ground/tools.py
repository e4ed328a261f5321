"""The ground tools an operator runs: ``zplatform cmd``, ``zplatform params`` and the line prompt.

Each is one function over a :class:`~.link.GroundLink` (the CLI only parses
arguments and prints). Both refuse before anything is sent: an unknown
command, element or parameter, a value that does not fit (or lies outside a
parameter's bounds), and a hazardous command, a WRITE of a protected
element or a PRM_SET of a hazardous parameter that is not armed
(:func:`~.logic.needs_arm`):
those go as ARM n, then the command n+1, in one step (``cmd ... --arm``,
``armed COMMAND [ARGS]`` at the prompt).
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections.abc import Callable, Iterable
from typing import TextIO

import msgspec

from ..config import Mission
from ..control.authority import Signer
from ..control.params import ParamFileError, decode_params, params_path, read_params_file
from ..control.uplink import CheckedCommand, validate_command, validate_words
from ..errors import CommandError, ZPlatformError
from ..telemetry.records import CommandOutcome, EventRecord, ParamRow, format_outcome, param_rows
from .link import GroundLink
from .logic import needs_arm
from .status import RateMeter, status_line

__all__ = [
    "PROMPT_HELP",
    "ParamListing",
    "check_command",
    "format_result",
    "list_params",
    "run_prompt",
    "send_command",
    "set_param",
]

PROMPT_HELP = (
    "commands: launch | abort | noop | hold | resume | arm | write ELEMENT VALUE |\n"
    "          prm_set PARAMETER VALUE | prm_save |\n"
    "          armed COMMAND [ARGS] (ARM n, then COMMAND n+1) | quit"
)


def check_command(
    mission: Mission, command: str, args: list[str], *, armed: bool, arm_hint: str
) -> CheckedCommand:
    """A command line checked (:func:`~zplatform.control.uplink.validate_words`) and
    refused (CommandError) before anything is sent: bad arguments, and a
    command that needs ARM first without ``armed`` (``arm_hint`` says how
    to arm it in this tool). The link sends what it returns unchecked."""
    checked = validate_words(mission, command, args)
    if armed and checked.command == "ARM":
        raise CommandError("ARM is the confirmation itself: send it alone")
    why = needs_arm(mission, checked.command, args[0] if args else None)
    if why is not None and not armed:
        raise CommandError(f"{why}: send it as ARM n, then {checked.command} n+1 ({arm_hint})")
    return checked


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
    signer: Signer | None = None,
) -> tuple[list[CommandOutcome], list[str]]:
    """Send one operator command and wait for its verdict(s) (``zplatform cmd``).

    Returns the outcomes and the steps the command meant to send (``["ARM",
    "LAUNCH"]`` armed). Refuses before opening a session (CommandError) what
    :func:`check_command` refuses; CommandError when telemetry, the CN or a
    verdict does not come within ``timeout_s`` (saying why). ``signer``:
    the operator and station the requests name (a mission with ``ground:``).
    """
    checked = check_command(mission, command, args, armed=armed, arm_hint="--arm")
    link = GroundLink(mission, key_file=key_file, commands=True, signer=signer)
    try:
        outcomes = link.command(
            checked, armed=armed, timeout_s=timeout_s, on_approval=_approval_hint(mission)
        )
        return outcomes, _steps(command, armed)
    finally:
        link.close()


def approval_line(mission: Mission, arm: int) -> str:
    """What an operator is told while their two-person command waits."""
    return (
        f"ARM #{arm} accepted: waiting for a second operator's approval "
        f"(`zplatform cmd {mission.mission} approve {arm} --operator NAME --station NAME`)"
    )


def _approval_hint(mission: Mission, out: TextIO | None = None) -> Callable[[int], None]:
    def tell(arm: int) -> None:
        print(approval_line(mission, arm), file=out or sys.stdout, flush=True)

    return tell


class ParamListing(msgspec.Struct, frozen=True):
    """What ``zplatform params MISSION`` shows: ``source`` says where the
    values come from (live telemetry, the parameter file on this host, or
    nowhere), then the rows."""

    mission: str
    source: str
    live: bool
    rows: list[ParamRow]


def list_params(
    mission: Mission, *, timeout_s: float = 10.0, key_file: str | None = None
) -> ParamListing:
    """The mission's parameters, with their values from live telemetry
    when its control node is alive (waiting up to ``timeout_s`` for a
    snapshot), else from the parameter file on this host, if there is a
    usable one. Blocks; CommandError when the CN is alive but no telemetry
    comes."""
    if not mission.params:
        raise CommandError(f"mission {mission.mission!r} has no parameters")
    link = GroundLink(mission, key_file=key_file, events=False)
    try:
        if set(mission.control_nodes) & set(link.alive_nodes()):
            link.wait_joined(timeout_s)
            dv = link.dv
            values = {p.name: dv.get(p.name) for p in mission.params}
            source = (
                f"live telemetry, loop {dv.get('cn_loop')} in state {dv.get_name('cn_state')}; "
                f"file: {dv.get_name('cn_prm_load_status')} at start; last save: "
                f"#{dv.get('cn_prm_save_seq')} {dv.get_name('cn_prm_save_status')}"
                + ("; unsaved changes" if dv.get("cn_prm_unsaved") else "")
            )
            return ParamListing(mission.mission, source, True, param_rows(mission, values))
    finally:
        link.close()
    path = params_path(mission)
    data = read_params_file(path)
    if isinstance(data, bytes):
        try:
            f = decode_params(mission, data)
        except ParamFileError as exc:
            why = f"the parameter file {path} is refused ({exc.status.name}: {exc})"
        else:
            return ParamListing(
                mission.mission,
                f"not running; values saved in {path} by PRM_SAVE #{f.seq}",
                False,
                param_rows(mission, f.values),
            )
    elif data is None:
        why = f"no parameter file at {path}"
    else:
        why = f"cannot read {path}: {data.strerror}"
    return ParamListing(
        mission.mission,
        f"not running; {why}: it starts at the defaults",
        False,
        param_rows(mission, None),
    )


def set_param(
    mission: Mission,
    name: str | None,
    value: str | None,
    *,
    armed: bool = False,
    save: bool = False,
    timeout_s: float = 10.0,
    key_file: str | None = None,
    signer: Signer | None = None,
) -> tuple[list[str], bool]:
    """``zplatform params MISSION NAME VALUE [--arm] [--save]``: PRM_SET
    (ARM n first when ``armed``), then with ``save`` PRM_SAVE, and wait
    until the control node has written the file. ``name`` None: only the
    save. Returns the lines to print and whether everything succeeded
    (every verdict ACCEPTED, the save SAVED). Refuses before sending
    (CommandError) what :func:`check_command` refuses; CommandError when
    telemetry or a verdict does not come within ``timeout_s``."""
    prm_set = prm_save = None
    if name is not None:
        prm_set = check_command(
            mission, "prm_set", [name, value or ""], armed=armed, arm_hint="--arm"
        )
    elif armed:
        raise CommandError("--arm arms a PRM_SET: give NAME VALUE")
    elif not save:
        raise CommandError("nothing to do: give NAME VALUE, --save, or both")
    if save:
        prm_save = validate_command(mission, "prm_save")
    events: list[EventRecord] = []
    link = GroundLink(
        mission, key_file=key_file, commands=True, on_event=events.append, signer=signer
    )
    lines: list[str] = []
    try:
        if prm_set is not None:
            outcomes = link.command(prm_set, armed=armed, timeout_s=timeout_s)
            steps = _steps("prm_set", armed)
            lines += format_result(outcomes, steps)
            if len(outcomes) != len(steps) or not all(o.accepted for o in outcomes):
                return lines, False
        if prm_save is None:
            return lines, True
        (saved,) = link.command(prm_save, timeout_s=timeout_s)
        lines.append(format_outcome(saved))
        if not saved.accepted:
            return lines, False
        line, ok = _wait_saved(link, saved, events, timeout_s)
        lines.append(line)
        return lines, ok
    finally:
        link.close()


def _wait_saved(
    link: GroundLink, outcome: CommandOutcome, events: list[EventRecord], timeout_s: float
) -> tuple[str, bool]:
    """After PRM_SAVE's verdict ``outcome``: wait for the control node to
    finish that save (``cn_prm_save_seq``/``cn_prm_save_status``, up to
    ``timeout_s``); returns the line that says how it ended and whether it
    is SAVED. ``events``: the records the link's ``on_event`` collects (the
    CN's ``prm_saved``/``prm_save_failed`` give the where and why)."""
    dv = link.dv
    deadline = time.monotonic() + timeout_s
    while True:
        if dv.get("cn_prm_save_seq") == outcome.seq and dv.get_name("cn_prm_save_status") in (
            "SAVED",
            "FAILED",
        ):
            break
        if time.monotonic() > deadline:
            return f"PRM_SAVE #{outcome.seq}: no result within {timeout_s:g} s", False
        link.next(0.1)
    status = dv.get_name("cn_prm_save_status")
    tag = f"#{outcome.seq}"
    end = time.monotonic() + 0.5  # the reason: the CN's event, when it comes
    while True:
        text = next(
            (e.text for e in events if e.id in ("prm_saved", "prm_save_failed") and tag in e.text),
            None,
        )
        if text is not None or time.monotonic() > end:
            break
        link.next(0.05)
    return f"PRM_SAVE #{outcome.seq}: {status}" + (f": {text}" if text else ""), status == "SAVED"


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
    signer: Signer | None = None,
) -> int:
    """The line prompt: a status line every ``interval_s`` (:func:`status_line`
    with ``watch``'s elements), every event as it comes, one command per
    line (``armed COMMAND [ARGS]`` for ARM n, then COMMAND n+1), until
    ``quit``, the end of ``lines`` or Ctrl-C. Blocks; returns 0. ``signer``:
    who commands (a mission with ``ground:``); the prompt keeps their command
    lock while they hold it, until they release it or the prompt ends.

    A reader thread only queues lines; this thread owns the link. Unknown
    ``watch`` elements fail at once (DataVectorError naming them).
    """
    watch = list(watch)
    link = GroundLink(
        mission, commands=True, on_event=lambda rec: _print_event(out, rec), signer=signer
    )
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
    if mission.authority and not link.logic.operator:
        print(
            "refused: this mission has command authority (ground:): start the prompt with "
            "--operator NAME --station NAME to command",
            file=out,
            flush=True,
        )
        return
    try:
        checked = check_command(
            mission, words[0], words[1:], armed=armed, arm_hint=f"armed {' '.join(words)}"
        )
    except ZPlatformError as exc:
        print(f"refused: {exc}", file=out, flush=True)
        return
    try:
        outcomes = link.command(
            checked, armed=armed, timeout_s=timeout_s, on_approval=_approval_hint(mission, out)
        )
    except ZPlatformError as exc:
        print(f"error: {exc}", file=out, flush=True)
        return
    for text in format_result(outcomes, _steps(words[0], armed)):
        print(text, file=out, flush=True)
