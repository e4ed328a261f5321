"""The vehicle world: its model (physics behind several nodes' boards) and the
checks of a mission's world section. Sans-IO; its process is
:mod:`zplatform.sim.world_server`. The layers:
docs/architecture.md#package-layout.
"""
