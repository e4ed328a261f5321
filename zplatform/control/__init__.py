"""The sans-IO control logic: one loop step of a control or device node and
everything it runs (state machine, commands, interlocks, controllers,
devices, faults, monitors, parameters), every input's intake, and the
standby control node's failover. No zenoh, no threads of its own. The
layers: docs/architecture.md#package-layout.
"""
