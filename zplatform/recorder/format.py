"""The flight recorder's formats: the record on disk, a directory's files,
and the gap-fill request and reply on ``{vehicle}/cn/recorder``.

Holds the constants and structs every reader and writer shares: the 24-byte
record header (:data:`HEADER`: sync word, CRC-32, length, type, flags, loop),
the record types (``HEAD``, ``FRAME``, ``EVENT``, ``DROPPED``, ``END``; ``WRAP``
marks the unused rest of the RAM ring and is never written to a file), the
segment names (:func:`segment_name`, :data:`SEGMENT_RE`), the gap-fill
request (:data:`REQUEST`, at most :data:`MAX_REQUEST_LOOPS` loops; for frames,
or for the events filed under them) and reply kinds (frames or events, at
most :data:`REPLY_BYTES` per reply; end, with totals).

Contract: pure definitions and :func:`record_crc`; nothing here does I/O,
blocks or raises. The checksum covers the length and the type, so a reader
detects a torn or damaged record and skips it rather than misreading it.

The records byte by byte and the gap-fill exchange: codecs/FORMAT.md
(section 12); the recorder's design: docs/architecture.md#flight-recorder.
"""

from __future__ import annotations

import re
import struct
import zlib

__all__ = [
    "DROPPED",
    "END",
    "EVENT",
    "EVENTS_MAGIC",
    "FORMAT_VERSION",
    "FRAME",
    "HEAD",
    "HEADER",
    "HEADER_LEN",
    "MAX_HEAD_LEN",
    "MAX_REQUEST_LOOPS",
    "REPLY_BYTES",
    "REPLY_DONE",
    "REPLY_END",
    "REPLY_EVENTS",
    "REPLY_FRAMES",
    "REQUEST",
    "REQUEST_MAGIC",
    "SEGMENT_RE",
    "SYNC",
    "TYPE_NAMES",
    "UNTAGGED_FORMATS",
    "WRAP",
    "record_crc",
    "segment_name",
]

SYNC = b"\x89ZFR"
HEADER = struct.Struct("<4sIIBBHQ")  # sync, crc, length, type, flags, reserved, loop
HEADER_LEN = HEADER.size
assert HEADER_LEN == 24

#: Not a record: the writer's marker for "the rest of the RAM ring is unused";
#: never written to a file.
WRAP = 0
HEAD, FRAME, EVENT, DROPPED, END = 1, 2, 3, 4, 5
TYPE_NAMES = {HEAD: "HEAD", FRAME: "FRAME", EVENT: "EVENT", DROPPED: "DROPPED", END: "END"}
COUNTS = struct.Struct("<QQQ")  # DROPPED: first, last, count; END: loops, dropped, events

FORMAT_VERSION = 2
"""The ``format`` a segment's HEAD names. 2: its frames carry the tag with a
header tag (codecs/FORMAT.md §6.1, 32 bytes); 1: an earlier zplatform's
24-byte tag, read only when the segment holds untagged frames (``channel``
null: an archive's, or a mission without authentication)."""
UNTAGGED_FORMATS = (1,)
"""Earlier formats still read when their frames carry no tag."""
MAX_HEAD_LEN = 64 * 1024
SEGMENT_RE = re.compile(r"seg-([0-9]{8})\.zfr")

REQUEST_MAGIC = b"ZRQ1"
EVENTS_MAGIC = b"ZRE1"
"""A request for the ``EVENT`` records filed under a range of loops (the
ground fills its event gaps so), where :data:`REQUEST_MAGIC` asks for frames."""
REQUEST = struct.Struct("<4sQQQq")  # magic, run, first loop, last loop, t_ns
MAX_REQUEST_LOOPS = 6000
"""Most loops one gap-fill request may ask for (a longer gap takes several)."""
REPLY_FRAMES, REPLY_END, REPLY_EVENTS = 1, 2, 3
REPLY_BYTES = 32 * 1024
"""Most bytes of frames in one reply (a longer frame goes alone): well under
what zenoh's lowlatency transport carries unfragmented."""
REPLY_LEN = struct.Struct("<I")
REPLY_TOTALS = struct.Struct("<QQQ")  # frames sent, loops not held, loops never run
# (an events request's END: events sent, loops not held, 0)
REPLY_DONE = struct.Struct("<BQQQq")
"""The ``END`` reply: its kind byte, :data:`REPLY_TOTALS`, then the stamp of
the request it answers; tagged (the telemetry channel, under the request's
run) when the mission authenticates, so a ground screens it as it does the
frames (codecs/FORMAT.md §12)."""


def segment_name(index: int) -> str:
    """``seg-00000042.zfr``: segment file names sort in age order."""
    return f"seg-{index:08d}.zfr"


def record_crc(buf: bytes | bytearray | memoryview, start: int, end: int) -> int:
    """The CRC-32 of the record at ``buf[start:end]`` (header fields after the
    crc, then the payload)."""
    return zlib.crc32(memoryview(buf)[start + 8 : end])
