"""The data core: the Data Vector, the region frame and its tag, the event
catalogue, message sizing, and the bases every part of a node builds on
(components, health elements). Sans-IO; imports only ``config`` and the
root modules. The layers: docs/architecture.md#package-layout.
"""
