"""The recorder's core: bus messages in (key, payload, receipt time), an MCAP file out.

No bus, no threads, no server, no metrics library: the runtime
(:mod:`services.recorder.runtime`) feeds it from its writing thread. What goes where:

=================================  ===============================  ============================
bus key (``aoi3d/<run>/<site>/…``)  MCAP topic                       schema
=================================  ===============================  ============================
``edge/<n>/frame`` (a delivery)    ``/<site>/cam<n>/image``          ``foxglove.CompressedImage``
                                                                     (png) or ``foxglove.RawImage``
                                   ``/<site>/cam<n>/calibration``    ``foxglove.CameraCalibration``
                                   ``/tf``                           ``foxglove.FrameTransform``
                                   ``/<site>/delivery``              ``aoi3d.v1.Frame`` (no pixels)
``truth/frame`` (held-out view)    ``/<site>/truth/image``, ``…/calibration``, ``/tf``,
                                   ``/<site>/truth`` (as above)
``decision``                       ``/<site>/decision``              ``aoi3d.v1.Decision``
``render``                         ``/<site>/render`` (no pixels),   ``aoi3d.v1.Render``,
                                   ``/<site>/render/image``          ``foxglove.CompressedImage``
``quality``                        ``/<site>/quality``               ``aoi3d.v1.Quality``
``outcome``                        ``/<site>/outcome``               ``aoi3d.v1.Outcome``
=================================  ===============================  ============================

A frame's pixels are stored once, in the Foxglove image message (the exact PNG bytes of the
wire: lossless, so a replay trains on the same pixels); the project's own message beside it
keeps everything else (camera, sequence, generation, send and delivery times, pose,
intrinsics, the image's encoding and size) with its data left empty. The image's
``timestamp`` is the frame's generation time on the run's sim clock (the replay joins the two
by it); ``/tf`` carries the camera's pose at that time in the optical convention Foxglove and
ROS use (x right, y down, z forward: aoi3d's OpenGL camera turned half a turn about x).

Every MCAP record's ``log_time`` is the recorder's receipt (wall clock, Unix ns) and its
``publish_time`` the message's own sim time (generation, decision or render time, in ns of the
run's sim clock). A metadata record ``aoi3d`` holds the run's clock and the settings a replay
needs (:class:`Recording` ``metadata``).

Segments: with ``max_bytes`` a file that reaches the cap is finished (summary, footer) and the
recording goes on in ``<stem>.part2.mcap``, ``part3`` … beside it, each a whole MCAP with its
own schemas, channels and metadata (a segment passes the cap by at most one chunk and its
summary). An ``OSError`` while writing (a full disk: ``ENOSPC``) ends the recording — it
rotates on a cap, never on a full disk: the state becomes ``failed`` with the error, later
messages are counted ``not_recording``. The segment being written is finished whole (summary,
index, footer) in the disk space its :class:`~services.recorder.sink.Sink` held back for it;
where even that does not fit, it is cut at its last whole message, which a streaming reader
reads to the end (:mod:`services.recorder.sink`).
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from mcap.writer import CompressionType
from mcap_protobuf.writer import Writer

from services.kit.rejected import Rejected, RejectReason
from services.recorder.entries import (
    WORLD,
    entries,
    segment_path,
    segments,
    sim_ms_of,
    sim_ns,
)
from services.recorder.sink import Sink

__all__ = ["COMPRESSIONS", "WORLD", "Recording", "RecordingStatus", "Written", "entries",
           "segment_path", "segments", "sim_ms_of", "sim_ns"]

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}


# ---------------------------------------------------------------- the file
@dataclass
class RecordingStatus:
    """What a recording did so far (the REST API shows it)."""

    path: str
    state: str = "recording"
    """``recording``, ``stopped`` or ``failed`` (``error`` says why)."""
    error: str | None = None
    whole: bool | None = None
    """After a failure: whether the last segment was finished whole (summary and index) in
    the space held for it, or left cut at its last whole message; None otherwise."""
    segments: list[str] = field(default_factory=list)
    messages: int = 0
    """Bus messages recorded (each is one or more MCAP messages)."""
    mcap_messages: int = 0
    bytes_written: int = 0
    """Bytes of the finished segments plus those of the open one written so far."""
    max_bytes: int = 0


@dataclass(frozen=True)
class Written:
    mcap_messages: int


class Recording:
    """One recording into ``path`` (and its segments); see the module docstring.

    ``max_bytes``: the cap of one segment (0: none); ``chunk_bytes``: MCAP chunk size (made
    smaller under a small cap so a segment passes it by at most a chunk); ``metadata``: the
    ``aoi3d`` metadata record of every segment. Each segment is written through a
    :class:`services.recorder.sink.Sink`, which holds disk space for its summary: a full disk
    finishes the segment whole where it can (:attr:`RecordingStatus.whole`)."""

    def __init__(self, path: Path, *, max_bytes: int = 0, chunk_bytes: int = 1 << 20,
                 compression: str = "zstd", metadata: dict[str, str] | None = None) -> None:
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {', '.join(COMPRESSIONS)}, "
                             f"got {compression!r}")
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.path = Path(path)
        self.max_bytes = int(max_bytes)
        self.chunk_bytes = (min(chunk_bytes, max(16 << 10, self.max_bytes // 8))
                            if self.max_bytes else chunk_bytes)
        self.compression = COMPRESSIONS[compression]
        self.metadata = dict(metadata or {})
        self.status = RecordingStatus(path=str(self.path), max_bytes=self.max_bytes)
        self._index = 0
        self._file: Sink | None = None
        self._writer: Writer | None = None
        self._done_bytes = 0
        self._largest = 0
        try:
            self._open_next()
        except OSError as err:
            self._fail(err)

    @property
    def active(self) -> bool:
        return self.status.state == "recording"

    def _open_next(self) -> None:
        self._index += 1
        target = segment_path(self.path, self._index)
        target.parent.mkdir(parents=True, exist_ok=True)
        self.status.segments.append(str(target))
        self._file = sink = Sink(target, self.chunk_bytes)  # OSError: no room for its reserve
        writer = Writer(sink, chunk_size=self.chunk_bytes,  # type: ignore[arg-type]  # a file
                        compression=self.compression)  # (write, tell) the stubs do not know
        writer.add_metadata("aoi3d", {**self.metadata, "segment": str(self._index)})
        sink.mark()
        self._writer = writer  # (until here a failure leaves no segment: see _fail)

    def _finish(self) -> None:
        writer, f = self._writer, self._file
        if writer is not None:
            writer.finish()  # type: ignore[no-untyped-call]  # (mcap is unannotated)
        self._writer = self._file = None
        if f is not None:
            self._done_bytes += f.tell()
            f.close()

    def _fail(self, err: OSError) -> None:
        """A write failed: the segment is cut at its last whole message (or, when it could
        not even be opened, not kept)."""
        what = ("the disk is full" if err.errno in (errno.ENOSPC, errno.EDQUOT)
                else os.strerror(err.errno) if err.errno else str(err))
        target = self.status.segments[-1] if self.status.segments else str(self.path)
        f, writer, self._file, self._writer = self._file, self._writer, None, None
        if writer is None or f is None:  # no room to open the segment: it is not kept
            if f is not None:
                f.close()
            with contextlib.suppress(OSError):
                Path(target).unlink()
            if self.status.segments and self.status.segments[-1] == target:
                self.status.segments.pop()
            self._ended(True if self.status.segments else None,
                        f"{what}: no room to start {target} ({err})"
                        + ("; the segments before are whole" if self.status.segments else ""))
            return
        f.cut()
        f.close()
        self._ended(False, f"{what} writing {target} ({err}); the file is cut at its last "
                           "whole message (`mcap recover` rewrites it whole)")

    def _stop_full(self) -> None:
        """The disk has no room for another chunk: finish the segment whole (its chunk in
        progress, summary, index) in the space its sink held back, and stop."""
        f, writer, self._file, self._writer = self._file, self._writer, None, None
        assert f is not None and writer is not None
        target = str(f.path)
        f.release()
        try:
            writer.finish()  # type: ignore[no-untyped-call]  # (mcap is unannotated)
            whole = True
        except OSError:
            f.cut()
            whole = False
        f.close()
        self._ended(whole, f"the disk is full: no room for another chunk beside {target}; "
                           + ("it was finished whole (summary and index)" if whole else
                              "it is cut at its last whole message (`mcap recover` "
                              "rewrites it whole)"))

    def _ended(self, whole: bool | None, why: str) -> None:
        for target in self.status.segments[-1:]:
            with contextlib.suppress(OSError):
                self._done_bytes += Path(target).stat().st_size
        self.status.state = "failed"
        self.status.whole = whole
        self.status.error = f"recording stopped: {why}"
        self._update_bytes()

    def _update_bytes(self) -> None:
        open_bytes = 0
        if self._file is not None:
            with contextlib.suppress(OSError, ValueError):
                open_bytes = self._file.tell()
        self.status.bytes_written = self._done_bytes + open_bytes

    def write(self, key: str, payload: bytes, log_ns: int) -> Written:
        """Record one bus message received at ``log_ns`` (wall, Unix ns). :class:`Rejected`
        for a message the recorder does not take; nothing happens once the recording ended
        (the caller checks :attr:`active`)."""
        if not self.active:
            raise Rejected(RejectReason.NOT_RECORDING, f"the recording is {self.status.state}")
        items = entries(key, payload)
        assert self._writer is not None and self._file is not None
        self._largest = max(self._largest, len(payload))
        if not self._file.room(self._largest):  # stop while the segment can end whole
            self._stop_full()
            return Written(0)
        try:
            for topic, msg, t_ms in items:
                self._writer.write_message(topic, msg, log_time=log_ns,
                                           publish_time=sim_ns(t_ms) if math.isfinite(t_ms)
                                           else log_ns)
            self._file.mark()
        except OSError as err:
            self._fail(err)
            return Written(len(items))
        self.status.messages += 1
        self.status.mcap_messages += len(items)
        try:
            self._file.reserve()
        except OSError:  # no room to hold more for the summary: end while it still fits
            self._stop_full()
            return Written(len(items))
        try:
            self._update_bytes()
            if self.max_bytes and self._file.tell() >= self.max_bytes:
                self._finish()
                self._open_next()
        except OSError as err:
            self._fail(err)
        return Written(len(items))

    def close(self) -> RecordingStatus:
        """Finish the open segment (summary and footer); the status, ``stopped`` unless it
        had failed."""
        if self.active:
            try:
                self._finish()
                self.status.state = "stopped"
            except OSError as err:
                self._fail(err)
        self._update_bytes()
        return self.status
