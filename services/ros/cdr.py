"""CDR (little-endian, with its 4-byte encapsulation header) both ways, with rosbags' type
store: a message → bytes, and bytes → a message, checked (size, header, exact length)."""

from __future__ import annotations

from services.kit.rejected import Rejected, RejectReason
from services.ros.types import CDR_LE, Message, typestore

__all__ = ["decode_cdr", "encode_cdr"]


def encode_cdr(msg: Message, ros_type: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, ros_type))


def decode_cdr(payload: bytes, ros_type: str, max_bytes: int) -> Message:
    """A CDR payload → the message (rosbags' dataclass). Refused before parsing when larger
    than ``max_bytes`` (``too_large``); ``bad_cdr`` when it is not a little-endian CDR
    encoding of ``ros_type`` (truncated, garbled, trailing bytes)."""
    if len(payload) > max_bytes:
        raise Rejected(RejectReason.TOO_LARGE,
                       f"{len(payload)}-byte sample exceeds {max_bytes} bytes")
    if len(payload) < 8 or payload[:4] != CDR_LE:
        raise Rejected(RejectReason.BAD_CDR,
                       f"not little-endian CDR (header {bytes(payload[:4]).hex()})")
    try:
        msg = typestore().deserialize_cdr(payload, ros_type)
    except Exception as err:  # rosbags raises struct.error, IndexError, ValueError, …
        raise Rejected(RejectReason.BAD_CDR, f"not a {ros_type} in CDR ({type(err).__name__}: "
                                             f"{str(err)[:120]})") from None
    # rosbags reads what the type needs; a sample longer than that (beyond CDR's 4-byte
    # padding) was not what its publisher meant
    try:
        again = len(typestore().serialize_cdr(msg, ros_type))
    except Exception as err:
        raise Rejected(RejectReason.BAD_CDR,
                       f"{ros_type} with unusable fields ({type(err).__name__})") \
            from None
    if not again <= len(payload) <= again + 3:
        raise Rejected(RejectReason.BAD_CDR,
                       f"{len(payload)}-byte sample holds a {again}-byte {ros_type}")
    return msg
