"""A zenoh session of the test process alone, for in-process round trips."""

from __future__ import annotations

import zenoh


def lone_session() -> zenoh.Session:
    """A peer that listens nowhere and scouts for no one: what it publishes
    or queries reaches only its own subscribers and queryables (no other
    test's nodes, whatever runs beside). The caller closes it."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)
