"""One ROS publisher: its key, its publisher id and its sequence numbers, and each sample as
sent (with rmw_zenoh's attachment). The test robot's and the recorder's player's."""

from __future__ import annotations

import os

from services.ros.attachment import build_attachment
from services.ros.cdr import encode_cdr
from services.ros.keys import KeyFormat

__all__ = ["RosPublisher"]


class RosPublisher:
    """One ROS publisher: its key, its publisher id and its sequence numbers (the robot's and
    the player's)."""

    def __init__(self, fmt: KeyFormat, topic: str, ros_type: str, hash_: str | None):
        self.key = fmt.key(topic, ros_type, hash_)
        self.topic = topic
        self.ros_type = ros_type
        self.attached = fmt.attached
        self.gid = os.urandom(16)
        self.seq = 0

    def encode(self, msg) -> bytes:
        return encode_cdr(msg, self.ros_type)

    def sample(self, payload: bytes, robot_ns: int) -> tuple[str, bytes, bytes | None]:
        """The sample as sent: the next sequence number and the source time go in the
        attachment (rmw_zenoh's, at the moment of publishing)."""
        self.seq += 1
        att = build_attachment(self.seq, robot_ns, self.gid) if self.attached else None
        return self.key, payload, att
