"""The camera rig's core: a configuration and a time in, the frames of a tick out.

No bus, no threads, no metrics library: the runtime (:mod:`services.camera.runtime`) calls it
from its loop and publishes what it returns; tests drive it directly.

Every period C (sim ms), at the aligned times t = k·C, each active training camera n shows
the dataset frame of scene time t + phase (``dataset.frame_index``), published on
``cam/<n>/frame``, and the held-out camera's frame goes to ``truth/frame``. The images are the
dataset's PNG files as-is. A frame's ``sequence`` is its tick index k on the grid of the period
in force (so it restarts on another scale after a period change).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from aoi3d.scene import DatasetError, SceneDataset
from services.kit.codec import PNG, encode_frame
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb

__all__ = ["MAX_PERIOD_MS", "MIN_PERIOD_MS", "CameraConfig", "CameraConfigError", "CameraCore",
           "Tick"]

MIN_PERIOD_MS = 1.0
"""One slot: time is slotted at 1 ms, so no camera generates faster (19 cameras at the
minimum already offer 19,000 frames per sim second)."""
MAX_PERIOD_MS = 60_000.0


class CameraConfigError(ValueError):
    """A configuration change that cannot be applied; the message says what is accepted."""


@dataclass(frozen=True)
class CameraConfig:
    """What the rig streams: the period C (sim ms), whether paused, the active camera ids."""

    period_ms: float
    paused: bool
    cameras: tuple[int, ...]


@dataclass
class Tick:
    """What one tick publishes: ``(key, payload, camera_id)`` per frame, and what could not
    be read (one line each; the frame is skipped, the tick goes on)."""

    k: int
    t_ms: float
    frames: list[tuple[str, bytes, int]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)


class CameraCore:
    """The rig of one site: its configuration, its tick grid and its frames. Not thread-safe:
    the runtime serialises calls.

    ``phase_ms``: shown scene time = generation time + this (another site's view of the
    loop)."""

    def __init__(self, dataset: SceneDataset, keys: Keys, *, n_cameras: int,
                 period_ms: float = 30.0, paused: bool = False,
                 cameras: list[int] | None = None, phase_ms: float = 0.0) -> None:
        self.dataset = dataset
        self.keys = keys
        self.phase_ms = float(phase_ms)
        self.heldout_id = int(dataset.heldout_id)
        train_ids = sorted(int(i) for i in dataset.train_ids)
        if n_cameras > len(train_ids):
            raise ValueError(
                f"{n_cameras} training cameras requested (AOI3D_CAMERAS) but the dataset at "
                f"{dataset.root} has {len(train_ids)} ({train_ids[0]}..{train_ids[-1]})")
        #: The training cameras of this run: ids 1..N of the dataset's rig.
        self.rig: tuple[int, ...] = tuple(i for i in train_ids if 1 <= i <= n_cameras)
        self.config = self._checked(CameraConfig(
            period_ms=float(period_ms), paused=bool(paused),
            cameras=self.rig if not cameras else tuple(cameras)))
        self.ticks = 0
        """Ticks published so far."""
        self.last_tick_ms = -math.inf

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

    def update(self, *, period_ms: float | None = None, paused: bool | None = None,
               cameras: list[int] | None = None) -> CameraConfig:
        """Partial update, effective from the next tick; nothing changes when it raises
        ``CameraConfigError``."""
        cfg = self.config
        self.config = self._checked(CameraConfig(
            period_ms=cfg.period_ms if period_ms is None else float(period_ms),
            paused=cfg.paused if paused is None else bool(paused),
            cameras=cfg.cameras if cameras is None else tuple(cameras)))
        return self.config

    # ------------------------------------------------------------------ the tick grid
    def first_tick(self, now_ms: float, period_ms: float) -> int:
        """Index of the first tick at or after ``now_ms`` that is later than the last one
        published (sim time starts at 0)."""
        k = max(0, math.ceil(now_ms / period_ms))
        if math.isfinite(self.last_tick_ms):
            k = max(k, math.floor(self.last_tick_ms / period_ms) + 1)
        return k

    @staticmethod
    def catch_up(next_k: int, now_ms: float, period_ms: float) -> tuple[int, int]:
        """(the tick to publish, ticks skipped): when the loop fell behind the clock it
        publishes the newest due tick rather than bursting stale frames."""
        due_k = math.floor(now_ms / period_ms)
        return (due_k, due_k - next_k) if due_k > next_k else (next_k, 0)

    # ------------------------------------------------------------------ frames
    def tick(self, k: int, t_ms: float, cameras: tuple[int, ...]) -> Tick:
        """The frames of tick ``k`` at ``t_ms``: the held-out camera's first, then each of
        ``cameras``; marks the tick published."""
        out = Tick(k, t_ms)
        ds = self.dataset
        try:
            index = ds.frame_index(t_ms + self.phase_ms)
            scene_ms = float(ds.scene_time_ms(t_ms + self.phase_ms))
        except Exception as err:  # reported; the loop goes on
            out.errors.append(f"dataset time lookup failed at t={t_ms:.1f} ms: {err!r}")
            return out
        for n in (self.heldout_id, *cameras):
            try:
                camera = ds.cameras[n]
                image = pb.Image(encoding=PNG, width=camera.width, height=camera.height,
                                 data=ds.frame_png(n, index))
                payload = encode_frame(camera_id=n, sequence=k, generation_ms=t_ms,
                                       scene_time_ms=scene_ms, send_ms=t_ms, camera=camera,
                                       image=image)
            except DatasetError as err:  # a missing or damaged file: skip it, one line
                out.errors.append(str(err))
                continue
            except Exception as err:  # anything else: skip this frame
                out.errors.append(f"frame {index} of camera {n} could not be read: {err!r}")
                continue
            key = self.keys.truth if n == self.heldout_id else self.keys.cam_frame(n)
            out.frames.append((key, payload, n))
        self.ticks += 1
        self.last_tick_ms = t_ms
        return out
