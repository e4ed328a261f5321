"""Event records: what a node tells the operator, apart from telemetry.

An :class:`Event` is one record (severity, id, text, time) published on
``{vehicle}/{node}/events`` (DESIGN.md §3). Node logic never publishes: it
calls :meth:`EventLog.emit`, which appends to a bounded in-memory queue, and
the runtime takes the queue after the loop (:meth:`~EventLog.drain`) and
publishes what it took. So emitting is sans-IO, never blocks and never raises.

The log is bounded (``capacity`` events between two drains). When it is full
the *oldest* pending events are kept and new ones are counted in
:attr:`EventLog.dropped`: the first events of a burst usually say what went
wrong, the rest repeat it. Every emitted event takes the next ``seq`` number,
dropped ones included, so a receiver sees a drop as a gap in ``seq``.

Wire form: MessagePack of the struct as a map (``{"node": ..., "seq": ...}``),
self-describing so a tap in any language can print it.
:func:`decode_event` raises :class:`~zplatform.errors.FrameFormatError` on
anything that is not an event record.
"""

from __future__ import annotations

import enum
from typing import Annotated

import msgspec
from msgspec import Meta

from .errors import FrameFormatError

__all__ = ["Event", "EventLog", "Severity", "decode_event", "encode_event"]


class Severity(enum.IntEnum):
    """How much an event matters (the ``severity`` of an :class:`Event`)."""

    DEBUG = 0
    INFO = 1
    WARNING = 2
    ERROR = 3
    CRITICAL = 4


_SEVERITY_NAMES = tuple(s.name for s in Severity)


class Event(msgspec.Struct, frozen=True, gc=False):
    """One event record.

    ``node`` is the emitting node (``cn``, ``dn0``, ...), ``seq`` its event
    number (0, 1, 2, ... per node, gaps are drops), ``t_ns`` the loop time
    of the emitting node, ``severity`` a :class:`Severity` value, ``id`` a
    stable machine-readable key (``state_change``, ``cmd_rejected``, ...)
    and ``text`` the human-readable message.
    """

    node: str
    seq: Annotated[int, Meta(ge=0)]
    t_ns: int
    severity: Annotated[int, Meta(ge=0, le=4)]
    id: str
    text: str

    @property
    def severity_name(self) -> str:
        """``"INFO"``, ``"WARNING"``, ... (``str(severity)`` if out of range)."""
        if 0 <= self.severity < len(_SEVERITY_NAMES):
            return _SEVERITY_NAMES[self.severity]
        return str(self.severity)


_encoder = msgspec.msgpack.Encoder()
_decoder = msgspec.msgpack.Decoder(Event)


def encode_event(e: Event) -> bytes:
    """The wire form of ``e`` (MessagePack map)."""
    return _encoder.encode(e)


def decode_event(b: bytes | bytearray | memoryview) -> Event:
    """Decode an event record; raises FrameFormatError on anything else."""
    try:
        return _decoder.decode(b)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise FrameFormatError(f"not an event record: {exc}") from exc
    except (TypeError, ValueError, OverflowError) as exc:  # defensive: never leak others
        raise FrameFormatError(f"not an event record: {exc}") from exc


class EventLog:
    """A node's bounded queue of events awaiting publication.

    Not thread-safe: the loop thread emits and drains (the runtime drains
    after each loop). ``emit`` costs one :class:`Event` allocation and a list
    append; it is meant for things that happen (a state change, a rejected
    command), not for every loop.
    """

    __slots__ = ("_dropped", "_pending", "_seq", "capacity", "node")

    def __init__(self, node: str, capacity: int = 1024) -> None:
        if capacity < 1:
            raise ValueError(f"EventLog capacity must be at least 1, got {capacity}")
        self.node = node
        self.capacity = capacity
        self._pending: list[Event] = []
        self._seq = 0
        self._dropped = 0

    def emit(self, severity: Severity, id: str, text: str, t_ns: int) -> None:
        """Queue one event. Never blocks, never raises.

        When ``capacity`` events are already pending, the new event is not
        kept and :attr:`dropped` grows by one (its ``seq`` is still used).
        """
        seq = self._seq
        self._seq = seq + 1
        if len(self._pending) >= self.capacity:
            self._dropped += 1
            return
        self._pending.append(Event(self.node, seq, t_ns, int(severity), id, text))

    def drain(self) -> list[Event]:
        """Take every pending event, oldest first; the log is empty afterwards.

        Returns a new list (the caller owns it). Check :attr:`pending` first to
        skip the call in the common case of nothing to publish.
        """
        out = self._pending
        self._pending = []
        return out

    @property
    def pending(self) -> int:
        """Events emitted and not yet drained."""
        return len(self._pending)

    @property
    def dropped(self) -> int:
        """Events not kept because the log was full (since construction)."""
        return self._dropped

    @property
    def emitted(self) -> int:
        """Events emitted since construction, dropped ones included."""
        return self._seq
