"""The recording container's layout: one file, a header, fixed-size frame records, an index.

See docs/recording-format.md for the prose. All integers little-endian.

    file header   "SVEREC\\r\\n" (8) | u32 version | u32 json length | u32 crc32(json) | json | zero pad
                  to a multiple of 4096 (HEADER_ALIGN)
    frame record  RECORD_HEADER (64 bytes) | payload (width*height*itemsize bytes, raw little-endian
                  samples in row order) | zero pad to a multiple of 64
                  RECORD_HEADER: "SVFR" | u32 crc32(bytes 8..63) | i64 index | i64 frame_id | i64 host_ns
                  | i64 device_ns | u32 payload length | u32 crc32(payload) | f64 exposure time | 8 zero bytes
    index         "SVIX" | u32 count | u32 crc32(table) | u32 0 | table int64 (count, 3):
                  frame_id, host_time_ns, device_time_ns (NO_TIME when absent)
    footer        "SVEREND\\0" | u64 index offset | u32 crc32(the 16 bytes before) | u32 0   (24 bytes)

Every record has the same size (the header fixes width, height and sample size),
so frame i starts at ``data_offset + i * record_size``: seeking is constant time
with or without the index, and the index (written on a clean close) only spares
a scan of the record headers. A recording killed mid-way has no index; the
reader rebuilds it by scanning and drops a torn last record.

The exposure time (the camera's global exposure in its own unit, GigE microseconds) sits in
bytes that were reserved and zero before it existed: 0.0 means "not recorded", so older
recordings read as frames without one, and older readers skip the field (it is inside the
record header's checksum, which they verify as before).
"""

from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from svelive.core.errors import SveliveError

MAGIC = b"SVEREC\r\n"
VERSION = 1
HEADER_ALIGN = 4096
RECORD_ALIGN = 64
FILE_HEADER = struct.Struct("<8sIII")
#: magic, crc32 of bytes 8..63, index, frame_id, host_ns, device_ns, payload length, payload crc32,
#: exposure time (f64; NO_EXPOSURE: not recorded), reserved
RECORD_HEADER = struct.Struct("<4sIqqqqIId8x")
#: the exposure time field of a frame recorded without one (the reserved bytes of older recordings)
NO_EXPOSURE = 0.0
RECORD_MAGIC = b"SVFR"
INDEX_HEADER = struct.Struct("<4sIII")
INDEX_MAGIC = b"SVIX"
FOOTER = struct.Struct("<8sQII")
FOOTER_MAGIC = b"SVEREND\0"
NO_TIME = -(2**63)
assert RECORD_HEADER.size == 64 and FOOTER.size == 24


class RecordingError(SveliveError):
    """A recording that cannot be read or written; the message says why."""


def crc32(data: bytes | memoryview | np.ndarray) -> int:
    """zlib CRC-32 of a bytes-like object (numpy arrays without a copy)."""
    return zlib.crc32(memoryview(data).cast("B") if isinstance(data, np.ndarray) else data) & 0xFFFFFFFF


@dataclass(frozen=True)
class Layout:
    """The fixed geometry of a recording, from its header."""

    width: int
    height: int
    dtype: str  # "uint8" or "uint16"
    data_offset: int

    @property
    def itemsize(self) -> int:
        return np.dtype(self.dtype).itemsize

    @property
    def payload_size(self) -> int:
        return self.width * self.height * self.itemsize

    @property
    def record_size(self) -> int:
        n = RECORD_HEADER.size + self.payload_size
        return -(-n // RECORD_ALIGN) * RECORD_ALIGN


def encode_header(meta: dict[str, Any]) -> bytes:
    """The file header bytes for the JSON metadata ``meta``, padded to HEADER_ALIGN."""
    body = json.dumps(meta, sort_keys=True).encode()
    head = FILE_HEADER.pack(MAGIC, VERSION, len(body), crc32(body)) + body
    return head + b"\0" * (-len(head) % HEADER_ALIGN)


def decode_header(head: bytes, name: str) -> tuple[dict[str, Any], Layout]:
    """Parse the first bytes of a file (at least the whole header) into metadata and layout."""
    if len(head) < FILE_HEADER.size:
        raise RecordingError(f"{name}: too short to be a recording ({len(head)} bytes)")
    magic, version, length, crc = FILE_HEADER.unpack_from(head)
    if magic != MAGIC:
        raise RecordingError(f"{name}: not an svelive recording (wrong magic {magic[:8]!r})")
    if version != VERSION:
        raise RecordingError(f"{name}: recording format version {version} is not supported (this reads {VERSION})")
    body = head[FILE_HEADER.size: FILE_HEADER.size + length]
    if len(body) != length:
        raise RecordingError(f"{name}: header is truncated")
    if crc32(body) != crc:
        raise RecordingError(f"{name}: header checksum mismatch (corrupt header)")
    try:
        meta = json.loads(body)
        width, height, dtype = int(meta["width"]), int(meta["height"]), str(meta["dtype"])
    except (ValueError, KeyError, TypeError) as exc:
        raise RecordingError(f"{name}: header metadata is unreadable ({exc})") from None
    if dtype not in ("uint8", "uint16") or width <= 0 or height <= 0:
        raise RecordingError(f"{name}: header describes an unsupported frame {width}x{height} {dtype}")
    offset = FILE_HEADER.size + length
    offset += -offset % HEADER_ALIGN
    return meta, Layout(width, height, dtype, offset)
