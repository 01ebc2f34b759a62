"""The parts of a rig file: a camera's entry (image source, intrinsics, pose), the rendered
view, the source (the key format) and the clock. Validated with pydantic: each error names its
field."""

from __future__ import annotations

import math
import re
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from aoi3d.rigfile.poses import convert_pose, quaternion_matrix

__all__ = ["CameraSpec", "ClockSpec", "IntrinsicsSpec", "PoseSpec", "SourceSpec", "Strict",
           "Topic", "ViewSpec"]


def _topic(value: str) -> str:
    """A ROS topic name: ``/a/b`` (the leading slash optional), no empty or wildcard parts."""
    name = value.strip()
    parts = name.strip("/").split("/")
    if not name.strip("/") or any(not p or any(c in p for c in "*$?#") for p in parts):
        raise ValueError(f"{value!r} is not a topic name like /cam0/image_raw")
    return "/" + "/".join(parts)


Topic = Annotated[str, Field(min_length=1, max_length=256)]
_PROTOCOL = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*):")
"""FFmpeg reads ``NAME:rest`` as protocol NAME when NAME has no ``/`` (``concat:a|b``,
``http://…``, ``file:…``); anything else is a file path."""


class Strict(BaseModel):
    """A part of the rig file: unknown fields are errors, every number finite (NaN and ±inf
    are refused where they are read, not at run time); frozen once read."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class IntrinsicsSpec(Strict):
    """Pinhole intrinsics: values in pixels of the camera's own image size, or a
    ``sensor_msgs/CameraInfo`` topic (its K and size; the newest message is used)."""

    fx: float | None = Field(None, gt=0)
    fy: float | None = Field(None, gt=0)
    cx: float | None = None
    cy: float | None = None
    width: int | None = Field(None, ge=1, le=16384)
    height: int | None = Field(None, ge=1, le=16384)
    camera_info: Topic | None = None

    @field_validator("camera_info")
    @classmethod
    def _t(cls, v: str | None) -> str | None:
        return None if v is None else _topic(v)

    @model_validator(mode="after")
    def _one_form(self) -> IntrinsicsSpec:
        values = (self.fx, self.fy, self.cx, self.cy, self.width, self.height)
        if self.camera_info is not None:
            if any(v is not None for v in values):
                raise ValueError("give either camera_info (a topic) or the values fx, fy, cx, "
                                 "cy, width, height — not both")
        elif any(v is None for v in values):
            missing = [n for n, v in zip(("fx", "fy", "cx", "cy", "width", "height"), values,
                                         strict=True) if v is None]
            raise ValueError(f"missing {', '.join(missing)} (or give camera_info: a "
                             "CameraInfo topic)")
        for name in ("cx", "cy"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"{name} must be finite")
        return self

    @property
    def static(self) -> bool:
        return self.camera_info is None


class PoseSpec(Strict):
    """The camera's pose: static (``c2w``, 16 values row-major or 4×4, or ``position`` +
    ``orientation`` as a quaternion x, y, z, w), or a ``geometry_msgs/PoseStamped`` or
    ``nav_msgs/Odometry`` topic matched to each image by stamp within ``tolerance_s``.
    ``convention``: the axes of the pose's camera frame (:data:`CONVENTIONS`); ``extrinsic``:
    an optional fixed 4×4 from the pose's frame to the camera (a body pose → its camera)."""

    c2w: list[float] | list[list[float]] | None = None
    position: list[float] | None = Field(None, min_length=3, max_length=3)
    orientation: list[float] | None = Field(None, min_length=4, max_length=4)
    topic: Topic | None = None
    type: Literal["PoseStamped", "Odometry"] = "PoseStamped"
    convention: Literal["optical", "opengl", "body"] | None = None
    tolerance_s: float | None = Field(None, gt=0, le=10)
    extrinsic: list[float] | list[list[float]] | None = None

    @field_validator("topic")
    @classmethod
    def _t(cls, v: str | None) -> str | None:
        return None if v is None else _topic(v)

    @field_validator("c2w", "extrinsic")
    @classmethod
    def _matrix(cls, v: list[float] | list[list[float]] | None) -> list[float] | None:
        if v is None:
            return None
        flat = [float(x) for row in v for x in (row if isinstance(row, list) else [row])]
        if len(flat) != 16 or not all(math.isfinite(x) for x in flat):
            raise ValueError("a 4x4 matrix: 16 finite numbers, row-major (or 4 rows of 4)")
        m = np.asarray(flat).reshape(4, 4)
        if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
            raise ValueError("the last row of a rigid transform is 0 0 0 1")
        r = m[:3, :3]
        with np.errstate(all="ignore"):  # 1e300 entries overflow: not a rotation either
            rotation = np.allclose(r.T @ r, np.eye(3), atol=1e-4) and np.linalg.det(r) >= 0
        if not rotation:
            raise ValueError("its rotation part is not a rotation (orthonormal, det +1)")
        return flat

    @model_validator(mode="after")
    def _one_form(self) -> PoseSpec:
        forms = [self.c2w is not None, self.position is not None or self.orientation is not None,
                 self.topic is not None]
        if sum(forms) != 1:
            raise ValueError("give exactly one of: c2w (a static 4x4), position + orientation "
                             "(static), or topic (PoseStamped/Odometry)")
        if forms[1] and (self.position is None or self.orientation is None):
            raise ValueError("position and orientation go together")
        if self.position is not None and self.orientation is not None:  # forms[1], checked
            try:
                quaternion_matrix(self.position, self.orientation)
            except ValueError as err:
                raise ValueError(str(err)) from None
        if self.topic is None and self.tolerance_s is not None:
            raise ValueError("tolerance_s applies to a pose topic only")
        return self

    @property
    def static(self) -> bool:
        return self.topic is None

    @property
    def axes(self) -> str:
        """The convention in force: ``opengl`` for ``c2w`` unless said, else ``optical``."""
        return self.convention or ("opengl" if self.c2w is not None else "optical")

    def to_gl(self, pose: np.ndarray) -> np.ndarray:
        """A pose of this spec's frame (from the file or a topic) → aoi3d's camera-to-world."""
        m = np.asarray(pose, dtype=np.float64).reshape(4, 4)
        if self.extrinsic is not None:
            m = m @ np.asarray(self.extrinsic).reshape(4, 4)
        return convert_pose(m, self.axes)

    def static_c2w(self) -> np.ndarray:
        if self.c2w is not None:
            return self.to_gl(np.asarray(self.c2w).reshape(4, 4))
        assert self.position is not None and self.orientation is not None, "a static pose"
        return self.to_gl(quaternion_matrix(self.position, self.orientation))


class CameraSpec(Strict):
    """One camera of the rig."""

    name: str = Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$",
                      description="Its name (in logs, metrics labels and the status).")
    image: Topic | None = Field(None, description="Its image topic: sensor_msgs/Image, or "
                                                  "sensor_msgs/CompressedImage (jpeg or png).")
    image_type: Literal["raw", "compressed"] | None = Field(
        None, description="raw (Image) or compressed (CompressedImage); default: compressed "
                          "when the topic ends in /compressed, else raw.")
    url: str | None = Field(
        None, min_length=1, max_length=1024,
        description="An IP camera or a video instead of a topic: rtsp://host:port/path or "
                    "rtsps:// (H.264 and whatever else FFmpeg decodes), or an existing video "
                    "file (played in a loop at its own rate); another FFmpeg protocol only "
                    "where the rig's url_protocols names it.")
    listen: bool = Field(False, description="rtsp:// only: wait for the camera to push its "
                                            "stream to this URL (RTSP RECORD) instead of "
                                            "pulling from it.")
    stamps: Literal["rtcp", "receipt"] = Field(
        "rtcp", description="rtsp:// only: a frame's generation time from the sender's clock "
                            "(its RTCP sender reports map the stream's clock to wall time) or "
                            "its receipt (when the sender has no usable clock: AoI then omits "
                            "the capture-to-receipt delay).")
    intrinsics: IntrinsicsSpec
    pose: PoseSpec

    @field_validator("image")
    @classmethod
    def _t(cls, v: str | None) -> str | None:
        return None if v is None else _topic(v)

    @model_validator(mode="after")
    def _source(self) -> CameraSpec:
        if (self.image is None) == (self.url is None):
            raise ValueError("give exactly one of image (a ROS topic) or url (rtsp://, "
                             "rtsps:// or a video file)")
        if self.url is not None:
            if self.image_type is not None:
                raise ValueError("image_type is for image topics")
            if self.intrinsics.camera_info is not None:
                raise ValueError("a url camera needs its intrinsics as values (fx, fy, cx, "
                                 "cy, width, height): it has no CameraInfo topic")
            if not self.is_rtsp and (self.listen or self.stamps != "rtcp"):
                raise ValueError("listen and stamps are for rtsp:// urls")
            if any(ord(c) < 32 for c in self.url):
                raise ValueError("url: no control characters")
        return self

    @property
    def protocol(self) -> str | None:
        """The url's FFmpeg protocol (``rtsp``, ``http``, ``concat``, …), lower case; None
        for a file path (and for an image topic)."""
        if self.url is None:
            return None
        m = _PROTOCOL.match(self.url)
        return m.group(1).lower() if m else None

    @property
    def is_rtsp(self) -> bool:
        return self.protocol in ("rtsp", "rtsps")

    @property
    def kind(self) -> str:
        if self.url is not None:
            return "rtsp" if self.is_rtsp else "video"
        assert self.image is not None, "_source: an image topic when no url"
        return self.image_type or ("compressed" if self.image.endswith("/compressed") else "raw")


class ViewSpec(Strict):
    """The camera the pipeline renders when no truth camera is named: a static pose and
    intrinsics (as in a camera's entry)."""

    intrinsics: IntrinsicsSpec
    pose: PoseSpec


class SourceSpec(Strict):
    """Where the ROS 2 topics are on Zenoh: ``rmw_zenoh`` keys (``<domain>/<topic>/<type>/<type
    hash>``, with an attachment per sample) or ``bridge`` keys (``zenoh-bridge-ros2dds``:
    ``[<namespace>/]<topic>``, no attachment) — or straight on DDS (``dds``: a ROS 2 node of
    the ingest's own, rclpy on Fast DDS, in domain ``domain_id``; ``pip install
    'aoi3d[ros2]'``)."""

    format: Literal["rmw_zenoh", "bridge", "dds"] = "rmw_zenoh"
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID (rmw_zenoh, dds).")
    qos: Literal["sensor_data", "reliable"] = Field(
        "sensor_data", description="dds: the subscriptions' QoS — sensor_data (best effort, "
                                   "keep last, what camera drivers publish with; it also "
                                   "matches reliable publishers) or reliable.")
    depth: int = Field(5, ge=1, le=1000, description="dds: the subscriptions' keep-last depth.")
    interface: str = Field(
        "loopback", pattern=r"^(loopback|all|[0-9]{1,3}(\.[0-9]{1,3}){3})$",
        description="dds: where DDS discovery and data go — loopback (127.0.0.1 only: a robot "
                    "on this host), all (Fast DDS's defaults: every interface, multicast "
                    "discovery) or one interface's IPv4 address.")
    namespace: str = Field("", pattern=r"^[A-Za-z0-9_/-]{0,128}$",
                           description="The bridge's namespace (its -n option), a key prefix.")
    connect: list[str] = Field(
        default_factory=list,
        description="Zenoh endpoints of the robots' router (e.g. tcp/10.0.0.5:7447); empty: "
                    "the pipeline's own router.")

    @model_validator(mode="after")
    def _fits(self) -> SourceSpec:
        if self.format == "rmw_zenoh" and self.namespace:
            raise ValueError("namespace is the bridge's; rmw_zenoh keys start with domain_id")
        if self.format == "dds" and (self.namespace or self.connect):
            raise ValueError("dds reads the topics straight from DDS: no namespace, no connect "
                             "(domain_id and interface say where)")
        dds_only = {"qos", "depth", "interface"} & self.model_fields_set
        if self.format != "dds" and dds_only:
            raise ValueError(f"{', '.join(sorted(dds_only))}: for format dds only")
        return self

    @property
    def prefix(self) -> str:
        return self.namespace.strip("/")


class ClockSpec(Strict):
    """Robot clocks are not the edge's. ``offset_s``: robot clock − edge clock, in seconds, a
    number or ``auto`` (estimated per camera from the arrivals: the 90th percentile of stamp −
    receipt over the last samples, i.e. assuming the fastest tenth took no time). Stamps
    further ahead of their receipt than ``future_tolerance_s`` (after the offset) are refused,
    those within it are clamped to the receipt; stamps older than ``max_age_s`` at receipt are
    refused."""

    offset_s: float | Literal["auto"] = 0.0
    future_tolerance_s: float = Field(0.5, ge=0, le=60)
    max_age_s: float = Field(30.0, gt=0, le=3600)

    @field_validator("offset_s")
    @classmethod
    def _finite(cls, v: float | Literal["auto"]) -> float | Literal["auto"]:
        if not isinstance(v, str) and not (math.isfinite(v) and abs(v) < 10 * 365 * 86400):
            raise ValueError("a finite number of seconds, or auto")
        return v

