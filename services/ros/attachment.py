"""rmw_zenoh's per-sample attachment: sequence number, source time and publisher id — built
(the current layout) and read (the current and the earlier, named one)."""

from __future__ import annotations

import struct
from dataclasses import dataclass

from services.kit.rejected import Rejected, RejectReason

__all__ = ["Attachment", "build_attachment", "parse_attachment"]


@dataclass(frozen=True)
class Attachment:
    """rmw_zenoh's per-sample attachment."""

    sequence: int
    source_ns: int
    gid: bytes


def build_attachment(sequence: int, source_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment of rmw_zenoh (Jazzy): int64 seq, int64 ns, len, 16-byte id."""
    if len(gid) > 127:
        raise ValueError("publisher id of at most 127 bytes")
    return struct.pack("<qqB", sequence, source_ns, len(gid)) + bytes(gid)


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if pos >= len(buf) or shift > 28:
            raise ValueError("bad length")
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos
        shift += 7


def parse_attachment(raw: bytes | None) -> Attachment:
    """The attachment of an rmw_zenoh sample: the current layout (int64, int64, length byte,
    id) or the earlier one with a name before each field (``sequence_number``, …).
    :class:`Rejected` (``bad_attachment``) otherwise."""
    if raw is None:
        raise Rejected(RejectReason.BAD_ATTACHMENT, "an rmw_zenoh sample without its attachment")
    raw = bytes(raw)
    try:
        if raw.startswith(b"\x0fsequence_number"):  # rmw_zenoh before 0.2: named fields
            pos = 16
            seq = struct.unpack_from("<q", raw, pos)[0]
            pos += 8
            n, pos = _varint(raw, pos)
            if raw[pos:pos + n] != b"source_timestamp":
                raise ValueError("no source_timestamp")
            ts = struct.unpack_from("<q", raw, pos + n)[0]
            pos += n + 8
            n, pos = _varint(raw, pos)
            if raw[pos:pos + n] != b"source_gid":
                raise ValueError("no source_gid")
            pos += n
        else:
            seq, ts = struct.unpack_from("<qq", raw, 0)
            pos = 16
        n, pos = _varint(raw, pos)
        gid = raw[pos:pos + n]
        if len(gid) != n or pos + n != len(raw) or not 1 <= n <= 64:
            raise ValueError(f"publisher id of {n} bytes in {len(raw)}")
    except (struct.error, ValueError) as err:
        raise Rejected(RejectReason.BAD_ATTACHMENT,
                       f"{len(raw)}-byte attachment is not rmw_zenoh's "
                       f"({err})") from None
    return Attachment(int(seq), int(ts), bytes(gid))
