"""Run a node with the one-line fix proposed for the CN's sync queries
(``congestion_control=DROP`` on ``ControlSync``'s ``Session.get``), without
editing ``zplatform``: ``python -m tests.faults.cn_drop_patch node MISSION cn``.

For comparing the cable-cut cases with and without the fix
(``ZP_FAULTS_CN_DROP_PATCH=1``, see ``live.case_partition_netns``).
"""

from __future__ import annotations

import sys
from typing import Any

import zenoh

import zplatform.runtime.sync as zsync


class _DropGets:
    def __init__(self, session: zenoh.Session) -> None:
        self._s = session

    def get(self, *a: Any, **k: Any) -> Any:
        k.setdefault("congestion_control", zenoh.CongestionControl.DROP)
        return self._s.get(*a, **k)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._s, name)


_init = zsync.ControlSync.__init__


def _patched_init(self: zsync.ControlSync, session: zenoh.Session, *a: Any, **k: Any) -> None:
    _init(self, session, *a, **k)
    self.session = _DropGets(session)  # type: ignore[assignment]


zsync.ControlSync.__init__ = _patched_init  # type: ignore[method-assign]

if __name__ == "__main__":
    from zplatform.cli.main import main

    raise SystemExit(main(sys.argv[1:]))
