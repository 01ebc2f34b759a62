"""The recorder's core: bus messages in (key, payload, receipt time), an MCAP file out.

No bus, no threads, no server, no metrics library: the runtime
(:mod:`services.recorder.worker`) feeds it from its writing thread. What goes where:

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
summary). An ``OSError`` while writing (a full disk: ``ENOSPC``) ends the recording: the state
becomes ``failed`` with the error, later messages are counted ``not_recording``; what reached
the disk before (whole chunks) stays readable with a streaming reader.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.writer import CompressionType
from mcap_protobuf.writer import Writer

from services.kit.codec import PNG, FrameData, decode_decision, decode_frame, decode_quality
from services.kit.codec import decode_render as _decode_render
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected, RejectReason

__all__ = ["COMPRESSIONS", "Recording", "RecordingStatus", "Written", "entries",
           "segment_path", "segments", "sim_ms_of", "sim_ns"]

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}
WORLD = "world"
"""The parent frame of every camera's transform."""
_KEY = re.compile(r"^aoi3d/[^/]+/(?P<site>[^/]+)/(?:(?P<edge>edge/(?P<cam>\d+)/frame)|"
                  r"(?P<what>truth/frame|decision|render|quality|outcome))$")
_GL_TO_OPTICAL = np.diag([1.0, -1.0, -1.0])


def sim_ns(ms: float) -> int:
    """Sim milliseconds as whole nanoseconds (an MCAP time or a Foxglove timestamp)."""
    return max(0, round(ms * 1e6))


def sim_ms_of(ts: Timestamp) -> float:
    ms: float = (ts.seconds * 1_000_000_000 + ts.nanos) / 1e6  # (protobuf: untyped)
    return ms


def _stamp(ms: float) -> Timestamp:
    ts = Timestamp()
    ts.FromNanoseconds(sim_ns(ms))
    return ts


def segment_path(path: Path, index: int) -> Path:
    """The ``index``-th segment (1: ``path`` itself; then ``<stem>.part<index><suffix>``)."""
    path = Path(path)
    return path if index == 1 else path.with_name(f"{path.stem}.part{index}{path.suffix}")


def segments(path: Path) -> list[Path]:
    """``path`` and the segments after it that exist, in order."""
    out, i = [], 1
    while segment_path(path, i).is_file():
        out.append(segment_path(path, i))
        i += 1
    return out


# ---------------------------------------------------------------- bus message → MCAP entries
def _camera_entries(site: str, name: str, frame: FrameData, image: pb.Image
                    ) -> list[tuple[str, Any]]:
    frame_id = f"{site}/{name}"
    stamp = _stamp(frame.generation_ms)
    cam = frame.camera
    if image.encoding == PNG:
        img: Any = CompressedImage(timestamp=stamp, frame_id=frame_id, data=image.data,
                                   format="png")
    else:
        img = RawImage(timestamp=stamp, frame_id=frame_id, width=image.width,
                       height=image.height, encoding="rgb8", step=image.width * 3,
                       data=image.data)
    calib = CameraCalibration(
        timestamp=stamp, frame_id=frame_id, width=cam.width, height=cam.height,
        distortion_model="plumb_bob", D=[0.0] * 5,
        K=[cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    c2w = np.asarray(cam.c2w, dtype=np.float64)
    from scipy.spatial.transform import Rotation

    qx, qy, qz, qw = Rotation.from_matrix(c2w[:3, :3] @ _GL_TO_OPTICAL).as_quat()
    tf = FrameTransform(timestamp=stamp, parent_frame_id=WORLD, child_frame_id=frame_id)
    tf.translation.x, tf.translation.y, tf.translation.z = (float(v) for v in c2w[:3, 3])
    tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = (float(qx), float(qy),
                                                                  float(qz), float(qw))
    topic = f"/{site}/{name}"
    return [(f"{topic}/image", img), (f"{topic}/calibration", calib), ("/tf", tf)]


def _without_pixels(msg: Any) -> Any:
    out = type(msg)()
    out.CopyFrom(msg)
    out.image.data = b""
    return out


def entries(key: str, payload: bytes) -> list[tuple[str, Any, float]]:
    """The MCAP entries of one bus message: ``(topic, protobuf message, sim time ms)``;
    :class:`Rejected` for a key the recorder does not record or a message its decoder
    refuses (the decoders every service uses)."""
    m = _KEY.match(key)
    if m is None:
        raise Rejected(RejectReason.UNKNOWN_KEY, f"not a recorded key: {key[:200]}")
    site = m["site"]
    if m["edge"]:
        frame = decode_frame(payload)
        if frame.camera_id != int(m["cam"]):
            raise Rejected(RejectReason.UNKNOWN_CAMERA, f"camera {frame.camera_id} on camera "
                                                        f"{m['cam']}'s key")
        msg = pb.Frame.FromString(payload)
        t = frame.generation_ms
        return [(topic, x, t) for topic, x in
                _camera_entries(site, f"cam{frame.camera_id}", frame, msg.image)] + [
            (f"/{site}/delivery", _without_pixels(msg), t)]
    what = m["what"]
    if what == "truth/frame":
        frame = decode_frame(payload)
        msg = pb.Frame.FromString(payload)
        t = frame.generation_ms
        return [(topic, x, t) for topic, x in
                _camera_entries(site, "truth", frame, msg.image)] + [
            (f"/{site}/truth", _without_pixels(msg), t)]
    if what == "decision":
        d = decode_decision(payload)
        return [(f"/{site}/decision", d, d.time_ms)]
    if what == "render":
        r, _camera = _decode_render(payload)
        img = CompressedImage(timestamp=_stamp(r.time_ms), frame_id=f"{site}/truth",
                              data=r.image.data, format="png")
        out = [(f"/{site}/render", _without_pixels(r), r.time_ms)]
        if r.image.encoding == PNG:
            out.append((f"/{site}/render/image", img, r.time_ms))
        return out
    if what == "quality":
        q = decode_quality(payload)
        return [(f"/{site}/quality", q, q.time_ms)]
    try:
        o = pb.Outcome.FromString(payload)
    except Exception as err:
        raise Rejected(RejectReason.MALFORMED, f"not a valid Outcome message ({err})") from None
    return [(f"/{site}/outcome", o, math.nan)]


# ---------------------------------------------------------------- the file
@dataclass
class RecordingStatus:
    """What a recording did so far (the REST API shows it)."""

    path: str
    state: str = "recording"
    """``recording``, ``stopped`` or ``failed`` (``error`` says why)."""
    error: str | None = None
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
    ``aoi3d`` metadata record of every segment."""

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
        self._file: BinaryIO | None = None
        self._writer: Writer | None = None
        self._done_bytes = 0
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
        self._file = open(target, "wb")  # noqa: SIM115 - closed by _finish or _fail
        self.status.segments.append(str(target))
        self._writer = Writer(self._file, chunk_size=self.chunk_bytes,
                              compression=self.compression)
        self._writer.add_metadata("aoi3d", {**self.metadata, "segment": str(self._index)})

    def _finish(self) -> None:
        writer, f = self._writer, self._file
        self._writer = self._file = None
        if writer is not None:
            writer.finish()  # type: ignore[no-untyped-call]  # mcap_protobuf: unannotated
        if f is not None:
            self._done_bytes += f.tell()
            f.close()

    def _fail(self, err: OSError) -> None:
        what = ("the disk is full" if err.errno in (errno.ENOSPC, errno.EDQUOT)
                else os.strerror(err.errno) if err.errno else str(err))
        target = self.status.segments[-1] if self.status.segments else str(self.path)
        self.status.state = "failed"
        self.status.error = f"recording stopped: {what} writing {target} ({err})"
        f, self._file, self._writer = self._file, None, None
        if f is not None:
            with contextlib.suppress(OSError, ValueError):
                self._done_bytes += f.tell()
            with contextlib.suppress(OSError, ValueError):
                f.close()
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
        writer, f = self._writer, self._file
        assert writer is not None and f is not None, "active: a segment is open"
        try:
            for topic, msg, t_ms in items:
                writer.write_message(topic, msg, log_time=log_ns,
                                     publish_time=sim_ns(t_ms) if math.isfinite(t_ms)
                                     else log_ns)
            self.status.messages += 1
            self.status.mcap_messages += len(items)
            self._update_bytes()
            if self.max_bytes and f.tell() >= self.max_bytes:
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
