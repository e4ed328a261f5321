"""What an operator types is checked with the same "did you mean" `check`
gives: command names (in a script and on the command line) and elements."""

from __future__ import annotations

from pathlib import Path

import pytest

from zplatform import CommandError
from zplatform.control.uplink import parse_commands, validate_command
from zplatform.mission.load import load_mission

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def test_a_mistyped_command_gets_its_closest_name() -> None:
    mission = load_mission(CONFIGS / "led_test.yaml", code=False)
    with pytest.raises(CommandError, match=r"unknown command 'lanch'; did you mean launch\?"):
        validate_command(mission, "lanch")
    with pytest.raises(CommandError, match=r"s:2: unknown command 'abrt'; did you mean abort\?"):
        parse_commands("at 1 launch\nat 2 abrt\n", "s")
    # Nothing close: the whole list, as before.
    with pytest.raises(CommandError, match="unknown command 'zzz'; expected one of noop, "):
        validate_command(mission, "zzz")


def test_a_mistyped_element_gets_its_closest_names() -> None:
    mission = load_mission(CONFIGS / "led_test.yaml", code=False)
    with pytest.raises(CommandError, match=r"'led_a_cmdd'.*did you mean led_a_cmd"):
        validate_command(mission, "write", "led_a_cmdd", "1")
