"""The ROS 2 wire on Zenoh, both ways: key expressions, the rmw_zenoh attachment, CDR messages
and their images. Pure (rosbags' type store for CDR, PIL for compressed images, numpy).

Key formats (docs/real-cameras.md):

- **rmw_zenoh** (ROS 2's Zenoh middleware): ``<domain>/<topic without its leading
  slash>/<DDS type>/<type hash>``, e.g. ``0/cam0/image_raw/sensor_msgs::msg::dds_::Image_/
  RIHS01_d31d…``; Humble puts ``TypeHashNotSupported`` where the hash goes. Each sample has an
  attachment: int64 sequence number, int64 source timestamp (ns, the publisher's clock), and
  the publisher's id (a length byte, then its bytes; 16 in Jazzy).
- **bridge** (zenoh-bridge-ros2dds): ``[<namespace>/]<topic without its leading slash>``, no
  attachment.

Payloads are CDR with its 4-byte encapsulation header (``00 01 00 00``: little-endian). Every
``decode_*`` raises :class:`Rejected` with a reason label on bad input; nothing here decodes
pixels before the declared size was checked against the limits.
"""

from __future__ import annotations

import io
import re
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from functools import cache

import numpy as np

from aoi3d.rigfile import quaternion_matrix
from services.kit.rejected import Rejected

__all__ = [
    "CAMERA_INFO",
    "COMPRESSED",
    "HUMBLE_HASH",
    "IMAGE",
    "ODOMETRY",
    "POSE_STAMPED",
    "Attachment",
    "GraphEntity",
    "KeyFormat",
    "build_attachment",
    "dds_type",
    "decode_cdr",
    "encode_cdr",
    "image_rgb",
    "liveliness_key",
    "node_tokens",
    "parse_attachment",
    "parse_liveliness",
    "stamp_s",
    "type_hash",
]

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TYPES = (IMAGE, COMPRESSED, CAMERA_INFO, POSE_STAMPED, ODOMETRY)
HUMBLE_HASH = "TypeHashNotSupported"
"""What Humble's rmw_zenoh puts in a key where Jazzy and later put the type hash."""
CDR_LE = b"\x00\x01\x00\x00"
_HASH_RE = re.compile(r"^RIHS01_[0-9a-f]{64}$")

#: Raw ``sensor_msgs/Image`` encodings accepted: bytes per pixel and how to make RGB of them.
ENCODINGS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8uc1": 1, "8uc3": 3,
             "mono16": 2, "16uc1": 2}


@cache
def _store():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def dds_type(ros_type: str) -> str:
    """``sensor_msgs/msg/Image`` → ``sensor_msgs::msg::dds_::Image_`` (rmw_zenoh's key)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


@cache
def type_hash(ros_type: str) -> str:
    """The type's RIHS01 hash (Jazzy and later; the same for these types through Lyrical)."""
    return _store().hash_rihs01(ros_type)


# ---------------------------------------------------------------- keys
@dataclass(frozen=True)
class KeyFormat:
    """How topics map to Zenoh keys: ``rmw_zenoh`` (with ``domain_id``) or ``bridge`` (with
    ``namespace``)."""

    format: str = "rmw_zenoh"
    domain_id: int = 0
    namespace: str = ""

    def __post_init__(self) -> None:
        if self.format not in ("rmw_zenoh", "bridge"):
            raise ValueError(f"key format {self.format!r}: rmw_zenoh or bridge")

    @property
    def attached(self) -> bool:
        """Whether samples carry the rmw_zenoh attachment."""
        return self.format == "rmw_zenoh"

    def _topic(self, topic: str) -> str:
        return topic.strip("/")

    def key(self, topic: str, ros_type: str, hash_: str | None = None) -> str:
        """The key a publisher of ``topic`` puts on; ``hash_`` (rmw_zenoh): the type hash,
        default the Jazzy one (:data:`HUMBLE_HASH` for Humble)."""
        if self.format == "bridge":
            ns = self.namespace.strip("/")
            return f"{ns}/{self._topic(topic)}" if ns else self._topic(topic)
        return (f"{self.domain_id}/{self._topic(topic)}/{dds_type(ros_type)}/"
                f"{hash_ or type_hash(ros_type)}")

    def subscription(self, topic: str, ros_type: str) -> str:
        """The key expression a subscriber of ``topic`` declares (any type hash)."""
        if self.format == "bridge":
            return self.key(topic, ros_type)
        return f"{self.domain_id}/{self._topic(topic)}/{dds_type(ros_type)}/*"

    def check_key(self, key: str, ros_type: str) -> None:
        """An rmw_zenoh key's type hash must be the type's or Humble's placeholder."""
        if self.format == "bridge":
            return
        got = key.rsplit("/", 1)[-1]
        if got == HUMBLE_HASH or got == type_hash(ros_type):
            return
        what = "another definition of the type" if _HASH_RE.match(got) else "not a type hash"
        raise Rejected("type_hash_mismatch",
                       f"{key}: {got[:80]!r} is {what} (expected {type_hash(ros_type)} or "
                       f"{HUMBLE_HASH})")


# ---------------------------------------------------------------- the ROS graph
LIVELINESS_SPACE = "@ros2_lv"
"""The key space of rmw_zenoh's liveliness tokens: how ROS 2 nodes see one another."""
ENTITY_KINDS = {"NN": "node", "MP": "publisher", "MS": "subscription", "SS": "service",
                "SC": "client"}
DEFAULT_QOS = "::,:,:,:,,"
"""A token's QoS chunk when every policy is rmw_zenoh's default (each non-default value goes
between its delimiters: reliability:durability:history,depth:deadline s,ns:lifespan
s,ns:liveliness,lease s,ns)."""
_DDS_RE = re.compile(r"^([A-Za-z0-9_]+)::(msg|srv|action)::dds_::([A-Za-z0-9_]+)_$")


@dataclass(frozen=True)
class GraphEntity:
    """One liveliness token of the ROS graph: a node, or a node's publisher, subscription,
    service or client with its topic (``/cam0/image_raw``), ROS type
    (``sensor_msgs/msg/Image``) and type hash."""

    kind: str
    domain_id: int
    session: str
    node: str
    namespace: str = "/"
    topic: str | None = None
    ros_type: str | None = None
    type_hash: str | None = None


def _mangle(name: str) -> str:
    return name.replace("/", "%")


def _demangle(name: str) -> str:
    return name.replace("%", "/")


def ros_type_of(dds: str) -> str:
    """``sensor_msgs::msg::dds_::Image_`` → ``sensor_msgs/msg/Image`` (other names as they
    are)."""
    m = _DDS_RE.match(dds)
    return f"{m[1]}/{m[2]}/{m[3]}" if m else dds


def liveliness_key(domain_id: int, session: str, node_id: int, entity_id: int, kind: str,
                   node: str, *, namespace: str = "/", enclave: str = "/",
                   topic: str | None = None, ros_type: str | None = None,
                   hash_: str | None = None, qos: str = DEFAULT_QOS) -> str:
    """The token rmw_zenoh declares for an entity (the layout of its Jazzy branch and its
    Humble backport, ``liveliness_utils.cpp``): ``@ros2_lv/<domain>/<session id>/<node
    id>/<entity id>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/<node>`` and, for a topic's
    entity, ``/<topic>/<DDS type>/<type hash>/<qos>``; a name's slashes become ``%``."""
    code = {v: k for k, v in ENTITY_KINDS.items()}[kind]
    parts = [LIVELINESS_SPACE, str(domain_id), session, str(node_id), str(entity_id), code,
             _mangle(enclave), _mangle(namespace), _mangle(node)]
    if kind != "node":
        if topic is None or ros_type is None:
            raise ValueError(f"a {kind}'s token names its topic and type")
        parts += [_mangle("/" + topic.strip("/")), dds_type(ros_type),
                  hash_ or type_hash(ros_type), qos]
    return "/".join(parts)


def node_tokens(domain_id: int, session: str, node: str,
                publishers: Iterable[tuple[str, str]], hash_: str | None = None) -> list[str]:
    """A node's liveliness tokens: the node, then a publisher of each (topic, ROS type), as
    rmw_zenoh declares them (entity ids 1, 2, … within node 0 of the session)."""
    out = [liveliness_key(domain_id, session, 0, 0, "node", node)]
    for entity_id, (topic, ros_type) in enumerate(publishers, start=1):
        out.append(liveliness_key(domain_id, session, 0, entity_id, "publisher", node,
                                  topic=topic, ros_type=ros_type, hash_=hash_))
    return out


def parse_liveliness(key: str) -> GraphEntity:
    """A token of the ROS graph (:func:`liveliness_key`'s layout). :class:`ValueError` that
    says what is wrong otherwise (another layout, another key space, a missing part)."""
    parts = str(key).split("/")
    if parts[0] != LIVELINESS_SPACE:
        raise ValueError(f"{key[:120]!r}: not under {LIVELINESS_SPACE}/")
    if len(parts) < 9 or any(not p for p in parts):
        raise ValueError(f"{key[:120]!r}: {len(parts)} parts, a token has 9 or 13")
    kind = ENTITY_KINDS.get(parts[5])
    if kind is None or not parts[1].isdigit():
        raise ValueError(f"{key[:120]!r}: no entity kind (NN, MP, MS, SS, SC) in part 6 or "
                         f"no domain id in part 2 (an older rmw_zenoh's layout?)")
    out = GraphEntity(kind, int(parts[1]), parts[2], _demangle(parts[8]),
                      _demangle(parts[7]))
    if kind == "node":
        return out
    if len(parts) < 13:
        raise ValueError(f"{key[:120]!r}: a {kind}'s token has 13 parts, not {len(parts)}")
    return GraphEntity(kind, out.domain_id, out.session, out.node, out.namespace,
                       "/" + _demangle(parts[9]).strip("/"), ros_type_of(_demangle(parts[10])),
                       parts[11])


# ---------------------------------------------------------------- attachment
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
        raise Rejected("bad_attachment", "an rmw_zenoh sample without its attachment")
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
        raise Rejected("bad_attachment", f"{len(raw)}-byte attachment is not rmw_zenoh's "
                                         f"({err})") from None
    return Attachment(int(seq), int(ts), bytes(gid))


# ---------------------------------------------------------------- CDR
def encode_cdr(msg: object, ros_type: str) -> bytes:
    return bytes(_store().serialize_cdr(msg, ros_type))


def decode_cdr(payload: bytes, ros_type: str, max_bytes: int) -> object:
    """A CDR payload → the message (rosbags' dataclass). Refused before parsing when larger
    than ``max_bytes`` (``too_large``); ``bad_cdr`` when it is not a little-endian CDR
    encoding of ``ros_type`` (truncated, garbled, trailing bytes)."""
    if len(payload) > max_bytes:
        raise Rejected("too_large", f"{len(payload)}-byte sample exceeds {max_bytes} bytes")
    if len(payload) < 8 or payload[:4] != CDR_LE:
        raise Rejected("bad_cdr", f"not little-endian CDR (header {bytes(payload[:4]).hex()})")
    try:
        msg = _store().deserialize_cdr(payload, ros_type)
    except Exception as err:  # rosbags raises struct.error, IndexError, ValueError, …
        raise Rejected("bad_cdr", f"not a {ros_type} in CDR ({type(err).__name__}: "
                                  f"{str(err)[:120]})") from None
    # rosbags reads what the type needs; a sample longer than that (beyond CDR's 4-byte
    # padding) was not what its publisher meant
    try:
        again = len(_store().serialize_cdr(msg, ros_type))
    except Exception as err:
        raise Rejected("bad_cdr", f"{ros_type} with unusable fields ({type(err).__name__})") \
            from None
    if not again <= len(payload) <= again + 3:
        raise Rejected("bad_cdr", f"{len(payload)}-byte sample holds a {again}-byte {ros_type}")
    return msg


def stamp_s(header) -> float:
    """A ``std_msgs/Header``'s stamp in seconds; ``stamp_invalid`` when nanosec ≥ 10⁹."""
    sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
    if not 0 <= nsec < 1_000_000_000:
        raise Rejected("stamp_invalid", f"nanosec {nsec} is not in [0, 1e9)")
    return sec + nsec * 1e-9


# ---------------------------------------------------------------- images
def _raw_rgb(msg, max_pixels: int) -> np.ndarray:
    enc = str(msg.encoding).lower()
    bpp = ENCODINGS.get(enc)
    if bpp is None:
        raise Rejected("unknown_encoding", f"raw image encoding {str(msg.encoding)[:40]!r} "
                                           f"(accepted: {', '.join(ENCODINGS)})")
    w, h, step = int(msg.width), int(msg.height), int(msg.step)
    if w < 1 or h < 1:
        raise Rejected("image_mismatch", f"a {w}x{h} image")
    if w * h > max_pixels:
        raise Rejected("too_large", f"a {w}x{h} image exceeds {max_pixels} pixels")
    if step < w * bpp:
        raise Rejected("image_mismatch", f"step {step} < width {w} × {bpp} bytes ({enc})")
    data = msg.data
    if len(data) != step * h:
        raise Rejected("image_mismatch", f"{len(data)} data bytes, but step {step} × height "
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


def _compressed_rgb(msg, max_pixels: int) -> np.ndarray:
    fmt = str(msg.format).lower()
    data = bytes(msg.data)
    if "jpeg" in fmt or "jpg" in fmt:
        kind, magic = "JPEG", b"\xff\xd8\xff"
    elif "png" in fmt:
        kind, magic = "PNG", b"\x89PNG\r\n\x1a\n"
    else:
        raise Rejected("unknown_encoding", f"compressed format {str(msg.format)[:40]!r} (accepted: "
                                           "jpeg, png)")
    if not data.startswith(magic):
        raise Rejected("bad_image", f"the data is not {kind} (format says {msg.format[:40]!r})")
    from PIL import Image as PILImage

    try:
        im = PILImage.open(io.BytesIO(data), formats=[kind])
        w, h = im.size  # the header only: nothing is decoded yet
    except Exception as err:
        raise Rejected("bad_image", f"{kind} header unreadable ({type(err).__name__})") from None
    if w * h > max_pixels:
        raise Rejected("too_large", f"a {w}x{h} {kind} exceeds {max_pixels} pixels")
    try:
        with im:
            return np.asarray(im.convert("RGB"))
    except Exception as err:  # truncated or corrupt data
        raise Rejected("bad_image", f"{kind} could not be decoded ({type(err).__name__})") \
            from None


def image_rgb(msg, ros_type: str, max_pixels: int) -> np.ndarray:
    """An ``Image`` or ``CompressedImage`` → uint8 H×W×3 RGB (checked before decoding)."""
    if ros_type == IMAGE:
        return _raw_rgb(msg, max_pixels)
    return _compressed_rgb(msg, max_pixels)


# ---------------------------------------------------------------- building messages
def header(stamp: float, frame_id: str):
    types = _store().types
    sec = int(np.floor(stamp))
    nsec = min(round((stamp - sec) * 1e9), 999_999_999)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id)


def image_msg(stamp: float, frame_id: str, rgb: np.ndarray, encoding: str = "rgb8"):
    """A ``sensor_msgs/Image`` of an RGB uint8 image (``rgb8`` or ``bgr8``)."""
    arr = np.ascontiguousarray(rgb[:, :, ::-1] if encoding == "bgr8" else rgb, dtype=np.uint8)
    h, w = arr.shape[:2]
    return _store().types[IMAGE](header=header(stamp, frame_id), height=h, width=w,
                                 encoding=encoding, is_bigendian=0, step=w * 3,
                                 data=arr.reshape(-1))


def compressed_msg(stamp: float, frame_id: str, rgb: np.ndarray, fmt: str = "jpeg"):
    """A ``sensor_msgs/CompressedImage`` (``jpeg`` quality 95, or ``png``)."""
    from PIL import Image as PILImage

    buf = io.BytesIO()
    im = PILImage.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), "RGB")
    if fmt == "png":
        im.save(buf, format="PNG", compress_level=1)
    else:
        im.save(buf, format="JPEG", quality=95)
    return _store().types[COMPRESSED](header=header(stamp, frame_id), format=fmt,
                                      data=np.frombuffer(buf.getvalue(), dtype=np.uint8))


def compressed_bytes_msg(stamp: float, frame_id: str, data: bytes, fmt: str):
    """A ``sensor_msgs/CompressedImage`` of image bytes already encoded as ``fmt``."""
    return _store().types[COMPRESSED](header=header(stamp, frame_id), format=fmt,
                                      data=np.frombuffer(data, dtype=np.uint8))


def camera_info_msg(stamp: float, frame_id: str, fx: float, fy: float, cx: float, cy: float,
                    width: int, height: int):
    types = _store().types
    k = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64)
    p = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64)
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                    do_rectify=False)
    return types[CAMERA_INFO](header=header(stamp, frame_id), height=height, width=width,
                              distortion_model="plumb_bob", d=np.zeros(5), k=k,
                              r=np.eye(3).reshape(-1), p=p, binning_x=0, binning_y=0, roi=roi)


def _pose(m: np.ndarray):
    from scipy.spatial.transform import Rotation

    types = _store().types
    x, y, z, w = Rotation.from_matrix(m[:3, :3]).as_quat()
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(m[0, 3]), y=float(m[1, 3]),
                                                  z=float(m[2, 3])),
        orientation=types["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z),
                                                          w=float(w)))


def pose_stamped_msg(stamp: float, frame_id: str, m: np.ndarray):
    return _store().types[POSE_STAMPED](header=header(stamp, frame_id), pose=_pose(m))


def odometry_msg(stamp: float, frame_id: str, child: str, m: np.ndarray):
    types = _store().types
    cov = np.zeros(36)
    vec = types["geometry_msgs/msg/Vector3"]
    return types[ODOMETRY](
        header=header(stamp, frame_id), child_frame_id=child,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(m), covariance=cov),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=vec(x=0.0, y=0.0, z=0.0),
                                                   angular=vec(x=0.0, y=0.0, z=0.0)),
            covariance=cov))


def pose_matrix(msg, ros_type: str) -> np.ndarray:
    """A ``PoseStamped`` or ``Odometry`` → 4×4 (``bad_pose`` when not finite or not a
    rotation)."""
    pose = msg.pose if ros_type == POSE_STAMPED else msg.pose.pose
    p, q = pose.position, pose.orientation
    values = [p.x, p.y, p.z, q.x, q.y, q.z, q.w]
    if not np.all(np.isfinite(values)):
        raise Rejected("bad_pose", "pose has NaN or infinity")
    try:
        return quaternion_matrix([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
    except ValueError as err:
        raise Rejected("bad_pose", str(err)) from None


@dataclass(frozen=True)
class Intrinsics:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


def camera_info(msg) -> Intrinsics:
    """A ``CameraInfo``'s pinhole intrinsics (``bad_intrinsics`` when unusable)."""
    k = np.asarray(msg.k, dtype=np.float64)
    w, h = int(msg.width), int(msg.height)
    if k.shape != (9,) or not np.all(np.isfinite(k)) or k[0] <= 0 or k[4] <= 0 or w < 1 \
            or h < 1:
        raise Rejected("bad_intrinsics", f"CameraInfo K {k.tolist()[:9]} size {w}x{h}")
    return Intrinsics(float(k[0]), float(k[4]), float(k[2]), float(k[5]), w, h)
