"""The console's ARM question is shown whole, however long, on any screen width."""

from __future__ import annotations

import asyncio
import re

import pytest
from textual.app import App
from textual.widgets import Label

from zplatform.console import ConfirmScreen

QUESTION = (
    "write dn0_ign_armed true is protected: a WRITE of it needs ARM first "
    "(commands.protected); the igniter circuit of dn0 arms with it, and the CN checks "
    "the state machine's whitelist for SAFE before it accepts. Send ARM, then WRITE "
    "dn0_ign_armed = true (element 87 of the CN vector)?"
)


class _Host(App[None]):
    def on_mount(self) -> None:
        self.push_screen(ConfirmScreen(QUESTION))


@pytest.mark.parametrize("size", [(80, 24), (200, 50), (300, 60)])
def test_a_long_arm_question_wraps_inside_the_dialog(size: tuple[int, int]) -> None:
    async def go() -> tuple[int, int, str]:
        app = _Host()
        async with app.run_test(size=size) as pilot:
            await pilot.pause()
            label = app.screen.query_one("#question", Label)
            shot = app.export_screenshot()
            return label.region.right, size[0], shot

    right, width, shot = asyncio.run(go())
    assert right <= width
    text = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", shot).replace("&#160;", " "))
    assert "element 87 of the CN vector)?" in text
