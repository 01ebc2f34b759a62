"""The ingest core: a ROS 2 sample (key, CDR bytes, attachment) and its receipt time in, the
pipeline's :class:`pb.Frame` out — or :class:`Rejected` with its reason.

No bus, no threads, no metrics library: the runtime (:mod:`services.ingest.runtime`) feeds it
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

Time: a frame's generation time is its stamp less the camera's clock offset in force, on the
pipeline's sim clock (:mod:`services.ingest.stamps`). Sequence gaps in the attachment count
as losses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from aoi3d.rigfile import TRUTH_ID, Rig, scaled_camera
from services import ros
from services.ingest.camera import CameraState, Wait
from services.ingest.graph import RosGraph
from services.ingest.routes import Route, subscriptions
from services.ingest.stamps import Stamps
from services.kit.codec import camera_to_pb, encode_png
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected, RejectReason

__all__ = ["WIRE_ENCODINGS", "IngestCore", "Published", "Route"]

WIRE_ENCODINGS = ("png", "raw")
HOLD_S = 0.5
"""Wall seconds an image waits for a pose (or a first CameraInfo) that may still come: topics
travel on separate Zenoh subscriptions, so an image can overtake the pose of its stamp."""
HELD_PER_CAMERA = 8
"""Images of one camera waiting at most (an older one is then refused)."""


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
        self.stamps = Stamps(self.epoch_s, self.time_scale, rig.clock)
        self.through_network = through_network
        self.wire_encoding = wire_encoding
        src = rig.source
        self.format = key_format or ros.KeyFormat(src.format, src.domain_id, src.prefix)
        self.size = rig.working_size
        ids = rig.ids()
        self.cameras = {c.name: CameraState(c, ids[c.name]) for c in rig.cameras}
        self.routes = subscriptions(rig, self.format)
        self.expired: list[tuple[str, Rejected]] = []
        self.ros_graph = RosGraph(self.format)
        """The ROS graph (rmw_zenoh's liveliness tokens of the rig's domain)."""

    # ------------------------------------------------------------------ the ROS graph
    # (services.ingest.graph: ros_graph; these are the worker's names)
    @property
    def graph_key(self) -> str | None:
        return self.ros_graph.key

    def on_liveliness(self, key: str, alive: bool) -> None:
        self.ros_graph.on_token(key, alive)

    def topic_publishers(self) -> list[dict[str, Any]]:
        return self.ros_graph.topic_publishers(self.routes)

    def graph_hint(self) -> str:
        return self.ros_graph.hint(self.routes)

    # ------------------------------------------------------------------ time
    def sim_ms(self, wall_s: float) -> float:
        return self.stamps.sim_ms(wall_s)

    def offset_in_force(self, state: CameraState) -> float:
        return self.stamps.offset_in_force(state)

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
            for s in states:
                s.sequence(route.topic, att)
        self.format.check_key(key, route.ros_type)
        cap = self.rig.max_image_bytes if route.kind == "image" else 1024 * 1024
        msg = ros.decode_cdr(payload, route.ros_type, cap)
        stamp = ros.stamp_s(msg.header)
        if not stamp > 0:
            raise Rejected(RejectReason.STAMP_INVALID,
                           f"stamp {stamp} (a publisher that does not stamp)")
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
            self.stamps.stamp_ms(s, stamp, receipt_s)  # refused before the pixels are decoded
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
                raise Rejected(RejectReason.STAMP_INVALID, f"stamp {stamp_s}")
            s.offsets.append(stamp_s - receipt_s)
            self.stamps.stamp_ms(s, stamp_s, receipt_s)
            h, w = rgb.shape[:2]
            if w * h > self.rig.max_image_pixels:
                raise Rejected(RejectReason.TOO_LARGE, f"a {w}x{h} frame exceeds "
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
            except Wait:
                if len(s.held) >= HELD_PER_CAMERA:
                    s.held.pop(0)
                    s.rejected[RejectReason.NO_POSE] += 1
                    self.expired.append((s.spec.name, Rejected(
                        RejectReason.NO_POSE, f"{s.spec.name}: more than {HELD_PER_CAMERA} "
                                              "images wait for their pose or intrinsics")))
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
                except Wait:
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

    def _frame(self, s: CameraState, rgb: np.ndarray, stamp: float,
               att: ros.Attachment | None, receipt_s: float, final: bool = False) -> Published:
        """The frame of a decoded image; :class:`Wait` when its pose or intrinsics may still
        come (unless ``final``)."""
        gen_ms, age = self.stamps.stamp_ms(s, stamp, receipt_s)
        clamped = stamp - self.offset_in_force(s) > receipt_s  # within the tolerance
        intr = s.intrinsics_in_force(final)
        c2w = s.pose_at(stamp, final, self.rig.pose_tolerance_s)
        h, w = rgb.shape[:2]
        if (w, h) != (intr.width, intr.height):
            raise Rejected(RejectReason.IMAGE_MISMATCH,
                           f"a {w}x{h} image, but its intrinsics are for "
                           f"{intr.width}x{intr.height}")
        camera = scaled_camera(c2w, intr.fx, intr.fy, intr.cx, intr.cy, (w, h), self.size)
        try:
            camera.validate()
        except ValueError as err:
            raise Rejected(RejectReason.BAD_POSE, str(err)) from None
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
        return encode_png(np.ascontiguousarray(rgb))  # (compress level 1)

    # ------------------------------------------------------------------ status
    def status(self, now_s: float) -> dict[str, Any]:
        """What the status route shows (plain JSON values)."""

        cams = [s.status(now_s, self.offset_in_force(s)) for s in self.cameras.values()]
        rig = self.rig
        return {
            "source": {"format": self.format.format, "domain_id": self.format.domain_id,
                       "namespace": self.format.namespace,
                       "connect": list(rig.source.connect) or "the pipeline's router",
                       "subscriptions": [r.key_expr for r in self.routes],
                       "graph": self.ros_graph.status(self.routes)},
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
