"""The camera worker: plays the dataset back on the shared clock, one frame per camera per tick.

What a tick publishes, the configuration and the tick grid are the core's
(:class:`services.camera.core.CameraCore`, no I/O); this worker runs its loop on the shared
clock (:class:`services.kit.runtime.Loops`), publishes and counts. When the loop falls behind
it skips to the newest due tick (and counts the skipped ones) rather than bursting stale
frames.
"""

from __future__ import annotations

import logging
import math
import threading
import time

from prometheus_client import CollectorRegistry, Counter

from aoi3d.clock import SimClock
from aoi3d.scene import SceneDataset
from services.camera.core import (
    MAX_PERIOD_MS,
    MIN_PERIOD_MS,
    CameraConfig,
    CameraConfigError,
    CameraCore,
)
from services.kit.bus import Bus
from services.kit.keys import Keys
from services.kit.runtime import Loops

log = logging.getLogger(__name__)

__all__ = ["MAX_PERIOD_MS", "MIN_PERIOD_MS", "CameraConfig", "CameraConfigError",
           "CameraRuntime"]

_ERROR_LOG_INTERVAL_S = 10.0


class CameraRuntime:
    """Publishes the rig's frames every period on its own thread."""

    def __init__(self, *, bus: Bus, registry: CollectorRegistry, dataset: SceneDataset,
                 clock: SimClock, keys: Keys, n_cameras: int, period_ms: float = 30.0,
                 paused: bool = False, cameras: list[int] | None = None,
                 phase_ms: float = 0.0) -> None:
        self._bus = bus
        self._clock = clock
        self.core = CameraCore(dataset, keys, n_cameras=n_cameras, period_ms=period_ms,
                               paused=paused, cameras=cameras, phase_ms=phase_ms)
        self.phase_ms = self.core.phase_ms
        self.heldout_id = self.core.heldout_id
        self.rig = self.core.rig

        self._frames = Counter("aoi3d_frames_generated", "Frames published by the camera rig "
                               "(camera 0 = held-out ground truth).", ["camera"],
                               registry=registry)
        self._skipped = Counter("aoi3d_camera_ticks_skipped", "Generation ticks skipped "
                                "because the loop fell behind the clock.", registry=registry)
        for n in (self.heldout_id, *self.rig):
            self._frames.labels(camera=str(n))

        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._loops = Loops("camera")
        self._loops.thread("loop", self._run)
        self._last_error_log_s = -math.inf

    # ------------------------------------------------------------------ configuration
    @property
    def config(self) -> CameraConfig:
        with self._lock:
            return self.core.config

    def update(self, *, period_ms: float | None = None, paused: bool | None = None,
               cameras: list[int] | None = None) -> CameraConfig:
        """Partial update; effective from the next tick. Raises ``CameraConfigError``."""
        with self._lock:
            new = self.core.update(period_ms=period_ms, paused=paused, cameras=cameras)
        self._wake.set()
        log.info("camera config: period %.6g ms, paused %s, cameras %s",
                 new.period_ms, new.paused, list(new.cameras))
        return new

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._loops.start()

    def stop(self) -> None:
        self._loops.stop_event.set()
        self._wake.set()
        self._loops.stop(timeout_s=2.0)

    def readiness(self) -> tuple[bool, str]:
        why_not = self._loops.not_running()
        if why_not is not None:
            return False, why_not
        if self.config.paused:
            return True, "paused"
        if self.core.ticks == 0:
            return False, "no tick published yet"
        return True, ""

    @property
    def ticks(self) -> int:
        """Ticks published so far."""
        return self.core.ticks

    # ------------------------------------------------------------------ the loop
    def _run(self, stop: threading.Event) -> None:
        clock, core = self._clock, self.core
        next_k: int | None = None
        while not stop.is_set():
            cfg = self.config
            if cfg.paused:
                self._wake.wait(0.5)
                self._wake.clear()
                next_k = None
                continue
            period = cfg.period_ms
            if next_k is None:
                with self._lock:
                    next_k = core.first_tick(clock.now_ms(), period)
            wait_s = clock.wall_s(next_k * period) - clock.wall()
            if wait_s > 0 and self._wake.wait(wait_s):
                self._wake.clear()  # config changed or stopping: re-plan the next tick
                next_k = None
                continue
            next_k, skipped = core.catch_up(next_k, clock.now_ms(), period)
            if skipped:
                self._skipped.inc(skipped)
            with self._lock:
                tick = core.tick(next_k, next_k * period, cfg.cameras)
            for key, payload, n in tick.frames:
                self._bus.publish(key, payload)
                self._frames.labels(camera=str(n)).inc()
            for error in tick.errors:
                self._log_error(error)
            next_k += 1

    def _log_error(self, msg: str) -> None:
        now = time.monotonic()
        if now - self._last_error_log_s >= _ERROR_LOG_INTERVAL_S:
            self._last_error_log_s = now
            log.error("%s", msg)
