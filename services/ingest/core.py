"""The ingest core: a ROS 2 sample (key, CDR bytes, attachment) and its receipt time in, the
pipeline's :class:`pb.Frame` out — or :class:`Rejected` with its reason.

No bus, no threads, no metrics library: the runtime (:mod:`services.ingest.worker`) feeds it
from its one thread and publishes what it returns; tests drive it directly.

What a camera of the rig file (:mod:`aoi3d.rigfile`) sends:

- its **image** (``sensor_msgs/Image`` raw, or ``CompressedImage`` jpeg/png) becomes a Frame:
  resized to the working size, with the pose and intrinsics in force at its stamp, published
  where the camera emulator's frames go — the truth camera's on ``truth/frame``, the others on
  ``edge/<n>/frame`` stamped delivered at their receipt (the link is real: the network
  emulator steps aside), or on ``cam/<n>/frame`` when emulated delay is asked for on top (the
  network service then delays each frame from its receipt, ``send_ms``);
- its **CameraInfo** (when the rig names one) sets its intrinsics from then on;
- its **pose** topic (``PoseStamped`` / ``Odometry``) feeds a short history; an image takes the
  pose whose stamp is nearest its own, within the tolerance.

Time (docs/real-cameras.md): a frame's generation time is its ``header.stamp`` − the camera's
clock offset (robot − edge) in force, its arrival the receipt at the edge; both go on the
pipeline's sim clock, ``sim_ms = (wall_s − epoch_s) × time_scale × 1000``. The offset is
measured per camera from every sample (the 90th percentile of stamp − receipt over the last
ones: the publisher's source time from the rmw_zenoh attachment when there is one), shown, and used
when the rig says ``offset_s: auto``. Sequence gaps in the attachment count as losses.
"""

from __future__ import annotations

import io
import math
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np

from aoi3d.rigfile import TRUTH_ID, CameraSpec, Rig, scaled_camera
from services import ros
from services.kit.codec import camera_to_pb
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected

__all__ = ["WIRE_ENCODINGS", "CameraState", "IngestCore", "Published", "Route"]

WIRE_ENCODINGS = ("png", "raw")
OFFSET_WINDOW = 64
"""Samples per camera over which the clock offset is estimated."""
POSES_KEPT = 256
"""Poses per camera kept for matching (8 s of a 30 Hz odometry)."""
HOLD_S = 0.5
"""Wall seconds an image waits for a pose (or a first CameraInfo) that may still come: topics
travel on separate Zenoh subscriptions, so an image can overtake the pose of its stamp."""
STREAMS_KEPT = 16
"""Publishers per camera whose sequence numbers are followed."""
HELD_PER_CAMERA = 8
"""Images of one camera waiting at most (an older one is then refused)."""
_KINDS = ("image", "camera_info", "pose")
GRAPH_MAX = 4096
"""Entities of the ROS graph kept at most (a token beyond is counted, not kept)."""


class _Wait(Exception):
    """An image whose pose or intrinsics may still come: held, not refused (yet)."""


@dataclass(frozen=True)
class Route:
    """One subscription: a topic of a kind (image, camera_info, pose), the cameras it feeds."""

    kind: str
    topic: str
    ros_type: str
    key_expr: str
    cameras: tuple[str, ...]


@dataclass(frozen=True)
class Published:
    """A frame to publish on the pipeline's bus."""

    key: str
    payload: bytes
    camera: str
    camera_id: int
    generation_ms: float
    receipt_ms: float
    age_s: float
    """Receipt − generation, in wall seconds (after the offset in force)."""


@dataclass
class CameraState:
    """One camera's live state and counts (read by the status and the metrics collector)."""

    spec: CameraSpec
    camera_id: int
    intrinsics: ros.Intrinsics | None = None
    poses: deque = field(default_factory=lambda: deque(maxlen=POSES_KEPT))
    offsets: deque = field(default_factory=lambda: deque(maxlen=OFFSET_WINDOW))
    last_seq: OrderedDict[tuple[str, bytes], int] = field(default_factory=OrderedDict)
    """The last sequence number of each publisher (topic, id): at most :data:`STREAMS_KEPT`,
    the least recently heard forgotten (a sender inventing ids cannot grow it)."""
    own_seq: int = 0
    received: Counter = field(default_factory=Counter)
    """Samples received by kind."""
    rejected: Counter = field(default_factory=Counter)
    """Samples rejected by reason."""
    published: int = 0
    lost: int = 0
    """Samples never received: gaps in the rmw_zenoh sequence numbers."""
    clamped: int = 0
    """Frames stamped ahead of their receipt (within the tolerance): generation = receipt."""
    last_stamp_s: float = math.nan
    last_receipt_s: float = math.nan
    last_age_s: float = math.nan
    publish_delay_s: float = math.nan
    """Source time (the rmw_zenoh attachment) − stamp of the last image: the robot's own
    delay between capture and publish."""
    ages: deque = field(default_factory=lambda: deque(maxlen=OFFSET_WINDOW))
    held: list = field(default_factory=list)
    """Images waiting for their pose or intrinsics: (deadline wall s, RGB, stamp, attachment,
    receipt wall s)."""

    @property
    def offset_estimate_s(self) -> float:
        """Robot clock − edge clock, estimated: the 90th percentile of (robot time − receipt)
        over the last samples — the offset if the fastest tenth of them took no time (NaN
        before any). Not the largest: a few samples stamped wrong cannot move it."""
        if not self.offsets:
            return math.nan
        ordered = sorted(self.offsets)
        return ordered[min(len(ordered) - 1, int(0.9 * len(ordered)))]

    @property
    def role(self) -> str:
        return "truth" if self.camera_id == TRUTH_ID else "train"


class IngestCore:
    """See the module docstring. Not thread-safe: the runtime serialises calls.

    ``epoch_s``/``time_scale``: the run's sim clock; ``through_network``: publish on the
    camera keys for the network emulator to delay (else on the edge keys, delivered at
    receipt); ``wire_encoding``: ``png`` or ``raw`` images on the pipeline's wire;
    ``key_format``: the keys samples arrive on, when not the rig's source (a rosbag's topics:
    the bridge's)."""

    def __init__(self, rig: Rig, keys: Keys, *, epoch_s: float, time_scale: float,
                 through_network: bool = False, wire_encoding: str = "png",
                 key_format: ros.KeyFormat | None = None) -> None:
        if wire_encoding not in WIRE_ENCODINGS:
            raise ValueError(f"wire encoding {wire_encoding!r}: one of {WIRE_ENCODINGS}")
        self.rig = rig
        self.keys = keys
        self.epoch_s = float(epoch_s)
        self.time_scale = float(time_scale)
        self.through_network = through_network
        self.wire_encoding = wire_encoding
        src = rig.source
        self.format = key_format or ros.KeyFormat(src.format, src.domain_id, src.prefix)
        self.size = rig.working_size
        ids = rig.ids()
        self.cameras = {c.name: CameraState(c, ids[c.name]) for c in rig.cameras}
        self.routes = self._routes()
        self.expired: list[tuple[str, Rejected]] = []
        self.graph: dict[str, ros.GraphEntity] = {}
        """The ROS graph (rmw_zenoh's liveliness tokens of the rig's domain), by token."""
        self.graph_unparsed = 0
        self.graph_dropped = 0

    # ------------------------------------------------------------------ subscriptions
    def _routes(self) -> list[Route]:
        by_topic: dict[tuple[str, str, str], list[str]] = {}
        for c in self.rig.cameras:
            if c.image is not None:  # (a url camera is read by the runtime: on_video)
                image_type = ros.COMPRESSED if c.kind == "compressed" else ros.IMAGE
                by_topic.setdefault(("image", c.image, image_type), []).append(c.name)
            if c.intrinsics.camera_info is not None:
                by_topic.setdefault(("camera_info", c.intrinsics.camera_info, ros.CAMERA_INFO),
                                    []).append(c.name)
            if c.pose.topic is not None:
                pose_type = ros.POSE_STAMPED if c.pose.type == "PoseStamped" else ros.ODOMETRY
                by_topic.setdefault(("pose", c.pose.topic, pose_type), []).append(c.name)
        kinds = {}
        for (kind, topic, _), _names in by_topic.items():
            other = kinds.setdefault(topic, kind)
            if other != kind:
                raise ValueError(f"topic {topic} is both an {other} and a {kind} topic")
        return [Route(kind, topic, t, self.format.subscription(topic, t), tuple(names))
                for (kind, topic, t), names in by_topic.items()]

    # ------------------------------------------------------------------ the ROS graph
    @property
    def graph_key(self) -> str | None:
        """The liveliness tokens to watch: the rig's domain (rmw_zenoh; the bridge has
        none)."""
        if self.format.format != "rmw_zenoh":
            return None
        return f"{ros.LIVELINESS_SPACE}/{self.format.domain_id}/**"

    def on_liveliness(self, key: str, alive: bool) -> None:
        """A token of the ROS graph appeared (``alive``) or vanished; one in another layout is
        counted (``graph_unparsed``) and otherwise left alone."""
        if not alive:
            self.graph.pop(key, None)
            return
        try:
            entity = ros.parse_liveliness(key)
        except ValueError:
            self.graph_unparsed += 1
            return
        if key not in self.graph and len(self.graph) >= GRAPH_MAX:
            self.graph_dropped += 1  # a flood of tokens cannot grow the ingest without bound
            return
        self.graph[key] = entity

    def topic_publishers(self) -> list[dict]:
        """Per subscribed topic: the live publishers of the rig's type, and the types others
        publish on it (a rig that names Image where the camera sends CompressedImage)."""
        out = []
        pubs = [e for e in self.graph.values() if e.kind == "publisher"]
        for r in self.routes:
            topic = "/" + r.topic.strip("/")
            mine = [e for e in pubs if e.topic == topic]
            same = [e for e in mine if e.ros_type == r.ros_type]
            out.append({"topic": topic, "type": r.ros_type, "publishers": len(same),
                        "nodes": sorted({e.namespace.rstrip("/") + "/" + e.node
                                         for e in same}),
                        "other_types": sorted({e.ros_type or "?" for e in mine} - {r.ros_type})})
        return out

    def graph_hint(self) -> str:
        """Why no frame may have come, from the graph: the rig's image topics nobody
        publishes (empty without a graph, or when each has a publisher)."""
        if self.graph_key is None or not self.graph:
            return ""
        missing = [t for t in self.topic_publishers()
                   if t["publishers"] == 0 and t["type"] in (ros.IMAGE, ros.COMPRESSED)]
        if not missing:
            return ""
        what = ", ".join(t["topic"] + (f" (published as {', '.join(t['other_types'])})"
                                       if t["other_types"] else "") for t in missing[:3])
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        return f"no publisher of the rig's type in the ROS graph on {what}{more}"

    # ------------------------------------------------------------------ time
    def sim_ms(self, wall_s: float) -> float:
        return (wall_s - self.epoch_s) * self.time_scale * 1000.0

    def offset_in_force(self, state: CameraState) -> float:
        off = self.rig.clock.offset_s
        if off == "auto":
            est = state.offset_estimate_s
            return 0.0 if math.isnan(est) else est
        return float(off)

    # ------------------------------------------------------------------ samples
    def on_sample(self, route: Route, key: str, payload: bytes, attachment: bytes | None,
                  receipt_s: float) -> list[Published]:
        """One sample of ``route`` received at wall time ``receipt_s``: the frames to publish
        (one per camera an image topic feeds; none for camera info and poses).
        :class:`Rejected` (counted per camera) when it cannot be used."""
        states = [self.cameras[name] for name in route.cameras]
        for s in states:
            s.received[route.kind] += 1
        try:
            return self._sample(route, states, key, payload, attachment, receipt_s)
        except Rejected as err:
            for s in states:
                s.rejected[err.reason] += 1
            raise

    def _sample(self, route: Route, states: list[CameraState], key: str, payload: bytes,
                attachment: bytes | None, receipt_s: float) -> list[Published]:
        att = ros.parse_attachment(attachment) if self.format.attached else None
        if att is not None and route.kind == "image":  # a sample received, whatever it holds
            self._sequence(states, route.topic, att)
        self.format.check_key(key, route.ros_type)
        cap = self.rig.max_image_bytes if route.kind == "image" else 1024 * 1024
        msg = ros.decode_cdr(payload, route.ros_type, cap)
        stamp = ros.stamp_s(msg.header)
        if not stamp > 0:
            raise Rejected("stamp_invalid", f"stamp {stamp} (a publisher that does not stamp)")
        robot_now = att.source_ns * 1e-9 if att is not None and att.source_ns > 0 else stamp
        for s in states:  # measured from every sample, whatever becomes of it
            s.offsets.append(robot_now - receipt_s)
        if route.kind == "camera_info":
            intr = ros.camera_info(msg)
            for s in states:
                s.intrinsics = intr
            return self._retry(states, receipt_s)
        if route.kind == "pose":
            m = ros.pose_matrix(msg, route.ros_type)
            for s in states:
                c2w = s.spec.pose.to_gl(m)
                s.poses.append((stamp, c2w))
            return self._retry(states, receipt_s)
        for s in states:
            self._stamp_ms(s, stamp, receipt_s)  # refused before the pixels are decoded
        rgb = ros.image_rgb(msg, route.ros_type, self.rig.max_image_pixels)
        return self._images(states, rgb, stamp, att, receipt_s)

    def on_video(self, name: str, rgb: np.ndarray, stamp_s: float,
                 receipt_s: float) -> list[Published]:
        """A decoded frame of a url camera (rtsp:// or a video file; the runtime reads them:
        :mod:`services.ingest.video`) generated at ``stamp_s`` (wall s, the sender's clock):
        its frame, or none while it waits for its pose; :class:`Rejected` as for a topic."""
        s = self.cameras[name]
        s.received["image"] += 1
        try:
            if not (math.isfinite(stamp_s) and stamp_s > 0):
                raise Rejected("stamp_invalid", f"stamp {stamp_s}")
            s.offsets.append(stamp_s - receipt_s)
            self._stamp_ms(s, stamp_s, receipt_s)
            h, w = rgb.shape[:2]
            if w * h > self.rig.max_image_pixels:
                raise Rejected("too_large", f"a {w}x{h} frame exceeds "
                                            f"{self.rig.max_image_pixels} pixels")
            return self._images([s], rgb, stamp_s, None, receipt_s)
        except Rejected as err:
            s.rejected[err.reason] += 1
            raise

    def _images(self, states: list[CameraState], rgb: np.ndarray, stamp: float,
                att: ros.Attachment | None, receipt_s: float) -> list[Published]:
        out = []
        for s in states:
            try:
                out.append(self._frame(s, rgb, stamp, att, receipt_s))
            except _Wait:
                if len(s.held) >= HELD_PER_CAMERA:
                    s.held.pop(0)
                    s.rejected["no_pose"] += 1
                    self.expired.append((s.spec.name, Rejected(
                        "no_pose", f"{s.spec.name}: more than {HELD_PER_CAMERA} images wait "
                                   "for their pose or intrinsics")))
                s.held.append((receipt_s + HOLD_S, rgb, stamp, att, receipt_s))
        return out

    def _retry(self, states: list[CameraState], now_s: float) -> list[Published]:
        """Held images that a new pose or CameraInfo completes."""
        out = []
        for s in states:
            waiting, s.held = s.held, []
            for deadline, rgb, stamp, att, receipt_s in waiting:
                try:
                    out.append(self._frame(s, rgb, stamp, att, receipt_s))
                except _Wait:
                    s.held.append((deadline, rgb, stamp, att, receipt_s))
                except Rejected as err:
                    s.rejected[err.reason] += 1
                    self.expired.append((s.spec.name, err))
        return out

    def expire(self, now_s: float) -> tuple[list[Published], list[tuple[str, Rejected]]]:
        """The held images whose wait is over, made with what there is — frames, or (camera,
        why) refusals, already counted per camera (the runtime counts them in its rejections)
        — and the refusals of earlier retries."""
        frames = []
        for s in self.cameras.values():
            keep = []
            for item in s.held:
                deadline, rgb, stamp, att, receipt_s = item
                if now_s < deadline:
                    keep.append(item)
                    continue
                try:
                    frames.append(self._frame(s, rgb, stamp, att, receipt_s, final=True))
                except Rejected as err:
                    s.rejected[err.reason] += 1
                    self.expired.append((s.spec.name, err))
            s.held = keep
        refused, self.expired = self.expired, []
        return frames, refused

    def next_deadline(self) -> float | None:
        times = [h[0] for s in self.cameras.values() for h in s.held]
        return min(times) if times else None

    def _sequence(self, states: list[CameraState], topic: str, att: ros.Attachment) -> None:
        for s in states:
            stream = (topic, att.gid)
            last = s.last_seq.get(stream)
            if last is not None and att.sequence <= last:
                raise Rejected("sequence_replayed", f"sequence {att.sequence} after {last} "
                                                    f"on {topic} (duplicate or reordered)")
            if last is not None and att.sequence > last + 1:
                s.lost += att.sequence - last - 1
            s.last_seq[stream] = att.sequence
            s.last_seq.move_to_end(stream)
            while len(s.last_seq) > STREAMS_KEPT:
                s.last_seq.popitem(last=False)

    def _stamp_ms(self, s: CameraState, stamp: float, receipt_s: float) -> tuple[float, float]:
        """(generation sim ms, age in wall s) of an image stamped ``stamp``."""
        clock = self.rig.clock
        edge_stamp = stamp - self.offset_in_force(s)
        age = receipt_s - edge_stamp
        if age < -clock.future_tolerance_s:
            raise Rejected("stamp_future",
                           f"stamped {-age:.3f} s after its receipt (tolerance "
                           f"{clock.future_tolerance_s:g} s; robot clock − edge clock "
                           f"measured {s.offset_estimate_s:+.3f} s, in force "
                           f"{self.offset_in_force(s):+.3f} s)")
        if age > clock.max_age_s:
            raise Rejected("stamp_stale", f"stamped {age:.1f} s before its receipt (limit "
                                          f"{clock.max_age_s:g} s)")
        if age < 0:
            edge_stamp, age = receipt_s, 0.0
        # The model's time is slotted (1 ms): a stamp maps to its nearest slot. Unrounded, a
        # phase-locked robot's frame of t = k·C lands at k·C + 3e-5 ms (float seconds since the
        # epoch), "after" a decision at k·C, and the metrics service paired that decision with
        # the truth frame one period older.
        gen = float(round(self.sim_ms(edge_stamp)))
        if gen < 0:
            raise Rejected("stamp_before_run", f"stamped {-gen / 1000 / self.time_scale:.1f} s "
                                               "before the run's clock started")
        return gen, age

    def _pose_at(self, s: CameraState, stamp: float, final: bool) -> np.ndarray:
        spec = s.spec.pose
        if spec.static:
            return spec.static_c2w()
        tol = spec.tolerance_s or self.rig.pose_tolerance_s
        best, best_dt, newest = None, math.inf, -math.inf
        for t, c2w in s.poses:
            dt = abs(t - stamp)
            newest = max(newest, t)
            if dt < best_dt:
                best, best_dt = c2w, dt
        if (best is None or best_dt > tol) and not final and newest < stamp + tol:
            raise _Wait  # a pose within the tolerance may still come
        if best is None or best_dt > tol:
            what = ("no pose received yet on " + spec.topic if best is None else
                    f"the nearest pose on {spec.topic} is {best_dt:.3f} s away")
            raise Rejected("no_pose", f"{what} (tolerance {tol:g} s)")
        return best

    def _intrinsics(self, s: CameraState, final: bool) -> ros.Intrinsics:
        spec = s.spec.intrinsics
        if spec.static:
            return ros.Intrinsics(spec.fx, spec.fy, spec.cx, spec.cy, spec.width, spec.height)
        if s.intrinsics is None and not final:
            raise _Wait
        if s.intrinsics is None:
            raise Rejected("no_intrinsics", f"no CameraInfo received yet on {spec.camera_info}")
        return s.intrinsics

    def _frame(self, s: CameraState, rgb: np.ndarray, stamp: float,
               att: ros.Attachment | None, receipt_s: float, final: bool = False) -> Published:
        """The frame of a decoded image; :class:`_Wait` when its pose or intrinsics may still
        come (unless ``final``)."""
        gen_ms, age = self._stamp_ms(s, stamp, receipt_s)
        clamped = stamp - self.offset_in_force(s) > receipt_s  # within the tolerance
        intr = self._intrinsics(s, final)
        c2w = self._pose_at(s, stamp, final)
        h, w = rgb.shape[:2]
        if (w, h) != (intr.width, intr.height):
            raise Rejected("image_mismatch", f"a {w}x{h} image, but its intrinsics are for "
                                             f"{intr.width}x{intr.height}")
        camera = scaled_camera(c2w, intr.fx, intr.fy, intr.cx, intr.cy, (w, h), self.size)
        try:
            camera.validate()
        except ValueError as err:
            raise Rejected("bad_pose", str(err)) from None
        image = self._wire_image(rgb)
        if att is not None:
            seq = att.sequence
        else:
            s.own_seq += 1
            seq = s.own_seq
        receipt_ms = self.sim_ms(receipt_s)
        n = s.camera_id
        if n == TRUTH_ID:
            key, delivery = self.keys.truth, 0.0
        elif self.through_network:
            key, delivery = self.keys.cam_frame(n), 0.0
        else:
            key, delivery = self.keys.edge_frame(n), max(receipt_ms, gen_ms)
        pose, intrinsics = camera_to_pb(camera)
        payload = pb.Frame(camera_id=n, sequence=max(int(seq), 0), generation_ms=gen_ms,
                           scene_time_ms=gen_ms, send_ms=max(receipt_ms, gen_ms),
                           delivery_ms=delivery, pose=pose, intrinsics=intrinsics,
                           image=image).SerializeToString()
        s.published += 1
        s.clamped += clamped
        s.last_stamp_s, s.last_receipt_s, s.last_age_s = stamp, receipt_s, age
        s.ages.append(age)
        if att is not None and att.source_ns > 0:
            s.publish_delay_s = att.source_ns * 1e-9 - stamp
        return Published(key, payload, s.spec.name, n, gen_ms, receipt_ms, age)

    def _wire_image(self, rgb: np.ndarray) -> pb.Image:
        w, h = self.size
        if rgb.shape[1] != w or rgb.shape[0] != h:
            from PIL import Image as PILImage

            rgb = np.asarray(PILImage.fromarray(rgb, "RGB").resize(
                (w, h), PILImage.Resampling.BILINEAR))
        if self.wire_encoding == "raw":
            return pb.Image(encoding=pb.IMAGE_ENCODING_RAW_RGB8, width=w, height=h,
                            data=np.ascontiguousarray(rgb).tobytes())
        from PIL import Image as PILImage

        buf = io.BytesIO()
        PILImage.fromarray(np.ascontiguousarray(rgb), "RGB").save(buf, format="PNG",
                                                                  compress_level=1)
        return pb.Image(encoding=pb.IMAGE_ENCODING_PNG, width=w, height=h, data=buf.getvalue())

    # ------------------------------------------------------------------ status
    def status(self, now_s: float) -> dict:
        """What the status route shows (plain JSON values)."""

        def num(x: float, scale: float = 1.0, nd: int = 3):
            return None if x is None or not math.isfinite(x) else round(x * scale, nd)

        cams = []
        for s in self.cameras.values():
            spec = s.spec
            ages = sorted(s.ages)
            cams.append({
                "name": spec.name, "id": s.camera_id, "role": s.role,
                "image": spec.image or spec.url,
                "image_type": spec.kind,
                "intrinsics": "static" if spec.intrinsics.static else spec.intrinsics.camera_info,
                "pose": "static" if spec.pose.static else spec.pose.topic,
                "received": dict(s.received), "published": s.published,
                "rejected": dict(s.rejected), "lost": s.lost, "clamped": s.clamped,
                "last_stamp_s": num(s.last_stamp_s, nd=6),
                "since_last_s": num(now_s - s.last_receipt_s),
                "age_ms_last": num(s.last_age_s, 1000.0, 1),
                "age_ms_median": num(ages[len(ages) // 2], 1000.0, 1) if ages else None,
                "clock_offset_s": num(s.offset_estimate_s, nd=4),
                "clock_offset_in_force_s": num(self.offset_in_force(s), nd=4),
                "publish_delay_ms": num(s.publish_delay_s, 1000.0, 1),
            })
        rig = self.rig
        return {
            "source": {"format": self.format.format, "domain_id": self.format.domain_id,
                       "namespace": self.format.namespace,
                       "connect": list(rig.source.connect) or "the pipeline's router",
                       "subscriptions": [r.key_expr for r in self.routes],
                       "graph": None if self.graph_key is None else {
                           "nodes": sum(e.kind == "node" for e in self.graph.values()),
                           "publishers": sum(e.kind == "publisher"
                                             for e in self.graph.values()),
                           "unparsed_tokens": self.graph_unparsed,
                           "dropped_tokens": self.graph_dropped,
                           "topics": self.topic_publishers()}},
            "time": {"time_scale": self.time_scale, "epoch_s": self.epoch_s,
                     "clock_offset": rig.clock.offset_s,
                     "future_tolerance_s": rig.clock.future_tolerance_s,
                     "max_age_s": rig.clock.max_age_s},
            "link": ("emulated delay on top (the network service delays each frame from its "
                     "receipt)" if self.through_network else
                     "real: frames delivered at their receipt (the network emulator steps "
                     "aside)"),
            "truth": rig.truth,
            "scoring": ("the truth camera " + rig.truth + " scores every render"
                        if rig.truth else "no truth camera: renders are made but cannot be "
                                          "scored"),
            "working_size": list(self.size),
            "cameras": cams,
        }
