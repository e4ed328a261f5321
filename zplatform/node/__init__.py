"""The nodes of a mission: per-loop logic and the zenoh runtime around it.

:mod:`zplatform.node.logic` holds each node's sans-IO loop step
(:class:`~zplatform.node.logic.ControlLogic`,
:class:`~zplatform.node.logic.DeviceLogic`), driven both by the zenoh runtime
(``control``, ``device``, ``ground``) and by the lockstep runner
(:mod:`zplatform.lockstep`). Importing this package does not import zenoh.
"""

from __future__ import annotations

from .logic import ControlLogic, DeviceLogic

__all__ = ["ControlLogic", "DeviceLogic"]
