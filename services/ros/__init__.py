"""The ROS 2 wire on Zenoh, both ways: key expressions, the ROS graph's tokens, the rmw_zenoh
attachment, CDR messages and their images. One library for the ingest (messages read), the test
robot and the recorder's player (messages built), and the commands.

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

This package exports the pure wire (no I/O: rosbags' type store for CDR, PIL for compressed
images, numpy): :mod:`.types` (type names, DDS names, hashes), :mod:`.keys` (:class:`KeyFormat`),
:mod:`.graph` (liveliness tokens), :mod:`.attachment`, :mod:`.cdr`, :mod:`.encode` (messages
built) and :mod:`.decode` (messages read). Imported by their module, not from here:
:mod:`.publisher` (one publisher's key, id and sequence numbers), :mod:`.robot` (the test
robot), :mod:`.publishing` (a Zenoh session to publish on) and :mod:`.rtsp` (an IP camera).
"""

from services.ros.attachment import Attachment, build_attachment, parse_attachment
from services.ros.cdr import decode_cdr, encode_cdr
from services.ros.decode import ENCODINGS, Intrinsics, camera_info, image_rgb, pose_matrix, stamp_s
from services.ros.encode import (
    camera_info_msg,
    compressed_bytes_msg,
    compressed_msg,
    image_msg,
    odometry_msg,
    pose_stamped_msg,
)
from services.ros.graph import (
    DEFAULT_QOS,
    ENTITY_KINDS,
    LIVELINESS_SPACE,
    GraphEntity,
    liveliness_key,
    node_tokens,
    parse_liveliness,
)
from services.ros.keys import KeyFormat
from services.ros.types import (
    CAMERA_INFO,
    CDR_LE,
    COMPRESSED,
    HUMBLE_HASH,
    IMAGE,
    ODOMETRY,
    POSE_STAMPED,
    TYPES,
    dds_type,
    ros_type_of,
    type_hash,
    typestore,
)

__all__ = [
    "CAMERA_INFO", "CDR_LE", "COMPRESSED", "DEFAULT_QOS", "ENCODINGS", "ENTITY_KINDS",
    "HUMBLE_HASH", "IMAGE", "LIVELINESS_SPACE", "ODOMETRY", "POSE_STAMPED", "TYPES",
    "Attachment", "GraphEntity", "Intrinsics", "KeyFormat", "build_attachment", "camera_info",
    "camera_info_msg", "compressed_bytes_msg", "compressed_msg", "dds_type", "decode_cdr",
    "encode_cdr", "image_msg", "image_rgb", "liveliness_key", "node_tokens", "odometry_msg",
    "parse_attachment", "parse_liveliness", "pose_matrix", "pose_stamped_msg", "ros_type_of",
    "stamp_s", "type_hash", "typestore",
]
