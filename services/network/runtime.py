"""The network worker: the cameras' D/G/1/0 uplinks between the rig and the edge server.

Offered frames (``cam/<n>/frame``) go through camera n's :class:`aoi3d.channel.link.Link`:
``offer(generation_ms)`` gives the delivery slot, or None when the previous frame is still in
flight (dropped). Accepted frames wait in a timer heap and are re-published on
``edge/<n>/frame``, stamped with their delivery time, at the wall time of their delivery slot.

The links and the frames in flight are the core's (:class:`services.network.core.NetworkCore`,
no I/O). Threads (:class:`services.kit.runtime.Loops`): the bus callback only enqueues; the
*links* thread decodes, validates and offers; the *delivery* thread publishes due frames.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Histogram

from aoi3d.channel import ACCEPTED_FORMS, CHANNEL_FORMS, parse_channel
from aoi3d.clock import SimClock
from services.kit.bus import Bus, Inbox
from services.kit.codec import with_delivery
from services.kit.keys import Keys
from services.kit.observe import Rejected, Rejections
from services.kit.runtime import Loops
from services.network.core import (
    ChannelConfig,
    ChannelConfigError,
    LinkStats,
    NetworkCore,
    Pending,
)

log = logging.getLogger(__name__)

#: Histogram buckets of the link delay, in sim seconds (slots of 1 ms … 2 s).
DELAY_BUCKETS_S = (0.001, 0.005, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.08, 0.1, 0.125, 0.15,
                   0.2, 0.3, 0.5, 1.0, 2.0)
_POLL_S = 0.1  # longest a thread blocks before checking for stop
#: Sim time over which the measured mean delay (delivery − generation) is taken.
MEASURE_WINDOW_MS = 3000.0
_CHANGES_KEPT = 200

__all__ = ["ChannelConfig", "ChannelConfigError", "LinkStats", "NetworkRuntime"]


class NetworkRuntime:
    """N independent links; frames delivered on the shared clock."""

    def __init__(self, *, bus: Bus, registry: CollectorRegistry, clock: SimClock, keys: Keys,
                 n_cameras: int, delay: str = "exp:60", per_camera: dict[int, str] | None = None,
                 seed: int = 1, max_skew_ms: float = 1000.0, inbox_size: int = 1024,
                 frame_encoding: str = "png") -> None:
        self._bus = bus
        self._clock = clock
        self._keys = keys
        self.core = NetworkCore(n_cameras, delay=delay, per_camera=per_camera, seed=seed,
                                max_skew_ms=max_skew_ms, now_ms=clock.now_ms(),
                                frame_encoding=frame_encoding)
        # the channel's changes, set over REST or by its regimes: {time_ms, spec, cause}
        self._changes: deque[dict[str, Any]] = deque(maxlen=_CHANGES_KEPT)
        self._changes.append({"time_ms": float(self.core.started_ms),
                              "spec": self.core.regime(self.core.started_ms), "cause": "set",
                              "delay": self.core.config.delay})
        self._changes_seen_ms = float(self.core.started_ms)
        self._recent: deque[tuple[float, float]] = deque()  # (delivery, delay) ms
        self.camera_ids = self.core.camera_ids
        self._cond = threading.Condition()  # guards the core; notified on a new frame in flight
        self._inbox = Inbox(inbox_size, on_drop=lambda: self._overflow.inc())
        self._loops = Loops("network")
        self._loops.forever("links", self._link_step)
        self._loops.thread("delivery", self._delivery_loop)

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
    @property
    def config(self) -> ChannelConfig:
        with self._cond:
            return self.core.config

    def update(self, *, delay: str | None = None, per_camera: dict[int, str] | None = None,
               seed: int | None = None) -> ChannelConfig:
        """Partial update (``per_camera`` replaces the whole override map); see
        :meth:`NetworkCore.update`. Raises ``DelaySpecError`` or ``ChannelConfigError``."""
        for spec in [delay, *(per_camera or {}).values()]:
            try:  # a trace is read (and cached, its mean too) here, not under the lock
                if spec is not None:
                    parse_channel(spec).mean_ms  # noqa: B018
            except ValueError:
                pass  # the core says what is wrong, and where
        now = self._clock.now_ms()
        with self._cond:
            self._note_regimes(now)
            old = self.core.config.delay
            new = self.core.update(delay=delay, per_camera=per_camera, seed=seed, now_ms=now)
            if new.delay != old:
                self._changes.append({"time_ms": float(now), "spec": self.core.regime(now),
                                      "cause": "set", "delay": new.delay})
                self._changes_seen_ms = float(now)
        log.info("channel: delay %s, per camera %s, seed %d", new.delay, new.per_camera,
                 new.seed)
        return new

    def _note_regimes(self, now_ms: float) -> None:
        """Log the regime changes of the default channel since the last look (under the
        lock)."""
        if now_ms <= self._changes_seen_ms:
            return
        channel = parse_channel(self.core.config.delay)
        start = max(self._changes_seen_ms, now_ms - 60_000.0 * 10)
        changes = channel.changes_between(start, now_ms, self.core.started_ms)
        for t, spec in changes[-_CHANGES_KEPT:]:
            self._changes.append({"time_ms": float(t), "spec": spec, "cause": "regime"})
            log.info("channel: regime %s at %.0f ms", spec, t)
        self._changes_seen_ms = now_ms

    def channel_state(self) -> dict[str, Any]:
        """The channel side of the console: the spec in force now, when the channel was set,
        its recent changes, and the mean delay (delivery − generation) of the frames
        delivered in the last ``MEASURE_WINDOW_MS`` of sim time."""
        now = self._clock.now_ms()
        with self._cond:
            self._note_regimes(now)
            while self._recent and self._recent[0][0] < now - MEASURE_WINDOW_MS:
                self._recent.popleft()
            delays = [d for _, d in self._recent]
            return {"now_ms": now, "in_force": self.core.regime(now),
                    "started_ms": float(self.core.started_ms),
                    "changes": list(self._changes),
                    "measured_delay_ms": (sum(delays) / len(delays)) if delays else None,
                    "measured_frames": len(delays), "measure_window_ms": MEASURE_WINDOW_MS}

    def link_stats(self) -> list[LinkStats]:
        """A snapshot of every link's counts and state."""
        now = self._clock.now_ms()
        with self._cond:
            return self.core.link_stats(now)

    @staticmethod
    def accepted_forms() -> tuple[str, ...]:
        return ACCEPTED_FORMS + CHANNEL_FORMS

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._loops.start()
        self._bus.subscribe(self._keys.cam_frames, self._on_frame)

    def stop(self) -> None:
        self._loops.stop_event.set()
        with self._cond:
            self._cond.notify_all()
        self._loops.stop(timeout_s=1.0)

    def readiness(self) -> tuple[bool, str]:
        why_not = self._loops.not_running()
        return (False, why_not) if why_not else (True, "")

    @property
    def pending(self) -> int:
        """Frames in flight (accepted, not yet delivered)."""
        with self._cond:
            return self.core.pending

    # ------------------------------------------------------------------ offered frames
    def _on_frame(self, key: str, payload: bytes) -> None:
        """Bus callback: hand off only."""
        self._inbox.put((key, payload))

    def _link_step(self) -> None:
        item = self._inbox.get(timeout=_POLL_S)
        if item is None:
            return
        key, payload = item
        try:
            with self._cond:
                n, queued = self.core.offer(key, payload, self._clock.now_ms())
                if queued is not None:
                    self._cond.notify()
        except Rejected as err:
            self.rejections.reject(err, key)
            return
        self._offered.labels(camera=str(n)).inc()
        if queued is None:
            self._dropped.labels(camera=str(n)).inc()

    # ------------------------------------------------------------------ deliveries
    def _delivery_loop(self, stop: threading.Event) -> None:
        clock = self._clock
        while not stop.is_set():
            with self._cond:
                due = self.core.pop_due(clock.now_ms())
                if not due:
                    head = self.core.next_due_ms()
                    wait_s = _POLL_S if head is None else clock.wall_s(head) - clock.wall()
                    self._cond.wait(min(max(wait_s, 0.0), _POLL_S))
                    continue
            for item in due:
                try:
                    self._deliver(item)
                except Exception:
                    log.exception("delivering a frame of camera %d failed", item.camera_id)

    def _deliver(self, item: Pending) -> None:
        n = item.camera_id
        self._bus.publish(self._keys.edge_frame(n), with_delivery(item.payload, item.delivery_ms))
        self._delivered.labels(camera=str(n)).inc()
        delay_ms = item.delivery_ms - item.generation_ms
        if math.isfinite(delay_ms):
            self._delay_s.observe(delay_ms / 1000.0)
            with self._cond:
                self._recent.append((item.delivery_ms, delay_ms))
                if len(self._recent) > 100_000:
                    self._recent.popleft()
