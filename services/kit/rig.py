"""The rig file: real cameras (ROS 2 over Zenoh) instead of the camera emulators.

``aoi3d up --rig rig.yaml`` reads it, and so do the ingest service (what to subscribe and how to
turn a ROS message into a :class:`pb.Frame`) and the trainer (the view it renders, the scene
box and the working size). YAML or JSON; validated here with pydantic, and every error names
its field (``cameras[2].pose.topic: …``). The format, with an example, is in
docs/real-cameras.md.

Pure: pydantic, numpy and the domain's :class:`Camera`; no bus, no server.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from aoi3d.scene.camera import Camera

__all__ = ["CameraSpec", "ClockSpec", "IntrinsicsSpec", "PoseSpec", "Rig", "RigError",
           "SourceSpec", "ViewSpec", "convert_pose", "load_rig", "rig_from_dict"]

TRUTH_ID = 0
"""The held-out camera's id on the wire (the truth key); training cameras are 1..N in the order
of the file."""
CONVENTIONS = ("optical", "opengl", "body")
"""Axes of a pose's camera frame: ``optical`` — ROS's camera optical frame (x right, y down, z
forward: REP 103, what ``image_raw`` is published in); ``opengl`` — aoi3d's own (x right, y up,
looking along −z); ``body`` — a ROS body/link frame (x forward, y left, z up)."""

_OPTICAL_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
_BODY_TO_GL = np.array([[0.0, 0.0, -1.0, 0.0],
                        [-1.0, 0.0, 0.0, 0.0],
                        [0.0, 1.0, 0.0, 0.0],
                        [0.0, 0.0, 0.0, 1.0]])


class RigError(ValueError):
    """A rig file that cannot be used: one line per problem, each naming its field."""


def convert_pose(c2w: np.ndarray, convention: str) -> np.ndarray:
    """A camera-to-world transform whose camera axes follow ``convention`` → aoi3d's (OpenGL)."""
    c2w = np.asarray(c2w, dtype=np.float64).reshape(4, 4)
    if convention == "opengl":
        return c2w.copy()
    if convention == "optical":
        return c2w @ _OPTICAL_TO_GL
    if convention == "body":
        return c2w @ _BODY_TO_GL
    raise ValueError(f"unknown pose convention {convention!r}; one of {', '.join(CONVENTIONS)}")


def quaternion_matrix(position: list[float], orientation: list[float]) -> np.ndarray:
    """4×4 from a position and a unit quaternion ``(x, y, z, w)`` (ROS's order)."""
    x, y, z, w = (float(v) for v in orientation)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not (math.isfinite(n) and n > 1e-9):
        raise ValueError(f"orientation {orientation} is not a rotation (norm {n})")
    x, y, z, w = x / n, y / n, z / n, w / n
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = [float(v) for v in position]
    return m


def _topic(value: str) -> str:
    """A ROS topic name: ``/a/b`` (the leading slash optional), no empty or wildcard parts."""
    name = value.strip()
    parts = name.strip("/").split("/")
    if not name.strip("/") or any(not p or any(c in p for c in "*$?#") for p in parts):
        raise ValueError(f"{value!r} is not a topic name like /cam0/image_raw")
    return "/" + "/".join(parts)


Topic = Annotated[str, Field(min_length=1, max_length=256)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class IntrinsicsSpec(_Strict):
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


class PoseSpec(_Strict):
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
    def _matrix(cls, v):
        if v is None:
            return None
        flat = [float(x) for row in v for x in (row if isinstance(row, list) else [row])]
        if len(flat) != 16 or not all(math.isfinite(x) for x in flat):
            raise ValueError("a 4x4 matrix: 16 finite numbers, row-major (or 4 rows of 4)")
        m = np.asarray(flat).reshape(4, 4)
        if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
            raise ValueError("the last row of a rigid transform is 0 0 0 1")
        r = m[:3, :3]
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0:
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
        if forms[1]:
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
        return self.to_gl(quaternion_matrix(self.position, self.orientation))


class CameraSpec(_Strict):
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
        description="An IP camera or a video instead of a topic: rtsp://host:port/path (H.264 "
                    "and whatever else FFmpeg decodes), or a video file (played in a loop at "
                    "its own rate).")
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
            raise ValueError("give exactly one of image (a ROS topic) or url (rtsp:// or a "
                             "video file)")
        if self.url is not None:
            if self.image_type is not None:
                raise ValueError("image_type is for image topics")
            if self.intrinsics.camera_info is not None:
                raise ValueError("a url camera needs its intrinsics as values (fx, fy, cx, "
                                 "cy, width, height): it has no CameraInfo topic")
            if not self.is_rtsp and (self.listen or self.stamps != "rtcp"):
                raise ValueError("listen and stamps are for rtsp:// urls")
        return self

    @property
    def is_rtsp(self) -> bool:
        return self.url is not None and self.url.lower().startswith("rtsp://")

    @property
    def kind(self) -> str:
        if self.url is not None:
            return "rtsp" if self.is_rtsp else "video"
        return self.image_type or ("compressed" if self.image.endswith("/compressed") else "raw")


class ViewSpec(_Strict):
    """The camera the pipeline renders when no truth camera is named: a static pose and
    intrinsics (as in a camera's entry)."""

    intrinsics: IntrinsicsSpec
    pose: PoseSpec


class SourceSpec(_Strict):
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


class ClockSpec(_Strict):
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
    def _finite(cls, v):
        if v != "auto" and not (math.isfinite(v) and abs(v) < 10 * 365 * 86400):
            raise ValueError("a finite number of seconds, or auto")
        return v


class Rig(_Strict):
    """A rig file. See docs/real-cameras.md."""

    source: SourceSpec = Field(default_factory=SourceSpec)
    cameras: list[CameraSpec] = Field(min_length=1, max_length=257)
    truth: str | None = Field(
        None, description="The camera held out as the ground truth (not trained on; the render "
                          "shows its view and is scored against it). None: renders are made "
                          "but cannot be scored.")
    view: ViewSpec | None = Field(None, description="The rendered view when there is no truth "
                                                    "camera (default: the first camera's).")
    aabb: list[float] = Field(min_length=6, max_length=6,
                              description="The scene box: min x, y, z, then max x, y, z (world "
                                          "units of the poses).")
    size: list[int] | None = Field(
        None, min_length=2, max_length=2,
        description="Working size [width, height]: every frame is resized to it (intrinsics "
                    "scaled). Default: the rendered view's own size.")
    time_scale: float = Field(1.0, gt=0, le=10,
                              description="Sim seconds per wall second of the run: 1 for a real "
                                          "robot; a played dataset's --time-scale.")
    truth_period_ms: float = Field(100.0, gt=0, le=60_000,
                                   description="Sim ms between two truth frames at most (the "
                                               "metrics service pairs a render with the truth "
                                               "frame of its time, or the newest this much "
                                               "older).")
    clock: ClockSpec = Field(default_factory=ClockSpec)
    pose_tolerance_s: float = Field(0.05, gt=0, le=10,
                                    description="A pose topic's message is matched to an image "
                                                "when their stamps differ by at most this.")
    max_image_bytes: int = Field(32 * 1024 * 1024, ge=1024, le=256 * 1024 * 1024,
                                 description="Larger samples are refused before decoding.")
    max_image_pixels: int = Field(2048 * 2048, ge=1, le=8192 * 8192,
                                  description="Larger images (width × height, as declared) are "
                                              "refused before decoding.")

    @field_validator("aabb")
    @classmethod
    def _box(cls, v: list[float]) -> list[float]:
        if not all(math.isfinite(x) for x in v) or any(v[i + 3] <= v[i] for i in range(3)):
            raise ValueError("6 finite numbers, min x y z then max x y z, each min < max")
        return v

    @field_validator("size")
    @classmethod
    def _size(cls, v: list[int] | None) -> list[int] | None:
        if v is not None and not all(8 <= x <= 4096 for x in v):
            raise ValueError("[width, height], each 8..4096 pixels")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> Rig:
        names = [c.name for c in self.cameras]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"cameras: names must differ ({', '.join(dupes)} repeated)")
        topics = [c.image or c.url for c in self.cameras]
        if len(set(topics)) != len(topics):
            raise ValueError("cameras: two cameras share an image topic or url")
        if self.truth is not None:
            if self.truth not in names:
                raise ValueError(f"truth: no camera is named {self.truth!r} (cameras: "
                                 f"{', '.join(names)})")
            cam = self.cameras[names.index(self.truth)]
            if not (cam.pose.static and cam.intrinsics.static):
                raise ValueError(f"truth: the truth camera {self.truth!r} needs a static pose "
                                 "and intrinsics in the file (the render is made from its view "
                                 "before any frame arrives)")
            if self.view is not None:
                raise ValueError("view: the truth camera is the rendered view; give view only "
                                 "without truth")
        elif self.view is None:
            first = self.cameras[0]
            if not (first.pose.static and first.intrinsics.static):
                raise ValueError("view: without a truth camera, give view (a static pose and "
                                 "intrinsics), or give the first camera a static pose and "
                                 "intrinsics")
        if self.view is not None and not (self.view.pose.static and self.view.intrinsics.static):
            raise ValueError("view: needs a static pose and intrinsics, not topics")
        if len(self.train) < 1:
            raise ValueError("cameras: at least one camera besides the truth camera")
        if len(self.train) > 256:
            raise ValueError("cameras: at most 256 training cameras")
        return self

    # ---------------------------------------------------------------- derived
    @property
    def train(self) -> list[CameraSpec]:
        """The training cameras, ids 1..N in file order."""
        return [c for c in self.cameras if c.name != self.truth]

    def ids(self) -> dict[str, int]:
        """Camera name → id on the wire: the truth camera 0, the others 1..N in file order."""
        out = {c.name: i for i, c in enumerate(self.train, start=1)}
        if self.truth is not None:
            out[self.truth] = TRUTH_ID
        return out

    def camera(self, name: str) -> CameraSpec:
        return next(c for c in self.cameras if c.name == name)

    def _view_spec(self) -> tuple[IntrinsicsSpec, PoseSpec]:
        if self.truth is not None:
            cam = self.camera(self.truth)
            return cam.intrinsics, cam.pose
        if self.view is not None:
            return self.view.intrinsics, self.view.pose
        return self.cameras[0].intrinsics, self.cameras[0].pose

    @property
    def working_size(self) -> tuple[int, int]:
        """(width, height) of every frame on the pipeline's wire."""
        if self.size is not None:
            return int(self.size[0]), int(self.size[1])
        intr, _ = self._view_spec()
        return int(intr.width), int(intr.height)

    def view_camera(self) -> Camera:
        """The rendered (held-out) camera at the working size."""
        intr, pose = self._view_spec()
        return scaled_camera(pose.static_c2w(), intr.fx, intr.fy, intr.cx, intr.cy,
                             (intr.width, intr.height), self.working_size)

    @property
    def scene_box(self) -> np.ndarray:
        return np.asarray(self.aabb, dtype=np.float64)


def scaled_camera(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                  native: tuple[int, int], size: tuple[int, int]) -> Camera:
    """A camera whose intrinsics (for an image of ``native`` size) are scaled to ``size``."""
    sx, sy = size[0] / native[0], size[1] / native[1]
    return Camera(c2w=c2w, fx=fx * sx, fy=fy * sy, cx=cx * sx, cy=cy * sy,
                  width=size[0], height=size[1])


def _where(loc: tuple) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("function-after", "function-before") or "[" in str(part):
            continue
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def rig_from_dict(doc: object, source: str = "rig") -> Rig:
    """Validate a parsed rig document; :class:`RigError` names each bad field."""
    if not isinstance(doc, dict):
        raise RigError(f"{source}: a rig file is a mapping (cameras:, aabb:, …), got "
                       f"{type(doc).__name__}")
    try:
        return Rig.model_validate(doc)
    except ValidationError as err:
        lines = []
        for e in err.errors():
            msg = e["msg"].removeprefix("Value error, ")
            lines.append(f"{source}: {_where(e['loc'])}: {msg}")
        raise RigError("\n".join(lines)) from None


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig file (``.json``, else YAML)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise RigError(f"{path}: cannot read the rig file ({err.strerror or err})") from None
    try:
        if path.suffix.lower() == ".json":
            doc = json.loads(text)
        else:
            import yaml

            doc = yaml.safe_load(text)
    except Exception as err:  # yaml.YAMLError, json.JSONDecodeError: the parser's own words
        raise RigError(f"{path}: not valid {'JSON' if path.suffix == '.json' else 'YAML'} "
                       f"({str(err).splitlines()[0]})") from None
    return rig_from_dict(doc, str(path))
