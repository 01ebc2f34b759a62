"""Translation between protobuf messages (the wire) and domain values, with validation.

Every ``decode_*`` raises :class:`Rejected` with a short reason label on bad input, so a
worker can drop and count the message (``Rejections``) instead of crashing.
"""

from __future__ import annotations

import io
import math
import struct
from dataclasses import dataclass

import numpy as np
from google.protobuf.message import DecodeError

from aoi3d.scene import to_uint8
from aoi3d.scene.camera import Camera
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected, RejectReason

PNG = pb.IMAGE_ENCODING_PNG
RAW = pb.IMAGE_ENCODING_RAW_RGB8
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Largest bus message any decoder parses (bytes): an 800×800 raw RGB frame is 1.9 MB.
MAX_MESSAGE_BYTES = 8 * 1024 * 1024
#: Largest image (width × height) any decoder accepts: 4 Mpx, 12 MB once decoded.
MAX_IMAGE_PIXELS = 2048 * 2048
#: Largest encoded image a frame may carry beyond its raw size (PNG's worst case is a little
#: over raw; this leaves room for headers and incompressible data).
_IMAGE_SLACK_BYTES = 64 * 1024


# ---------------------------------------------------------------- parsing
def _parse(cls, payload: bytes):
    if len(payload) > MAX_MESSAGE_BYTES:
        raise Rejected(RejectReason.TOO_LARGE,
                       f"{cls.__name__} message of {len(payload)} bytes exceeds "
                       f"{MAX_MESSAGE_BYTES} bytes")
    msg = cls()
    try:
        msg.ParseFromString(payload)
    except (DecodeError, ValueError, RuntimeError) as err:
        raise Rejected(RejectReason.MALFORMED,
                       f"not a valid {cls.__name__} message ({err})") from err
    return msg


def _finite(name: str, *values: float) -> None:
    for v in values:
        if not math.isfinite(v):
            raise Rejected(RejectReason.NON_FINITE, f"{name} is not finite ({v})")


# ---------------------------------------------------------------- cameras
def camera_to_pb(camera: Camera) -> tuple[pb.Pose, pb.Intrinsics]:
    pose = pb.Pose(c2w=[float(x) for x in np.asarray(camera.c2w, dtype=np.float64).ravel()])
    intr = pb.Intrinsics(fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy,
                         width=camera.width, height=camera.height)
    return pose, intr


_CAMERAS: dict[tuple[bytes, bytes], Camera] = {}
"""Cameras already validated, by their pose and intrinsics bytes: a rig's cameras send the
same few poses 33 times a second, to several services each (a Camera is immutable)."""
_CAMERAS_KEPT = 4096


def camera_from_pb(pose: pb.Pose, intr: pb.Intrinsics) -> Camera:
    """The validated :class:`Camera` of a pose and intrinsics; :class:`Rejected` when they
    are not one (each pose validated once, then remembered)."""
    key = (pose.SerializeToString(), intr.SerializeToString())
    camera = _CAMERAS.get(key)
    if camera is None:
        camera = _camera_from_pb(pose, intr)
        if len(_CAMERAS) >= _CAMERAS_KEPT:  # a rig of moving cameras: start again
            _CAMERAS.clear()
        _CAMERAS[key] = camera
    return camera


def _camera_from_pb(pose: pb.Pose, intr: pb.Intrinsics) -> Camera:
    if len(pose.c2w) != 16:
        raise Rejected(RejectReason.BAD_POSE, f"pose has {len(pose.c2w)} values, expected 16 (4x4)")
    c2w = np.asarray(pose.c2w, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(c2w)):
        raise Rejected(RejectReason.BAD_POSE, "pose contains NaN or infinity")
    _finite("intrinsics", intr.fx, intr.fy, intr.cx, intr.cy)
    if intr.width == 0 or intr.height == 0 or intr.fx <= 0 or intr.fy <= 0:
        raise Rejected(RejectReason.BAD_INTRINSICS,
                       f"need positive focal and size, got {intr.fx}x{intr.fy} "
                       f"{intr.width}x{intr.height}")
    camera = Camera(c2w=c2w, fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy,
                    width=int(intr.width), height=int(intr.height))
    try:
        camera.validate()
    except ValueError as err:
        raise Rejected(RejectReason.BAD_POSE, str(err)) from err
    return camera


# ---------------------------------------------------------------- images
def png_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk, without decoding the image."""
    if len(data) < 24 or not data.startswith(_PNG_SIGNATURE) or data[12:16] != b"IHDR":
        raise Rejected(RejectReason.BAD_IMAGE, "image bytes are not a PNG")
    return struct.unpack(">II", data[16:24])


def check_image(img: pb.Image) -> None:
    """Cheap structural check: the encoded size matches the declared one, which is at most
    :data:`MAX_IMAGE_PIXELS` (before anything is decoded)."""
    if img.width * img.height > MAX_IMAGE_PIXELS:
        raise Rejected(RejectReason.TOO_LARGE, f"a {img.width}x{img.height} image exceeds "
                                               f"{MAX_IMAGE_PIXELS} pixels")
    if img.encoding == PNG:
        w, h = png_size(img.data)
    elif img.encoding == RAW:
        if len(img.data) != img.width * img.height * 3:
            raise Rejected(RejectReason.IMAGE_SIZE_MISMATCH,
                           f"raw image has {len(img.data)} bytes, expected "
                           f"{img.width}x{img.height}x3")
        w, h = img.width, img.height
    else:
        raise Rejected(RejectReason.BAD_IMAGE, f"unsupported image encoding {img.encoding}")
    if (w, h) != (img.width, img.height):
        raise Rejected(RejectReason.IMAGE_SIZE_MISMATCH,
                       f"image is {w}x{h} but the message says {img.width}x{img.height}")


def decode_image(img: pb.Image) -> np.ndarray:
    """uint8 H×W×3."""
    check_image(img)
    if img.encoding == RAW:
        return np.frombuffer(img.data, dtype=np.uint8).reshape(img.height, img.width, 3)
    from PIL import Image as PILImage

    try:
        with PILImage.open(io.BytesIO(img.data)) as im:
            arr = np.asarray(im.convert("RGB"))
    except Exception as err:  # truncated/corrupt PNG
        raise Rejected(RejectReason.BAD_IMAGE, f"PNG could not be decoded ({err})") from err
    return arr


def encode_png(image: np.ndarray) -> pb.Image:
    from PIL import Image as PILImage

    arr = to_uint8(image)
    buf = io.BytesIO()
    PILImage.fromarray(arr, "RGB").save(buf, format="PNG", compress_level=1)
    return pb.Image(encoding=PNG, width=arr.shape[1], height=arr.shape[0], data=buf.getvalue())


def png_bytes(img: pb.Image) -> bytes:
    """The image as PNG file bytes: its own when it is a PNG, else encoded."""
    if img.encoding == PNG:
        return bytes(img.data)
    return encode_png(decode_image(img)).data


# ---------------------------------------------------------------- frames
@dataclass(frozen=True)
class FrameData:
    """A validated frame: the camera and metadata decoded, the image still encoded."""

    camera_id: int
    sequence: int
    generation_ms: float
    scene_time_ms: float
    send_ms: float
    delivery_ms: float
    camera: Camera
    image: pb.Image

    def rgb(self) -> np.ndarray:
        return decode_image(self.image)


def encode_frame(*, camera_id: int, sequence: int, generation_ms: float, scene_time_ms: float,
                 camera: Camera, image: pb.Image, send_ms: float = 0.0,
                 delivery_ms: float = 0.0) -> bytes:
    pose, intr = camera_to_pb(camera)
    return pb.Frame(camera_id=camera_id, sequence=sequence, generation_ms=generation_ms,
                    scene_time_ms=scene_time_ms, send_ms=send_ms, delivery_ms=delivery_ms,
                    pose=pose, intrinsics=intr, image=image).SerializeToString()


def check_size(img: pb.Image, size: tuple[int, int]) -> None:
    """The image is exactly ``size`` = (width, height) and its bytes are bounded by it: a
    receiver that knows the scene's size checks it before decoding anything (a 4096×4096 PNG
    in a small envelope would otherwise cost gigabytes once decoded)."""
    w, h = size
    if (img.width, img.height) != (w, h):
        raise Rejected(RejectReason.IMAGE_SIZE_MISMATCH,
                       f"image is {img.width}x{img.height} but the scene's is {w}x{h}")
    if len(img.data) > w * h * 3 + _IMAGE_SLACK_BYTES:
        raise Rejected(RejectReason.TOO_LARGE, f"a {w}x{h} image of {len(img.data)} bytes")


def decode_frame(payload: bytes, camera_ids: set[int] | frozenset[int] | None = None,
                 size: tuple[int, int] | None = None) -> FrameData:
    """Parse and validate a Frame; ``camera_ids`` restricts the accepted cameras and ``size``
    = (width, height), when given, is the only accepted image size (:func:`check_size`)."""
    return frame_data(_parse(pb.Frame, payload), camera_ids, size)


def frame_data(msg: pb.Frame, camera_ids: set[int] | frozenset[int] | None = None,
               size: tuple[int, int] | None = None) -> FrameData:
    """:func:`decode_frame`'s validation of a Frame already parsed (one a Job carries)."""
    if camera_ids is not None and msg.camera_id not in camera_ids:
        raise Rejected(RejectReason.UNKNOWN_CAMERA,
                       f"camera id {msg.camera_id} is not part of this rig")
    _finite("frame time", msg.generation_ms, msg.scene_time_ms, msg.send_ms, msg.delivery_ms)
    if not msg.HasField("pose") or not msg.HasField("intrinsics") or not msg.HasField("image"):
        raise Rejected(RejectReason.MALFORMED, "frame lacks pose, intrinsics or image")
    if size is not None:
        check_size(msg.image, size)
    camera = camera_from_pb(msg.pose, msg.intrinsics)
    check_image(msg.image)
    if (msg.image.width, msg.image.height) != (camera.width, camera.height):
        raise Rejected(RejectReason.IMAGE_SIZE_MISMATCH,
                       f"image is {msg.image.width}x{msg.image.height} but the intrinsics say "
                       f"{camera.width}x{camera.height}")
    return FrameData(camera_id=msg.camera_id, sequence=msg.sequence,
                     generation_ms=msg.generation_ms, scene_time_ms=msg.scene_time_ms,
                     send_ms=msg.send_ms, delivery_ms=msg.delivery_ms, camera=camera,
                     image=msg.image)


def with_delivery(payload: bytes, delivery_ms: float) -> bytes:
    """The same frame with its delivery time set (the network service's stamp)."""
    msg = _parse(pb.Frame, payload)
    msg.delivery_ms = delivery_ms
    return msg.SerializeToString()


# ---------------------------------------------------------------- decisions, renders, quality
def decode_decision(payload: bytes) -> pb.Decision:
    msg = _parse(pb.Decision, payload)
    _finite("decision time", msg.time_ms)
    if len(msg.aoi_ms) != len(msg.camera_ids):
        raise Rejected(RejectReason.MALFORMED, f"{len(msg.aoi_ms)} AoI values for "
                                               f"{len(msg.camera_ids)} cameras")
    return msg


def decode_render(payload: bytes) -> tuple[pb.Render, Camera]:
    msg = _parse(pb.Render, payload)
    _finite("render time", msg.time_ms)
    if msg.HasField("ready_ms"):
        _finite("render ready time", msg.ready_ms)
    camera = camera_from_pb(msg.pose, msg.intrinsics)
    check_image(msg.image)
    if (msg.image.width, msg.image.height) != (camera.width, camera.height):
        raise Rejected(RejectReason.IMAGE_SIZE_MISMATCH, "render size differs from its intrinsics")
    return msg, camera


def decode_quality(payload: bytes) -> pb.Quality:
    msg = _parse(pb.Quality, payload)
    _finite("quality time", msg.time_ms)
    if msg.HasField("dynamic_fraction") and not 0.0 <= msg.dynamic_fraction <= 1.0:
        raise Rejected(RejectReason.MALFORMED,
                       f"dynamic_fraction {msg.dynamic_fraction} is not in [0, 1]")
    return msg


def quality_scores(msg: pb.Quality) -> dict[str, float | None]:
    """A Quality's scores by the names the virtual clock's scores have (``psnr_db``,
    ``ssim``, ``reward``, ``psnr_dynamic_db``; None where absent: the reward of a render
    scored without LPIPS, ``lpips_skipped``): what a policy rewarded by
    quality is told (``policy.observe_quality``)."""
    return {"psnr_db": msg.psnr_db, "ssim": msg.ssim,
            "reward": None if msg.lpips_skipped else msg.reward,
            "psnr_dynamic_db": msg.psnr_dynamic_db if msg.HasField("psnr_dynamic_db")
            else None}
