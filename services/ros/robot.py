"""A pure-Python robot: plays a dataset aoi3d reads (the turbine, a D-NeRF or DyNeRF folder) as
ROS 2 cameras on Zenoh — images, camera info and poses, in either key format — at any rate and
time scale. ``aoi3d ros2 publish`` runs it; users test their setup with it, the tests use it.

Every period (scene ms) each camera publishes, stamped with the robot's clock (wall time plus
``clock_offset_s``, to stand for a robot whose clock is off): its pose (``PoseStamped`` or
``Odometry`` in the camera optical frame, when poses go on a topic), its ``CameraInfo`` (when
intrinsics go on a topic), then its image (``Image`` rgb8/bgr8, or ``CompressedImage``
jpeg/png). On rmw_zenoh keys each sample carries the attachment (sequence number per
publisher, source time, a 16-byte publisher id). The held-out camera (the dataset's novel
view) is published too, as ``cam00``: the rig's truth camera. :func:`rig_document` writes the
rig file that reads exactly what is published.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.ros.encode import (
    camera_info_msg,
    compressed_msg,
    image_msg,
    odometry_msg,
    pose_stamped_msg,
)
from services.ros.graph import node_tokens
from services.ros.keys import KeyFormat
from services.ros.publisher import RosPublisher
from services.ros.types import CAMERA_INFO, COMPRESSED, HUMBLE_HASH, IMAGE, ODOMETRY, POSE_STAMPED

__all__ = ["DISTROS", "IMAGE_FORMATS", "OPTICAL", "ROBOT_NODE", "PublishConfig", "Robot",
           "camera_ids", "camera_name", "rig_document", "source_document"]

IMAGE_FORMATS = ("rgb8", "bgr8", "jpeg", "png")
DISTROS = {"jazzy": None, "humble": HUMBLE_HASH}
"""The type hash each distribution's rmw_zenoh puts in its keys (None: the type's RIHS01)."""
OPTICAL = np.diag([1.0, -1.0, -1.0, 1.0])
"""OpenGL camera axes → the ROS optical frame (x right, y down, z forward)."""
ROBOT_NODE = "aoi3d_robot"
"""The robot's node name in the ROS graph (rmw_zenoh keys)."""


@dataclass
class PublishConfig:
    """What the robot publishes and how."""

    dataset: Path
    format: str = "rmw_zenoh"
    domain_id: int = 0
    distro: str = "jazzy"
    namespace: str = ""
    connect: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    period_ms: float = 30.0
    """Scene ms between two frames of a camera (the camera emulator's period C)."""
    time_scale: float = 1.0
    """Scene seconds per wall second: 0.1 plays the scene ten times slower."""
    cameras: int | None = None
    """Training cameras 1..N of the dataset (default all)."""
    image: str = "rgb8"
    intrinsics: str = "topic"
    """``topic`` (CameraInfo) or ``file`` (values in the rig file)."""
    pose: str = "topic"
    """``topic`` (PoseStamped), ``odometry`` (Odometry) or ``file`` (static in the rig)."""
    truth: bool = True
    clock_offset_s: float = 0.0
    duration_s: float | None = None
    frames: int | None = None
    """Stop after this many periods (default: run for duration_s, else until stopped)."""
    epoch_s: float | None = None
    """Phase-lock to a pipeline's clock (its epoch, Unix s, e.g. the ingest's GET /status
    ``time.epoch_s``): frame k at wall epoch + k·period / time scale showing scene time
    k·period, as the camera emulator does. Default: the robot's own start."""

    def __post_init__(self) -> None:
        checks = [(self.format in ("rmw_zenoh", "bridge"), "format: rmw_zenoh or bridge"),
                  (self.distro in DISTROS, f"distro: one of {', '.join(DISTROS)}"),
                  (self.image in IMAGE_FORMATS, f"image: one of {', '.join(IMAGE_FORMATS)}"),
                  (self.intrinsics in ("topic", "file"), "intrinsics: topic or file"),
                  (self.pose in ("topic", "odometry", "file"), "pose: topic, odometry or file"),
                  (math.isfinite(self.period_ms) and self.period_ms >= 1, "period_ms >= 1"),
                  (math.isfinite(self.time_scale) and 0 < self.time_scale <= 10,
                   "time_scale in (0, 10]"),
                  (math.isfinite(self.clock_offset_s), "clock_offset_s finite")]
        for ok, what in checks:
            if not ok:
                raise ValueError(what)
        if self.format == "rmw_zenoh" and self.namespace:
            raise ValueError("namespace: the bridge's (rmw_zenoh keys start with the domain)")


def camera_name(camera_id: int) -> str:
    return f"cam{camera_id:02d}"


def _topics(cfg: PublishConfig, camera_id: int) -> dict[str, str]:
    name = camera_name(camera_id)
    image = f"/{name}/image_raw" + ("/compressed" if cfg.image in ("jpeg", "png") else "")
    return {"image": image, "camera_info": f"/{name}/camera_info",
            "pose": f"/{name}/{'odom' if cfg.pose == 'odometry' else 'pose'}"}


def camera_ids(cfg: PublishConfig, ds) -> list[int]:
    """The dataset's cameras the robot publishes: the held-out one (with ``truth``), then the
    training cameras 1..N."""
    train = sorted(int(i) for i in ds.train_ids)
    n = len(train) if cfg.cameras is None else cfg.cameras
    if not 1 <= n <= len(train):
        raise ValueError(f"cameras: 1..{len(train)} (the dataset's training cameras), got {n}")
    return ([int(ds.heldout_id)] if cfg.truth else []) + train[:n]


def source_document(fmt: str, domain_id: int, namespace: str) -> dict:
    """A rig file's ``source``: the key format with its domain id (rmw_zenoh) or namespace
    (the bridge)."""
    return ({"format": fmt, "domain_id": domain_id} if fmt == "rmw_zenoh"
            else {"format": fmt, "namespace": namespace})


def rig_document(cfg: PublishConfig, ds) -> dict:
    """The rig file (a plain dict, to dump as YAML or JSON) that reads what ``cfg`` publishes."""
    source = source_document(cfg.format, cfg.domain_id, cfg.namespace)
    cams = []
    for n in camera_ids(cfg, ds):
        c = ds.cameras[n]
        topics = _topics(cfg, n)
        if cfg.intrinsics == "topic":
            intr: dict = {"camera_info": topics["camera_info"]}
        else:
            intr = {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width,
                    "height": c.height}
        is_truth = cfg.truth and n == ds.heldout_id
        if cfg.pose == "file" or is_truth:
            pose: dict = {"c2w": [float(x) for x in np.asarray(c.c2w).ravel()],
                          "convention": "opengl"}
        else:
            pose = {"topic": topics["pose"],
                    "type": "Odometry" if cfg.pose == "odometry" else "PoseStamped",
                    "convention": "optical"}
        if is_truth:  # the rendered view: static values in the file
            intr = {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width,
                    "height": c.height}
        cams.append({"name": camera_name(n), "image": topics["image"], "intrinsics": intr,
                     "pose": pose})
    doc = {"source": source, "cameras": cams,
           "aabb": [float(x) for x in np.asarray(ds.aabb).ravel()],
           "size": [int(ds.cameras[0].width), int(ds.cameras[0].height)],
           "time_scale": cfg.time_scale,
           "truth_period_ms": cfg.period_ms}
    if cfg.truth:
        doc["truth"] = camera_name(int(ds.heldout_id))
    return doc


class Robot:
    """The robot: ``put(key, payload, attachment)`` publishes one sample (a Zenoh session's put,
    or a test's bus). :meth:`run` plays until ``stop`` is set, the frames or the duration."""

    def __init__(self, cfg: PublishConfig, put: Callable[[str, bytes, bytes | None], None],
                 dataset=None, clock: Callable[[], float] = time.time) -> None:
        from aoi3d.scene import open_dataset

        self.cfg = cfg
        self.ds = dataset if dataset is not None else open_dataset(cfg.dataset)
        self._put = put
        self._clock = clock
        fmt = KeyFormat(cfg.format, cfg.domain_id, cfg.namespace)
        hash_ = DISTROS[cfg.distro]
        image_type = COMPRESSED if cfg.image in ("jpeg", "png") else IMAGE
        pose_type = ODOMETRY if cfg.pose == "odometry" else POSE_STAMPED
        self.ids = camera_ids(cfg, self.ds)
        self._pubs: dict[int, dict[str, RosPublisher]] = {}
        for n in self.ids:
            t = _topics(cfg, n)
            pubs = {"image": RosPublisher(fmt, t["image"], image_type, hash_)}
            if cfg.intrinsics == "topic":
                pubs["camera_info"] = RosPublisher(fmt, t["camera_info"], CAMERA_INFO, hash_)
            if cfg.pose != "file":
                pubs["pose"] = RosPublisher(fmt, t["pose"], pose_type, hash_)
            self._pubs[n] = pubs
        self.frames_sent = 0
        self.periods = 0
        self.skipped = 0

    def keys(self) -> list[str]:
        return [p.key for pubs in self._pubs.values() for p in pubs.values()]

    def tokens(self, session: str) -> list[str]:
        """The ROS graph's liveliness tokens of the robot on rmw_zenoh keys (none for the
        bridge, whose DDS side announces its own): its node, then each publisher, so that
        ``ros2 node list`` / ``ros2 topic list`` on rmw_zenoh and the ingest's /status see it.
        ``session``: the Zenoh session's id, as rmw_zenoh puts it."""
        cfg = self.cfg
        if cfg.format != "rmw_zenoh":
            return []
        return node_tokens(cfg.domain_id, session, ROBOT_NODE,
                               [(p.topic, p.ros_type) for n in self.ids
                                for p in self._pubs[n].values()], DISTROS[cfg.distro])

    def prepare_frame(self, scene_ms: float, stamp: float) -> list[tuple[RosPublisher, bytes]]:
        """Every camera's samples of the frame shown at ``scene_ms``, stamped ``stamp``, encoded
        (pose, camera info, then image, camera by camera) and not yet sent."""
        cfg, ds = self.cfg, self.ds
        index = ds.frame_index(scene_ms)
        out: list[tuple[RosPublisher, bytes]] = []
        for n in self.ids:
            c, pubs, name = ds.cameras[n], self._pubs[n], camera_name(n)
            if "pose" in pubs:
                m = np.asarray(c.c2w) @ OPTICAL
                msg = (odometry_msg(stamp, "world", name, m) if cfg.pose == "odometry"
                       else pose_stamped_msg(stamp, "world", m))
                out.append((pubs["pose"], pubs["pose"].encode(msg)))
            if "camera_info" in pubs:
                msg = camera_info_msg(stamp, name, c.fx, c.fy, c.cx, c.cy, c.width,
                                          c.height)
                out.append((pubs["camera_info"], pubs["camera_info"].encode(msg)))
            rgb = ds.frame(n, index)
            if cfg.image in ("jpeg", "png"):
                msg = compressed_msg(stamp, name, rgb, cfg.image)
            else:
                msg = image_msg(stamp, name, rgb, cfg.image)
            out.append((pubs["image"], pubs["image"].encode(msg)))
        return out

    def send(self, prepared: list[tuple[RosPublisher, bytes]]) -> None:
        """Publish prepared samples, each with its attachment of this moment."""
        for pub, payload in prepared:
            robot_ns = int((self._clock() + self.cfg.clock_offset_s) * 1e9)
            self._put(*pub.sample(payload, robot_ns))
            if pub.ros_type in (IMAGE, COMPRESSED):
                self.frames_sent += 1

    def publish_frame(self, scene_ms: float, stamp: float) -> None:
        """Every camera's samples of the frame shown at ``scene_ms``, stamped ``stamp``."""
        self.send(self.prepare_frame(scene_ms, stamp))

    def run(self, stop: threading.Event | None = None) -> None:
        """Play: frame k shows scene time k·period at wall start + k·period / time scale (a
        robot that falls behind publishes the newest due frame, counting the skipped).

        Each frame is encoded before it is due and its cameras are sent together at its time,
        as cameras that capture at once do: encoding 19 images one after another at the due
        time made the last camera's frame reach the edge ~60 ms (wall) after its stamp, an
        extra age the pure-Python robot added, not the link."""
        cfg = self.cfg
        stop = stop or threading.Event()
        period_wall_s = cfg.period_ms / 1000.0 / cfg.time_scale
        now = self._clock()
        if cfg.epoch_s is None:
            start, k = now, 0
        else:  # on the pipeline's grid: the first frame due from now on
            start = cfg.epoch_s
            k = max(0, math.ceil((now - start) / period_wall_s))
        first = start + k * period_wall_s
        while not stop.is_set():
            if cfg.frames is not None and self.periods >= cfg.frames:
                break
            late = math.floor((self._clock() - start) / period_wall_s)
            if late > k:  # behind: on to the newest frame due, before encoding anything
                self.skipped += late - k
                k = late
            due = start + k * period_wall_s
            if cfg.duration_s is not None and due - first >= cfg.duration_s:
                break
            prepared = self.prepare_frame(k * cfg.period_ms, due + cfg.clock_offset_s)
            wait = due - self._clock()
            if wait > 0 and stop.wait(wait):
                break
            self.send(prepared)
            self.periods += 1
            k += 1
