"""The flight recorder's formats: the record on disk, a directory's files,
and the gap-fill request and reply on ``{vehicle}/cn/recorder``.

A recorder directory (one node's) holds a ring of **segment files**
``seg-00000001.zfr``, ``seg-00000002.zfr``, ... numbered on across runs;
the highest number is the newest. A segment is a sequence of
self-delimiting, checksummed **records**, all integers little-endian::

    offset  size  field
         0     4  sync: b"\\x89ZFR"
         4     4  crc: CRC-32 (zlib) of bytes 8..end of the record
         8     4  length: bytes of payload after the 24-byte header
        12     1  type (below)
        13     1  flags (0)
        14     2  reserved (0)
        16     8  loop: u64, the loop the record belongs to
        24     -  payload (length bytes)

The checksum covers the length and the type, so a torn or damaged record
is detected, never misread: a reader skips it (to the next sync word whose
record checks) and says so. Types:

* ``HEAD`` (1): the first record of every segment: JSON (UTF-8, at most
  :data:`MAX_HEAD_LEN` bytes) naming the format, mission, vehicle, node,
  run, what the frames are (``kind``: ``telemetry`` for the CN, the region
  ``dnX_to_cn`` for a device node) with their ``layout_id`` and
  authentication ``channel`` (null when the mission does not authenticate),
  the loop period, the telemetry divisor, the segment number and the wall
  time it was started (``created_unix_ns``);
* ``FRAME`` (2): one frame exactly as the node sent it (a telemetry frame
  with its tag, or a device node's reply frame); ``loop`` is its sequence
  number;
* ``EVENT`` (3): one event record in its wire form
  (:func:`zplatform.events.encode_event`); ``loop`` is the node's loop when
  it was published;
* ``DROPPED`` (4): loops the recorder could not keep: ``u64 first, u64 last,
  u64 count`` (written before the next loop it keeps, or at the end);
* ``END`` (5): the run ended cleanly (``u64 loops kept, u64 loops dropped,
  u64 events kept``); a run without one ended by a kill or a power loss.

Gap fill: the ground asks the CN's recorder (a queryable on
``{vehicle}/cn/recorder``) with a request payload::

    b"ZRQ1"  u64 run (cn_epoch)  u64 first loop  u64 last loop  i64 t_ns (asker's clock)

followed by the telemetry channel's tag (:mod:`zplatform.auth`) when the
mission authenticates: whoever may read the recorded frames (they carry
that channel's tag) may ask. ``last - first`` is at most
:data:`MAX_REQUEST_LOOPS`. Each reply's payload starts with a kind byte:
``1`` (frames) then ``u32 length, frame`` repeated (at most
:data:`REPLY_BYTES` per reply, or one longer frame alone); ``2`` (end) then
``u64 frames sent, u64 telemetry loops of the range the recorder does not
hold, u64 loops of the range that never ran`` (periods the CN's scheduler
skipped: there is no telemetry of them anywhere).
"""

from __future__ import annotations

import re
import struct
import zlib

__all__ = [
    "DROPPED",
    "END",
    "EVENT",
    "FORMAT_VERSION",
    "FRAME",
    "HEAD",
    "HEADER",
    "HEADER_LEN",
    "MAX_HEAD_LEN",
    "MAX_REQUEST_LOOPS",
    "REPLY_BYTES",
    "REPLY_END",
    "REPLY_FRAMES",
    "REQUEST",
    "REQUEST_MAGIC",
    "SEGMENT_RE",
    "SYNC",
    "TYPE_NAMES",
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

FORMAT_VERSION = 1
MAX_HEAD_LEN = 64 * 1024
SEGMENT_RE = re.compile(r"seg-([0-9]{8})\.zfr")

REQUEST_MAGIC = b"ZRQ1"
REQUEST = struct.Struct("<4sQQQq")  # magic, run, first loop, last loop, t_ns
MAX_REQUEST_LOOPS = 6000
"""Most loops one gap-fill request may ask for (a longer gap takes several)."""
REPLY_FRAMES, REPLY_END = 1, 2
REPLY_BYTES = 32 * 1024
"""Most bytes of frames in one reply (a longer frame goes alone): well under
what zenoh's lowlatency transport carries unfragmented."""
REPLY_LEN = struct.Struct("<I")
REPLY_TOTALS = struct.Struct("<QQQ")  # frames sent, loops not held, loops never run


def segment_name(index: int) -> str:
    """``seg-00000042.zfr``: segment file names sort in age order."""
    return f"seg-{index:08d}.zfr"


def record_crc(buf: bytes | bytearray | memoryview, start: int, end: int) -> int:
    """The CRC-32 of the record at ``buf[start:end]`` (header fields after the
    crc, then the payload)."""
    return zlib.crc32(memoryview(buf)[start + 8 : end])
