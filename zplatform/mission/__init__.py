"""A mission file checked whole: :func:`~zplatform.mission.load.load_mission`
(the structs of :mod:`zplatform.config`, then every semantic check), its
JSON Schema and reference page, and ``check``'s safety smells. The layers:
docs/architecture.md#package-layout.
"""
