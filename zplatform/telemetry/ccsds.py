"""CCSDS space-packet downlink of telemetry (an optional radio-link path).

The CN's telemetry is its whole Data Vector; over a radio link it travels as
CCSDS space packets (CCSDS 133.0-B-2), one per non-empty region per
downlinked snapshot (APID = ``apid_base`` + the region's index; a region too
long for one packet is segmented), as :mod:`zplatform.cli.xtce` describes them.

Contract: :class:`CcsdsEncoder` (the CN's side) downlinks every
``divisor``-th snapshot within a ``budget_bps`` token bucket refilled from the
snapshots' own CN time, so the same snapshots give the same packets; a
snapshot that does not fit is dropped whole and counted, never half of one.
:class:`CcsdsDecoder` checks length, CRC-16, APID and segment order before
anything touches its Data Vector (a refused packet raises
:class:`CcsdsError` and is counted by reason) and applies a snapshot only once
all its regions arrived (a CSV byte-identical to the telemetry's).
:func:`packet_plan` raises ConfigError for an APID past 0x7FE or a
``max_data`` too small. Sans-IO: no zenoh, no clock.

The packet byte by byte, segmentation and rate control: codecs/FORMAT.md (section 13).
"""

from __future__ import annotations

import binascii
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from spacepackets.ccsds.spacepacket import (
    SPACE_PACKET_HEADER_SIZE,
    PacketType,
    SequenceFlags,
    SpacePacketHeader,
)

from ..config import Mission
from ..core.datavector import DataVector, Layout
from ..errors import CodecError, ConfigError

__all__ = [
    "APID_BASE",
    "CRC_SIZE",
    "MAX_DATA",
    "SECONDARY_HEADER",
    "CcsdsDecoder",
    "CcsdsEncoder",
    "CcsdsError",
    "PacketPlan",
    "crc16",
    "decode_to_csv",
    "packet_plan",
    "split_stream",
]

APID_BASE = 0x100
MAX_APID = 0x7FE  # 0x7FF is the idle APID
MAX_DATA = 65536  # the packet data field can hold at most 2**16 bytes
SEQ_MODULO = 1 << 14
SECONDARY_HEADER = struct.Struct(">QqI")  # loop, t_ns, segment offset
CRC_SIZE = 2
_OVERHEAD = SECONDARY_HEADER.size + CRC_SIZE  # data-field bytes that are not region bytes
_CRC = struct.Struct(">H")


class CcsdsError(CodecError):
    """A space packet was refused (length, CRC, APID or segment order)."""


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (the ECSS/PUS packet error control).

    ``binascii.crc_hqx`` with init 0xFFFF is that CRC and reads any buffer
    without a copy; the tests check it against spacepackets' own CRC
    (``fastcrc.crc16.ibm_3740``), which needs ``bytes``.
    """
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True, slots=True)
class PacketPlan:
    """One packet of a snapshot: which region bytes it carries, under which APID."""

    region: str
    apid: int
    seq_flags: SequenceFlags
    offset: int  # from the start of the region
    length: int  # region bytes in this packet
    vector_offset: int  # from the start of the Data Vector

    @property
    def packet_size(self) -> int:
        return SPACE_PACKET_HEADER_SIZE + _OVERHEAD + self.length


def packet_plan(
    mission: Mission, *, apid_base: int = APID_BASE, max_data: int = MAX_DATA
) -> list[PacketPlan]:
    """The packets of one snapshot, in order (regions in buffer order).

    Raises ConfigError when an APID would pass 0x7FE or ``max_data`` cannot
    hold a single region byte.
    """
    if not _OVERHEAD < max_data <= MAX_DATA:
        raise ConfigError(
            f"CCSDS max_data must be {_OVERHEAD + 1}..{MAX_DATA} bytes, got {max_data}",
            "ccsds.max_data",
        )
    names = mission.region_names()
    if apid_base < 0 or apid_base + len(names) - 1 > MAX_APID:
        raise ConfigError(
            f"APIDs {apid_base:#x}+{len(names)} regions pass {MAX_APID:#x}", "ccsds.apid_base"
        )
    layout = Layout.for_node(mission, "cn")
    room = max_data - _OVERHEAD
    plan: list[PacketPlan] = []
    for i, name in enumerate(names):
        r = layout.region(name)
        if r.size == 0:
            continue
        apid = apid_base + i
        if r.size <= room:
            plan.append(PacketPlan(name, apid, SequenceFlags.UNSEGMENTED, 0, r.size, r.offset))
            continue
        starts = range(0, r.size, room)
        for k, off in enumerate(starts):
            flags = (
                SequenceFlags.FIRST_SEGMENT
                if k == 0
                else SequenceFlags.LAST_SEGMENT
                if k == len(starts) - 1
                else SequenceFlags.CONTINUATION_SEGMENT
            )
            n = min(room, r.size - off)
            plan.append(PacketPlan(name, apid, flags, off, n, r.offset + off))
    return plan


class CcsdsEncoder:
    """Packs telemetry snapshots into space packets; call once per telemetry loop.

    Every packet buffer is allocated at construction; :meth:`encode` fills
    them in place and returns the same list object each time (views into
    those buffers, valid until the next call), or an empty tuple when the
    snapshot is decimated or over budget. Per packet it allocates only
    spacepackets' 6-byte packed header and a few memoryview slices. Not
    thread-safe (the loop thread owns it).

    The runtime calls ``encode(dv, loop, t_ns)`` once per telemetry loop
    with the frame's loop number and time and hands each returned packet to
    the radio (or writes them to a file, as ``zplatform ccsds --record``).
    """

    def __init__(
        self,
        mission: Mission,
        *,
        divisor: int = 1,
        budget_bps: int | None = None,
        apid_base: int = APID_BASE,
        max_data: int = MAX_DATA,
    ) -> None:
        if divisor < 1:
            raise ConfigError(f"CCSDS divisor must be >= 1, got {divisor}", "ccsds.divisor")
        self.plan = packet_plan(mission, apid_base=apid_base, max_data=max_data)
        self.layout = Layout.for_node(mission, "cn")
        self.snapshot_bytes = sum(p.packet_size for p in self.plan)
        if budget_bps is not None and budget_bps < self.snapshot_bytes:
            raise ConfigError(
                f"CCSDS budget {budget_bps} B/s is below one snapshot "
                f"({self.snapshot_bytes} B): nothing could ever be sent",
                "ccsds.budget_bps",
            )
        self.divisor = divisor
        self.budget_bps = budget_bps
        self._bufs = [bytearray(p.packet_size) for p in self.plan]
        self._views = [memoryview(b) for b in self._bufs]
        self._headers = [
            SpacePacketHeader(
                PacketType.TM,
                p.apid,
                0,
                p.packet_size - SPACE_PACKET_HEADER_SIZE - 1,
                sec_header_flag=True,
                seq_flags=p.seq_flags,
            )
            for p in self.plan
        ]
        self._counts: dict[int, int] = {p.apid: 0 for p in self.plan}
        self._out = list(self._views)
        self._offered = 0
        self._tokens = float(budget_bps or 0)
        self._last_t: int | None = None
        self.sent_snapshots = 0
        self.sent_packets = 0
        self.sent_bytes = 0
        self.decimated = 0
        self.dropped_budget = 0

    def encode(self, dv: DataVector, loop: int, t_ns: int) -> list[memoryview] | tuple[()]:
        """Packets of ``dv``'s current snapshot, or ``()`` when not downlinked.

        ``loop`` and ``t_ns`` are the telemetry frame's loop number and CN
        time. Raises CcsdsError when ``dv`` is not of the CN layout.
        """
        if dv.layout.layout_id != self.layout.layout_id:
            raise CcsdsError(
                f"vector layout {dv.layout.layout_id:#010x} is not the CN's "
                f"{self.layout.layout_id:#010x}"
            )
        self._offered += 1
        if (self._offered - 1) % self.divisor:
            self.decimated += 1
            return ()
        if self.budget_bps is not None:
            if self._last_t is not None and t_ns > self._last_t:
                self._tokens = min(
                    float(self.budget_bps),
                    self._tokens + (t_ns - self._last_t) * 1e-9 * self.budget_bps,
                )
            self._last_t = t_ns
            if self._tokens < self.snapshot_bytes:
                self.dropped_budget += 1
                return ()
            self._tokens -= self.snapshot_bytes
        src = dv.view()
        for p, hdr, buf, view in zip(
            self.plan, self._headers, self._bufs, self._views, strict=True
        ):
            # The source sequence count runs per APID, one per packet (segments too).
            count = self._counts[p.apid]
            self._counts[p.apid] = (count + 1) % SEQ_MODULO
            hdr.seq_count = count
            buf[:SPACE_PACKET_HEADER_SIZE] = hdr.pack()
            SECONDARY_HEADER.pack_into(buf, SPACE_PACKET_HEADER_SIZE, loop, t_ns, p.offset)
            body = SPACE_PACKET_HEADER_SIZE + SECONDARY_HEADER.size
            view[body : body + p.length] = src[p.vector_offset : p.vector_offset + p.length]
            end = body + p.length
            _CRC.pack_into(buf, end, crc16(view[:end]))
        self.sent_snapshots += 1
        self.sent_packets += len(self.plan)
        self.sent_bytes += self.snapshot_bytes
        return self._out


@dataclass(slots=True)
class _Pending:
    loop: int
    t_ns: int
    got: set[tuple[int, int]] = field(default_factory=set)  # (apid, region offset)


class CcsdsDecoder:
    """Reassembles space packets into CN Data Vector snapshots.

    :meth:`feed` takes one packet and returns ``(loop, t_ns)`` when it
    completed a snapshot, which is then in :attr:`dv`; otherwise None. A
    refused packet raises CcsdsError (and is counted in :attr:`bad`);
    callers that must not stop on one bad packet use :meth:`feed_all`.
    The encoder's settings (``apid_base``, ``max_data``) must match.
    """

    def __init__(
        self, mission: Mission, *, apid_base: int = APID_BASE, max_data: int = MAX_DATA
    ) -> None:
        self.plan = packet_plan(mission, apid_base=apid_base, max_data=max_data)
        self.layout = Layout.for_node(mission, "cn")
        self.dv = DataVector(self.layout)
        self._stage = bytearray(self.layout.size)
        self._by_key = {(p.apid, p.offset): p for p in self.plan}
        self._need = len(self.plan)
        self._next_count: dict[int, int] = {}
        self._pending: _Pending | None = None
        self.snapshots = 0
        self.packets = 0
        self.bad: dict[str, int] = {}
        self.seq_gaps = 0
        self.incomplete = 0

    def _refuse(self, reason: str, msg: str) -> CcsdsError:
        self.bad[reason] = self.bad.get(reason, 0) + 1
        return CcsdsError(msg)

    def feed(self, packet: bytes | bytearray | memoryview) -> tuple[int, int] | None:
        """Check and apply one packet; see the class doc."""
        pkt = memoryview(packet)
        if len(pkt) < SPACE_PACKET_HEADER_SIZE + _OVERHEAD:
            raise self._refuse("short", f"packet of {len(pkt)} bytes is shorter than any of ours")
        hdr = SpacePacketHeader.unpack(bytes(pkt[:SPACE_PACKET_HEADER_SIZE]))
        if hdr.packet_len != len(pkt):
            raise self._refuse(
                "length", f"packet is {len(pkt)} bytes; its header says {hdr.packet_len}"
            )
        end = len(pkt) - CRC_SIZE
        (crc,) = _CRC.unpack_from(pkt, end)
        if crc16(pkt[:end]) != crc:
            raise self._refuse("crc", f"CRC mismatch on APID {hdr.apid:#x} #{hdr.seq_count}")
        if hdr.packet_type != PacketType.TM or not hdr.sec_header_flag:
            raise self._refuse("type", "not a telemetry packet with a secondary header")
        loop, t_ns, offset = SECONDARY_HEADER.unpack_from(pkt, SPACE_PACKET_HEADER_SIZE)
        p = self._by_key.get((hdr.apid, offset))
        if p is None:
            raise self._refuse(
                "apid", f"APID {hdr.apid:#x} offset {offset} is not a packet of this mission"
            )
        body = SPACE_PACKET_HEADER_SIZE + SECONDARY_HEADER.size
        if end - body != p.length or hdr.seq_flags != p.seq_flags:
            raise self._refuse(
                "layout", f"packet of region {p.region} has another layout (other mission?)"
            )
        expected = self._next_count.get(hdr.apid)
        if expected is not None and hdr.seq_count != expected:
            self.seq_gaps += (hdr.seq_count - expected) % SEQ_MODULO
        self._next_count[hdr.apid] = (hdr.seq_count + 1) % SEQ_MODULO
        self.packets += 1
        pend = self._pending
        if pend is None or pend.loop != loop:
            if pend is not None:
                self.incomplete += 1
            pend = self._pending = _Pending(loop, t_ns)
        self._stage[p.vector_offset : p.vector_offset + p.length] = pkt[body:end]
        pend.got.add((p.apid, p.offset))
        if len(pend.got) < self._need:
            return None
        self.dv.write_all(self._stage)
        self._pending = None
        self.snapshots += 1
        return loop, t_ns

    def feed_all(
        self, packets: Iterable[bytes | bytearray | memoryview]
    ) -> Iterator[tuple[int, int]]:
        """Feed every packet; yield ``(loop, t_ns)`` per completed snapshot.

        Refused packets are counted in :attr:`bad` and skipped.
        """
        for pkt in packets:
            try:
                done = self.feed(pkt)
            except CcsdsError:
                continue
            if done is not None:
                yield done


def split_stream(data: bytes | bytearray | memoryview) -> Iterator[memoryview]:
    """Cut a byte stream of concatenated space packets into packets.

    Uses each primary header's length field; raises CcsdsError on a
    truncated tail (a radio recording cut mid-packet).
    """
    mv = memoryview(data)
    pos = 0
    while pos < len(mv):
        if len(mv) - pos < SPACE_PACKET_HEADER_SIZE:
            raise CcsdsError(f"{len(mv) - pos} stray bytes at the end of the stream")
        (data_len,) = struct.unpack_from(">H", mv, pos + 4)
        n = SPACE_PACKET_HEADER_SIZE + data_len + 1
        if pos + n > len(mv):
            raise CcsdsError(f"truncated packet at byte {pos}: needs {n}, has {len(mv) - pos}")
        yield mv[pos : pos + n]
        pos += n


def decode_to_csv(
    mission: Mission,
    data: bytes | bytearray | memoryview,
    out: str | Path | TextIO,
    *,
    apid_base: int = APID_BASE,
    max_data: int = MAX_DATA,
) -> CcsdsDecoder:
    """Decode a recorded packet stream into the telemetry CSV (docs/architecture.md#files).

    One row per complete snapshot; its ``rx_time_ns`` is the snapshot's CN
    time carried in the packets (the link has no receive time of its own).
    Refused packets and incomplete snapshots are counted on the returned
    decoder (``bad``, ``incomplete``, ``seq_gaps``), never written.
    """
    from .logs import CsvLogger

    dec = CcsdsDecoder(mission, apid_base=apid_base, max_data=max_data)
    with CsvLogger(out, dec.layout) as log:
        for _, t_ns in dec.feed_all(split_stream(data)):
            log.write(t_ns, dec.dv)
    return dec
