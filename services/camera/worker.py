"""The camera worker: plays the dataset back on the shared clock, one frame per camera per tick.

Every period C (sim ms) at the aligned times t = k·C it publishes, for each active training
camera n, the dataset frame shown at t (``dataset.frame_index(t)``) on ``cam/<n>/frame``, and
the held-out camera's frame on ``truth/frame``. The images are the dataset's PNG files as-is.
When the loop falls behind it skips to the newest due tick (and counts the skipped ones)
rather than bursting stale frames. A frame's ``sequence`` is its tick index k on the grid of
the period in force (so it restarts on another scale after a period change).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, replace

from prometheus_client import CollectorRegistry, Counter

from aoi3d.clock import SimClock
from aoi3d.scene import DatasetError, SceneDataset
from services.kit.bus import Bus
from services.kit.codec import PNG, encode_frame
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb

log = logging.getLogger(__name__)

MIN_PERIOD_MS = 1.0
"""One slot: time is slotted at 1 ms, so no camera generates faster (19 cameras at the
minimum already offer 19,000 frames per sim second)."""
MAX_PERIOD_MS = 60_000.0
_ERROR_LOG_INTERVAL_S = 10.0


class CameraConfigError(ValueError):
    """A configuration change that cannot be applied; the message says what is accepted."""


@dataclass(frozen=True)
class CameraConfig:
    """What the rig streams: the period C (sim ms), whether paused, the active camera ids."""

    period_ms: float
    paused: bool
    cameras: tuple[int, ...]


class CameraWorker:
    """Publishes the rig's frames every period on its own thread."""

    def __init__(self, *, bus: Bus, registry: CollectorRegistry, dataset: SceneDataset,
                 clock: SimClock, keys: Keys, n_cameras: int, period_ms: float = 30.0,
                 paused: bool = False, cameras: list[int] | None = None,
                 phase_ms: float = 0.0) -> None:
        self._bus = bus
        self.phase_ms = float(phase_ms)
        """Shown scene time = generation time + this (another site's view of the loop)."""
        self._dataset = dataset
        self._clock = clock
        self._keys = keys
        self.heldout_id = int(dataset.heldout_id)
        train_ids = sorted(int(i) for i in dataset.train_ids)
        if n_cameras > len(train_ids):
            raise ValueError(
                f"{n_cameras} training cameras requested (AOI3D_CAMERAS) but the dataset at "
                f"{dataset.root} has {len(train_ids)} ({train_ids[0]}..{train_ids[-1]})")
        #: The training cameras of this run: ids 1..N of the dataset's rig.
        self.rig: tuple[int, ...] = tuple(i for i in train_ids if 1 <= i <= n_cameras)
        self._config = self._checked(CameraConfig(
            period_ms=float(period_ms), paused=bool(paused),
            cameras=self.rig if not cameras else tuple(cameras)))

        self._frames = Counter("aoi3d_frames_generated", "Frames published by the camera rig "
                               "(camera 0 = held-out ground truth).", ["camera"],
                               registry=registry)
        self._skipped = Counter("aoi3d_camera_ticks_skipped", "Generation ticks skipped "
                                "because the loop fell behind the clock.", registry=registry)
        for n in (self.heldout_id, *self.rig):
            self._frames.labels(camera=str(n))

        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ticks = 0
        self._last_tick_ms = -math.inf
        self._last_error_log_s = -math.inf

    # ------------------------------------------------------------------ configuration
    def _checked(self, cfg: CameraConfig) -> CameraConfig:
        if not (math.isfinite(cfg.period_ms) and MIN_PERIOD_MS <= cfg.period_ms <= MAX_PERIOD_MS):
            raise CameraConfigError(
                f"period_ms must be >= {MIN_PERIOD_MS:g} and <= {MAX_PERIOD_MS:g} sim ms, got "
                f"{cfg.period_ms}")
        unknown = sorted(set(cfg.cameras) - set(self.rig))
        if unknown:
            what = ("camera 0 is the held-out view (always published on truth/frame)"
                    if unknown == [self.heldout_id] else f"unknown camera id(s) {unknown}")
            raise CameraConfigError(
                f"{what}; accepted training camera ids: {self.rig[0]}..{self.rig[-1]}")
        return replace(cfg, cameras=tuple(sorted(set(cfg.cameras))))

    @property
    def config(self) -> CameraConfig:
        with self._lock:
            return self._config

    def update(self, *, period_ms: float | None = None, paused: bool | None = None,
               cameras: list[int] | None = None) -> CameraConfig:
        """Partial update; effective from the next tick. Raises ``CameraConfigError``."""
        with self._lock:
            cfg = self._config
            new = self._checked(CameraConfig(
                period_ms=cfg.period_ms if period_ms is None else float(period_ms),
                paused=cfg.paused if paused is None else bool(paused),
                cameras=cfg.cameras if cameras is None else tuple(cameras)))
            self._config = new
        self._wake.set()
        log.info("camera config: period %.6g ms, paused %s, cameras %s",
                 new.period_ms, new.paused, list(new.cameras))
        return new

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="camera-loop", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                log.warning("camera loop did not stop within 2 s")

    def readiness(self) -> tuple[bool, str]:
        if self._thread is None or not self._thread.is_alive():
            return False, "camera loop not running"
        if self.config.paused:
            return True, "paused"
        if self._ticks == 0:
            return False, "no tick published yet"
        return True, ""

    @property
    def ticks(self) -> int:
        """Ticks published so far."""
        return self._ticks

    # ------------------------------------------------------------------ the loop
    def _first_tick(self, period_ms: float) -> int:
        """Index of the first tick at or after now that is later than the last one published."""
        k = max(0, math.ceil(self._clock.now_ms() / period_ms))  # sim time starts at 0
        if math.isfinite(self._last_tick_ms):
            k = max(k, math.floor(self._last_tick_ms / period_ms) + 1)
        return k

    def _run(self) -> None:
        next_k: int | None = None
        while not self._stop.is_set():
            cfg = self.config
            if cfg.paused:
                self._wake.wait(0.5)
                self._wake.clear()
                next_k = None
                continue
            period = cfg.period_ms
            if next_k is None:
                next_k = self._first_tick(period)
            t_ms = next_k * period
            wait_s = self._clock.wall_s(t_ms) - self._clock.wall()
            if wait_s > 0 and self._wake.wait(wait_s):
                self._wake.clear()  # config changed or stopping: re-plan the next tick
                next_k = None
                continue
            due_k = math.floor(self._clock.now_ms() / period)
            if due_k > next_k:  # fell behind: publish the newest due tick, skip the rest
                self._skipped.inc(due_k - next_k)
                next_k = due_k
                t_ms = next_k * period
            self._tick(next_k, t_ms, cfg.cameras)
            next_k += 1

    def _tick(self, k: int, t_ms: float, cameras: tuple[int, ...]) -> None:
        ds = self._dataset
        try:
            index = ds.frame_index(t_ms + self.phase_ms)
            scene_ms = float(ds.scene_time_ms(t_ms + self.phase_ms))
        except Exception:
            self._log_error("dataset time lookup failed at t=%.1f ms", t_ms)
            return
        for n in (self.heldout_id, *cameras):
            try:
                camera = ds.cameras[n]
                image = pb.Image(encoding=PNG, width=camera.width, height=camera.height,
                                 data=ds.frame_png(n, index))
                payload = encode_frame(camera_id=n, sequence=k, generation_ms=t_ms,
                                       scene_time_ms=scene_ms, send_ms=t_ms, camera=camera,
                                       image=image)
            except DatasetError as err:  # a missing or damaged file: skip it, one line
                self._log_error("%s", err, trace=False)
                continue
            except Exception:  # anything else: skip this frame, keep the loop alive
                self._log_error("frame %d of camera %d could not be read", index, n)
                continue
            key = self._keys.truth if n == self.heldout_id else self._keys.cam_frame(n)
            self._bus.publish(key, payload)
            self._frames.labels(camera=str(n)).inc()
        self._ticks += 1
        self._last_tick_ms = t_ms

    def _log_error(self, msg: str, *args: object, trace: bool = True) -> None:
        now = time.monotonic()
        if now - self._last_error_log_s >= _ERROR_LOG_INTERVAL_S:
            self._last_error_log_s = now
            (log.exception if trace else log.error)(msg, *args)
