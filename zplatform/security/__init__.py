"""Who may say what where: the key space as one table, zenoh's access control
and TLS deployment files, and the mission PKI. The frame tags themselves
are :mod:`zplatform.core.auth` (under the frame). The layers:
docs/architecture.md#package-layout.
"""
