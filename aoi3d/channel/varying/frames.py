"""How a frame's size is counted on a trace channel: its PNG bytes or its JPEG bytes."""

from __future__ import annotations

import numpy as np

FRAME_ENCODINGS = ("png", "jpeg:Q")


def check_frame_encoding(encoding: str) -> int | None:
    """``png`` (the frame's PNG bytes, what the cameras send) or ``jpeg:Q`` (the frame
    encoded as JPEG at quality Q, 1–95): how a frame's size is counted on a trace channel.
    Returns Q (None for PNG); raises ``ValueError``."""
    if encoding == "png":
        return None
    kind, _, q = str(encoding).partition(":")
    if kind == "jpeg" and q.isdigit() and 1 <= int(q) <= 95:
        return int(q)
    raise ValueError(f"frame encoding must be one of {FRAME_ENCODINGS} (Q in 1..95), got "
                     f"{encoding!r}")


def jpeg_bytes(rgb: np.ndarray, quality: int) -> int:
    """Bytes of an (H, W, 3) uint8 image encoded as JPEG at ``quality``."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(rgb, dtype=np.uint8)).save(buf, format="JPEG", quality=quality)
    return buf.tell()
