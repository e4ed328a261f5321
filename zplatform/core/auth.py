"""Authentication of every frame a node takes from the network: per-link keys and tags.

With ``security.auth`` on (the default), every region frame, telemetry
snapshot, command request, clock exchange, probe, mirror and event record
travels as ``frame || tag``: the sender's *run* (:data:`RUN_LEN` bytes), a
header tag over the run, the length and the first :data:`HEADER_LEN`
bytes, then a MAC (keyed BLAKE3 or HMAC-SHA256) over the whole frame, under
keys derived from the link's key, the channel and that run. Receivers
check the header first (:meth:`Channel.open_header`, microseconds at any
size), then freshness, then the body (:meth:`Channel.check_body`). A frame
tagged for one channel fails on every other; a receiver bound to a run
(:class:`Run`) refuses every frame of another run (:class:`RunError`).
Each host role holds only the links it speaks on (:func:`role_links`).

:class:`Channel` tags and checks one channel's frames (``open`` returns a
view, no copy, or raises :class:`AuthError`; constant-time, before any
decode; one per thread). :func:`load_keys` finds a host's keys and
:func:`check_key` refuses weak or exposed ones (:class:`KeyError_`);
loading blocks on file I/O, tagging never blocks. Tag: codecs/FORMAT.md §6.1.
"""

from __future__ import annotations

import hmac
import os
import re
import secrets
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import blake3

from ..config import Mission
from ..errors import CodecError, ZPlatformError

__all__ = [
    "BULK_PREFIX",
    "HEADER_LEN",
    "HTAG_LEN",
    "KEY_ENV",
    "KEY_FILE_ENV",
    "MACS",
    "MAC_LEN",
    "NO_RUN",
    "OPERATORS_LINK",
    "RUN_LEN",
    "TAG_LEN",
    "AuthError",
    "Channel",
    "KeyError_",
    "KeySet",
    "Run",
    "RunError",
    "bulk_links",
    "channel",
    "channel_key",
    "check_key",
    "default_key_dir",
    "header_key",
    "host_roles",
    "key_file_name",
    "link_of",
    "load_keys",
    "new_run_epoch",
    "read_key_file",
    "role_host",
    "role_links",
    "run_key",
    "write_key_set",
]

#: What :meth:`Channel.seal_tail` tags in place: its own buffer, or a view.
_Buf = TypeVar("_Buf", bytearray, memoryview)

RUN_LEN = 8
"""Bytes of the run word that opens every tag (codecs/FORMAT.md §6.1): the
sender's run (the control node's ``cn_epoch``, little-endian), or
:data:`NO_RUN`."""
HTAG_LEN = 8
"""Bytes of the header tag (codecs/FORMAT.md §6.1): a MAC over the run word,
the frame's length and its first :data:`HEADER_LEN` bytes, checked before
the body's; the body's MAC follows, so 64 bits suffice (§6.1's argument)."""
HEADER_LEN = 40
"""How many of a frame's first bytes the header tag covers: a region
frame's whole fixed header (29 bytes at most, codecs/FORMAT.md §2: seq and
t_ns among them) and the first bytes of its data; a shorter message whole.
With the run word and the length, one 64-byte block of either MAC."""
MAC_LEN = 16
"""Bytes of MAC per frame (truncated to 128 bits, as RFC 4868's HMAC-SHA-256-128)."""
TAG_LEN = RUN_LEN + HTAG_LEN + MAC_LEN
"""Bytes of tag per frame: the run word, the header tag, then the body's MAC."""
NO_RUN = 0
"""The run of a sender that knows none (a node before its first clock
exchange, the ground): its frames are tagged under the run-0 key, which
only a receiver that is bound to no run takes (:class:`Run`)."""
KEY_ENV = "ZPLATFORM_KEY"
KEY_FILE_ENV = "ZPLATFORM_KEY_FILE"
KEY_LEN = 32
"""Bytes of every key zplatform makes, and the least it accepts."""
MACS: tuple[str, ...] = ("blake3", "hmac-sha256")
"""The MACs ``security.mac`` may name."""

_PREFIX = "zplatform/2/"
_HEADER_CONTEXT = b"zplatform/3/header/"
"""Derives a run's header key from the channel key (codecs/FORMAT.md §6.1):
the tag's version 3 (version 2's tag had no header tag)."""
_MAX_FILE = 64 * 1024  # far more than any key set; a bound on what is read
# Keys published in the repository (the golden vectors of codecs/vectors/auth,
# BLAKE3's own test key): anyone can read them, so they are never a real key.
_KNOWN_TEST_KEYS = frozenset(
    {
        bytes.fromhex("5a9c4e1f0b7d3a6e82c5f19d4b07e3a8c6d2f5910e8b4a7c3d6f1e0b9a5c8d27"),
        b"whats the Elvish word for friend",
    }
)


class AuthError(CodecError):
    """A frame without a valid tag for its channel: never applied, counted
    as a bad frame like any other malformed input."""


class RunError(AuthError):
    """A frame tagged for another run than the receiver's (or before the
    receiver knows its run): refused before its MAC is computed. Receivers
    count it as stale (an earlier run's frame is a replay), not as bad."""


class KeyError_(ZPlatformError):
    """A key is missing, unreadable, exposed or weak; the message names the
    link or the file and says what to do."""


# -- links and host roles -------------------------------------------------------


def link_of(channel_name: str) -> str:
    """The link whose key tags ``channel_name`` (module doc); ValueError for
    a name that is no channel."""
    if channel_name in ("telemetry", "run_hello", "run_answer"):
        # The run exchange (zplatform.runtime.clocksync.RunAsker): whoever
        # reads telemetry may learn the run it is bound to.
        return "downlink"
    if channel_name == "gn_to_cn":
        return "uplink"
    if channel_name.startswith("events_"):
        return "events-" + channel_name[len("events_") :]
    if channel_name in PEER_CHANNELS:
        return PEER_LINK
    if channel_name.startswith(BULK_PREFIX):
        # A bulk channel's samples for one reader (zplatform.runtime.bulk):
        # ``bulk_NAME/READER``, their own link, held by the channel's owner
        # and that reader only (no reader can forge another's samples).
        name, sep, reader = channel_name[len(BULK_PREFIX) :].partition("/")
        if sep and name and reader:
            return f"bulk-{name}-{reader}"
        raise ValueError(f"{channel_name!r} is not a channel (bulk: bulk_NAME/READER)")
    name = channel_name.removeprefix("clock_").removeprefix("probe_")
    src, sep, dst = name.partition("_to_")
    if sep and src == "cn" and dst:
        return f"cn-{dst}"
    if sep and dst == "cn" and src:
        return f"cn-{src}"
    raise ValueError(f"{channel_name!r} is not a channel")


OPERATORS_LINK = "operators"
"""The key (in the control nodes' key files only) that operators' and
stations' keys derive from (a mission with ``ground:``;
:mod:`zplatform.control.authority`). No channel is tagged with it."""
PEER_LINK = "cn-cn_b"
"""The link between a mission's two control nodes (a standby's mirror and clock)."""
BULK_PREFIX = "bulk_"
"""Bulk channel ``NAME``'s samples carry one tag per reader: reader R's on
auth channel ``bulk_NAME/R``, tagged by link ``bulk-NAME-R``
(:func:`bulk_links`); no other channel name starts so (node names are
``cn``, ``cn_b``, ``gn``, ``dnN``)."""
PEER_CHANNELS = frozenset({"mirror", "clock_peer_to_cn", "clock_cn_to_peer"})
"""The channels :data:`PEER_LINK` tags: the commander's whole Data Vector to
the standby every loop (``mirror``) and the standby's clock exchange with
the commander."""


def _event_links(mission: Mission) -> list[str]:
    nodes = [*mission.control_nodes, *mission.device_nodes, *(["gn"] if mission.has_ground else [])]
    return [f"events-{n}" for n in nodes]


def bulk_links(mission: Mission, role: str) -> list[str]:
    """The bulk channels' links host role ``role`` holds: ``bulk-NAME-R``
    for every reader R of every channel it owns, and its own
    ``bulk-NAME-ROLE`` for every channel it reads. A reader holds no other
    reader's link (so it cannot forge samples another reader takes), and
    ``tool`` none (a tap shows bulk samples unverified; docs/security.md,
    "Keys per link")."""
    out: list[str] = []
    for ch in mission.bulk:
        if ch.node == role:
            out += [f"bulk-{ch.name}-{r}" for r in ch.readers]
        elif role in ch.readers:
            out.append(f"bulk-{ch.name}-{role}")
    return out


def host_roles(mission: Mission) -> tuple[str, ...]:
    """The mission's host roles, one key file each: ``cn`` (and the standby
    ``cn_b``), every device node, ``gn`` (when the mission has a ground
    node) and ``tool``."""
    return (
        *mission.control_nodes,
        *mission.device_nodes,
        *(("gn",) if mission.has_ground else ()),
        "tool",
    )


def role_links(mission: Mission, role: str) -> tuple[str, ...]:
    """The links host role ``role`` holds (module doc); KeyError_ for a role
    the mission does not have."""
    dns = mission.device_nodes
    if role in mission.control_nodes:
        # A standby control node holds what the commander holds: it may command.
        up = ["uplink"] if mission.has_ground else []
        peer = [PEER_LINK] if mission.standby is not None else []
        # The secret every operator's and station's key derives from
        # (zplatform.control.authority): a control node's alone.
        ops = [OPERATORS_LINK] if mission.ground is not None and mission.has_ground else []
        return (
            *(f"cn-{dn}" for dn in dns),
            *up,
            "downlink",
            *peer,
            *ops,
            f"events-{role}",
            *bulk_links(mission, role),
        )
    if role in dns:
        return (f"cn-{role}", f"events-{role}", *bulk_links(mission, role))
    if role == "gn" and mission.has_ground:
        return ("uplink", "downlink", *_event_links(mission), *bulk_links(mission, role))
    if role == "tool":
        return ("downlink", *_event_links(mission), *bulk_links(mission, role))
    raise KeyError_(
        f"mission {mission.mission!r} has no host role {role!r}; its roles: "
        f"{', '.join(host_roles(mission))}"
    )


def _mission_links(mission: Mission) -> tuple[str, ...]:
    seen: dict[str, None] = {}
    for role in host_roles(mission):
        seen.update(dict.fromkeys(role_links(mission, role)))
    return tuple(seen)


_ROLE_HOSTS = {
    "cn": "the control node's host",
    "cn_b": "the standby control node's host",
    "gn": "the ground station (ground node, console, cmd)",
    "tool": "read-only tools (tap, log)",
}


def role_host(role: str) -> str:
    """Where host role ``role``'s key file belongs, in words."""
    return _ROLE_HOSTS.get(role, f"{role}'s host")


# -- keys ---------------------------------------------------------------------------


def check_key(key: bytes, where: str) -> bytes:
    """Return ``key`` if it can be a secret; KeyError_ naming ``where`` if not.

    Refused: shorter than :data:`KEY_LEN` bytes; one repeated byte; a
    repeated pattern (period up to half the key); bytes counting up or down
    by a fixed step; every byte printable ASCII (a passphrase, not a random
    key: 32 random bytes are all printable with probability 2e-14); a key
    published as a test key (:data:`_KNOWN_TEST_KEYS`). A key from
    ``zplatform keygen`` (``secrets.token_bytes``) passes.
    """
    n = len(key)
    if n < KEY_LEN:
        raise KeyError_(
            f"{where}: the key is {n} bytes; at least {KEY_LEN} random bytes are needed "
            "(make keys with `zplatform keygen`)"
        )
    weak = ""
    step = (key[1] - key[0]) % 256
    if all((key[i + 1] - key[i]) % 256 == step for i in range(n - 1)):
        weak = "one repeated byte" if step == 0 else "bytes counting by a fixed step"
    elif any(key[p:] == key[:-p] for p in range(2, n // 2 + 1)):
        weak = "a repeated pattern"
    elif all(0x20 <= b < 0x7F for b in key):
        weak = "printable text (a passphrase, not random bytes)"
    elif key in _KNOWN_TEST_KEYS:
        weak = "a published test key"
    if weak:
        raise KeyError_(f"{where}: the key is {weak}: refused; make keys with `zplatform keygen`")
    return key


def _parse_hex(text: str, where: str) -> bytes:
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise KeyError_(f"{where}: a key must be hex ({2 * KEY_LEN} hex digits)") from None
    return check_key(key, where)


def _derive(key: bytes, context: str) -> bytes:
    return hmac.digest(key, context.encode(), "sha256")


def run_key(ch_key: bytes, run: int) -> bytes:
    """The key of a channel in run ``run`` (codecs/FORMAT.md §6.1):
    HMAC-SHA256(channel_key, "zplatform/2/run/" || run as u64 little-endian)."""
    return hmac.digest(ch_key, _RUN_CONTEXT + _run_word(run), "sha256")


def header_key(ch_key: bytes, run: int) -> bytes:
    """The key of a channel's header tags in run ``run`` (codecs/FORMAT.md
    §6.1): HMAC-SHA256(channel_key, "zplatform/3/header/" || run as u64
    little-endian). One HMAC from the channel key, so checking the header
    of a frame naming an unseen run costs one derivation, not two."""
    return hmac.digest(ch_key, _HEADER_CONTEXT + _run_word(run), "sha256")


def _run_word(run: int) -> bytes:
    return (run & _U64).to_bytes(RUN_LEN, "little")


_RUN_CONTEXT = (_PREFIX + "run/").encode()
_U64 = (1 << 64) - 1
_RUN_LOW_BITS = 24


def new_run_epoch(now_ns: int) -> int:
    """A control node's new run: its clock ``now_ns`` with the low 24 bits
    (17 ms) replaced by random ones, never :data:`NO_RUN`. Runs started
    more than 17 ms apart keep their clocks' order (the ground orders
    telemetry by run); two runs on a clock that repeats (a host without a
    real-time clock, reset at every boot) still differ but with chance
    2**-24, so an earlier run's frames do not verify in the new one."""
    mask = (1 << _RUN_LOW_BITS) - 1
    run = ((now_ns & ~mask) | secrets.randbits(_RUN_LOW_BITS)) & _U64
    return run or 1


class Run:
    """The run a node's channels are bound to (module doc), shared by every
    :class:`Channel` of the node that names it: ``epoch`` (a u64; 0, i.e.
    :data:`NO_RUN`, while unknown) and ``word``, its :data:`RUN_LEN` bytes
    as the tag carries them. :meth:`set` is the one writer (the loop thread
    following ``cn_epoch``, or the clock exchange that learned it); each
    channel re-keys once when it sees a new run, never per frame. Reading
    from other threads is safe (one attribute read)."""

    __slots__ = ("epoch", "word")

    def __init__(self, epoch: int = NO_RUN) -> None:
        self.epoch = NO_RUN
        self.word = _run_word(NO_RUN)
        self.set(epoch)

    def set(self, epoch: int) -> None:
        """Bind to run ``epoch`` (allocates only when it changes)."""
        if epoch != self.epoch:
            # One assignment publishes both: readers take (epoch, word) via .word.
            self.word = _run_word(epoch)
            self.epoch = epoch

    @property
    def known(self) -> bool:
        return self.epoch != NO_RUN


def channel_key(link_key: bytes, vehicle: str, mac: str, name: str) -> bytes:
    """The key of channel ``name`` (codecs/FORMAT.md §6.1): the MAC's name is
    part of it, so peers configured with different MACs never agree on a tag."""
    return _derive(link_key, f"{_PREFIX}{vehicle}/{mac}/{name}")


class Channel:
    """Tags and checks the frames of one channel (module doc).

    ``link_key``: the key of the channel's link; ``mac``: ``blake3`` or
    ``hmac-sha256``; ``run``: the :class:`Run` this end is bound to (None:
    bound to none). A tag is the run word, the header tag, then the body's
    MAC, under the run's keys (:func:`run_key`, :func:`header_key`,
    codecs/FORMAT.md §6.1). Sending, the run word is ``run``'s
    (:data:`NO_RUN` without one). Receiving, a channel bound to a run takes
    only frames of that run: another run's (or any while its run is
    unknown) is refused, as :class:`RunError` when its header tag checks
    under the keys of the run it names (an earlier run's genuine frame,
    replayed: stale) and AuthError when not (junk: bad); an unbound channel
    (the ground's) takes any run's frame whose tags check under that run's
    keys. Refusing another run's frame never computes the body's MAC. The
    keys of this end's run and of the last other run seen are kept, so
    re-keying (two HMACs) happens once per run, not per frame (a flood of
    frames each naming a new run costs those two HMACs each on top of the
    header tag).

    Checking is two steps, so a receiver can refuse a replay by its header
    before it pays for the body: :meth:`open_header` (the length, the run,
    the header tag: microseconds, whatever the frame's size) and
    :meth:`check_body` (the MAC over the whole frame); :meth:`open` is both.

    :meth:`seal` copies the frame into this channel's own buffer and tags it
    there (the buffer is overwritten by the next call; resized only if the
    frame length changes); :meth:`seal_tail` tags a frame in the buffer that
    carries it, without copying it (a sender that frames into a
    :class:`~zplatform.core.codec.FrameEncoder` with ``tail`` room: what the
    loops do, whose frames are up to the whole Data Vector). :meth:`open`
    returns a view of the frame inside ``payload`` (no copy) or raises
    AuthError; :meth:`strip` is the same view for a payload whose tag this
    channel's key was already checked on. :meth:`tag` allocates only the
    tag's 32 bytes. Not thread-safe (the BLAKE3 hashers and the header
    buffer are kept and reused per frame): one per sending or receiving
    thread.
    """

    __slots__ = ("_buf", "_main", "_other", "mac", "name", "run")

    def __init__(
        self,
        link_key: bytes,
        vehicle: str,
        name: str,
        mac: str = "blake3",
        run: Run | None = None,
    ) -> None:
        if mac not in MACS:
            raise ValueError(f"unknown MAC {mac!r}; one of {', '.join(MACS)}")
        self.name = name
        self.mac = mac
        self.run = run
        base = channel_key(link_key, vehicle, mac, name)
        self._buf = bytearray()
        # Two run keys: this end's run's, and the last other run seen (to
        # tell an earlier run's authentic frame, stale, from junk, bad).
        self._main = _RunKey(base, mac)
        self._other = _RunKey(base, mac)

    def twin(self) -> Channel:
        """A channel of the same key, name, MAC and run with hashers and
        buffers of its own: for a second thread (this class is not
        thread-safe). Costs no key derivation."""
        c = Channel.__new__(Channel)
        c.name, c.mac, c.run = self.name, self.mac, self.run
        base = self._main._base
        c._buf = bytearray()
        c._main = _RunKey(base, self.mac)
        c._other = _RunKey(base, self.mac)
        return c

    def tag(self, frame: bytes | bytearray | memoryview) -> bytes:
        """The tag of ``frame`` in this channel's sending run: run word,
        header tag and MAC."""
        run = self.run
        k = self._main.use(run.word if run is not None else _NO_WORD)
        return k.word + k.htag(frame) + k.mac(frame)

    def seal(self, frame: bytes | bytearray | memoryview) -> bytearray:
        n = len(frame)
        if len(self._buf) != n + TAG_LEN:
            self._buf = bytearray(n + TAG_LEN)
        buf = self._buf
        buf[:n] = frame
        self._seal_at(memoryview(buf), n)
        return buf

    def _seal_at(self, mv: memoryview, n: int) -> None:
        run = self.run
        k = self._main.use(run.word if run is not None else _NO_WORD)
        frame = mv[:n]
        mv[n : n + RUN_LEN] = k.word
        mv[n + RUN_LEN : n + _MAC_AT] = k.htag(frame)
        mv[n + _MAC_AT :] = k.mac(frame)

    def seal_tail(self, buf: _Buf) -> _Buf:
        """Tag the frame that fills ``buf`` but for its last :data:`TAG_LEN`
        bytes, and write the tag there; returns ``buf`` (the frame is read
        through a view, never copied; ``buf`` may be a writable memoryview,
        e.g. a loaned shared-memory sample). ValueError when ``buf`` has no
        room for a frame and a tag."""
        mv = memoryview(buf)
        n = len(mv) - TAG_LEN
        if n <= 0:
            raise ValueError(f"{self.name}: {len(mv)} bytes hold no frame and tag")
        self._seal_at(mv, n)
        return buf

    def strip(self, payload: bytes | bytearray | memoryview) -> memoryview:
        """The frame in ``payload`` (a view, no copy), its tag not checked:
        only for a payload whose tag was already checked with this channel's
        key, on the very same bytes (a node's intake, ahead of its loop
        thread). AuthError when it is too short to carry a tag."""
        mv = memoryview(payload)
        n = len(mv) - TAG_LEN
        if n <= 0:
            raise AuthError(f"{self.name}: {len(mv)} bytes, too short to carry a tag")
        return mv[:n]

    @staticmethod
    def run_of(payload: bytes | bytearray | memoryview) -> int:
        """The run a tagged ``payload`` names (not checked; 0 when too short)."""
        mv = memoryview(payload)
        n = len(mv) - TAG_LEN
        return int.from_bytes(mv[n : n + RUN_LEN], "little") if n > 0 else NO_RUN

    def open(self, payload: bytes | bytearray | memoryview, *, any_run: bool = False) -> memoryview:
        """The frame in ``payload`` (a view, no copy) if its tag checks (class
        doc): :meth:`open_header`, then :meth:`check_body`. RunError for
        another run's frame on a bound channel, AuthError for any other bad
        tag. ``any_run``: take any run's frame, even on a bound channel (a
        clock reply that echoes this end's fresh nonce: how a node learns
        its run, :mod:`zplatform.runtime.clocksync`)."""
        self.open_header(payload, any_run=any_run)
        return self.check_body(payload)

    def open_header(
        self, payload: bytes | bytearray | memoryview, *, any_run: bool = False
    ) -> memoryview:
        """The frame in ``payload`` (a view, no copy) if its run and header
        tag check: only its first :data:`HEADER_LEN` bytes (and its length)
        are then authentic; the rest is not until :meth:`check_body` on the
        same payload. Reads the run word, the header tag and the first
        :data:`HEADER_LEN` bytes, never the rest (constant time, whatever the
        frame's size). RunError for another run's frame whose header tag
        checks under that run's keys (bound channel, not ``any_run``: see
        :meth:`open`), AuthError for anything else that does not check."""
        mv = memoryview(payload)
        n = len(mv) - TAG_LEN
        if n <= 0:
            raise AuthError(f"{self.name}: {len(mv)} bytes, too short to carry a tag")
        word = mv[n : n + RUN_LEN]
        body = mv[:n]
        got = mv[n + RUN_LEN : n + _MAC_AT]
        run = self.run
        if run is not None and not any_run and word != run.word:
            # Another run's: refused either way. Its header tag (under that
            # run's keys, kept for the next one) tells a replay from junk.
            if hmac.compare_digest(self._other.use(word).htag(body), got):
                epoch = int.from_bytes(word, "little")
                raise RunError(
                    f"{self.name}: a frame of run {epoch}, not of this run ({run.epoch})"
                    if run.known
                    else f"{self.name}: a frame of run {epoch} before this node knows its run"
                )
        elif hmac.compare_digest(self._main.use(word).htag(body), got):
            return body
        raise self._bad()

    def check_body(self, payload: bytes | bytearray | memoryview) -> memoryview:
        """The frame in ``payload`` (a view, no copy) if the MAC over all of
        it checks under the keys of the run it names: the second step, after
        :meth:`open_header` passed on the same payload (which chose those
        keys; alone it checks the MAC of whatever run the payload names).
        AuthError when it does not check (a genuine header spliced onto
        another body, or junk)."""
        mv = memoryview(payload)
        n = len(mv) - TAG_LEN
        if n <= 0:
            raise AuthError(f"{self.name}: {len(mv)} bytes, too short to carry a tag")
        body = mv[:n]
        k = self._main.use(mv[n : n + RUN_LEN])
        if hmac.compare_digest(k.mac(body), mv[n + _MAC_AT :]):
            return body
        raise self._bad()

    def _bad(self) -> AuthError:
        return AuthError(
            f"{self.name}: bad authentication tag (wrong key, forged, or a peer with "
            f"another security.mac; this node's is {self.mac})"
        )


_NO_WORD = _run_word(NO_RUN)
_MAC_AT = RUN_LEN + HTAG_LEN
_HEAD_IN = RUN_LEN + 4 + HEADER_LEN


class _RunKey:
    """A channel's keys in one run (:func:`header_key`, :func:`run_key`) and
    its MACs; re-keyed only when asked for another run (:meth:`use`: the
    header key alone, one HMAC; the body's key when its MAC is first
    asked for, so a frame refused by its header never derives it).
    :meth:`htag` builds its input in a buffer of its own (no allocation but
    the 8-byte result)."""

    __slots__ = ("_base", "_blake3", "_head", "hasher", "hhasher", "hkey", "key", "word")

    def __init__(self, base: bytes, mac: str) -> None:
        self._base = base
        self._blake3 = mac == "blake3"
        self._head = bytearray(_HEAD_IN)
        self.word = b""
        self.key = b""
        self.hkey = b""
        self.hasher: Any = None
        self.hhasher: Any = None

    def use(self, word: bytes | memoryview) -> _RunKey:
        if word != self.word:
            w = bytes(word)
            self.hkey = hmac.digest(self._base, _HEADER_CONTEXT + w, "sha256")
            if self._blake3:
                self.hhasher = blake3.blake3(key=self.hkey)
            self.key = b""  # derived by mac() when first needed
            self.hasher = None
            self._head[:RUN_LEN] = w
            self.word = w
        return self

    def htag(self, frame: bytes | bytearray | memoryview) -> bytes:
        """The header tag of ``frame`` (codecs/FORMAT.md §6.1): reads its
        length and its first :data:`HEADER_LEN` bytes only."""
        n = len(frame)
        h = n if n < HEADER_LEN else HEADER_LEN
        head = self._head
        head[RUN_LEN : RUN_LEN + 4] = (n & 0xFFFFFFFF).to_bytes(4, "little")
        head[RUN_LEN + 4 : RUN_LEN + 4 + h] = frame[:h]
        data = memoryview(head)[: RUN_LEN + 4 + h]
        hh = self.hhasher
        if hh is None:
            return hmac.digest(self.hkey, data, "sha256")[:HTAG_LEN]
        hh.reset()
        hh.update(data)
        return hh.digest(HTAG_LEN)

    def mac(self, frame: bytes | bytearray | memoryview) -> bytes:
        """The MAC over all of ``frame`` (the body's)."""
        if not self.key:
            self.key = hmac.digest(self._base, _RUN_CONTEXT + self.word, "sha256")
            if self._blake3:
                self.hasher = blake3.blake3(key=self.key)
        h = self.hasher
        if h is None:
            return hmac.digest(self.key, frame, "sha256")[:MAC_LEN]
        h.reset()
        h.update(frame)
        return h.digest(MAC_LEN)


class KeySet:
    """The link keys one host holds, and the channels they tag (module doc).

    Made by :func:`load_keys` (a host's keys), :meth:`from_master` (every
    link, derived from one master key) or :meth:`generate` (every link,
    independent random keys, for :func:`write_key_set`). ``source`` says
    where the keys came from, for error messages; ``role`` the host role
    whose keys they are (None: not one role's). Immutable after construction.
    """

    __slots__ = ("_keys", "_mission", "mac", "role", "source", "vehicle")

    def __init__(
        self, mission: Mission, keys: Mapping[str, bytes], *, source: str, role: str | None = None
    ) -> None:
        self._mission = mission
        self.vehicle = mission.vehicle
        self.mac: str = mission.security.mac
        self.source = source
        self.role = role
        self._keys = dict(keys)

    @classmethod
    def from_master(cls, mission: Mission, master: bytes, *, source: str = KEY_ENV) -> KeySet:
        """Every link of ``mission``, each key derived from ``master`` (module
        doc). ``master`` is not checked here (the lockstep runner's fixed key
        is deliberately trivial); :func:`load_keys` checks what it reads."""
        v = mission.vehicle
        keys = {ln: _derive(master, f"{_PREFIX}link/{v}/{ln}") for ln in _mission_links(mission)}
        return cls(mission, keys, source=source)

    @classmethod
    def generate(cls, mission: Mission) -> KeySet:
        """Every link of ``mission`` with its own random key."""
        keys = {ln: secrets.token_bytes(KEY_LEN) for ln in _mission_links(mission)}
        return cls(mission, keys, source="zplatform keygen")

    @property
    def links(self) -> tuple[str, ...]:
        """The links held, in the mission's order."""
        return tuple(self._keys)

    def has(self, link: str) -> bool:
        return link in self._keys

    def link_key(self, link: str) -> bytes:
        """The key of ``link``; KeyError_ naming the link and the source if not held."""
        try:
            return self._keys[link]
        except KeyError:
            held = f"host role {self.role}'s keys" if self.role else "its keys"
            raise KeyError_(
                f"no key for link {link}: {self.source} has none ({held}: "
                f"{', '.join(self._keys) or 'none'})"
            ) from None

    def channel(self, name: str, run: Run | None = None) -> Channel:
        """A new :class:`Channel` for ``name``, keyed by its link and bound to
        ``run`` (None: to none); KeyError_ when the link is not held."""
        return Channel(self.link_key(link_of(name)), self.vehicle, name, self.mac, run)

    def for_node(self, role: str) -> KeySet:
        """The keys host role ``role`` holds, taken from these; KeyError_ (one
        line: the role, the first missing link, where it was looked for) when
        one is missing."""
        need = role_links(self._mission, role)
        missing = [ln for ln in need if ln not in self._keys]
        if missing:
            mine = f" (the key file of host role {self.role})" if self.role else ""
            raise KeyError_(
                f"{role} needs the key of link {missing[0]}, and {self.source}{mine} has none: "
                f"give {role} its own key file, {role}.keys from `zplatform keygen`"
            )
        return KeySet(
            self._mission, {ln: self._keys[ln] for ln in need}, source=self.source, role=role
        )


def channel(keys: KeySet | None, name: str, run: Run | None = None) -> Channel | None:
    """``keys.channel(name, run)``, or None when the mission does not
    authenticate (``keys`` None): what every node builds its channels with."""
    return keys.channel(name, run) if keys is not None else None


# -- key files ------------------------------------------------------------------------


def default_key_dir(mission: Mission | str) -> Path:
    """``~/.config/zplatform/keys/<mission>/`` (XDG_CONFIG_HOME respected): the
    key set directory of a mission, or of a mission name."""
    name = mission if isinstance(mission, str) else mission.mission
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "zplatform" / "keys" / name


def key_file_name(role: str) -> str:
    """The file of host role ``role`` in a key set directory."""
    return f"{role}.keys"


def write_key_set(
    mission: Mission, directory: str | Path, *, replace: bool = False
) -> dict[str, Path]:
    """Write a new key set for ``mission`` into ``directory``: one file per
    host role (:func:`host_roles`), each holding that role's links with
    independent random keys; files mode 0600, the directory 0700 (made, with
    its parents, if missing). Returns ``{role: path}``.

    Refuses (KeyError_) to overwrite a key file unless ``replace`` (a key
    rotation): a new key set locks out every host that still has the old
    one. With ``replace`` each file is replaced whole (written aside, then
    renamed), so a reader never sees half a key file."""
    d = Path(directory)
    keys = KeySet.generate(mission)
    try:
        d.mkdir(parents=True, exist_ok=True, mode=0o700)
        os.chmod(d, 0o700)
    except OSError as exc:
        raise KeyError_(f"cannot make the key directory {d}: {exc.strerror}") from exc
    out: dict[str, Path] = {}
    roles = host_roles(mission)
    for role in roles:
        p = d / key_file_name(role)
        if p.exists() and not replace:
            raise KeyError_(
                f"{p} exists; `zplatform keygen --rotate` replaces the key set (every host "
                "then needs its new file)"
            )
    for role in roles:
        p = d / key_file_name(role)
        mine = keys.for_node(role)
        lines = [
            f"# zplatform key set of mission {mission.mission!r}: host role {role!r}, "
            f"for {role_host(role)}.",
            "# Secret: keep it mode 0600, on that host only. Made by `zplatform keygen`.",
            f"mission {mission.mission}",
            f"role {role}",
            *(f"{ln} {mine.link_key(ln).hex()}" for ln in mine.links),
        ]
        aside = p.with_name(p.name + ".new") if replace else p
        try:
            if replace:
                aside.unlink(missing_ok=True)
            fd = os.open(aside, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except OSError as exc:
            raise KeyError_(f"cannot write a key file {p}: {exc.strerror}") from exc
        with os.fdopen(fd, "w") as f:
            f.write("\n".join(lines) + "\n")
        if replace:
            os.replace(aside, p)
        out[role] = p
    return out


_LINE_RE = re.compile(r"^([a-z][a-z0-9_-]*)\s+(\S+)$")


def read_key_file(path: str | Path, mission: Mission) -> KeySet:
    """The keys in one host's key file (format: docs/security.md, key files).

    KeyError_ (one line, naming the file) when it is missing, not a regular
    file, readable or writable by group or others (with the ``chmod`` that
    fixes it), malformed, another mission's, or holds a weak key."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise KeyError_(f"no key file at {p}") from None
    except OSError as exc:
        raise KeyError_(f"cannot read the key file {p}: {exc.strerror}") from exc
    if not stat.S_ISREG(st.st_mode):
        raise KeyError_(f"{p} is not a regular file, so it is no key file")
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o077:
        raise KeyError_(
            f"{p} is open to others (mode {mode:04o}): keys must be private to their owner; "
            f"run `chmod 600 {p}`"
        )
    if st.st_size > _MAX_FILE:
        raise KeyError_(f"{p} is {st.st_size} bytes, too large for a key file")
    try:
        with open(p, "rb") as f:
            raw = f.read(_MAX_FILE + 1)
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        raise KeyError_(f"{p} is not a key file (not ASCII text)") from None
    except OSError as exc:
        raise KeyError_(f"cannot read the key file {p}: {exc.strerror}") from exc
    keys: dict[str, bytes] = {}
    role: str | None = None
    known = set(_mission_links(mission))
    for n, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        m = _LINE_RE.fullmatch(line)
        if m is None:
            if re.fullmatch(r"[0-9a-fA-F]+", line):
                raise KeyError_(
                    f"{p}: a single mission key (an earlier zplatform's, which opened every "
                    "link): make a key set with `zplatform keygen MISSION`"
                )
            raise KeyError_(f"{p}:{n}: expected `LINK HEXKEY`, `mission NAME` or `role ROLE`")
        name, value = m.groups()
        if name == "mission":
            if value != mission.mission:
                raise KeyError_(
                    f"{p} is a key file of mission {value!r}, not of {mission.mission!r}"
                )
        elif name == "role":
            role = value
        elif name in known:
            keys[name] = _parse_hex(value, f"{p}:{n} ({name})")
        else:
            raise KeyError_(f"{p}:{n}: {name!r} is no link of mission {mission.mission!r}")
    return KeySet(mission, keys, source=str(p), role=role)


def load_keys(
    mission: Mission,
    role: str,
    key_file: str | Path | None = None,
    *,
    create: bool = False,
) -> KeySet | None:
    """The keys of host role ``role`` (module doc for where they are looked
    up), or None when the mission turns authentication off.

    ``create``: make the mission's key set directory when no key is found
    anywhere (what ``zplatform up`` does on first use). A ``tool`` without
    its own file in a key set directory takes the ground's (``gn.keys``).
    Raises KeyError_ (one line) when a key the role needs is missing
    (naming the link and the file looked in), or a file or key is refused."""
    if not mission.security.auth:
        return None
    role_links(mission, role)  # an unknown role fails first, whatever the keys
    src = key_file if key_file is not None else os.environ.get(KEY_FILE_ENV) or None
    if src is None and os.environ.get(KEY_ENV):
        master = _parse_hex(os.environ[KEY_ENV], KEY_ENV)
        return KeySet.from_master(mission, master).for_node(role)
    if src is not None:
        path = Path(src)
        if path.is_dir():
            path = _role_file(path, role)
    else:
        d = default_key_dir(mission)
        if create and not d.exists():
            write_key_set(mission, d)
        path = _role_file(d, role)
        if not path.exists():
            raise KeyError_(
                f"mission {mission.mission!r} authenticates its traffic and {role} has no key "
                f"file at {path}: make a key set with `zplatform keygen MISSION_FILE` and copy "
                f"{path.name} to this host (or point {KEY_FILE_ENV} at it)"
            )
    return read_key_file(path, mission).for_node(role)


def _role_file(directory: Path, role: str) -> Path:
    p = directory / key_file_name(role)
    if role == "tool" and not p.exists() and (directory / key_file_name("gn")).exists():
        return directory / key_file_name("gn")
    return p
