"""The zenoh runtime and the process: sessions and the key space on zenoh,
the sync, bulk channels, the clock exchange, the one way to ask, node
clocks, the periodic loop and real-time set-up, and what every node
process shares (logging, events, stop and parent watch). The layers:
docs/architecture.md#package-layout.
"""
