"""The metrics worker: pairs each render of the novel view with its ground truth and scores it.

Bus handlers only enqueue; one scoring thread decodes, pairs, calls
:func:`aoi3d.quality.score` and publishes a ``Quality`` message. Pairing rule: a render at
decision time t is compared with the ground-truth frame generated exactly at t; failing
that, with the newest one generated in [t − C, t] (C = ``truth_period_ms``); failing that the
render is rejected with reason ``no_truth`` (counted in ``aoi3d_messages_rejected_total``).

Dynamic region: the truth frame paired with a render, generated at t', is compared with the
truth frames generated at t' − C and t' − 2C (each the newest generated within half a period
of that time, from the same ring) to build the mask of :func:`aoi3d.quality.dynamic_mask`;
the render's PSNR and SSIM over it and its pixel fraction go into the Quality message. When
those earlier frames are missing (the first two periods, a gap, a size change) the dynamic
fields are absent and the render is counted in ``aoi3d_quality_dynamic_missing_total`` with
reason ``no_history``; an empty mask (nothing moved) leaves the two scores absent and counts
reason ``empty_mask``. The full-image scores and the reward do not depend on either.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from aoi3d.clock import SimClock
from aoi3d.quality import DYNAMIC_FRAMES, LpipsFn, RewardWeights, score
from aoi3d.scene import HELDOUT_ID  # the held-out novel view: the only camera on the truth key
from services.kit.bus import Bus, Inbox
from services.kit.codec import check_size, decode_frame, decode_image, decode_render
from services.kit.keys import DEFAULT_SITE, Keys
from services.kit.observe import Heartbeat, Rejected, Rejections
from services.kit.pb import aoi3d_pb2 as pb

log = logging.getLogger(__name__)

_POLL_S = 0.1  # longest wait on the inbox before checking the stop flag
_TIME_TOL_MS = 1e-6  # generation times this close to t count as "at t" (float round-off)


@dataclass(frozen=True)
class TruthFrame:
    """A ground-truth frame of the held-out camera, image still encoded."""

    generation_ms: float
    scene_time_ms: float
    image: pb.Image


class TruthRing:
    """The most recent ground-truth frames, by generation time (not thread-safe)."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self._capacity = capacity
        self._times: list[float] = []  # sorted generation times
        self._frames: dict[float, TruthFrame] = {}

    def __len__(self) -> int:
        return len(self._times)

    def add(self, frame: TruthFrame) -> None:
        """Keep ``frame`` (a repeat of a generation time replaces it); evict the oldest."""
        if frame.generation_ms not in self._frames:
            bisect.insort(self._times, frame.generation_ms)
        self._frames[frame.generation_ms] = frame
        while len(self._times) > self._capacity:
            del self._frames[self._times.pop(0)]

    def pair(self, time_ms: float, period_ms: float) -> TruthFrame:
        """The frame generated at ``time_ms``, else the newest in [time_ms − period_ms,
        time_ms]; raises ``Rejected("no_truth")`` when there is none."""
        exact = self._frames.get(time_ms)
        if exact is not None:
            return exact
        i = bisect.bisect_right(self._times, time_ms + _TIME_TOL_MS) - 1
        if i >= 0 and time_ms - self._times[i] <= period_ms + _TIME_TOL_MS:
            return self._frames[self._times[i]]
        held = (f"holding {len(self)} frame(s) generated in [{self._times[0]:g}, "
                f"{self._times[-1]:g}] ms" if self._times else "holding no frame")
        raise Rejected("no_truth", f"no ground-truth frame generated at t = {time_ms:g} ms or "
                                   f"within {period_ms:g} ms before it ({held})")

    def before(self, generation_ms: float, period_ms: float, count: int
               ) -> list[TruthFrame] | None:
        """The frames generated at ``generation_ms`` − k·``period_ms``, k = 1..``count``:
        for each, the newest generated in (that time − period/2, that time + period/2];
        None when any of them is missing."""
        half = period_ms / 2.0
        frames = []
        for k in range(1, count + 1):
            target = generation_ms - k * period_ms
            i = bisect.bisect_right(self._times, target + half) - 1
            if i < 0 or self._times[i] <= target - half:
                return None
            frames.append(self._frames[self._times[i]])
        return frames


@dataclass(frozen=True)
class QualityRecord:
    """One scored render (the published Quality plus the render's context)."""

    decision_id: int
    time_ms: float
    truth_time_ms: float
    scene_time_ms: float
    psnr_db: float
    ssim: float
    lpips: float | None
    reward: float
    reward_terms: tuple[str, ...]
    training_step: int
    n_views: int
    backend: str
    lag_ms: float
    """Sim ms between the render's time t and its scoring."""
    psnr_dynamic_db: float | None = None
    """PSNR over the dynamic region; None when its mask is empty or could not be built."""
    ssim_dynamic: float | None = None
    """SSIM over the dynamic region; None likewise."""
    dynamic_fraction: float | None = None
    """Pixel fraction of the dynamic mask; None when the earlier truth frames were missing."""


class MetricsWorker:
    """Subscribes ``truth/frame`` and ``render``; publishes ``quality``; keeps a history."""

    def __init__(self, bus: Bus, registry: CollectorRegistry, *, run_id: str,
                 site: str = DEFAULT_SITE, clock: SimClock,
                 truth_period_ms: float = 30.0, truth_frames: int = 512, history: int = 1000,
                 inbox_size: int = 256, weights: RewardWeights | None = None,
                 lpips_fn: LpipsFn | None = None, max_skew_ms: float = 50.0,
                 stall_s: float = 30.0) -> None:
        if not (math.isfinite(truth_period_ms) and truth_period_ms > 0):
            raise ValueError(f"truth_period_ms must be > 0, got {truth_period_ms}")
        self._bus = bus
        self._keys = Keys(run_id, site)
        self.site = site
        self._clock = clock
        self._period_ms = truth_period_ms
        self._skew_ms = float(max_skew_ms)
        self._quality_beat = Heartbeat(stall_s)  # a Quality published
        self._weights = weights or RewardWeights()
        self._lpips_fn = lpips_fn
        self._inbox = Inbox(inbox_size, on_drop=lambda: self._m_inbox_dropped.inc())
        self._ring = TruthRing(truth_frames)  # used by the scoring thread only
        self._history: deque[QualityRecord] = deque(maxlen=history)
        self._scored = 0
        self._lock = threading.Lock()  # guards _history and _scored
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._started = False

        self.rejections = Rejections(registry)
        self._m_quality = Counter("aoi3d_quality", "Renders scored against their ground truth.",
                                  registry=registry)
        self._m_truth = Counter("aoi3d_truth_frames", "Ground-truth frames received.",
                                registry=registry)
        self._m_inbox_dropped = Counter(
            "aoi3d_inbox_dropped", "Messages dropped because the scoring thread fell behind.",
            registry=registry)
        self._m_psnr = Gauge("aoi3d_render_psnr_db", "PSNR of the latest scored render (dB); "
                             "NaN before the first.", registry=registry)
        self._m_ssim = Gauge("aoi3d_render_ssim", "SSIM of the latest scored render; NaN "
                             "before the first.", registry=registry)
        self._m_reward = Gauge("aoi3d_reward", "Reward of the latest scored render; NaN before "
                               "the first.", registry=registry)
        self._m_psnr_dyn = Gauge(
            "aoi3d_render_psnr_dynamic_db", "PSNR of the latest scored render over the dynamic "
            "region, the pixels whose truth changed over the last two frame periods (dB); NaN "
            "when that render has none.", registry=registry)
        self._m_ssim_dyn = Gauge(
            "aoi3d_render_ssim_dynamic", "SSIM of the latest scored render over the dynamic "
            "region; NaN when that render has none.", registry=registry)
        self._m_dyn_fraction = Gauge(
            "aoi3d_render_dynamic_fraction", "Pixel fraction of the latest scored render's "
            "dynamic mask (0 to 1); NaN when the earlier truth frames were missing.",
            registry=registry)
        for gauge in (self._m_psnr, self._m_ssim, self._m_reward, self._m_psnr_dyn,
                      self._m_ssim_dyn, self._m_dyn_fraction):
            gauge.set(math.nan)
        self._m_dyn_missing = Counter(
            "aoi3d_quality_dynamic_missing", "Scored renders without a dynamic-region score: "
            "no_history (the truth frames one and two periods earlier were missing) or "
            "empty_mask (nothing in the view moved).", ["reason"], registry=registry)
        for reason in ("no_history", "empty_mask"):
            self._m_dyn_missing.labels(reason=reason)
        self._dyn_missing = {"no_history": 0, "empty_mask": 0}  # guarded by _lock
        # Exported only when LPIPS is available: a 0 would read as a perfect score.
        self._m_lpips = None
        if lpips_fn is not None:
            self._m_lpips = Gauge("aoi3d_render_lpips", "LPIPS of the latest scored render.",
                                  registry=registry)
            self._m_lpips.set(math.nan)
        # Every score also into a histogram: a scrape every 5 s sees one render in three with
        # the last-value gauges, but rate(_sum)/rate(_count) averages every render since.
        db = (10.0, 14.0, 18.0, 20.0, 22.0, 24.0, 26.0, 28.0, 30.0, 35.0, 40.0)
        unit = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 1.0)
        every = " of every scored render (rate(_sum)/rate(_count): the mean over a window)."
        self._h_psnr = Histogram("aoi3d_quality_psnr_db", "PSNR (dB)" + every, buckets=db,
                                 registry=registry)
        self._h_psnr_dyn = Histogram("aoi3d_quality_psnr_dynamic_db",
                                     "Dynamic-region PSNR (dB)" + every, buckets=db,
                                     registry=registry)
        self._h_ssim = Histogram("aoi3d_quality_ssim", "SSIM" + every, buckets=unit,
                                 registry=registry)
        self._h_reward = Histogram("aoi3d_quality_reward", "Reward" + every,
                                   buckets=(0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5),
                                   registry=registry)
        self._h_lpips = None
        if lpips_fn is not None:
            self._h_lpips = Histogram("aoi3d_quality_lpips", "LPIPS" + every, buckets=unit,
                                      registry=registry)
        self._m_lag = Histogram(
            "aoi3d_render_lag_seconds",
            "Sim seconds between a render's decision time t and its scoring.",
            buckets=(0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0), registry=registry)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._started:
            raise RuntimeError("the metrics worker was already started")
        self._started = True
        self._bus.subscribe(self._keys.truth, self._enqueue("truth"))
        self._bus.subscribe(self._keys.render, self._enqueue("render"))
        self._thread = threading.Thread(target=self._run, name="metrics-scoring", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def readiness(self) -> tuple[bool, str]:
        if self._thread is None or not self._thread.is_alive():
            return False, "scoring thread not running"
        with self._lock:
            scored = self._scored
        if self._quality_beat.stalled():
            return False, (f"no Quality for {self._quality_beat.idle_s():.0f} s (no renders, "
                           f"or none with a truth frame of their time)")
        return True, f"{scored} render(s) scored" if scored else "waiting for renders"

    # ------------------------------------------------------------------ queries
    @property
    def lpips_available(self) -> bool:
        return self._lpips_fn is not None

    @property
    def reward_terms(self) -> tuple[str, ...]:
        """The terms the reward is built from with the metrics available now."""
        return ("psnr", "ssim", "lpips") if self._lpips_fn is not None else ("psnr", "ssim")

    @property
    def scored_total(self) -> int:
        with self._lock:
            return self._scored

    def dynamic_missing(self, reason: str) -> int:
        """Scored renders without a dynamic score, by reason (no_history, empty_mask)."""
        with self._lock:
            return self._dyn_missing[reason]

    def history(self, limit: int | None = None) -> list[QualityRecord]:
        """The most recent ``limit`` results (all kept when None), oldest first."""
        with self._lock:
            records = list(self._history)
        return records if limit is None else records[max(0, len(records) - limit):]

    # ------------------------------------------------------------------ the scoring thread
    def _enqueue(self, kind: str):
        def handler(key: str, payload: bytes) -> None:
            self._inbox.put((kind, key, payload))

        return handler

    def _run(self) -> None:
        while not self._stop.is_set():
            item = self._inbox.get(timeout=_POLL_S)
            if item is None:
                continue
            kind, key, payload = item
            try:
                if kind == "truth":
                    self._on_truth(payload)
                else:
                    self._on_render(payload)
            except Rejected as err:
                self.rejections.reject(err, key)
            except Exception as err:  # a bug must not kill the thread; count and go on
                log.exception("failed to handle a message on %s", key)
                self.rejections.reject(Rejected("internal_error", repr(err)), key)

    def _ahead(self, what: str, time_ms: float) -> None:
        """Reject a message stamped ahead of this clock by more than the skew: 512 truth
        frames from the future would otherwise push every real one out of the ring."""
        now_ms = self._clock.now_ms()
        if time_ms > now_ms + self._skew_ms:
            raise Rejected("clock_skew", f"{what} at {time_ms:g} ms but this clock says "
                                         f"{now_ms:g} ms")

    def _on_truth(self, payload: bytes) -> None:
        frame = decode_frame(payload, camera_ids={HELDOUT_ID})
        self._ahead("truth frame generated", frame.generation_ms)
        self._ring.add(TruthFrame(generation_ms=frame.generation_ms,
                                  scene_time_ms=frame.scene_time_ms, image=frame.image))
        self._m_truth.inc()

    def _on_render(self, payload: bytes) -> None:
        render, _camera = decode_render(payload)
        self._ahead("render for", render.time_ms)
        truth = self._ring.pair(render.time_ms, self._period_ms)
        check_size(render.image, (truth.image.width, truth.image.height))
        pred = decode_image(render.image)
        gt = decode_image(truth.image)
        if pred.shape != gt.shape:
            raise Rejected("image_size_mismatch",
                           f"render is {pred.shape[1]}x{pred.shape[0]} but the ground truth is "
                           f"{gt.shape[1]}x{gt.shape[0]}")
        previous = self._previous_truth(truth, gt.shape)
        try:
            q = score(pred, gt, self._weights, lpips_fn=self._lpips_fn, previous=previous)
        except ValueError as err:
            raise Rejected("unscorable", str(err)) from err
        dyn = q.dynamic

        msg = pb.Quality(decision_id=render.decision_id,
                         decision_incarnation=render.decision_incarnation,
                         time_ms=render.time_ms,
                         scene_time_ms=truth.scene_time_ms, psnr_db=q.psnr_db, ssim=q.ssim,
                         reward=q.reward, reward_terms=list(q.reward_terms),
                         training_step=render.training_step,
                         truth_time_ms=truth.generation_ms, site=self.site)
        if q.lpips is not None:
            msg.lpips = q.lpips  # proto3 optional: left unset (absent) when unavailable
        if dyn is not None:
            msg.dynamic_fraction = dyn.fraction
            if dyn.psnr_db is not None:
                msg.psnr_dynamic_db = dyn.psnr_db
            if dyn.ssim is not None:
                msg.ssim_dynamic = dyn.ssim
        self._bus.publish(self._keys.quality, msg.SerializeToString())

        lag_ms = self._clock.now_ms() - render.time_ms
        record = QualityRecord(
            decision_id=render.decision_id, time_ms=render.time_ms,
            truth_time_ms=truth.generation_ms, scene_time_ms=truth.scene_time_ms,
            psnr_db=q.psnr_db, ssim=q.ssim, lpips=q.lpips, reward=q.reward,
            reward_terms=q.reward_terms, training_step=render.training_step,
            n_views=render.n_views, backend=render.backend, lag_ms=lag_ms,
            psnr_dynamic_db=dyn.psnr_db if dyn else None,
            ssim_dynamic=dyn.ssim if dyn else None,
            dynamic_fraction=dyn.fraction if dyn else None)
        missing = ("no_history" if dyn is None else
                   "empty_mask" if dyn.psnr_db is None else None)
        with self._lock:
            self._history.append(record)
            self._scored += 1
            if missing is not None:
                self._dyn_missing[missing] += 1
        self._m_quality.inc()
        self._quality_beat.beat()
        self._m_psnr.set(q.psnr_db)
        self._m_ssim.set(q.ssim)
        self._m_reward.set(q.reward)
        self._m_psnr_dyn.set(_or_nan(record.psnr_dynamic_db))
        self._m_ssim_dyn.set(_or_nan(record.ssim_dynamic))
        self._m_dyn_fraction.set(_or_nan(record.dynamic_fraction))
        if missing is not None:
            self._m_dyn_missing.labels(reason=missing).inc()
        if self._m_lpips is not None and q.lpips is not None:
            self._m_lpips.set(q.lpips)
        self._h_psnr.observe(q.psnr_db)
        self._h_ssim.observe(q.ssim)
        self._h_reward.observe(q.reward)
        if record.psnr_dynamic_db is not None:
            self._h_psnr_dyn.observe(record.psnr_dynamic_db)
        if self._h_lpips is not None and q.lpips is not None:
            self._h_lpips.observe(q.lpips)
        if math.isfinite(lag_ms) and lag_ms >= 0:
            self._m_lag.observe(lag_ms / 1000.0)


    def _previous_truth(self, truth: TruthFrame, shape: tuple[int, ...]
                        ) -> list[np.ndarray] | None:
        """The decoded truth one to K periods before ``truth`` (see :meth:`TruthRing.before`),
        or None when a frame is missing, undecodable or of another size."""
        frames = self._ring.before(truth.generation_ms, self._period_ms, DYNAMIC_FRAMES)
        if frames is None:
            return None
        images = []
        for frame in frames:
            try:
                image = decode_image(frame.image)
            except Rejected:
                return None
            if image.shape != shape:
                return None
            images.append(image)
        return images


def _or_nan(value: float | None) -> float:
    return math.nan if value is None else value


def mean_of_present(values: list[float | None]) -> float | None:
    """The mean of the values that are not None, or None when there are none."""
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None


def mean_or_none(values: list[float | None]) -> float | None:
    """The mean of ``values``, or None when empty or when any value is None."""
    if not values or any(v is None for v in values):
        return None
    return float(np.mean(values))
