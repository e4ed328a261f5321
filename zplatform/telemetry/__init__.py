"""What comes down and what is kept of it: the typed records the ground, the
logs, the summaries and the console share, the CSV and event logs, the
CCSDS downlink and the run summaries. The layers:
docs/architecture.md#package-layout.
"""
