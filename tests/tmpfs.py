"""A small tmpfs of a test's own, for a real full disk (the archive's and
the health monitor's full-disk tests).

Mounting needs root and mount(8): where either is missing, or the mount is
refused, the test is skipped, saying why (never failed)."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest


@contextlib.contextmanager
def mounted_tmpfs(where: Path, size: str = "2m") -> Iterator[Path]:
    """A tmpfs of ``size`` (mount's ``size=`` option) at ``where`` (made
    here; it must not exist), unmounted at the end (lazily if a handle is
    left open). Skips the calling test when it cannot be mounted."""
    where.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs for a real full disk needs root and mount(8)")
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
        capture_output=True,
        text=True,
        check=False,
    )
    if r.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs for a real full disk: {r.stderr.strip()}")
    try:
        yield where
    finally:
        if subprocess.run(["umount", str(where)], check=False).returncode != 0:
            subprocess.run(["umount", "-l", str(where)], check=False)  # a handle left: detach


def fill(path: Path, leave: int = 0) -> None:
    """Write ``path`` until its disk is full, then give ``leave`` bytes back
    (a writer then fills those itself, its last writes cut short as on a
    real disk)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)
    try:
        with contextlib.suppress(OSError):
            while True:
                os.write(fd, b"\0" * 4096)
        with contextlib.suppress(OSError):  # the last bytes, one by one
            while True:
                os.write(fd, b"\0")
        if leave:
            os.ftruncate(fd, max(0, os.fstat(fd).st_size - leave))
    finally:
        os.close(fd)
