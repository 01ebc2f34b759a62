"""What the recorder writes for one bus message (:func:`entries`): the MCAP topics, the
protobuf messages and their sim times (the table in :mod:`services.recorder.core`), and the
times and segment names every reader of a recording shares."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.timestamp_pb2 import Timestamp

from services.kit.codec import PNG, FrameData, decode_decision, decode_frame, decode_quality
from services.kit.codec import decode_render as _decode_render
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected, RejectReason

__all__ = ["WORLD", "entries", "segment_path", "segments", "sim_ms_of", "sim_ns"]

WORLD = "world"
"""The parent frame of every camera's transform."""
_KEY = re.compile(r"^aoi3d/[^/]+/(?P<site>[^/]+)/(?:(?P<edge>edge/(?P<cam>\d+)/frame)|"
                  r"(?P<what>truth/frame|decision|render|quality|outcome))$")
_GL_TO_OPTICAL = np.diag([1.0, -1.0, -1.0])


def sim_ns(ms: float) -> int:
    """Sim milliseconds as whole nanoseconds (an MCAP time or a Foxglove timestamp)."""
    return max(0, round(ms * 1e6))


def sim_ms_of(ts: Timestamp) -> float:
    return (ts.seconds * 1_000_000_000 + ts.nanos) / 1e6


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
