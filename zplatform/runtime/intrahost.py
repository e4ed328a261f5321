"""The intra-host carrier: the sync's trigger and reply, and bulk channels'
samples, over iceoryx2 shared memory between nodes of one host.

:class:`IntraHostClient` (the CN's end) and :class:`IntraHostServer` (the
DN's) move bytes only: frames, tags and freshness stay the sync's
(``zplatform/runtime/sync.py``). Each link is one request/response service
and two event services that wake the other side (request/response ports
cannot join a wait set); each side blocks on its listener with a deadline
(:class:`_Waiter`), never spinning. A timeout is "no reply", counted;
:attr:`IntraHostClient.state` says when the link has no peer or has stalled,
so the sync falls back to zenoh. :class:`IntraHostPublisher`/:class:`IntraHostSubscriber`:
a publish/subscribe service, a bulk channel's (:func:`bulk_service_name`,
``bulk.py``) or the telemetry's (:func:`telemetry_service_name`, ``tmiox.py``).

Copies per hop: the sender encodes into the loan, the receiver checks it in
place and copies once. Names (:func:`sync_link_names`: one kernel and network
namespace) hold both nodes; segments are sized (:func:`mission_link_sizes`) and
refused when ``/dev/shm`` cannot hold them (:func:`check_shm`); dead processes'
resources go before an end opens (:func:`remove_stale`). docs/architecture.md#intra-host.
"""

from __future__ import annotations

import ctypes
import enum
import hashlib
import math
import os
import re
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgspec

from ..config import Mission
from ..core.auth import TAG_LEN
from ..core.codec import frame_overhead, max_frame_length
from ..core.datavector import Layout
from ..core.messages import check_intra_host, intra_host_mode
from ..errors import IntraHostError

__all__ = [
    "DEFAULT_DEADLINE_S",
    "PREFIX",
    "STALL_AFTER",
    "TELEMETRY_BUFFER",
    "IntraHostClient",
    "IntraHostPublisher",
    "IntraHostServer",
    "IntraHostSubscriber",
    "LinkNames",
    "LinkState",
    "bulk_segment_bytes",
    "bulk_service_name",
    "check_intra_host",
    "check_shm",
    "host_tag",
    "iceoryx2_config",
    "intra_host_mode",
    "link_names",
    "mission_link_sizes",
    "remove_stale",
    "segment_bytes",
    "sync_link_names",
    "telemetry_sample_bytes",
    "telemetry_segment_bytes",
    "telemetry_service_name",
]

#: The file-name prefix of every iceoryx2 resource zplatform creates (in
#: /dev/shm and iceoryx2's root directory), apart from other iceoryx2 users.
PREFIX = "zp_"
#: A reply later than this is no reply (the zenoh sync's deadline too).
DEFAULT_DEADLINE_S = 0.002
#: Consecutive timeouts after which the link counts as stalled.
STALL_AFTER = 3
#: Samples preallocated per direction: one the sender loans, two queued at
#: the receiver (its buffer: a timed-out trigger is withdrawn but stays
#: there until the receiver drains it), and the one the DN holds until its
#: next wait (its loop copies the trigger's data from it after the reply).
#: The client keeps at most one request pending.
SLOTS = 4
#: Per-sample bookkeeping iceoryx2 adds to a segment, and the fixed part of
#: a link (management segments, connections), both measured on 0.10 with
#: margin (tests/unit/test_intrahost.py checks the bound on the real files).
#: Telemetry frames queued for the ground's subscriber (every frame counts:
#: the ground logs them all); an older one is overwritten only when its
#: receiving thread is this many frames behind, and zenoh still carries it.
TELEMETRY_BUFFER = 8
_SAMPLE_OVERHEAD = 256
_LINK_FIXED = 64 * 1024
_NAME_RE = re.compile(r"[A-Za-z0-9_.-]{1,64}")


class LinkState(enum.Enum):
    """What the client's last exchanges say about the link."""

    UP = "up"  #: the last exchange got its reply, or fewer than STALL_AFTER timed out
    NO_PEER = "no_peer"  #: no server is attached to the service
    STALLED = "stalled"  #: STALL_AFTER or more consecutive exchanges without a reply


@dataclass(frozen=True, slots=True)
class LinkNames:
    """The iceoryx2 service names of one CN-DN link."""

    sync: str  #: the request/response service
    request_event: str  #: the client notifies it after sending a trigger
    reply_event: str  #: the server notifies it after sending a reply


def link_names(mission: str, vehicle: str, run: str | int, cn: str, dn: str) -> LinkNames:
    """Service names of the link ``cn`` -> ``dn`` of one run of one mission.

    Two missions on one host, or two runs of one, never share a service.
    Raises IntraHostError for a part that is empty, longer than 64 or holds
    a character other than ``[A-Za-z0-9_.-]`` (a ``/`` would shift levels).
    """
    parts = {"mission": mission, "vehicle": vehicle, "run": str(run), "cn": cn, "dn": dn}
    for what, text in parts.items():
        if not _NAME_RE.fullmatch(text):
            raise IntraHostError(f"intra-host link: {what} {text!r} is not [A-Za-z0-9_.-]{{1,64}}")
    base = f"zplatform/{mission}/{vehicle}/{run}/{cn}/{dn}"
    return LinkNames(f"{base}/sync", f"{base}/trigger", f"{base}/reply")


def host_tag() -> str:
    """What names this host for the intra-host links: the kernel's boot and
    this process's network namespace. Two nodes see the same tag only on
    one host in one network namespace, so nodes that talk over a network
    (other hosts, or namespaces standing for them) never open one link.
    Not a secret and not a proof: the tagged round trip is
    (docs/architecture.md#intra-host). Never raises ("na" when unknown)."""
    parts = []
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            parts.append(f.read().strip().replace("-", "")[:12])
    except OSError:
        parts.append("na")
    try:
        parts.append(f"{os.stat('/proc/self/ns/net').st_ino:x}")
    except OSError:
        parts.append("na")
    return ".".join(parts)


def _name_part(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text)[:64] or "_"


def _mission_name(mission: Mission) -> str:
    digest = hashlib.sha256(msgspec.json.encode(mission)).hexdigest()[:12]
    return f"{_name_part(mission.mission)[:48]}.{digest}"


def bulk_service_name(mission: Mission, owner: str, channel: str) -> str:
    """The iceoryx2 publish/subscribe service of bulk channel ``channel``
    owned by ``owner`` on this host: named as the sync's links
    (:func:`sync_link_names`: the mission's name and digest, the vehicle,
    :func:`host_tag`), so only an owner and readers of one mission on one
    kernel and network namespace meet. Raises IntraHostError as :func:`link_names`."""
    names = link_names(_mission_name(mission), mission.vehicle, host_tag(), owner, channel)
    return names.sync.rsplit("/", 1)[0] + "/bulk"


def telemetry_service_name(mission: Mission) -> str:
    """The iceoryx2 publish/subscribe service of the CN's telemetry to a
    ground node on this host, named as :func:`bulk_service_name` (the
    mission's name and digest, the vehicle, :func:`host_tag`): only the
    control node and the ground node of one mission on one kernel and
    network namespace meet. Its wake-up event service is this name and
    ``_wake``. Raises IntraHostError as :func:`link_names`."""
    names = link_names(_mission_name(mission), mission.vehicle, host_tag(), "cn", "gn")
    return names.sync.rsplit("/", 1)[0] + "/telemetry"


def telemetry_sample_bytes(mission: Mission, auth: bool) -> int:
    """Bytes of one telemetry sample: the CN's whole-vector frame as its
    encoder writes it (the fixed-width header, :func:`frame_overhead`) and,
    with ``auth``, its tag. Every sample is exactly this long; the
    ground's intake refuses any other length."""
    n = Layout.for_node(mission, "cn").size
    return frame_overhead(n) + n + (TAG_LEN if auth else 0)


def telemetry_segment_bytes(sample_bytes: int, publishers: int) -> int:
    """Upper bound of the telemetry service's shared memory: each
    publisher's data segment (every subscriber slot's queue and borrow,
    and the loan) and the fixed part."""
    slots = bulk_subscribers(1) * (TELEMETRY_BUFFER + 1) + 1
    return publishers * slots * (sample_bytes + _SAMPLE_OVERHEAD) + _LINK_FIXED


def sync_link_names(mission: Mission, dn: str, cn: str = "cn") -> LinkNames:
    """The names of the sync's link ``cn`` -> ``dn`` on this host
    (:func:`link_names`): the mission's name and a digest of its whole
    configuration (two copies of a mission on other endpoints, as tests run
    them side by side, never share a link), and :func:`host_tag` for the
    run part. The same for every run: the frames' tags bind each to its run."""
    return link_names(_mission_name(mission), mission.vehicle, host_tag(), cn, dn)


def mission_link_sizes(mission: Mission, dn: str) -> tuple[int, int]:
    """``(largest trigger, largest reply)`` in bytes for the link to ``dn``:
    the region frame at its widest (:func:`zplatform.core.codec.max_frame_length`)
    plus the tag. Anything longer is malformed and refused."""
    sizes = []
    for region in (f"cn_to_{dn}", f"{dn}_to_cn"):
        n = Layout.for_regions(mission, [region]).size
        sizes.append(max_frame_length(n) + TAG_LEN)
    return sizes[0], sizes[1]


def segment_bytes(max_trigger: int, max_reply: int) -> int:
    """Upper bound of the shared memory one link takes (both ends)."""
    return (
        SLOTS * (max_trigger + _SAMPLE_OVERHEAD)
        + SLOTS * (max_reply + _SAMPLE_OVERHEAD)
        + _LINK_FIXED
    )


def bulk_segment_bytes(sample_bytes: int, readers: int) -> int:
    """Upper bound of one bulk channel's iceoryx2 data segment: one sample
    per subscriber slot (:func:`bulk_subscribers`, each buffering one and
    borrowing one) and the publisher's loan."""
    return (2 * bulk_subscribers(readers) + 1) * (sample_bytes + _SAMPLE_OVERHEAD) + _LINK_FIXED


def bulk_subscribers(readers: int) -> int:
    """Subscriber ports a bulk channel's service admits: each reader, and
    each again restarted before its dead port is removed."""
    return 2 * readers


def check_shm(need: int, shm_dir: str = "/dev/shm", what: str = "the intra-host links") -> None:
    """Raise IntraHostError, naming both figures, when ``shm_dir`` has less
    than ``need`` bytes free (or does not exist). Does not block."""
    try:
        free = shutil.disk_usage(shm_dir).free
    except OSError as exc:
        raise IntraHostError(f"{what}: shared memory {shm_dir} unusable ({exc})") from exc
    if free < need:
        raise IntraHostError(
            f"{what} need {need} bytes of shared memory, {shm_dir} has {free} free: "
            f"enlarge it (mount -o remount,size=... {shm_dir}; docker --shm-size) "
            "or pin the link to zenoh"
        )


def _iox() -> Any:
    # Imported on first use: a mission that never takes the intra-host path
    # does not load the library (nor its 4 MB extension).
    import iceoryx2

    iceoryx2.set_log_level(iceoryx2.LogLevel.Error)
    return iceoryx2


def iceoryx2_config(prefix: str = PREFIX) -> Any:
    """An iceoryx2 config whose files all carry ``prefix`` (their own namespace)."""
    iox = _iox()
    cfg = iox.config.default()
    cfg.global_cfg.prefix = iox.FileName.new(prefix)
    return cfg


def remove_stale(prefix: str = PREFIX) -> int:
    """Remove what dead processes (a kill -9) left under ``prefix``: their
    nodes, and their ports in every service. Returns how many dead nodes were
    removed; skips what another process is removing. Does not block."""
    iox = _iox()
    removed = 0
    try:
        states = iox.Node.list(iox.ServiceType.Ipc, iceoryx2_config(prefix))
    except Exception as exc:  # iceoryx2's NodeListFailure: a directory we cannot read
        raise IntraHostError(f"intra-host: cannot list iceoryx2 nodes ({exc})") from exc
    for state in states:
        if isinstance(state, iox.NodeState.Dead):
            view = state._0
            try:
                # 0.10 returns None once removed (its docstring says True).
                removed += view.try_remove_stale_resources() is not False
            except Exception:  # NodeCleanupFailure: another process holds it; it cleans
                pass
    return removed


class _End:
    """What both ends hold: an iceoryx2 node and the link's three services."""

    def __init__(
        self, names: LinkNames, max_trigger: int, max_reply: int, prefix: str, check: bool
    ) -> None:
        if not (max_trigger >= 1 and max_reply >= 1):
            raise IntraHostError("intra-host link: frame bounds must be >= 1 byte")
        if check:
            check_shm(segment_bytes(max_trigger, max_reply), what=f"intra-host link {names.sync}")
        self.stale_removed = remove_stale(prefix)
        iox = self._iox = _iox()
        self.names = names
        self.max_trigger = max_trigger
        self.max_reply = max_reply
        u8 = iox.Slice[ctypes.c_uint8]
        try:
            self._node = (
                iox.NodeBuilder.new()
                .config(iceoryx2_config(prefix))
                # The node's own SIGTERM handler stays the process's.
                .signal_handling_mode(iox.SignalHandlingMode.Disabled)
                .create(iox.ServiceType.Ipc)
            )
            self._service = (
                self._node.service_builder(iox.ServiceName.new(names.sync))
                .request_response(u8, u8)
                .max_clients(2)  # the CN, and a restarted CN before the dead one is removed
                .max_servers(1)
                .max_nodes(4)
                .max_active_requests_per_client(2)
                .max_loaned_requests(1)
                .max_response_buffer_size(1)
                .max_borrowed_responses_per_pending_response(1)
                .enable_fire_and_forget_requests(False)
                .enable_safe_overflow_for_requests(True)
                .enable_safe_overflow_for_responses(True)
                .open_or_create()
            )
            self._req_ev = self._event(names.request_event)
            self._res_ev = self._event(names.reply_event)
        except IntraHostError:
            raise
        except Exception as exc:
            raise IntraHostError(f"intra-host link {names.sync}: cannot open ({exc!r})") from exc

    def _event(self, name: str) -> Any:
        iox = self._iox
        return (
            self._node.service_builder(iox.ServiceName.new(name))
            .event()
            .max_nodes(4)
            .max_listeners(2)
            .max_notifiers(3)  # the CN, a restarted CN, and the DN's waker (DeviceSync)
            .open_or_create()
        )

    def _ports(self, what: str, make: Callable[[], Any], *, notify: Any, listen: Any) -> Any:
        """This end's port (``make()``: the client or the server) and its
        notifier on the ``notify`` event and listener on the ``listen`` one
        (the two ends cross them). Raises IntraHostError naming ``what``."""
        try:
            port = make()
            self._notifier = notify.notifier_builder().create()
            self._listener = listen.listener_builder().create()
            self._waiter = _Waiter(self._iox, self._listener)
        except Exception as exc:
            raise IntraHostError(f"intra-host link {self.names.sync}: no {what} ({exc!r})") from exc
        return port

    def close(self) -> None:
        """Drop every port, then the services, then the node (shared memory
        goes with its last holder). Idempotent."""
        waiter = self.__dict__.pop("_waiter", None)
        if waiter is not None:
            waiter.close()
        for attr in ("_client", "_server", "_notifier", "_listener"):
            self.__dict__.pop(attr, None)
        for attr in ("_req_ev", "_res_ev", "_service", "_node"):
            self.__dict__.pop(attr, None)


class _Waiter:
    """A blocking wait on one listener with a timeout, through an iceoryx2
    ``WaitSet`` (epoll) the listener is attached to, never the listener's own
    ``timed_wait``.

    Why: in iceoryx2 0.10 ``Listener.timed_wait`` hands its timeout to the
    socket's SO_RCVTIMEO, which the kernel counts in whole jiffies (4 ms at
    HZ=250) from whole microseconds. A missed 2 ms deadline cost 5.7 ms
    (p50; up to 8), and a wait of under a microsecond (a deadline's last
    sliver) became 0, which the kernel reads as *forever*: a device node
    blocked there until its next trigger, and for good once the control node
    had gone. The WaitSet waits in milliseconds rounded up (a missed 2 ms
    deadline costs 2.2 ms; a sliver, 1 ms; ``python -m bench.intrahost
    --misses``); its own
    signal handling is off, so a node's SIGTERM handler ends a wait early
    (epoll's EINTR), as a spurious wake-up. Every caller checks its deadline
    and what arrived after a wait. Never raises.
    """

    #: Waits of up to this many milliseconds take a Duration built once per
    #: process, by the first end that opens (the WaitSet counts whole
    #: milliseconds, rounded up, so nothing finer is lost): a loop's waits
    #: allocate none. A longer wait (no loop's) builds one.
    TABLE_MS = 1000
    _table: tuple[Any, ...] = ()

    def __init__(self, iox: Any, listener: Any) -> None:
        self._listener = listener
        self._duration = iox.Duration.from_secs_f64
        if not _Waiter._table:
            _Waiter._table = tuple(iox.Duration.from_millis(i) for i in range(self.TABLE_MS + 1))
        self._ms = _Waiter._table
        self._ws = (
            iox.WaitSetBuilder.new()
            .signal_handling_mode(iox.SignalHandlingMode.Disabled)
            .create(iox.ServiceType.Ipc)
        )
        self._guard = self._ws.attach_notification(listener)

    def wait(self, duration: Any) -> None:
        """Block until the listener is notified or ``duration`` (an iceoryx2
        Duration) passes; returns at once if a notification is pending, and
        consumes what is pending when it returns."""
        try:
            ids, _result = self._ws.wait_and_process_with_timeout(duration)
            if ids:
                self._listener.try_wait()  # consumed: the next wait blocks again
        except Exception:  # WaitSetRunError / ListenerWaitError: a broken reactor
            # It returns at once, every time: pause, never spin (the
            # caller's deadline still ends its wait).
            time.sleep(0.001)

    def wait_s(self, seconds: float) -> None:
        """:meth:`wait` for ``seconds``, rounded up to a whole millisecond as
        the WaitSet would; returns at once when it is <= 0."""
        if seconds > 0:
            self.wait(self.duration(seconds))

    def duration(self, seconds: float) -> Any:
        """The Duration a wait of ``seconds`` (> 0) takes: whole milliseconds,
        rounded up (at least 1), from the table up to :attr:`TABLE_MS`."""
        ms = math.ceil(seconds * 1000.0)
        if ms <= self.TABLE_MS:
            return self._ms[ms if ms > 0 else 1]
        return self._duration(seconds)

    def close(self) -> None:
        """Detach before the listener goes (the guard, then the set). Idempotent."""
        self.__dict__.pop("_guard", None)
        self.__dict__.pop("_ws", None)


def _view(ptr: int, n: int) -> memoryview:
    # A memoryview over shared memory, no copy; ctypes caches the array type.
    return memoryview((ctypes.c_uint8 * n).from_address(ptr)).cast("B")


class IntraHostClient(_End):
    """The CN's end of one link: :meth:`trigger`, then :meth:`exchange` (or
    :meth:`send` and :meth:`collect`), then :meth:`release`.

    Not thread-safe: one loop thread owns it. Raises IntraHostError when the
    link cannot open (names, shared memory, iceoryx2); after that nothing
    raises but a caller's bug (a trigger above ``max_trigger``).
    """

    def __init__(
        self,
        names: LinkNames,
        max_trigger: int,
        max_reply: int,
        *,
        deadline_s: float = DEFAULT_DEADLINE_S,
        stall_after: int = STALL_AFTER,
        prefix: str = PREFIX,
        check: bool = True,
    ) -> None:
        super().__init__(names, max_trigger, max_reply, prefix, check)
        iox = self._iox
        self._client = self._ports(
            "client",
            lambda: (
                self._service.client_builder()
                .initial_max_slice_len(max_trigger)
                .allocation_strategy(iox.AllocationStrategy.Static)
                .max_active_requests(2)
                .override_request_preallocation(SLOTS)
                .create()
            ),
            notify=self._req_ev,
            listen=self._res_ev,
        )
        self.set_deadline(deadline_s)
        self.stall_after = stall_after
        self._loan: Any = None
        self._waiting: Any = None  # sent, its reply not collected yet
        self._t_sent = 0.0
        self._pending: Any = None
        self._response: Any = None
        #: Counters (never reset): exchanges sent, replies returned, timeouts
        #: (no reply within the deadline, no peer, or no sample to loan),
        #: replies refused (longer than ``max_reply``).
        self.sent = 0
        self.replies = 0
        self.timeouts = 0
        self.refused = 0
        self.no_peer = 0
        self.consecutive_timeouts = 0
        self._peerless = False

    def set_deadline(self, deadline_s: float) -> None:
        """How long :meth:`exchange` waits for a reply from now on."""
        self.deadline_s = deadline_s
        self._deadline = self._iox.Duration.from_secs_f64(deadline_s)

    @property
    def state(self) -> LinkState:
        """UP, NO_PEER (the last send found no server) or STALLED
        (``stall_after`` consecutive exchanges without a reply)."""
        if self._peerless:
            return LinkState.NO_PEER
        if self.consecutive_timeouts >= self.stall_after:
            return LinkState.STALLED
        return LinkState.UP

    def trigger(self, n: int) -> memoryview | None:
        """A writable view of ``n`` bytes of a loaned request in shared memory:
        encode the trigger frame straight into it, then :meth:`exchange`.
        None (counted as a timeout) when no sample can be loaned (the server
        holds them all). Releases the previous reply first."""
        if not 1 <= n <= self.max_trigger:
            raise IntraHostError(f"intra-host trigger of {n} bytes, bound {self.max_trigger}")
        self.release()
        # A loan not sent (a caller that lent and never sent) goes back first:
        # the client may hold one loan at a time.
        self._loan = None
        try:
            self._loan = self._client.loan_slice_uninit(n)
        except Exception:  # LoanError: every slot held by a stuck peer
            self._loan = None
            self._missed()
            return None
        return _view(self._loan.payload_ptr, n)

    def exchange(self) -> memoryview | None:
        """:meth:`send` the loaned trigger, then :meth:`collect` its reply within
        ``deadline_s``. Blocks at most ``deadline_s`` (plus scheduling)."""
        if not self.send():
            return None
        return self.collect()

    def send(self) -> bool:
        """Send the loaned trigger and wake the server; does not block. False
        (counted as a miss) when no server is attached or the send failed."""
        loan, self._loan = self._loan, None
        if loan is None:
            raise IntraHostError("intra-host send without a trigger")
        self.sent += 1
        self._t_sent = time.monotonic()
        try:
            pending = loan.assume_init().send()
        except Exception:  # RequestSendError: the connection broke
            self._missed()
            return False
        if pending.number_of_server_connections == 0:
            self._peerless = True
            self.no_peer += 1
            self._missed()
            return False
        self._peerless = False
        self._waiting = pending
        self._notifier.notify()
        return True

    def collect(self, t_end: float | None = None) -> memoryview | None:
        """Wait for the reply to the trigger :meth:`send` sent, until ``t_end``
        (``time.monotonic()``; default: ``deadline_s`` after the send, so a CN
        can send to every DN, then collect each against one deadline).
        Returns a read-only view of the reply in shared memory, valid until
        :meth:`release` or the next :meth:`trigger`; None when no reply came
        in time (counted; the request is withdrawn, so a late reply is never
        taken for the next one's). Blocks at most until ``t_end``; never spins."""
        pending, self._waiting = self._waiting, None
        if pending is None:
            return None
        if t_end is None:
            t_end = self._t_sent + self.deadline_s
            wait = self._deadline  # preallocated: the common case allocates no Duration
        else:
            wait = self._waiter.duration(t_end - time.monotonic())
        while True:
            response = pending.receive()
            if response is not None:
                break
            if t_end - time.monotonic() <= 0:
                # Dropping the pending request tells iceoryx2 a late reply
                # has nobody to go to.
                del pending
                self._missed()
                return None
            self._waiter.wait(wait)
            # Woken by an earlier, late reply's event: wait out what is left.
            wait = self._waiter.duration(t_end - time.monotonic())
        n = response.header.number_of_elements
        if n > self.max_reply:
            self.refused += 1
            del response, pending
            self._missed()
            return None
        self._pending, self._response = pending, response
        self.replies += 1
        self.consecutive_timeouts = 0
        return _view(response.payload_ptr, n).toreadonly()

    def call(
        self, frame: bytes | bytearray | memoryview, out: bytearray | memoryview
    ) -> int | None:
        """One exchange of a finished frame: copy it into the loan, exchange,
        copy the reply into ``out``. Returns the reply's length, or None (no
        reply, or one longer than ``out``, counted as refused)."""
        buf = self.trigger(len(frame))
        if buf is None:
            return None
        buf[:] = frame
        reply = self.exchange()
        if reply is None:
            return None
        n = len(reply)
        if n > len(out):
            self.refused += 1
            self.release()
            return None
        out[:n] = reply
        self.release()
        return n

    def release(self) -> None:
        """Give the reply's sample back (its view must not be used after), and
        withdraw a trigger sent but not collected."""
        self._response = None
        self._pending = None
        self._waiting = None

    def _missed(self) -> None:
        self.timeouts += 1
        self.consecutive_timeouts += 1

    def close(self) -> None:
        self._loan = None
        self.release()
        super().close()


class IntraHostServer(_End):
    """The DN's end of one link: :meth:`wait` for a trigger, :meth:`reply`, :meth:`send`.

    Not thread-safe: one loop thread owns it. When triggers queue up (the
    client timed out and sent anew) the newest is served, the older dropped
    and counted in ``superseded``.
    """

    def __init__(
        self,
        names: LinkNames,
        max_trigger: int,
        max_reply: int,
        *,
        prefix: str = PREFIX,
        check: bool = True,
    ) -> None:
        super().__init__(names, max_trigger, max_reply, prefix, check)
        iox = self._iox
        self._server = self._ports(
            "server",
            lambda: (
                self._service.server_builder()
                .initial_max_slice_len(max_reply)
                .allocation_strategy(iox.AllocationStrategy.Static)
                .max_loaned_responses_per_request(1)
                .override_response_preallocation(SLOTS)
                .create()
            ),
            notify=self._res_ev,
            listen=self._req_ev,
        )
        # The waker's notifier (:meth:`waker`), made with the link: a link
        # whose event admits no more notifiers fails to open, not later.
        try:
            self._wake_notifier = self._req_ev.notifier_builder().create()
        except Exception as exc:
            raise IntraHostError(f"intra-host link {names.sync}: no waker ({exc!r})") from exc
        self._active: Any = None
        self._held: Any = None  # the last trigger answered: its view lives until the next wait
        self._loan: Any = None
        #: Counters (never reset): triggers served, replies sent, triggers
        #: refused (longer than ``max_trigger``), superseded (a newer one came).
        self.received = 0
        self.replied = 0
        self.refused = 0
        self.superseded = 0

    def wait(self, timeout_s: float) -> memoryview | None:
        """The next trigger, as a read-only view in shared memory valid until
        the next :meth:`wait` (or :meth:`poll`, :meth:`close`): the sample is
        held after :meth:`send` too, so the DN's loop copies the trigger's
        data into its Data Vector straight from it (the trigger's one copy
        on this end); None after ``timeout_s`` without one. Blocks at most
        ``timeout_s``; never spins."""
        self._active = self._loan = self._held = None
        t_end = time.monotonic() + timeout_s
        while True:
            request = None
            while (newer := self._server.receive()) is not None:
                if request is not None:
                    self.superseded += 1
                request = newer
            if request is not None:
                n = request.header.number_of_elements
                if n > self.max_trigger:
                    self.refused += 1
                    continue
                self._active = request
                self.received += 1
                return _view(request.payload_ptr, n).toreadonly()
            left = t_end - time.monotonic()
            if left <= 0:
                return None
            self._waiter.wait_s(left)

    def poll(self) -> memoryview | None:
        """:meth:`wait` without waiting: the newest trigger queued, or None."""
        return self.wait(0.0)

    def block(self, timeout_s: float) -> None:
        """Wait until any notification on the trigger event (a trigger, or a
        :meth:`waker`'s) or ``timeout_s``; returns at once if one is pending.
        Never spins. Then :meth:`poll`: the wake may be for something else."""
        self._waiter.wait_s(timeout_s)

    def waker(self) -> Callable[[], None]:
        """A function that wakes :meth:`block` (another notifier on the
        trigger event), for what else this end's thread waits for (a DN's
        zenoh triggers). Thread-safe: calls from several threads are
        serialised. Never raises (its notifier was made when the link opened)."""
        notifier = self._wake_notifier
        lock = threading.Lock()

        def wake() -> None:
            with lock:
                notifier.notify()

        return wake

    def reply(self, n: int) -> memoryview | None:
        """A writable view of ``n`` bytes of a loaned reply to the trigger
        :meth:`wait` returned; None when there is none, or its client has gone."""
        if not 1 <= n <= self.max_reply:
            raise IntraHostError(f"intra-host reply of {n} bytes, bound {self.max_reply}")
        if self._active is None or not self._active.is_connected:
            return None
        try:
            self._loan = self._active.loan_slice_uninit(n)
        except Exception:  # LoanError: the client holds every reply sample
            return None
        return _view(self._loan.payload_ptr, n)

    def send(self) -> bool:
        """Send the loaned reply and wake the client. False when it could not go."""
        loan, self._loan = self._loan, None
        active, self._active = self._active, None
        if loan is None or active is None:
            return False
        # Held (not dropped) until the next wait: its view stays valid.
        self._held = active
        try:
            loan.assume_init().send()
        except Exception:  # SendError: the client dropped the request meanwhile
            return False
        self._notifier.notify()
        self.replied += 1
        return True

    def respond(self, frame: bytes | bytearray | memoryview) -> bool:
        """Copy a finished reply frame into a loan and :meth:`send` it."""
        buf = self.reply(len(frame))
        if buf is None:
            return False
        buf[:] = frame
        return self.send()

    def close(self) -> None:
        self._loan = self._active = self._held = None
        self.__dict__.pop("_wake_notifier", None)
        super().close()


class _PubSub:
    """What both ends of a publish/subscribe service hold (a bulk channel's,
    :func:`bulk_service_name`, or the telemetry's, :func:`telemetry_service_name`):
    a node and the service, sized from the channel alone so its owner and
    readers open it alike. ``buffer``: samples queued per subscriber (a
    bulk channel's 1: newest wins; the telemetry's :data:`TELEMETRY_BUFFER`);
    ``publishers``: publisher ports the service admits; ``wake``: also an
    event service (the name and ``_wake``) the publisher notifies after each
    sample, so a subscriber can block (:meth:`IntraHostSubscriber.wait`)."""

    def __init__(
        self,
        name: str,
        sample_bytes: int,
        readers: int,
        prefix: str,
        *,
        buffer: int = 1,
        publishers: int = 1,
        wake: bool = False,
    ) -> None:
        if sample_bytes < 1 or readers < 1 or buffer < 1 or publishers < 1:
            raise IntraHostError(
                "intra-host pub/sub: a sample of >= 1 byte, >= 1 reader, buffer and publisher"
            )
        # A node's start removes what dead processes left (a kill -9'd owner's
        # publisher would hold the service's one publisher slot).
        self.stale_removed = remove_stale(prefix)
        iox = self._iox = _iox()
        self.name = name
        self.sample_bytes = sample_bytes
        self._wake: Any = None
        try:
            self._node = (
                iox.NodeBuilder.new()
                .config(iceoryx2_config(prefix))
                .signal_handling_mode(iox.SignalHandlingMode.Disabled)
                .create(iox.ServiceType.Ipc)
            )
            subs = bulk_subscribers(readers)
            self._service = (
                self._node.service_builder(iox.ServiceName.new(name))
                .publish_subscribe(iox.Slice[ctypes.c_uint8])
                .max_publishers(publishers)
                .max_subscribers(subs)
                .max_nodes(subs + 2 * publishers)
                .history_size(0)
                .subscriber_max_buffer_size(buffer)
                .subscriber_max_borrowed_samples(1)
                .enable_safe_overflow(True)  # a slow reader never stalls the owner
                .open_or_create()
            )
            if wake:
                self._wake = (
                    self._node.service_builder(iox.ServiceName.new(f"{name}_wake"))
                    .event()
                    .max_nodes(subs + 2 * publishers)
                    .max_listeners(subs)
                    .max_notifiers(publishers)
                    .open_or_create()
                )
        except Exception as exc:
            raise IntraHostError(f"intra-host pub/sub {name}: cannot open ({exc!r})") from exc

    @property
    def publishers(self) -> int:
        """Publishers attached now (a dead one until removed); under a µs."""
        return int(self._service.dynamic_config.number_of_publishers)

    @property
    def subscribers(self) -> int:
        """Subscribers attached now (a dead one until removed); under a µs."""
        return int(self._service.dynamic_config.number_of_subscribers)

    def close(self) -> None:
        """Drop the ports, the services, the node. Idempotent."""
        waiter = self.__dict__.pop("_waiter", None)
        if waiter is not None:
            waiter.close()
        for attr in ("_port", "_sample", "_notifier", "_listener", "_wake", "_service", "_node"):
            self.__dict__.pop(attr, None)


class IntraHostPublisher(_PubSub):
    """A publisher (a bulk channel owner's, the CN's telemetry): :meth:`loan`
    a sample, write it, :meth:`send`. Samples are exactly ``sample_bytes``
    long. Not thread-safe (the owner's loop thread). Raises IntraHostError
    when it cannot open (``/dev/shm`` too small with ``check``, iceoryx2
    refused, every publisher slot held by a live process); never after.
    ``buffer``, ``publishers``, ``wake``: the service's (:class:`_PubSub`),
    the same at every end; ``need``: the shared memory ``check`` asks for
    (default: a bulk channel's, :func:`bulk_segment_bytes`)."""

    def __init__(
        self,
        name: str,
        sample_bytes: int,
        readers: int,
        *,
        prefix: str = PREFIX,
        check: bool = True,
        buffer: int = 1,
        publishers: int = 1,
        wake: bool = False,
        need: int | None = None,
    ) -> None:
        if check:
            if need is None:
                need = bulk_segment_bytes(sample_bytes, readers)
            check_shm(need, what=f"intra-host pub/sub {name}")
        super().__init__(
            name, sample_bytes, readers, prefix, buffer=buffer, publishers=publishers, wake=wake
        )
        iox = self._iox
        try:
            self._port = (
                self._service.publisher_builder()
                .initial_max_slice_len(sample_bytes)
                .allocation_strategy(iox.AllocationStrategy.Static)
                .max_loaned_samples(1)
                .create()
            )
            self._notifier = self._wake.notifier_builder().create() if wake else None
        except Exception as exc:
            raise IntraHostError(f"intra-host pub/sub {name}: no publisher ({exc!r})") from exc
        self._sample: Any = None

    def loan(self) -> memoryview | None:
        """A writable view of a loaned sample in shared memory (``sample_bytes``),
        or None when none is free (counted by the caller as a drop)."""
        try:
            self._sample = self._port.loan_slice_uninit(self.sample_bytes)
        except Exception:  # LoanError: every sample held by subscribers
            self._sample = None
            return None
        return _view(self._sample.payload_ptr, self.sample_bytes)

    def withdraw(self) -> None:
        """Give a loaned sample back unsent (its view must not be used after)."""
        self._sample = None

    def send(self) -> bool:
        """Deliver the loaned sample to every subscriber (a full buffer drops
        its oldest) and, with ``wake``, notify; False when it could not go.
        Never blocks."""
        sample, self._sample = self._sample, None
        if sample is None:
            return False
        try:
            sample.assume_init().send()
            if self._notifier is not None:
                self._notifier.notify()
        except Exception:  # SendError, NotifierNotifyError: a broken connection
            return False
        return True


class IntraHostSubscriber(_PubSub):
    """A subscriber (a bulk channel reader's, the ground's telemetry):
    :meth:`receive` the newest sample, or :meth:`receive_next` each in
    order, in place. Not thread-safe (the reader's thread). Raises
    IntraHostError when it cannot open; never after. ``buffer``,
    ``publishers``, ``wake``: the service's (:class:`IntraHostPublisher`)."""

    def __init__(
        self,
        name: str,
        sample_bytes: int,
        readers: int,
        *,
        prefix: str = PREFIX,
        buffer: int = 1,
        publishers: int = 1,
        wake: bool = False,
    ) -> None:
        super().__init__(
            name, sample_bytes, readers, prefix, buffer=buffer, publishers=publishers, wake=wake
        )
        try:
            self._port = self._service.subscriber_builder().buffer_size(buffer).create()
            self._listener = self._wake.listener_builder().create() if wake else None
            self._waiter = _Waiter(self._iox, self._listener) if wake else None
        except Exception as exc:
            raise IntraHostError(f"intra-host pub/sub {name}: no subscriber ({exc!r})") from exc
        self._sample: Any = None

    def receive(self) -> memoryview | None:
        """The newest sample (older ones are dropped) as a read-only view in
        shared memory, valid until the next :meth:`receive` or :meth:`release`;
        None when none arrived. Any length comes back: the caller's intake
        checks it. Never blocks."""
        self._sample = None
        sample = None
        try:
            while (newer := self._port.receive()) is not None:
                sample = newer
        except Exception:  # ReceiveError: a broken connection; nothing to take
            return None
        if sample is None:
            return None
        self._sample = sample
        return _view(sample.payload_ptr, sample.header.number_of_elements).toreadonly()

    def receive_next(self) -> memoryview | None:
        """The oldest sample queued (each in the order sent) as a read-only
        view in shared memory, valid until the next call or :meth:`release`;
        None when none is queued. Any length comes back (the caller's intake
        checks it). Never blocks. Raises IntraHostError for a broken
        connection (the caller's path has failed)."""
        self._sample = None
        try:
            sample = self._port.receive()
        except Exception as exc:  # ReceiveError
            raise IntraHostError(f"intra-host pub/sub {self.name}: {exc!r}") from exc
        if sample is None:
            return None
        self._sample = sample
        return _view(sample.payload_ptr, sample.header.number_of_elements).toreadonly()

    def wait(self, timeout_s: float) -> None:
        """Block until a publisher's notification (a sample was sent) or
        ``timeout_s``; returns at once if one is pending. Never spins; a
        subscriber opened without ``wake`` sleeps ``timeout_s``. Then
        :meth:`receive_next` until None."""
        waiter = self._waiter
        if waiter is None:
            time.sleep(max(0.0, timeout_s))
            return
        waiter.wait_s(timeout_s)

    def release(self) -> None:
        """Give the sample back (its view must not be used after)."""
        self._sample = None
