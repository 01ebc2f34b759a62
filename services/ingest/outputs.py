"""aoi3d's outputs in ROS 2: what the pipeline makes, published on the rig's source — straight
on DDS (``format: dds``, through the ingest's own node) or on Zenoh in the rig's key format
(rmw_zenoh keys with their attachment and liveliness tokens, or the bridge's keys).

Topics (settable: the ingest's ``AOI3D_INGEST_ROS_*_TOPIC``), every message CDR-encoded as ROS
2 encodes it and stamped with the **decision time** (the pipeline's sim time ``time_ms`` of
the decision, as wall time on the pipeline's clock: ``epoch_s + time_ms / 1000 /
time_scale``):

- ``/aoi3d/render`` — ``sensor_msgs/Image``, ``rgb8``, the dispatcher's render of the view
  (its size: the rig's working size), ``frame_id`` ``aoi3d_view``;
- ``/aoi3d/camera_info`` — ``sensor_msgs/CameraInfo`` of that render (pinhole K and P, no
  distortion), published with each render, same stamp (image_transport's pairing);
- ``/aoi3d/decision`` — ``diagnostic_msgs/DiagnosticArray``: a status ``decision`` (values
  ``decision_id``, ``policy``, ``time_ms``, ``selected``: the chosen camera names, and
  ``gamma_ms`` when the policy has one), then one status per camera (``name``: the rig's camera
  name, ``hardware_id``: its id) with ``aoi_ms`` (its Age of Information at the decision,
  ``nan`` before its first frame) and ``selected`` (``true``/``false``);
- ``/aoi3d/quality`` — ``diagnostic_msgs/DiagnosticArray``: a status ``quality`` with
  ``decision_id``, ``time_ms``, ``psnr_db`` and ``ssim`` (at the decision time),
  ``display_time_ms``, ``psnr_display_db`` and ``ssim_display`` (at display time: when the
  render was ready; ``nan`` when not scored there), ``lpips`` when measured.

No standard ROS message carries an AoI vector or a PSNR: ``DiagnosticArray`` is the standard
key-value carrier (``ros2 topic echo`` and rqt show it); the keys above are the contract.
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from aoi3d.rigfile import Rig
from services import ros
from services.kit.codec import decode_image
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from services.ros.encode import header

if TYPE_CHECKING:
    from services.kit.bus import Bus, Token

log = logging.getLogger(__name__)

__all__ = ["DIAGNOSTIC_ARRAY", "NODE", "OutputTopics", "RosOutputs", "dds_sender",
           "decision_msg", "quality_msg", "render_msgs", "zenoh_sender"]

DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
NODE = "aoi3d"
"""The outputs' node name in the ROS graph on rmw_zenoh keys (on DDS: the ingest's node)."""
VIEW_FRAME = "aoi3d_view"

Sender = Callable[[str, str], Callable[[bytes], None]]
"""``sender(topic, ROS type)`` → a function publishing one CDR sample on that topic."""


class PublishingSource(Protocol):
    """What publishes straight in ROS (:class:`services.ingest.dds.DdsSource`)."""

    def publisher(self, topic: str, ros_type: str, depth: int = 5) -> Callable[[bytes], None]:
        ...


class KeyedBus(Protocol):
    """A Zenoh session that puts with attachments and declares tokens (the kit's buses)."""

    def put(self, key: str, payload: bytes, attachment: bytes | None = None) -> None: ...

    def declare_token(self, key: str) -> Token: ...


@dataclass(frozen=True)
class OutputTopics:
    render: str = "/aoi3d/render"
    camera_info: str = "/aoi3d/camera_info"
    decision: str = "/aoi3d/decision"
    quality: str = "/aoi3d/quality"

    def types(self) -> list[tuple[str, str]]:
        return [(self.render, ros.IMAGE), (self.camera_info, ros.CAMERA_INFO),
                (self.decision, DIAGNOSTIC_ARRAY), (self.quality, DIAGNOSTIC_ARRAY)]


def _num(x: float | None) -> str:
    return "nan" if x is None or not math.isfinite(x) else f"{x:.6g}"


def _status(name: str, hardware_id: str, message: str, values: dict[str, str]) -> Any:
    t = ros.typestore().types
    return t["diagnostic_msgs/msg/DiagnosticStatus"](
        level=0, name=name, message=message, hardware_id=hardware_id,
        values=[t["diagnostic_msgs/msg/KeyValue"](key=k, value=v) for k, v in values.items()])


def _diagnostics(stamp: float, statuses: list[Any]) -> bytes:
    t = ros.typestore().types
    return ros.encode_cdr(t[DIAGNOSTIC_ARRAY](header=header(stamp, VIEW_FRAME),
                                              status=statuses), DIAGNOSTIC_ARRAY)


def render_msgs(render: pb.Render, stamp: float) -> tuple[bytes, bytes]:
    """A Render → (``sensor_msgs/Image`` rgb8, ``sensor_msgs/CameraInfo``), CDR, stamped."""
    rgb = decode_image(render.image)
    h, w = rgb.shape[:2]
    image = ros.encode_cdr(ros.image_msg(stamp, VIEW_FRAME, np.ascontiguousarray(rgb), "rgb8"),
                           ros.IMAGE)
    k = render.intrinsics
    info = ros.encode_cdr(ros.camera_info_msg(stamp, VIEW_FRAME, k.fx, k.fy, k.cx, k.cy, w, h),
                          ros.CAMERA_INFO)
    return image, info


def decision_msg(d: pb.Decision, stamp: float, names: dict[int, str]) -> bytes:
    """A Decision → ``DiagnosticArray`` (its values, then each camera's AoI)."""
    chosen = {f.camera_id for f in d.selected}
    head = {"decision_id": str(d.decision_id), "policy": d.policy, "time_ms": _num(d.time_ms),
            "selected": ",".join(names.get(i, str(i)) for i in sorted(chosen))}
    if d.HasField("gamma_ms"):
        head["gamma_ms"] = _num(d.gamma_ms)
    statuses = [_status("decision", "aoi3d", f"{len(chosen)} cameras selected", head)]
    for cam, aoi in zip(d.camera_ids, d.aoi_ms, strict=False):
        statuses.append(_status(names.get(cam, str(cam)), str(cam), "age of information",
                                {"aoi_ms": _num(aoi),
                                 "selected": "true" if cam in chosen else "false"}))
    return _diagnostics(stamp, statuses)


def quality_msg(q: pb.Quality, stamp: float) -> bytes:
    """A Quality → ``DiagnosticArray`` (PSNR at the decision and at display time)."""
    values = {"decision_id": str(q.decision_id), "time_ms": _num(q.time_ms),
              "psnr_db": _num(q.psnr_db), "ssim": _num(q.ssim),
              "display_time_ms": _num(q.display_time_ms),
              "psnr_display_db": _num(q.psnr_display_db if q.HasField("psnr_display_db")
                                      else math.nan),
              "ssim_display": _num(q.ssim_display if q.HasField("ssim_display") else math.nan)}
    if q.HasField("lpips"):
        values["lpips"] = _num(q.lpips)
    return _diagnostics(stamp, [_status("quality", "aoi3d", "render quality", values)])


# ---------------------------------------------------------------- senders
def dds_sender(source: PublishingSource) -> Sender:
    """Publishers of the ingest's DDS node (:class:`services.ingest.dds.DdsSource`)."""
    return source.publisher


def zenoh_sender(bus: KeyedBus, fmt: ros.KeyFormat, tokens: list[Token]) -> Sender:
    """Publishers on Zenoh in ``fmt``'s keys (rmw_zenoh: with the attachment, a sequence
    number per publisher, and — in ``tokens`` — the liveliness tokens of node :data:`NODE`
    and each publisher, declared on ``bus``)."""
    declared: list[tuple[str, str]] = []
    session = os.urandom(16).hex()

    def sender(topic: str, ros_type: str) -> Callable[[bytes], None]:
        key = fmt.key(topic, ros_type)
        gid, seq = os.urandom(16), [0]
        lock = threading.Lock()
        if fmt.attached:
            declared.append((topic, ros_type))
            for tok in tokens:
                tok.undeclare()
            tokens[:] = [bus.declare_token(k) for k in
                         ros.node_tokens(fmt.domain_id, session, NODE, declared)]

        def send(payload: bytes) -> None:
            import time

            with lock:
                seq[0] += 1
                att = (ros.build_attachment(seq[0], time.time_ns(), gid) if fmt.attached
                       else None)
            bus.put(key, payload, att)
        return send
    return sender


# ---------------------------------------------------------------- the outputs
class RosOutputs:
    """Subscribes to the pipeline's render, decision and quality (on ``bus``) and publishes
    each in ROS through ``sender``. A message that cannot be converted is logged, never
    raised into the bus's thread."""

    def __init__(self, *, bus: Bus, keys: Keys, rig: Rig, epoch_s: float, time_scale: float,
                 sender: Sender, topics: OutputTopics | None = None,
                 on_stop: Callable[[], None] | None = None) -> None:
        self.bus = bus
        self.keys = keys
        self.epoch_s = float(epoch_s)
        self.time_scale = float(time_scale)
        self.topics = topics or OutputTopics()
        self.names = {i: n for n, i in rig.ids().items()}
        self._sender = sender
        self._on_stop = on_stop
        self.sent = {"render": 0, "decision": 0, "quality": 0}
        self._pub: dict[str, Callable[[bytes], None]] = {}

    def stamp(self, time_ms: float) -> float:
        """A sim time (ms) → wall seconds on the pipeline's clock."""
        return self.epoch_s + time_ms / 1000.0 / self.time_scale

    def start(self) -> None:
        t = self.topics
        for topic, ros_type in t.types():
            self._pub[topic] = self._sender(topic, ros_type)
        self.bus.subscribe(self.keys.render, self._guard("render", self._on_render))
        self.bus.subscribe(self.keys.decision, self._guard("decision", self._on_decision))
        self.bus.subscribe(self.keys.quality, self._guard("quality", self._on_quality))
        log.info("outputs in ROS: %s", ", ".join(f"{a} ({b})" for a, b in t.types()))

    def stop(self) -> None:
        if self._on_stop is not None:
            self._on_stop()

    def _guard(self, what: str,
               fn: Callable[[bytes], None]) -> Callable[[str, bytes], None]:
        def on(_key: str, payload: bytes) -> None:
            try:
                fn(payload)
                self.sent[what] += 1
            except Exception as err:  # a bad message is a log line, not a dead subscriber
                log.warning("%s not published in ROS: %r", what, err)
        return on

    def _on_render(self, payload: bytes) -> None:
        r = pb.Render.FromString(payload)
        image, info = render_msgs(r, self.stamp(r.time_ms))
        self._pub[self.topics.camera_info](info)
        self._pub[self.topics.render](image)

    def _on_decision(self, payload: bytes) -> None:
        d = pb.Decision.FromString(payload)
        self._pub[self.topics.decision](decision_msg(d, self.stamp(d.time_ms), self.names))

    def _on_quality(self, payload: bytes) -> None:
        q = pb.Quality.FromString(payload)
        self._pub[self.topics.quality](quality_msg(q, self.stamp(q.time_ms)))
