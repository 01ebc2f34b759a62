"""A recording played into a running pipeline as its cameras (``aoi3d replay --live``).

The recorded frames of one site — every delivered frame and the truth frames, with their
pixels, poses and intrinsics — go out as ROS 2 cameras on Zenoh, exactly as the test robot's
(:mod:`services.ros.robot`) do: per frame its ``PoseStamped`` (the frame's own pose: a
moving camera stays moving), its ``CameraInfo`` and its image as a ``CompressedImage`` holding
the recorded PNG bytes (lossless, not re-encoded). A pipeline started with ``aoi3d up --rig``
on the rig file :func:`rig_document` writes takes them in through its ingest, so every service
— scheduler, policies, pool, metrics, ledger, console, recorder — meets the recording as it
would meet real cameras.

**Time.** A frame generated at g ms of the recording's clock is stamped and sent at wall
``start + (g + shift − g0) / 1000 / time_scale``: the recording's spacing, scaled. With
``epoch_s`` (the pipeline's epoch) the recording is shifted by whole periods onto the
pipeline's clock, keeping its phase on the decision grid: the first frame lands on the first
time still to come of the pipeline's clock that is a whole number of ``period_ms`` away from
its recorded time, each later one where its recorded offset puts it.

**What it is not.** A recording holds the frames that reached the edge: a frame the recorded
link lost is not played (the live pipeline sees that camera's older frame for longer), and
the live link — the real one and, with ``aoi3d up --delay``, the emulated one on top — delays
the played frames again. So a live replay re-runs the recorded *generations*, not the recorded
arrivals; ``aoi3d replay`` (virtual clock) is the one that reproduces decisions exactly.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services import ros
from services.kit.codec import camera_from_pb, png_bytes
from services.kit.pb import aoi3d_pb2 as pb
from services.ros.publisher import RosPublisher
from services.ros.robot import OPTICAL, source_document

__all__ = ["PlayConfig", "Player", "rig_document"]



@dataclass
class PlayConfig:
    format: str = "rmw_zenoh"
    domain_id: int = 0
    namespace: str = ""
    time_scale: float = 1.0
    epoch_s: float | None = None
    period_ms: float = 30.0
    """The grid a phase-locked play keeps the recording's phase on (the camera period C)."""

    def __post_init__(self) -> None:
        if self.format not in ("rmw_zenoh", "bridge"):
            raise ValueError("format: rmw_zenoh or bridge")
        if not (math.isfinite(self.time_scale) and 0 < self.time_scale <= 10):
            raise ValueError("time_scale in (0, 10]")
        if not (math.isfinite(self.period_ms) and self.period_ms >= 1):
            raise ValueError("period_ms >= 1")
        if self.format == "rmw_zenoh" and self.namespace:
            raise ValueError("namespace: the bridge's (rmw_zenoh keys start with the domain)")


PLAYER_NODE = "aoi3d_player"
"""The player's node name in the ROS graph (rmw_zenoh keys)."""


def _name(camera_id: int) -> str:
    return f"cam{camera_id:02d}"


def _topics(camera_id: int) -> dict[str, str]:
    name = _name(camera_id)
    return {"image": f"/{name}/image_raw/compressed", "camera_info": f"/{name}/camera_info",
            "pose": f"/{name}/pose"}


def rig_document(frames: dict[int, list[pb.Frame]], cfg: PlayConfig,
                 aabb: np.ndarray) -> dict:
    """The rig file that reads what :class:`Player` publishes of ``frames`` (camera id → its
    frames; 0 is the truth camera, rendered from its first frame's pose and intrinsics)."""
    source = source_document(cfg.format, cfg.domain_id, cfg.namespace)
    cams = []
    for n in sorted(frames):
        topics = _topics(n)
        first = frames[n][0]
        if n == 0:
            c = camera_from_pb(first.pose, first.intrinsics)
            cams.append({"name": _name(n), "image": topics["image"],
                         "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                                        "width": c.width, "height": c.height},
                         "pose": {"c2w": [float(x) for x in np.asarray(c.c2w).ravel()],
                                  "convention": "opengl"}})
        else:
            cams.append({"name": _name(n), "image": topics["image"],
                         "intrinsics": {"camera_info": topics["camera_info"]},
                         "pose": {"topic": topics["pose"], "type": "PoseStamped",
                                  "convention": "optical"}})
    first = frames[min(frames)][0]
    doc = {"source": source, "cameras": cams,
           "aabb": [float(x) for x in np.asarray(aabb).ravel()],
           "size": [int(first.intrinsics.width), int(first.intrinsics.height)],
           "time_scale": cfg.time_scale, "truth_period_ms": cfg.period_ms}
    if 0 in frames:
        doc["truth"] = _name(0)
    return doc


class Player:
    """Plays ``frames`` (camera id → its recorded frames) through ``put(key, payload,
    attachment)``; :meth:`run` until ``stop`` or the last frame."""

    def __init__(self, frames: dict[int, list[pb.Frame]], cfg: PlayConfig,
                 put: Callable[[str, bytes, bytes | None], None],
                 clock: Callable[[], float] = time.time,
                 pixels: Callable[[int, pb.Frame], pb.Frame] | None = None) -> None:
        """``pixels(camera, frame)``: the frame with its pixels, read when it is sent (a
        recording played from its file: memory holds the frames' metadata only); default:
        the frames carry them."""
        self.cfg = cfg
        self._pixels = pixels or (lambda _n, fr: fr)
        self._put = put
        self._clock = clock
        fmt = ros.KeyFormat(cfg.format, cfg.domain_id, cfg.namespace)
        self._pubs: dict[tuple[int, str], RosPublisher] = {}
        types = {"image": ros.COMPRESSED, "camera_info": ros.CAMERA_INFO,
                 "pose": ros.POSE_STAMPED}
        for n in frames:
            for kind, topic in _topics(n).items():
                if n != 0 or kind == "image":  # the truth camera's pose and intrinsics: file
                    self._pubs[(n, kind)] = RosPublisher(fmt, topic, types[kind], None)
        self.order = sorted(((fr.generation_ms, n, fr) for n, lst in frames.items()
                             for fr in lst), key=lambda x: (x[0], x[1]))
        self.sent = 0
        self.shift_ms = 0.0

    def keys(self) -> list[str]:
        return [p.key for p in self._pubs.values()]

    def tokens(self, session: str) -> list[str]:
        """The player's node and publishers in the ROS graph (rmw_zenoh keys; none for the
        bridge), as :meth:`services.ros.robot.Robot.tokens`."""
        if self.cfg.format != "rmw_zenoh":
            return []
        return ros.node_tokens(self.cfg.domain_id, session, PLAYER_NODE,
                               [(p.topic, p.ros_type) for p in self._pubs.values()])

    def _prepare(self, n: int, fr: pb.Frame, stamp: float) -> list[tuple[str, bytes]]:
        """The frame's samples (pose, camera info, image), CDR-encoded."""
        name = _name(n)
        out: list[tuple[str, object]] = []
        if (n, "pose") in self._pubs:
            m = np.asarray(fr.pose.c2w, dtype=np.float64).reshape(4, 4) @ OPTICAL
            out.append(("pose", ros.pose_stamped_msg(stamp, "world", m)))
        if (n, "camera_info") in self._pubs:
            i = fr.intrinsics
            out.append(("camera_info", ros.camera_info_msg(stamp, name, i.fx, i.fy, i.cx, i.cy,
                                                           i.width, i.height)))
        png = png_bytes(self._pixels(n, fr).image)
        out.append(("image", ros.compressed_bytes_msg(stamp, name, png, "png")))
        return [(kind, self._pubs[(n, kind)].encode(msg)) for kind, msg in out]

    def run(self, stop: threading.Event | None = None) -> None:
        stop = stop or threading.Event()
        if not self.order:
            return
        cfg, g0 = self.cfg, self.order[0][0]
        scale = 1000.0 * cfg.time_scale
        now = self._clock()
        if cfg.epoch_s is None:
            start = now
        else:  # the first frame on the first grid time still to come of the pipeline's clock
            sim_now = (now - cfg.epoch_s) * scale
            first = g0 + math.ceil((sim_now - g0) / cfg.period_ms) * cfg.period_ms
            self.shift_ms = first - g0
            start = cfg.epoch_s + first / scale
        for gen, group in itertools.groupby(self.order, key=lambda x: x[0]):
            due = start + (gen - g0) / scale
            # every camera's frame of this time encoded before it, all sent at it
            prepared = [(n, self._prepare(n, fr, due)) for _, n, fr in group]
            wait = due - self._clock()
            if wait > 0 and stop.wait(wait):
                return
            if stop.is_set():
                return
            for n, samples in prepared:
                for kind, payload in samples:
                    self._put(*self._pubs[(n, kind)].sample(payload, int(self._clock() * 1e9)))
                self.sent += 1
