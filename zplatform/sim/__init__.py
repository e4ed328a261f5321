"""Runs without the vehicle: the lockstep runner (the whole mission in one
process, in virtual time), the replay recording of a live control node's
inputs, and the world's process (``zplatform world MISSION``). The layers:
docs/architecture.md#package-layout.
"""
