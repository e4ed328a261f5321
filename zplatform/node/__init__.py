"""The zenoh runtime of each node kind: ``control``, ``device``, ``ground``.

Each module is a driver of the sans-IO loop in :mod:`zplatform.control.loop`: it
opens the session, moves frames between zenoh and the loop, and keeps the
time. None of them holds protocol logic of its own.
"""
