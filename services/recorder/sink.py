"""The file a recording's segment is written to, made to survive a full disk (issue 44).

:class:`Sink` is what the MCAP writer writes to: every write whole (a short write is retried,
an error raised), unbuffered, so the file on disk is always the bytes handed over — and
:meth:`Sink.mark` notes the offset after the last whole bus message. Beside it, a hidden
**reserve** file holds disk space for the end of the segment (two chunks and the summary,
growing with the chunks written), so that other writers on the disk cannot take it.

Before each bus message the recording asks :meth:`Sink.room` whether the disk still has room
for the next chunk; when it has not, the recording stops *before* the disk is full: the
reserve is given back and the writer finishes the segment there — the chunk it was building,
the summary with every index, the footer — a whole MCAP. Should a write still fail (the disk
filled faster than a chunk), :meth:`Sink.cut` drops what follows the mark: the file is then a
run of whole records that a streaming reader (``aoi3d replay``, ``mcap recover``) reads to its
end.
"""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path
from typing import Any

__all__ = ["RESERVE_BASE_BYTES", "RESERVE_PER_CHUNK_BYTES", "Sink"]

RESERVE_BASE_BYTES = 64 << 10
"""Disk held for a segment's summary beyond two chunks: its schemas (about 23 kB) and more."""
RESERVE_PER_CHUNK_BYTES = 256
"""And per chunk written: its index in the summary (about 160 bytes)."""
_CHUNK_OPCODE = 0x06


class Sink:
    """An unbuffered file written whole, the offset of its last whole message, and its
    reserve of disk space (``OSError`` when even that cannot be had: the disk is full)."""

    def __init__(self, path: Path, chunk_bytes: int) -> None:
        self.path = Path(path)
        self.good = 0
        self.chunks = 0
        """Chunk records written."""
        self._chunk_bytes = int(chunk_bytes)
        self._reserve_path = self.path.with_name(f".{self.path.name}.reserve")
        self._reserved = 0
        self._raw = open(self.path, "wb", buffering=0)  # noqa: SIM115 - closed by close()
        try:
            self.reserve()
        except OSError:
            self.close()
            raise

    # the writer's side: write, tell, flush
    def write(self, data: Any) -> int:
        view = memoryview(data).cast("B")
        if len(view) and view[0] == _CHUNK_OPCODE:  # (the writer hands a record a write)
            self.chunks += 1
        done = 0
        while done < len(view):
            n = self._raw.write(view[done:])
            if not n:  # (a raw write that takes nothing: the disk is full)
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))
            done += n
        return done

    def tell(self) -> int:
        return self._raw.tell()

    def flush(self) -> None:
        """Nothing is buffered."""

    # the recording's side
    def mark(self) -> None:
        """The file ends with a whole message's records: the offset to cut back to."""
        self.good = self._raw.tell()

    def room(self, message_bytes: int) -> bool:
        """Whether the disk (beside the reserve) has room for the next chunk: one of
        ``chunk_bytes`` plus two messages of ``message_bytes`` and 16 KiB to spare."""
        try:
            st = os.statvfs(self.path.parent)
        except OSError:
            return True  # cannot tell: the writes will say
        need = self._chunk_bytes + 2 * int(message_bytes) + (16 << 10)
        return st.f_bavail * st.f_frsize >= need

    def reserve(self) -> None:
        """Hold two chunks, the summary and its index of the chunks written so far of disk
        space (grown in steps of 16 KiB; ``OSError`` when the disk cannot give it)."""
        want = (2 * self._chunk_bytes + RESERVE_BASE_BYTES
                + RESERVE_PER_CHUNK_BYTES * self.chunks)
        if want <= self._reserved:
            return
        want = -(-want // (16 << 10)) * (16 << 10)
        fd = os.open(self._reserve_path, os.O_WRONLY | os.O_CREAT, 0o600)
        try:
            try:
                os.posix_fallocate(fd, 0, want)
            except OSError as err:
                if err.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
                    raise
                os.lseek(fd, self._reserved, os.SEEK_SET)  # no fallocate here: zeros
                zeros = bytes(16 << 10)
                for _ in range((want - self._reserved) // len(zeros)):
                    os.write(fd, zeros)
                os.fsync(fd)
        finally:
            os.close(fd)
        self._reserved = want

    def release(self) -> None:
        """Give the reserved space back."""
        with contextlib.suppress(OSError):
            self._reserve_path.unlink()
        self._reserved = 0

    def cut(self) -> None:
        """Drop what follows the mark."""
        with contextlib.suppress(OSError, ValueError):
            os.ftruncate(self._raw.fileno(), self.good)
            self._raw.seek(self.good)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._raw.close()
        self.release()
