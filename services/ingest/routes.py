"""The ingest's subscriptions: each topic the rig file names (images, CameraInfo, poses), its
ROS type and key expression, and the cameras it feeds."""

from __future__ import annotations

from dataclasses import dataclass

from aoi3d.rigfile import Rig
from services import ros

__all__ = ["Route", "subscriptions"]


@dataclass(frozen=True)
class Route:
    """One subscription: a topic of a kind (image, camera_info, pose), the cameras it feeds."""

    kind: str
    topic: str
    ros_type: str
    key_expr: str
    cameras: tuple[str, ...]


def subscriptions(rig: Rig, fmt: ros.KeyFormat) -> list[Route]:
    """A route per topic of the rig (a topic two cameras share feeds both); :class:`ValueError`
    when one topic is of two kinds."""
    by_topic: dict[tuple[str, str, str], list[str]] = {}
    for c in rig.cameras:
        if c.image is not None:  # (a url camera is read by the runtime: on_video)
            image_type = ros.COMPRESSED if c.kind == "compressed" else ros.IMAGE
            by_topic.setdefault(("image", c.image, image_type), []).append(c.name)
        if c.intrinsics.camera_info is not None:
            by_topic.setdefault(("camera_info", c.intrinsics.camera_info, ros.CAMERA_INFO),
                                []).append(c.name)
        if c.pose.topic is not None:
            pose_type = ros.POSE_STAMPED if c.pose.type == "PoseStamped" else ros.ODOMETRY
            by_topic.setdefault(("pose", c.pose.topic, pose_type), []).append(c.name)
    kinds: dict[str, str] = {}
    for (kind, topic, _), _names in by_topic.items():
        other = kinds.setdefault(topic, kind)
        if other != kind:
            raise ValueError(f"topic {topic} is both an {other} and a {kind} topic")
    return [Route(kind, topic, t, fmt.subscription(topic, t), tuple(names))
            for (kind, topic, t), names in by_topic.items()]
