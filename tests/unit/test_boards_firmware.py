"""The C reference firmware compiles as portable C99 and speaks the spec's bytes."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

SOURCE = Path(__file__).resolve().parents[2] / "firmware" / "serial_board" / "serial_board.c"
GCC = shutil.which("gcc")

pytestmark = [
    pytest.mark.skipif(GCC is None, reason="no gcc on PATH"),
    pytest.mark.timeout(60),
]


def test_compiles_as_c99_without_warnings(tmp_path: Path) -> None:
    assert GCC is not None
    r = subprocess.run(
        [GCC, "-std=c99", "-Wall", "-Wextra", "-pedantic", "-Werror", "-c", str(SOURCE),
         "-o", str(tmp_path / "serial_board.o")],
        capture_output=True, text=True, timeout=50,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr


def test_selftest_matches_the_worked_example(tmp_path: Path) -> None:
    """HELLO, garbage, then the spec's WRITE: the C device answers with the spec's bytes."""
    assert GCC is not None
    exe = tmp_path / "sb_selftest"
    r = subprocess.run(
        [GCC, "-std=c99", "-Wall", "-Werror", "-DSB_SELFTEST", str(SOURCE), "-o", str(exe)],
        capture_output=True, text=True, timeout=50,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    out = subprocess.run([str(exe)], capture_output=True, text=True, timeout=10).stdout
    assert out.splitlines() == [
        "crc 29b1",
        "03 01 81 01 04 08 01 c8 03 7b 48 00",  # HELLO_ACK: D=8, A=1, watchdog 200 ms
        "03 01 7f 01 02 01 02 fe 01 00",  # ERROR BAD_CRC (seq 0) for the garbage
        "04 01 82 01 02 15 01 01 01 01 01 01 01 01 05 c0 3f 9d 48 00",  # INPUTS
    ]
