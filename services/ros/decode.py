"""Messages read (the ingest's side): a header's stamp, an image's RGB pixels (checked against
the limits before any is decoded), a pose's 4×4 and a CameraInfo's intrinsics. Each raises
:class:`Rejected` with a reason label on what cannot be used."""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from aoi3d.rigfile import quaternion_matrix
from services.kit.rejected import Rejected, RejectReason
from services.ros.types import IMAGE, POSE_STAMPED, Message

__all__ = ["ENCODINGS", "Intrinsics", "camera_info", "image_rgb", "pose_matrix", "stamp_s"]

#: Raw ``sensor_msgs/Image`` encodings accepted: bytes per pixel and how to make RGB of them.
ENCODINGS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8uc1": 1, "8uc3": 3,
             "mono16": 2, "16uc1": 2}


def stamp_s(header: Message) -> float:
    """A ``std_msgs/Header``'s stamp in seconds; ``stamp_invalid`` when nanosec ≥ 10⁹."""
    sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
    if not 0 <= nsec < 1_000_000_000:
        raise Rejected(RejectReason.STAMP_INVALID, f"nanosec {nsec} is not in [0, 1e9)")
    return sec + nsec * 1e-9


def _raw_rgb(msg: Message, max_pixels: int) -> np.ndarray:
    enc = str(msg.encoding).lower()
    bpp = ENCODINGS.get(enc)
    if bpp is None:
        raise Rejected(RejectReason.UNKNOWN_ENCODING,
                       f"raw image encoding {str(msg.encoding)[:40]!r} "
                       f"(accepted: {', '.join(ENCODINGS)})")
    w, h, step = int(msg.width), int(msg.height), int(msg.step)
    if w < 1 or h < 1:
        raise Rejected(RejectReason.IMAGE_MISMATCH, f"a {w}x{h} image")
    if w * h > max_pixels:
        raise Rejected(RejectReason.TOO_LARGE, f"a {w}x{h} image exceeds {max_pixels} pixels")
    if step < w * bpp:
        raise Rejected(RejectReason.IMAGE_MISMATCH,
                       f"step {step} < width {w} × {bpp} bytes ({enc})")
    data = msg.data
    if len(data) != step * h:
        raise Rejected(RejectReason.IMAGE_MISMATCH,
                       f"{len(data)} data bytes, but step {step} × height "
                       f"{h} = {step * h}")
    rows = np.asarray(data, dtype=np.uint8).reshape(h, step)[:, :w * bpp]
    if bpp == 2:
        order = ">u2" if msg.is_bigendian else "<u2"
        gray = rows.copy().view(order).reshape(h, w)
        return np.repeat((gray >> 8).astype(np.uint8)[:, :, None], 3, axis=2)
    px = rows.reshape(h, w, bpp)
    if bpp == 1:
        return np.repeat(px, 3, axis=2)
    if enc in ("bgr8", "bgra8"):
        return np.ascontiguousarray(px[:, :, 2::-1])
    return np.ascontiguousarray(px[:, :, :3])


def _compressed_rgb(msg: Message, max_pixels: int) -> np.ndarray:
    fmt = str(msg.format).lower()
    data = bytes(msg.data)
    if "jpeg" in fmt or "jpg" in fmt:
        kind, magic = "JPEG", b"\xff\xd8\xff"
    elif "png" in fmt:
        kind, magic = "PNG", b"\x89PNG\r\n\x1a\n"
    else:
        raise Rejected(RejectReason.UNKNOWN_ENCODING,
                       f"compressed format {str(msg.format)[:40]!r} (accepted: "
                       "jpeg, png)")
    if not data.startswith(magic):
        raise Rejected(RejectReason.BAD_IMAGE,
                       f"the data is not {kind} (format says {msg.format[:40]!r})")
    from PIL import Image as PILImage

    try:
        im = PILImage.open(io.BytesIO(data), formats=[kind])
        w, h = im.size  # the header only: nothing is decoded yet
    except PILImage.DecompressionBombError as err:  # declared over PIL's own limit
        raise Rejected(RejectReason.TOO_LARGE, f"a {kind} whose header says {err}"[:200]) from None
    except Exception as err:
        raise Rejected(RejectReason.BAD_IMAGE,
                       f"{kind} header unreadable ({type(err).__name__})") from None
    if w * h > max_pixels:
        raise Rejected(RejectReason.TOO_LARGE, f"a {w}x{h} {kind} exceeds {max_pixels} pixels")
    try:
        with im:
            return np.asarray(im.convert("RGB"))
    except Exception as err:  # truncated or corrupt data
        raise Rejected(RejectReason.BAD_IMAGE,
                       f"{kind} could not be decoded ({type(err).__name__})") \
            from None


def image_rgb(msg: Message, ros_type: str, max_pixels: int) -> np.ndarray:
    """An ``Image`` or ``CompressedImage`` → uint8 H×W×3 RGB (checked before decoding)."""
    if ros_type == IMAGE:
        return _raw_rgb(msg, max_pixels)
    return _compressed_rgb(msg, max_pixels)


def pose_matrix(msg: Message, ros_type: str) -> np.ndarray:
    """A ``PoseStamped`` or ``Odometry`` → 4×4 (``bad_pose`` when not finite or not a
    rotation)."""
    pose = msg.pose if ros_type == POSE_STAMPED else msg.pose.pose
    p, q = pose.position, pose.orientation
    values = [p.x, p.y, p.z, q.x, q.y, q.z, q.w]
    if not np.all(np.isfinite(values)):
        raise Rejected(RejectReason.BAD_POSE, "pose has NaN or infinity")
    try:
        return quaternion_matrix([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
    except ValueError as err:
        raise Rejected(RejectReason.BAD_POSE, str(err)) from None


@dataclass(frozen=True)
class Intrinsics:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


def camera_info(msg: Message) -> Intrinsics:
    """A ``CameraInfo``'s pinhole intrinsics (``bad_intrinsics`` when unusable)."""
    k = np.asarray(msg.k, dtype=np.float64)
    w, h = int(msg.width), int(msg.height)
    if k.shape != (9,) or not np.all(np.isfinite(k)) or k[0] <= 0 or k[4] <= 0 or w < 1 \
            or h < 1:
        raise Rejected(RejectReason.BAD_INTRINSICS, f"CameraInfo K {k.tolist()[:9]} size {w}x{h}")
    return Intrinsics(float(k[0]), float(k[4]), float(k[2]), float(k[5]), w, h)
