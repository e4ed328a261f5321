"""The CN's telemetry over iceoryx2 to a ground node on its host (issue 27).

Zenoh carries every frame as before (taps, tools, stations, a remote
ground, and the ground node's own subscriber). With a ground node and
``transport.intra_host`` not ``zenoh``, the CN also publishes each frame
into an iceoryx2 service (:func:`~.intrahost.telemetry_service_name`, every
frame queued, an event to wake the reader): :class:`TelemetryPublisher`
encodes and tags it straight into the loan when zenoh takes no copy
(:meth:`~TelemetryPublisher.lend`), else copies it into one, and sends it
before the zenoh put. The ground node's :class:`TelemetryReceiver` (a
thread blocked on the event) hands each sample in place to the same
telemetry intake as zenoh's (``Intake.admit_view``), which takes each
frame once (``Dedupe``: the other path's copy is a duplicate, never a
refusal). :class:`TelemetryPaths` tells the path: ``iox`` from a frame it
brought first (``tm_on_shm``), back to ``zenoh`` once (``tm_fallback``)
after :data:`STALE_FRAMES` frames only zenoh brought, a frame with the
publisher gone, or a failed receiver; no frame zenoh carried is lost.
Detail and figures: docs/architecture.md#intra-host.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

from ..control.intake import IOX
from ..errors import IntraHostError, TransportError
from . import intrahost

if TYPE_CHECKING:
    from ..config import Mission
    from ..control.intake import TelemetryIntake

__all__ = [
    "STALE_FRAMES",
    "WAIT_S",
    "TelemetryPaths",
    "TelemetryPublisher",
    "TelemetryReceiver",
    "open_telemetry_publisher",
    "open_telemetry_subscriber",
    "telemetry_path_wanted",
]

log = logging.getLogger("zplatform.tmiox")

STALE_FRAMES = 10
"""Frames in a row that zenoh carried and iceoryx2 did not, after which the
ground's telemetry counts as fallen back to zenoh (a frame or two may come
by zenoh first when the receiving thread is scheduled late)."""
WAIT_S = 0.05
"""How long the ground's receiving thread blocks between looks at its stop
flag (a sample wakes it at once)."""


def telemetry_path_wanted(mission: Mission) -> bool:
    """Whether the mission's telemetry may take iceoryx2 to a ground on the
    CN's host: it has a ground node and ``transport.intra_host`` is not
    ``zenoh`` (the rule of the sync's links and bulk channels)."""
    return bool(mission.has_ground) and mission.transport.intra_host != "zenoh"


def _publishers(mission: Mission) -> int:
    # Each control node, and each again restarted before its dead port is removed.
    return 2 * len(mission.control_nodes)


def open_telemetry_publisher(
    mission: Mission, length: int, *, prefix: str = intrahost.PREFIX
) -> TelemetryPublisher | None:
    """The CN's end (``length``: its telemetry frame's bytes, tag included,
    ``ControlLogic.telemetry_length``), or None when the mission keeps
    telemetry on zenoh (:func:`telemetry_path_wanted`) or, under ``auto``,
    the end cannot open (logged). Raises TransportError under ``shm``
    when it cannot open (the operator asked for it)."""
    if not telemetry_path_wanted(mission):
        return None
    pubs = _publishers(mission)
    try:
        name = intrahost.telemetry_service_name(mission)
        pub = intrahost.IntraHostPublisher(
            name,
            length,
            1,
            prefix=prefix,
            buffer=intrahost.TELEMETRY_BUFFER,
            publishers=pubs,
            wake=True,
            need=intrahost.telemetry_segment_bytes(length, pubs),
        )
    except IntraHostError as exc:
        if mission.transport.intra_host == "shm":
            raise TransportError(f"telemetry over iceoryx2: {exc}") from exc
        log.warning("telemetry stays on zenoh: %s", exc)
        return None
    return TelemetryPublisher(pub)


def open_telemetry_subscriber(
    mission: Mission, auth: bool, *, prefix: str = intrahost.PREFIX
) -> intrahost.IntraHostSubscriber:
    """The ground node's subscriber of the telemetry service. Raises
    IntraHostError when it cannot open."""
    return intrahost.IntraHostSubscriber(
        intrahost.telemetry_service_name(mission),
        intrahost.telemetry_sample_bytes(mission, auth),
        1,
        prefix=prefix,
        buffer=intrahost.TELEMETRY_BUFFER,
        publishers=_publishers(mission),
        wake=True,
    )


class TelemetryPublisher:
    """The CN's iceoryx2 end of its telemetry (module doc). Not thread-safe:
    the CN's loop thread. Never raises after it opened; a frame that cannot
    go (no sample free, a broken connection) is counted in :attr:`dropped`
    (zenoh still carries it)."""

    def __init__(self, pub: intrahost.IntraHostPublisher) -> None:
        self.pub = pub
        self.length = pub.sample_bytes
        self.sent = 0
        """Frames sent over iceoryx2 (never reset)."""
        self.dropped = 0
        """Frames a subscriber was attached for that could not go."""
        self.lent = 0
        """Of :attr:`sent`, frames encoded straight into their loan (no copy)."""
        self._lent = False

    @property
    def subscribed(self) -> bool:
        """Whether a subscriber (a ground node on this host) is attached; under a µs."""
        return self.pub.subscribers > 0

    def lend(self, copied: bool) -> memoryview | None:
        """A loaned sample of :attr:`length` bytes to encode this loop's
        frame in (``ControlLogic.finish``'s ``tm_into``), when a subscriber
        is attached and nobody reads the frame after the send (``copied``
        False: no zenoh subscriber matches); else None (the frame is the
        logic's own and :meth:`publish` copies it). Valid until
        :meth:`publish` or :meth:`withdraw`. Never blocks."""
        if copied or not self.subscribed:
            return None
        view = self.pub.loan()
        self._lent = view is not None
        return view

    def publish(self, frame: bytes | bytearray | memoryview) -> bool:
        """Send ``frame``: the lent sample as it is, or a copy of the logic's
        buffer into a loan (only when a subscriber is attached). True when
        it went; a frame with nobody attached is neither sent nor dropped."""
        if self._lent:
            self._lent = False
            ok = self.pub.send()
            self.lent += ok
        else:
            if not self.subscribed:
                return False
            loan = self.pub.loan() if len(frame) == self.length else None
            if loan is None:
                self.dropped += 1
                return False
            loan[:] = frame  # the frame's one copy on this path
            ok = self.pub.send()
        if ok:
            self.sent += 1
        else:
            self.dropped += 1
        return ok

    def withdraw(self) -> None:
        """Give a lent sample back unsent (a loop that made no frame)."""
        if self._lent:
            self._lent = False
            self.pub.withdraw()

    def close(self) -> None:
        self.withdraw()
        self.pub.close()


class TelemetryReceiver:
    """The ground node's iceoryx2 path (module doc): a thread that blocks on
    the service's wake-up event and hands each sample to ``intake``
    (:meth:`~zplatform.control.intake.Intake.admit_view`, stamped
    ``now_ns()`` on arrival), in place, then releases it. Its counts are
    written by that thread only and read by the ground's. A broken
    connection ends the thread (:attr:`error` says why). :meth:`close`
    stops it (within :data:`WAIT_S`) and closes the subscriber."""

    def __init__(
        self,
        sub: intrahost.IntraHostSubscriber,
        intake: TelemetryIntake,
        now_ns: Callable[[], int],
    ) -> None:
        self.sub = sub
        self._intake = intake
        self._now = now_ns
        self._path = IOX
        self.taken = 0
        """Frames the intake admitted from iceoryx2 (never reset; the
        intake's ``taken_iox`` too)."""
        self.samples = 0
        """Samples received, admitted or not."""
        self.error = ""
        """Why the path failed (the thread ended); empty while it runs."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gn-telemetry-iox", daemon=True)
        self._thread.start()

    @property
    def publishers(self) -> int:
        """Publishers attached to the service now (a dead one until removed)."""
        return self.sub.publishers

    def _run(self) -> None:
        sub, admit, now, path = self.sub, self._intake.admit_view, self._now, self._path
        stop = self._stop
        try:
            while not stop.is_set():
                sub.wait(WAIT_S)
                while (view := sub.receive_next()) is not None:
                    self.samples += 1
                    if admit(view, now(), path):
                        self.taken += 1
                    del view
                    sub.release()
        except IntraHostError as exc:
            self.error = str(exc)
        except Exception as exc:  # never let the thread die silently
            self.error = f"{exc!r}"

    def close(self) -> None:
        """Stop the thread and close the subscriber (idempotent)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()
        self.sub.close()


class TelemetryPaths:
    """Which path the ground's telemetry takes (module doc), told from the
    counts of what each path's intake admitted: :meth:`update` on the
    ground's thread, after each item it takes. Returns the change to event
    (``("iox" | "zenoh", why)``), at most one per call; the caller events it."""

    def __init__(self) -> None:
        self.path = "zenoh"
        """``iox`` or ``zenoh``: the path of the last frames taken."""
        self.fallbacks = 0
        """Times the path fell back from iceoryx2 to zenoh."""
        self._iox = 0
        self._zenoh = 0
        self._quiet = 0  # frames in a row zenoh carried and iceoryx2 did not
        self._failed = False

    def update(self, iox: int, zenoh: int, publishers: int, error: str) -> tuple[str, str] | None:
        """``iox``, ``zenoh``: frames each path's intake admitted so far;
        ``publishers``: the service's now; ``error``: the receiver's."""
        d_iox, d_zen = iox - self._iox, zenoh - self._zenoh
        self._iox, self._zenoh = iox, zenoh
        if error and not self._failed:
            self._failed = True
            if self.path == "iox":
                return self._fall(f"iceoryx2 failed ({error})")
            return None
        if d_iox > 0:
            self._quiet = 0
            if self.path != "iox" and not self._failed:
                self.path = "iox"
                return ("iox", "a frame over it passed the intake")
            return None
        if self.path != "iox" or d_zen <= 0:
            return None
        self._quiet += d_zen
        if publishers == 0:
            return self._fall("the control node's iceoryx2 publisher is gone")
        if self._quiet >= STALE_FRAMES:
            return self._fall(f"zenoh carried the last {self._quiet} frames, iceoryx2 none")
        return None

    def _fall(self, why: str) -> tuple[str, str]:
        self.path = "zenoh"
        self.fallbacks += 1
        self._quiet = 0
        return ("zenoh", why)
