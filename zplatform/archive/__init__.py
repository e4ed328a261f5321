"""The ground archive: every run the ground node receives, kept and queryable.

The ground node writes it by default (a mission's ``archive`` section,
:class:`~zplatform.config.ArchiveConfig`): every accepted snapshot, gap-filled
loops included, and every event, as raw checksummed segments (the flight
recorder's format, the source of truth) and as Parquet files partitioned by
run and hour, one column per element. The package: :mod:`.store` (the
files), :mod:`.writer` (:class:`ArchiveWriter`: the receive path copies, a
thread writes), :mod:`.query` (:class:`Archive`, :class:`Query`: DuckDB in
process) and :mod:`.cli` (``zplatform archive``).

Contract: the receive path never blocks on the archive; a reader never sees
half a file. The guide: docs/archive.md.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..config import Mission
from .query import Archive, Query
from .store import RunInfo
from .writer import ArchiveWriter

__all__ = ["ARCHIVE_DIR_ENV", "Archive", "ArchiveWriter", "Query", "RunInfo", "archive_dir"]

ARCHIVE_DIR_ENV = "ZPLATFORM_ARCHIVE_DIR"


def archive_dir(mission: Mission) -> Path:
    """Where ``mission``'s archive lives: ``$ZPLATFORM_ARCHIVE_DIR/<mission>``
    when that is set, else ``<archive.dir>/<mission>`` (made absolute when the
    mission loaded), else ``zplatform/archive/<mission>`` in the state
    directory (``$XDG_STATE_HOME``, ``~/.local/state``; ``/var/lib`` for root)."""
    env = os.environ.get(ARCHIVE_DIR_ENV)
    if env:
        return Path(env) / mission.mission
    if mission.archive.dir is not None:
        return Path(mission.archive.dir) / mission.mission
    if os.geteuid() == 0:
        base = Path("/var/lib")
    else:
        base = Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state")
    return base / "zplatform" / "archive" / mission.mission
