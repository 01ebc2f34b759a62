"""ROS 2 type names, their DDS names and RIHS01 hashes (rmw_zenoh puts both in its keys), and
rosbags' type store that knows them."""

from __future__ import annotations

import re
from functools import cache
from typing import Any

__all__ = ["CAMERA_INFO", "CDR_LE", "COMPRESSED", "HUMBLE_HASH", "IMAGE", "ODOMETRY",
           "POSE_STAMPED", "TYPES", "Message", "dds_type", "ros_type_of", "type_hash",
           "typestore"]

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TYPES = (IMAGE, COMPRESSED, CAMERA_INFO, POSE_STAMPED, ODOMETRY)
HUMBLE_HASH = "TypeHashNotSupported"
"""What Humble's rmw_zenoh puts in a key where Jazzy and later put the type hash."""
CDR_LE = b"\x00\x01\x00\x00"
_DDS_RE = re.compile(r"^([A-Za-z0-9_]+)::(msg|srv|action)::dds_::([A-Za-z0-9_]+)_$")
Message = Any
"""A ROS message: rosbags' dataclass of its type (rosbags ships no type information)."""


@cache
def typestore() -> Any:  # rosbags' Typestore (untyped)
    """rosbags' type store of ROS 2 Jazzy (the messages' definitions, CDR both ways)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def dds_type(ros_type: str) -> str:
    """``sensor_msgs/msg/Image`` → ``sensor_msgs::msg::dds_::Image_`` (rmw_zenoh's key)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


@cache
def type_hash(ros_type: str) -> str:
    """The type's RIHS01 hash (Jazzy and later; the same for these types through Lyrical)."""
    digest: str = typestore().hash_rihs01(ros_type)
    return digest


def ros_type_of(dds: str) -> str:
    """``sensor_msgs::msg::dds_::Image_`` → ``sensor_msgs/msg/Image`` (other names as they
    are)."""
    m = _DDS_RE.match(dds)
    return f"{m[1]}/{m[2]}/{m[3]}" if m else dds
