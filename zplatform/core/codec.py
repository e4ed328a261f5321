"""The region frame: the wire format of every region and telemetry sample.

A frame is a MessagePack array of four items (``codecs/FORMAT.md`` pins it
byte by byte)::

    [layout_id: u32, seq: u64, t_ns: i64, data: bin]

``layout_id`` identifies the region's names, types and order
(:func:`zplatform.core.datavector.layout_id_of`), ``seq`` is the sender's loop
number, ``t_ns`` the sender's synchronised time, ``data`` the region's raw
little-endian bytes.

Encoding goes into a preallocated ``bytearray`` owned by the encoder (no
allocation per frame once the buffer has grown to the frame size). Decoding
checks shape, types, ranges, ``layout_id`` and length, in that order, before
anything touches a Data Vector; every failure raises a
:class:`~zplatform.errors.CodecError` subclass and nothing else.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Annotated

import msgspec
from msgspec import Meta

from ..errors import CodecError, FrameFormatError, FrameSizeError, LayoutMismatchError
from .datavector import DataVector

__all__ = [
    "BUNDLE_MAGIC",
    "BundleEncoder",
    "Frame",
    "FrameDecoder",
    "FrameEncoder",
    "RegionCodec",
    "bundle_entry",
    "bundle_size",
    "decode_frame",
    "encode_frame",
    "fixed_stamp",
    "frame_data",
    "frame_overhead",
    "frame_stamp",
    "is_bundle",
    "max_frame_length",
]

U32 = Annotated[int, Meta(ge=0, le=0xFFFF_FFFF)]
# MessagePack ints stop at 2**64-1, so ge=0 is the whole u64 check.
U64 = Annotated[int, Meta(ge=0)]
I64 = Annotated[int, Meta(ge=-(1 << 63), le=(1 << 63) - 1)]


# fixarray(4), 0xce u32, 0xcf u64, 0xd3 i64: big-endian, as MessagePack says.
_HDR = struct.Struct(">BBIBQBq")
_HDR_LEN = _HDR.size  # 24
_BIN8 = struct.Struct(">BB")
_BIN16 = struct.Struct(">BH")
_BIN32 = struct.Struct(">BI")


class Frame(msgspec.Struct, array_like=True, gc=False, frozen=True, forbid_unknown_fields=True):
    """A decoded frame. ``data`` is a zero-copy view into the received buffer:
    valid as long as that buffer is; copy it (``write_region``) to keep it.

    ``forbid_unknown_fields``: an array-like struct otherwise ignores extra
    trailing items, and a frame is an array of exactly four."""

    layout_id: U32
    seq: U64
    t_ns: I64
    data: memoryview


def frame_overhead(size: int) -> int:
    """Bytes a frame adds around ``size`` data bytes (26, 27 or 29)."""
    # fixarray(1) + u32(5) + u64(9) + i64(9) = the 24-byte header, then the
    # bin header (2, 3 or 5 bytes, by the data length).
    return _HDR_LEN + (2 if size < 256 else 3 if size < 65536 else 5)


class FrameEncoder:
    """Encodes frames into one reusable buffer.

    :meth:`encode` returns the encoder's own ``bytearray``: it is overwritten
    by the next call, so hand it to zenoh (which copies) before encoding
    again. The buffer is resized only when the data length changes (never,
    for a region). Not thread-safe; one per sending loop.

    ``tail``: bytes of room the buffer keeps after the frame, so that a tag
    can be written there in place (:meth:`zplatform.core.auth.Channel.seal_tail`)
    instead of the frame being copied into a tagged buffer of its own.
    :meth:`encode` then returns the frame followed by that room, whose bytes
    are whatever the last tag left there until it is tagged.
    """

    __slots__ = ("_at", "_buf", "_mv", "_n", "tail")

    def __init__(self, capacity: int = 0, tail: int = 0) -> None:
        if tail < 0:
            raise ValueError(f"tail room must be >= 0, not {tail}")
        self.tail = tail
        self._buf = bytearray()
        self._mv = memoryview(self._buf)
        self._n = -1
        self._at = 0
        self._resize(capacity)

    def _resize(self, n: int) -> None:
        # A bytearray cannot be resized while a memoryview is exported: a new
        # one is made instead (a caller may still hold a view of the old).
        self._mv.release()
        at = frame_overhead(n)
        self._buf = bytearray(at + n + self.tail)
        if n < 256:
            _BIN8.pack_into(self._buf, _HDR_LEN, 0xC4, n)
        elif n < 65536:
            _BIN16.pack_into(self._buf, _HDR_LEN, 0xC5, n)
        else:
            _BIN32.pack_into(self._buf, _HDR_LEN, 0xC6, n)
        self._mv = memoryview(self._buf)
        self._n = n
        self._at = at

    def encode(
        self, layout_id: int, seq: int, t_ns: int, data: bytes | bytearray | memoryview
    ) -> bytearray:
        """Encode one frame (one copy of ``data``, into the buffer); raises
        FrameFormatError for out-of-range header fields.

        Why not msgspec's ``encode_into`` here: it writes the smallest int
        markers, so a frame's length would vary with ``seq``. The fixed-width
        header keeps every frame of a region the same length, with fields at
        fixed offsets a peer in any language can index; it is still plain
        MessagePack, and msgspec decodes it. Speed is on par from 64 KB up
        and about 0.5 us slower below (``python -m bench.codec``).
        """
        n = len(data)
        if n != self._n:
            self._resize(n)
        try:
            _HDR.pack_into(self._buf, 0, 0x94, 0xCE, layout_id, 0xCF, seq, 0xD3, t_ns)
        except struct.error as exc:
            raise FrameFormatError(
                f"header out of range (layout_id {layout_id}, seq {seq}, t_ns {t_ns}): {exc}"
            ) from exc
        at = self._at
        self._mv[at : at + n] = data
        return self._buf

    def frame_len(self, size: int) -> int:
        """Bytes :meth:`encode` returns for ``size`` data bytes: the frame and
        the tail room. What :meth:`encode_into` needs."""
        return frame_overhead(size) + size + self.tail

    def encode_into(
        self,
        out: memoryview,
        layout_id: int,
        seq: int,
        t_ns: int,
        data: bytes | bytearray | memoryview,
    ) -> memoryview:
        """Encode one frame into ``out`` (a writable byte view, e.g. a loaned
        shared-memory sample) instead of the encoder's buffer: the same bytes
        :meth:`encode` writes, with the tail room left as it is (a tag goes
        there in place). One copy of ``data``, no allocation. ``out`` must be
        exactly :meth:`frame_len` long (ValueError otherwise); raises
        FrameFormatError for out-of-range header fields. Returns ``out``."""
        n = len(data)
        at = frame_overhead(n)
        if len(out) != at + n + self.tail:
            raise ValueError(
                f"a frame of {n} data bytes and {self.tail} of tail room is "
                f"{at + n + self.tail} bytes, the buffer {len(out)}"
            )
        try:
            _HDR.pack_into(out, 0, 0x94, 0xCE, layout_id, 0xCF, seq, 0xD3, t_ns)
        except struct.error as exc:
            raise FrameFormatError(
                f"header out of range (layout_id {layout_id}, seq {seq}, t_ns {t_ns}): {exc}"
            ) from exc
        if n < 256:
            _BIN8.pack_into(out, _HDR_LEN, 0xC4, n)
        elif n < 65536:
            _BIN16.pack_into(out, _HDR_LEN, 0xC5, n)
        else:
            _BIN32.pack_into(out, _HDR_LEN, 0xC6, n)
        out[at : at + n] = data
        return out


_decoder = msgspec.msgpack.Decoder(Frame)


def decode_frame(frame: bytes | bytearray | memoryview) -> Frame:
    """Decode any frame (no layout check). Raises FrameFormatError on malformed input.

    Accepts any valid MessagePack encoding of the four items (a peer may use
    smaller int markers); :meth:`FrameEncoder.encode` always writes the
    fixed-width form.
    """
    try:
        return _decoder.decode(frame)
    # DecodeError includes ValidationError; the others defensively: never leak them.
    except (msgspec.DecodeError, TypeError, ValueError, OverflowError) as exc:
        raise FrameFormatError(f"not a region frame: {exc}") from exc


def encode_frame(
    layout_id: int, seq: int, t_ns: int, data: bytes | bytearray | memoryview
) -> bytes:
    """Encode one frame into new ``bytes`` (allocates; for tools and tests)."""
    return bytes(FrameEncoder(len(data)).encode(layout_id, seq, t_ns, data))


def _fixed_width(frame: bytes | bytearray | memoryview) -> bool:
    """Whether ``frame`` starts with the fixed-width header (codecs/FORMAT.md §2)."""
    return (
        len(frame) >= _HDR_LEN + 2
        and frame[0] == 0x94
        and frame[1] == 0xCE
        and frame[6] == 0xCF
        and frame[15] == 0xD3
    )


def max_frame_length(size: int) -> int:
    """The longest valid frame of ``size`` data bytes: the fixed-width header
    and the widest bin header a peer may use. Anything longer is malformed."""
    return _HDR_LEN + 5 + size


def frame_stamp(frame: bytes | bytearray | memoryview) -> tuple[int, int]:
    """``(seq, t_ns)`` of a frame, read without decoding it when it has the
    fixed-width header (FORMAT.md §2: the fields at offsets 7 and 16, what
    zplatform always writes), else from :func:`decode_frame` (any valid
    MessagePack form). Constant time; raises FrameFormatError (a
    CodecError) for what is not a frame. For a receiver's intake, which
    must tell a newer frame from a replayed one before anything else."""
    if _fixed_width(frame):
        _, _, _, _, seq, _, t_ns = _HDR.unpack_from(frame, 0)
        return seq, t_ns
    f = decode_frame(frame)
    return f.seq, f.t_ns


def fixed_stamp(frame: bytes | bytearray | memoryview) -> tuple[int, int] | None:
    """``(seq, t_ns)`` of a frame with the fixed-width header (what
    zplatform writes), read at their offsets; None for anything else
    (never decoded, never raises). Constant time, no copy."""
    if not _fixed_width(frame):
        return None
    _, _, _, _, seq, _, t_ns = _HDR.unpack_from(frame, 0)
    return seq, t_ns


def frame_data(frame: bytes | bytearray | memoryview, size: int) -> memoryview:
    """The ``size`` data bytes of a frame, as a zero-copy view: by offset
    when it has the fixed-width form of a region of ``size`` bytes, else
    from :func:`decode_frame`. Checks only the shape and the length (not the
    layout: :meth:`RegionCodec.check` does that); raises FrameFormatError or
    FrameSizeError (CodecErrors) otherwise. Constant time, no copy."""
    mv = memoryview(frame)
    at = frame_overhead(size)
    if _fixed_width(mv) and len(mv) == at + size:
        return mv[at:]
    data = decode_frame(mv).data
    if len(data) != size:
        raise FrameSizeError(f"frame carries {len(data)} data bytes, expected {size}")
    return data


class FrameDecoder:
    """Decodes frames of one expected layout and size.

    :meth:`decode` raises :class:`LayoutMismatchError` or
    :class:`FrameSizeError` after :func:`decode_frame`'s format checks.
    """

    __slots__ = ("layout_id", "name", "size")

    def __init__(self, layout_id: int, size: int, name: str = "region") -> None:
        self.layout_id = layout_id
        self.size = size
        self.name = name

    def decode(self, frame: bytes | bytearray | memoryview) -> Frame:
        f = decode_frame(frame)
        if f.layout_id != self.layout_id:
            raise LayoutMismatchError(
                f"{self.name}: frame layout_id {f.layout_id:#010x}, expected "
                f"{self.layout_id:#010x} (the peer runs another mission config)"
            )
        if len(f.data) != self.size:
            raise FrameSizeError(
                f"{self.name}: frame carries {len(f.data)} data bytes, region is {self.size}"
            )
        return f


class RegionCodec:
    """Encoder and decoder bound to one region of one Data Vector, or to the
    whole vector (``region=None``: the telemetry frame).

    ``encode(seq, t_ns)`` frames the region's current bytes (one copy, into
    the encoder's buffer; ``tail``: bytes of room kept after the frame for
    a tag written in place, :class:`FrameEncoder`). Receiving is decode
    once, then copy once:
    :meth:`check` decodes and checks a frame without touching the vector and
    :meth:`write` copies a checked frame's data in; :meth:`apply` does both.
    """

    __slots__ = ("_dec", "_enc", "_view", "dv", "layout_id", "region", "size")

    def __init__(self, dv: DataVector, region: str | None = None, *, tail: int = 0) -> None:
        if region is None:
            layout_id, size, view, name = (
                dv.layout.layout_id,
                dv.layout.size,
                dv.view(),
                "telemetry",
            )
        else:
            spec = dv.layout.region(region)
            layout_id, size, view, name = spec.layout_id, spec.size, dv.region_view(region), region
        self.dv = dv
        self.region = region
        self.layout_id = layout_id
        self.size = size
        self._view = view
        self._enc = FrameEncoder(size, tail)
        self._dec = FrameDecoder(layout_id, size, name)

    @property
    def max_frame_len(self) -> int:
        """The longest valid frame of this region (:func:`max_frame_length`)."""
        return max_frame_length(self.size)

    def encode(self, seq: int, t_ns: int) -> bytearray:
        """Frame the region now (followed by the tail room, if any); the
        returned buffer is reused by the next call."""
        return self._enc.encode(self.layout_id, seq, t_ns, self._view)

    @property
    def frame_len(self) -> int:
        """Bytes :meth:`encode` returns: the region's frame and the tail room."""
        return self._enc.frame_len(self.size)

    def encode_into(self, out: memoryview, seq: int, t_ns: int) -> memoryview:
        """Frame the region now straight into ``out`` (exactly
        :attr:`frame_len` bytes, e.g. a loaned shared-memory sample: the tail
        room is left for the tag, written in place); the same bytes as
        :meth:`encode`, one copy of the region, no allocation. Returns ``out``;
        ValueError for another length, FrameFormatError as :meth:`encode`."""
        return self._enc.encode_into(out, self.layout_id, seq, t_ns, self._view)

    def check(self, frame: bytes | bytearray | memoryview) -> Frame:
        """Decode and check without applying (raises CodecError)."""
        return self._dec.decode(frame)

    def write(self, frame: Frame) -> None:
        """Copy the data of a frame returned by :meth:`check` into the region.

        The frame's data is a view into the received buffer, so call this
        before that buffer is reused."""
        self._view[:] = frame.data

    def apply(self, frame: bytes | bytearray | memoryview) -> Frame:
        """Decode, check, then copy the data into the region (raises CodecError;
        the region is untouched when it does)."""
        f = self._dec.decode(frame)
        self._view[:] = f.data
        return f


__all__ += ["CodecError"]


# -- the sync bundle (codecs/FORMAT.md §6.2) ---------------------------------

#: First bytes of a sync bundle: "ZB", version 1. A frame starts 0x94
#: (fixarray of 4), so the two never mix up.
BUNDLE_MAGIC = b"ZB\x01"
_BUNDLE_HDR = struct.Struct("<3sB")  # magic and version, frame count
_BUNDLE_LEN = struct.Struct("<I")
_BUNDLE_MAX = 255


def bundle_size(frame_sizes: list[int]) -> int:
    """Bytes of a bundle of frames of these sizes."""
    return _BUNDLE_HDR.size + sum(_BUNDLE_LEN.size + n for n in frame_sizes)


class BundleEncoder:
    """Packs every DN's query frame into one sync bundle, for one wildcard
    query per loop (:class:`zplatform.runtime.sync.ControlSync`).

    ``pack`` copies the frames into a buffer owned by the encoder (no
    allocation once it has the bundle's size) and returns it; the next call
    overwrites it. Raises ValueError for more than 255 frames.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def pack(self, frames: Sequence[bytes | bytearray | memoryview]) -> bytearray:
        n = len(frames)
        if n > _BUNDLE_MAX:
            raise ValueError(f"a sync bundle holds at most {_BUNDLE_MAX} frames, got {n}")
        size = _BUNDLE_HDR.size
        for f in frames:
            size += _BUNDLE_LEN.size + len(f)
        if len(self._buf) != size:
            self._buf = bytearray(size)
        buf = self._buf
        _BUNDLE_HDR.pack_into(buf, 0, BUNDLE_MAGIC, n)
        o = _BUNDLE_HDR.size
        for f in frames:
            m = len(f)
            _BUNDLE_LEN.pack_into(buf, o, m)
            o += _BUNDLE_LEN.size
            buf[o : o + m] = f
            o += m
        return buf


def is_bundle(payload: bytes | bytearray | memoryview) -> bool:
    """Whether ``payload`` starts like a sync bundle (cheap: two byte reads)."""
    return len(payload) >= _BUNDLE_HDR.size and payload[0] == 0x5A and payload[1] == 0x42


def bundle_entry(payload: bytes | bytearray | memoryview, i: int) -> memoryview:
    """Frame ``i`` of a sync bundle, as a zero-copy view into ``payload``.

    Checks the magic, the version, that the bundle holds frame ``i`` and
    that every length up to it stays inside the payload; frames after ``i``
    are not examined (they are other nodes'). Raises FrameFormatError (a
    CodecError) for anything else; never anything else.
    """
    mv = memoryview(payload)
    if len(mv) < _BUNDLE_HDR.size or not (mv[0] == 0x5A and mv[1] == 0x42 and mv[2] == 1):
        raise FrameFormatError("not a sync bundle (magic 'ZB', version 1)")
    count = mv[3]
    if not 0 <= i < count:
        raise FrameFormatError(f"the sync bundle holds {count} frames, none for node number {i}")
    o = _BUNDLE_HDR.size
    end = len(mv)
    for k in range(i + 1):
        if o + _BUNDLE_LEN.size > end:
            raise FrameFormatError(f"the sync bundle ends inside the length of frame {k}")
        (n,) = _BUNDLE_LEN.unpack_from(mv, o)
        o += _BUNDLE_LEN.size
        if n > end - o:
            raise FrameFormatError(
                f"frame {k} of the sync bundle says {n} bytes, {end - o} are left"
            )
        if k == i:
            return mv[o : o + n]
        o += n
    raise FrameFormatError("unreachable")  # pragma: no cover
