"""The network worker: the cameras' D/G/1/0 uplinks between the rig and the edge server.

Offered frames (``cam/<n>/frame``) go through camera n's :class:`aoi3d.channel.link.Link`:
``offer(generation_ms)`` gives the delivery slot, or None when the previous frame is still in
flight (dropped). Accepted frames wait in a timer heap and are re-published on
``edge/<n>/frame``, stamped with their delivery time, at the wall time of their delivery slot.

Threads: the bus callback only enqueues; the *link* thread decodes, validates and offers;
the *delivery* thread publishes due frames.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import threading
from dataclasses import dataclass, field

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Histogram

from aoi3d.channel import ACCEPTED_FORMS, DelayDistribution, Link, camera_rngs, parse_delay
from aoi3d.clock import SimClock
from services.kit.bus import Bus, Inbox
from services.kit.codec import decode_frame, with_delivery
from services.kit.keys import Keys
from services.kit.observe import Rejected, Rejections

log = logging.getLogger(__name__)

#: Histogram buckets of the link delay, in sim seconds (slots of 1 ms … 2 s).
DELAY_BUCKETS_S = (0.001, 0.005, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.08, 0.1, 0.125, 0.15,
                   0.2, 0.3, 0.5, 1.0, 2.0)
_POLL_S = 0.1  # longest a thread blocks before checking for stop


class ChannelConfigError(ValueError):
    """A channel change that cannot be applied; the message says what is accepted."""


@dataclass(frozen=True)
class ChannelConfig:
    """The links' settings: the default delay spec, per-camera overrides and the seed."""

    delay: str
    per_camera: dict[int, str] = field(default_factory=dict)
    seed: int = 1

    def spec_of(self, camera_id: int) -> str:
        return self.per_camera.get(camera_id, self.delay)


@dataclass
class LinkStats:
    """One link's counts since the service started (they survive a reseed)."""

    camera_id: int
    delay: DelayDistribution
    offered: int = 0
    dropped: int = 0
    delivered: int = 0
    in_flight: bool = False


@dataclass(order=True)
class _Pending:
    delivery_ms: float
    order: int
    camera_id: int = field(compare=False)
    generation_ms: float = field(compare=False)
    payload: bytes = field(compare=False, repr=False)


class NetworkWorker:
    """N independent links; frames delivered on the shared clock."""

    def __init__(self, *, bus: Bus, registry: CollectorRegistry, clock: SimClock, keys: Keys,
                 n_cameras: int, delay: str = "exp:60", per_camera: dict[int, str] | None = None,
                 seed: int = 1, max_skew_ms: float = 1000.0, inbox_size: int = 1024) -> None:
        self._bus = bus
        self._clock = clock
        self._keys = keys
        self.camera_ids: tuple[int, ...] = tuple(range(1, n_cameras + 1))
        self._accepted = frozenset(self.camera_ids)
        self._max_skew_ms = float(max_skew_ms)
        self._lock = threading.Lock()
        self._config = self._checked(delay, per_camera or {}, seed)
        rngs = camera_rngs(self._config.seed, n_cameras)
        self._links = {n: Link(self._config.spec_of(n), rngs[n - 1]) for n in self.camera_ids}
        self._reseed: dict[int, np.random.Generator] = {}
        self._stats = {n: LinkStats(n, self._links[n].delay) for n in self.camera_ids}

        self._inbox = Inbox(inbox_size, on_drop=lambda: self._overflow.inc())
        self._heap: list[_Pending] = []
        self._heap_cond = threading.Condition()
        self._order = itertools.count()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

        self.rejections = Rejections(registry)
        self._offered = Counter("aoi3d_frames_offered", "Frames offered to a camera's link.",
                                ["camera"], registry=registry)
        self._dropped = Counter("aoi3d_frames_dropped", "Frames dropped because the camera's "
                                "previous frame was still in flight.", ["camera"],
                                registry=registry)
        self._delivered = Counter("aoi3d_frames_delivered", "Frames delivered to the edge.",
                                  ["camera"], registry=registry)
        self._delay_s = Histogram("aoi3d_link_delay_seconds", "Delay of delivered frames, "
                                  "delivery − generation, in sim seconds.",
                                  buckets=DELAY_BUCKETS_S, registry=registry)
        self._overflow = Counter("aoi3d_network_inbox_overflow", "Offered frames dropped "
                                 "before reaching the links because the inbox was full.",
                                 registry=registry)
        for n in self.camera_ids:
            for counter in (self._offered, self._dropped, self._delivered):
                counter.labels(camera=str(n))

    # ------------------------------------------------------------------ configuration
    def _checked(self, delay: str, per_camera: dict[int, str], seed: int) -> ChannelConfig:
        """Validate a full config (raises ``DelaySpecError`` / ``ChannelConfigError``)."""
        spec = parse_delay(delay).spec
        unknown = sorted(set(per_camera) - self._accepted)
        if unknown:
            raise ChannelConfigError(
                f"per_camera names unknown camera id(s) {unknown}; the links are cameras "
                f"{self.camera_ids[0]}..{self.camera_ids[-1]}")
        overrides: dict[int, str] = {}
        for n, camera_spec in sorted(per_camera.items()):
            try:
                overrides[n] = parse_delay(camera_spec).spec
            except ValueError as err:
                raise ChannelConfigError(f"per_camera {n}: {err}") from err
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ChannelConfigError(f"seed must be an integer >= 0, got {seed!r}")
        return ChannelConfig(delay=spec, per_camera=overrides, seed=seed)

    @property
    def config(self) -> ChannelConfig:
        with self._lock:
            return self._config

    def update(self, *, delay: str | None = None, per_camera: dict[int, str] | None = None,
               seed: int | None = None) -> ChannelConfig:
        """Partial update (``per_camera`` replaces the whole override map).

        A new delay applies to the frames offered from now on (a frame in flight keeps its
        delivery slot). A new seed restarts each link's random stream once its frame in
        flight is delivered. Raises ``DelaySpecError`` or ``ChannelConfigError``.
        """
        with self._lock:
            old = self._config
            new = self._checked(old.delay if delay is None else delay,
                                old.per_camera if per_camera is None else per_camera,
                                old.seed if seed is None else seed)
            for n, link in self._links.items():
                if link.delay.spec != new.spec_of(n):
                    link.set_delay(new.spec_of(n))
                    self._stats[n].delay = link.delay
            if new.seed != old.seed:
                rngs = camera_rngs(new.seed, len(self.camera_ids))
                self._reseed = {n: rngs[n - 1] for n in self.camera_ids}
            self._config = new
        log.info("channel: delay %s, per camera %s, seed %d", new.delay, new.per_camera,
                 new.seed)
        return new

    def link_stats(self) -> list[LinkStats]:
        """A snapshot of every link's counts and state."""
        now = self._clock.now_ms()
        with self._lock:
            return [LinkStats(n, s.delay, s.offered, s.dropped, s.delivered,
                              self._links[n].in_flight(now)) for n, s in self._stats.items()]

    @staticmethod
    def accepted_forms() -> tuple[str, ...]:
        return ACCEPTED_FORMS

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._link_loop, name="network-links", daemon=True),
            threading.Thread(target=self._delivery_loop, name="network-delivery", daemon=True),
        ]
        for thread in self._threads:
            thread.start()
        self._bus.subscribe(self._keys.cam_frames, self._on_frame)

    def stop(self) -> None:
        self._stop.set()
        with self._heap_cond:
            self._heap_cond.notify_all()
        for thread in self._threads:
            thread.join(timeout=1.0)
            if thread.is_alive():
                log.warning("%s did not stop within 1 s", thread.name)

    def readiness(self) -> tuple[bool, str]:
        if not self._threads or not all(t.is_alive() for t in self._threads):
            return False, "link threads not running"
        return True, ""

    @property
    def pending(self) -> int:
        """Frames in flight (accepted, not yet delivered)."""
        with self._heap_cond:
            return len(self._heap)

    # ------------------------------------------------------------------ offered frames
    def _on_frame(self, key: str, payload: bytes) -> None:
        """Bus callback: hand off only."""
        self._inbox.put((key, payload))

    def _link_loop(self) -> None:
        while not self._stop.is_set():
            item = self._inbox.get(timeout=_POLL_S)
            if item is None:
                continue
            key, payload = item
            try:
                self._offer(key, payload)
            except Rejected as err:
                self.rejections.reject(err, key)
            except Exception:  # a bug must not stop the links
                log.exception("offering a frame from %s failed", key)

    def _offer(self, key: str, payload: bytes) -> None:
        frame = decode_frame(payload, self._accepted)
        key_camera = key.rsplit("/", 2)[-2]
        if key_camera != str(frame.camera_id):
            raise Rejected("key_mismatch", f"frame of camera {frame.camera_id} published on "
                                           f"{key}")
        now_ms = self._clock.now_ms()
        if frame.generation_ms > now_ms + self._max_skew_ms:
            raise Rejected("clock_skew",
                           f"frame generated at {frame.generation_ms:.0f} ms but the clock "
                           f"says {now_ms:.0f} ms; check AOI3D_EPOCH_S and AOI3D_TIME_SCALE")
        n = frame.camera_id
        with self._lock:
            link = self._links[n]
            rng = self._reseed.get(n)
            if rng is not None and not link.in_flight(frame.generation_ms):
                link = self._links[n] = Link(link.delay, rng)
                del self._reseed[n]
            slot = link.offer(frame.generation_ms)
            stats = self._stats[n]
            stats.offered += 1
            if slot is None:
                stats.dropped += 1
        self._offered.labels(camera=str(n)).inc()
        if slot is None:
            self._dropped.labels(camera=str(n)).inc()
            return
        with self._heap_cond:
            heapq.heappush(self._heap, _Pending(float(slot), next(self._order), n,
                                                frame.generation_ms, payload))
            self._heap_cond.notify()

    # ------------------------------------------------------------------ deliveries
    def _delivery_loop(self) -> None:
        while not self._stop.is_set():
            with self._heap_cond:
                if not self._heap:
                    self._heap_cond.wait(_POLL_S)
                    continue
                head = self._heap[0]
                wait_s = self._clock.wall_s(head.delivery_ms) - self._clock.wall()
                if wait_s > 0:
                    self._heap_cond.wait(min(wait_s, _POLL_S))
                    continue
                heapq.heappop(self._heap)
            try:
                self._deliver(head)
            except Exception:
                log.exception("delivering a frame of camera %d failed", head.camera_id)

    def _deliver(self, item: _Pending) -> None:
        n = item.camera_id
        self._bus.publish(self._keys.edge_frame(n), with_delivery(item.payload, item.delivery_ms))
        with self._lock:
            self._stats[n].delivered += 1
        self._delivered.labels(camera=str(n)).inc()
        delay_ms = item.delivery_ms - item.generation_ms
        if math.isfinite(delay_ms):
            self._delay_s.observe(delay_ms / 1000.0)
