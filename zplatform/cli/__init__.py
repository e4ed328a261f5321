"""The ``zplatform`` command: thin fronts that parse arguments and call the
library (``main.py``, ``args.py``, ``runtime.py``, ``ground.py``,
``sim.py``), ``up``'s supervisor of the node processes, the registry of
running missions and the XTCE export. Nothing below imports it. The layers:
docs/architecture.md#package-layout.
"""
