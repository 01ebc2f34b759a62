"""The ingest worker: Zenoh subscriptions on the rig's ROS 2 topics, one decoding thread, the
frames published where the camera emulator's would go.

The Zenoh callbacks only stamp the receipt (wall time) and enqueue (:class:`Inbox`, bounded:
the oldest sample is dropped and counted when the decoder falls behind); the *decode* thread
hands each sample to the core (:class:`services.ingest.core.IngestCore`) and publishes the
frames it returns. A bad sample is a counted rejection with its reason
(``aoi3d_messages_rejected_total{reason}`` and ``aoi3d_ingest_rejected_total{camera,
reason}``), never an exception out of the loop.

The ROS topics are read from the pipeline's own Zenoh session, or — when the rig names the
robots' router (``source.connect``) — from a second session connected there, or straight from
DDS (``source.format: dds``: the ingest's own ROS 2 node, :mod:`services.ingest.dds`).
aoi3d's outputs in ROS (:mod:`services.ingest.outputs`) start and stop with the worker.
"""

from __future__ import annotations

import functools
import logging
import threading
import time

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from aoi3d.rigfile import CameraSpec, Rig
from services.ingest.core import IngestCore
from services.ingest.dds import DdsIngestCore
from services.ingest.outputs import RosOutputs
from services.ingest.routes import Route
from services.kit.bus import Bus, Inbox
from services.kit.keys import Keys
from services.kit.observe import Heartbeat, Rejected, Rejections
from services.kit.runtime import Loops

log = logging.getLogger(__name__)

_POLL_S = 0.1
#: Receipt − stamp of the published frames, wall seconds.
AGE_BUCKETS_S = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)

__all__ = ["IngestRuntime"]


class _Collector:
    """The core's per-camera counts as Prometheus series, read at scrape time."""

    def __init__(self, worker: IngestRuntime) -> None:
        self._worker = worker

    def describe(self):
        return []

    def collect(self):
        samples = CounterMetricFamily("aoi3d_ingest_samples", "ROS 2 samples received, by "
                                      "camera and kind (image, camera_info, pose).",
                                      labels=["camera", "kind"])
        frames = CounterMetricFamily("aoi3d_ingest_frames", "Frames published to the "
                                     "pipeline, by camera.", labels=["camera"])
        rejected = CounterMetricFamily("aoi3d_ingest_rejected", "Samples rejected, by camera "
                                       "and reason.", labels=["camera", "reason"])
        lost = CounterMetricFamily("aoi3d_ingest_frames_lost", "Images never received: gaps "
                                   "in the rmw_zenoh sequence numbers.", labels=["camera"])
        clamped = CounterMetricFamily("aoi3d_ingest_stamps_clamped", "Images stamped after "
                                      "their receipt (within the tolerance): generation set "
                                      "to the receipt.", labels=["camera"])
        offset = GaugeMetricFamily("aoi3d_ingest_clock_offset_seconds", "Robot clock − edge "
                                   "clock as measured (the 90th percentile of robot time − "
                                   "receipt over the last samples).", labels=["camera"])
        in_force = GaugeMetricFamily("aoi3d_ingest_clock_offset_in_force_seconds", "The "
                                     "offset subtracted from the stamps.", labels=["camera"])
        publishers = GaugeMetricFamily("aoi3d_ingest_ros_publishers", "Live publishers of "
                                       "the rig's type on each subscribed topic, from the ROS "
                                       "graph (rmw_zenoh's liveliness tokens; absent for the "
                                       "bridge).", labels=["topic"])
        with self._worker.lock:
            if self._worker.core.graph_key is not None:
                for t in self._worker.core.topic_publishers():
                    publishers.add_metric([t["topic"]], t["publishers"])
            for s in self._worker.core.cameras.values():
                name = s.spec.name
                for kind in ("image", "camera_info", "pose"):
                    samples.add_metric([name, kind], s.received[kind])
                frames.add_metric([name], s.published)
                for reason, n in s.rejected.items():
                    rejected.add_metric([name, reason], n)
                lost.add_metric([name], s.lost)
                clamped.add_metric([name], s.clamped)
                if s.offsets:
                    offset.add_metric([name], s.offset_estimate_s)
                in_force.add_metric([name], self._worker.core.offset_in_force(s))
        yield from (samples, frames, rejected, lost, clamped, offset, in_force, publishers)


class IngestRuntime:
    """See the module docstring. ``source``: the bus the ROS topics are read from (default
    ``bus``)."""

    def __init__(self, *, bus: Bus, registry: CollectorRegistry, rig: Rig, keys: Keys,
                 epoch_s: float, time_scale: float, stall_s: float,
                 through_network: bool = False, wire_encoding: str = "png",
                 inbox_size: int = 512, source: Bus | None = None,
                 own_source: bool = False, outputs: RosOutputs | None = None) -> None:
        self._bus = bus
        self._source = source or bus
        self._own_source = own_source and source is not None
        self._outputs = outputs  # aoi3d's outputs in ROS (services.ingest.outputs), or None
        core_class = DdsIngestCore if rig.source.format == "dds" else IngestCore
        self.core = core_class(rig, keys, epoch_s=epoch_s, time_scale=time_scale,
                               through_network=through_network, wire_encoding=wire_encoding)
        self.lock = threading.Lock()
        self._inbox = Inbox(inbox_size, on_drop=lambda: self._overflow.inc())
        self._beat = Heartbeat(stall_s)
        self._first = False
        self.rejections = Rejections(registry)
        self._generated = Counter("aoi3d_frames_generated", "Frames published to the pipeline "
                                  "by camera id (0 = the truth camera), as the camera "
                                  "emulator counts its own.", ["camera"], registry=registry)
        self._overflow = Counter("aoi3d_ingest_inbox_overflow", "Samples dropped before "
                                 "decoding because the inbox was full.", registry=registry)
        self._age = Histogram("aoi3d_ingest_frame_age_seconds", "Receipt − stamp of the "
                              "published frames (wall seconds, after the clock offset in "
                              "force).", buckets=AGE_BUCKETS_S, registry=registry)
        for s in self.core.cameras.values():
            self._generated.labels(camera=str(s.camera_id))
        registry.register(_Collector(self))
        self._stream_errors = Counter("aoi3d_ingest_stream_errors", "Times a url camera's "
                                      "stream (rtsp:// or a video file) failed or ended and "
                                      "was opened again.", ["camera"], registry=registry)
        self._loops = Loops("ingest")
        self._loops.forever("decode", self._step)
        self._time_scale = float(time_scale)
        for spec in rig.cameras:
            if spec.url is not None:
                self._stream_errors.labels(camera=spec.name)
                self._loops.thread(f"video-{spec.name}", functools.partial(self._video, spec))

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._loops.start()
        for route in self.core.routes:
            self._source.subscribe_attached(route.key_expr, self._handler(route))
        if self.core.graph_key is not None:  # rmw_zenoh: who publishes what, for /status
            self._source.watch_liveliness(self.core.graph_key, self._on_token)
        log.info("ingest: %s keys, subscribed to %s", self.core.format.format,
                 ", ".join(r.key_expr for r in self.core.routes))
        if self._outputs is not None:
            self._outputs.start()

    def stop(self) -> None:
        self._loops.stop(timeout_s=2.0)
        if self._outputs is not None:
            self._outputs.stop()
        if self._own_source:
            self._source.close()

    def readiness(self) -> tuple[bool, str]:
        why_not = self._loops.not_running()
        if why_not is not None:
            return False, why_not
        if not self._first:
            with self.lock:
                hint = self.core.graph_hint()
            return False, "no frame from the cameras yet" + (f" ({hint})" if hint else "")
        if self._beat.stalled():
            return False, f"no frame for {self._beat.idle_s():.0f} s"
        return True, ""

    def status(self) -> dict:
        with self.lock:
            out = self.core.status(time.time())
        out["inbox"] = {"queued": len(self._inbox), "dropped": self._inbox.dropped}
        return out

    def _on_token(self, key: str, alive: bool) -> None:
        with self.lock:
            self.core.on_liveliness(key, alive)

    # ------------------------------------------------------------------ samples
    def _handler(self, route: Route):
        def on_sample(key: str, payload: bytes, attachment: bytes | None) -> None:
            self._inbox.put((route, key, payload, attachment, time.time()))
        return on_sample

    def _step(self) -> None:
        item = self._inbox.get(timeout=_POLL_S)
        with self.lock:
            late, refused = self.core.expire(time.time())
        for camera, err in refused:
            self.rejections.reject(err, camera)
        self._publish(late)
        if item is None:
            return
        route, key, payload, attachment, receipt_s = item
        try:
            with self.lock:
                out = self.core.on_sample(route, key, payload, attachment, receipt_s)
        except Rejected as err:
            self.rejections.reject(err, key)
            return
        self._publish(out)

    def _video(self, spec: CameraSpec, stop: threading.Event) -> None:
        """Read a url camera until the worker stops, opening it again (after 0.5, 1, 2 … 10 s)
        whenever it fails or ends; an RTSP listener just waits for its camera again."""
        from services.ingest.video import StreamEnded, read_video

        url = spec.url
        assert url is not None, "started for url cameras only"
        backoff = 0.5
        while not stop.is_set():
            got = False
            try:
                for frame in read_video(url, listen=spec.listen, stamps=spec.stamps,
                                        time_scale=self._time_scale,
                                        max_pixels=self.core.rig.max_image_pixels,
                                        stop=stop.is_set):
                    got = True
                    try:
                        with self.lock:
                            out = self.core.on_video(spec.name, frame.rgb, frame.stamp_s,
                                                     frame.receipt_s)
                    except Rejected as err:
                        self.rejections.reject(err, url)
                        continue
                    self._publish(out)
                if stop.is_set():
                    return
            except StreamEnded as err:
                waiting = spec.listen and not got and "timed out" in str(err).lower()
                if waiting:  # a listener with no camera yet: not a failure
                    continue
                self._stream_errors.labels(camera=spec.name).inc()
                log.warning("camera %s: %s; opening it again in %.1f s", spec.name, err,
                            backoff)
            except Exception as err:  # a bad stream never stops the worker
                self._stream_errors.labels(camera=spec.name).inc()
                log.warning("camera %s: %r; opening it again in %.1f s", spec.name, err,
                            backoff)
            backoff = 0.5 if got else min(backoff * 2, 10.0)
            if stop.wait(backoff):
                return

    def _publish(self, out) -> None:
        for frame in out:
            self._bus.publish(frame.key, frame.payload)
            self._generated.labels(camera=str(frame.camera_id)).inc()
            self._age.observe(frame.age_s)
            self._beat.beat()
            self._first = True
