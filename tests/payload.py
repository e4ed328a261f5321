"""A stand-in for a zenoh payload in in-process intake tests."""

from __future__ import annotations


class Bytes:
    """A payload as zenoh hands it over: the length for free; ``to_bytes``
    counted (class-wide), so a test can tell a frame was refused unread."""

    copies = 0

    def __init__(self, data: bytes) -> None:
        self._data = data

    def __len__(self) -> int:
        return len(self._data)

    def to_bytes(self) -> bytes:
        Bytes.copies += 1
        return self._data
