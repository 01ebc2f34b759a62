"""The metrics worker: the runtime of :class:`services.metrics.core.MetricsCore` (the pairing
and scoring rules are documented there).

Bus handlers only enqueue; one scoring thread hands truth frames and renders to the core,
publishes the ``Quality`` it returns, keeps the history the REST API shows and updates the
Prometheus series. The same thread keeps the site's decision ledger
(:mod:`services.metrics.bookkeeping`): Decisions, the dispatcher's Outcomes and each render's
fate close every decision in exactly one state.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from pathlib import Path
from typing import cast

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from aoi3d.clock import SimClock
from aoi3d.quality import LpipsFn, RewardWeights
from services.kit.bus import Bus, Inbox
from services.kit.keys import DEFAULT_SITE, Keys
from services.kit.observe import Heartbeat, Rejected, Rejections
from services.kit.rejected import RejectReason
from services.kit.runtime import Loops
from services.metrics.bookkeeping import LedgerKeeper
from services.metrics.core import (
    MetricsCore,
    QualityRecord,
    or_nan,
)
from services.metrics.ledger import render_header
from services.metrics.sampling import LpipsSampler

log = logging.getLogger(__name__)

_POLL_S = 0.1  # longest wait on the inbox before checking the stop flag
_TICK_S = 0.2  # how often the ledger expires and saves, and held renders are given up
_MAX_WAITING = 64  # renders held for their truth frame at most
_TIME_TOL_MS = 1e-6  # generation times this close to t count as "at t" (float round-off)


class MetricsRuntime:
    """Subscribes ``truth/frame`` and ``render``; publishes ``quality``; keeps a history."""

    def __init__(self, bus: Bus, registry: CollectorRegistry, *, run_id: str,
                 site: str = DEFAULT_SITE, clock: SimClock,
                 truth_period_ms: float = 30.0, truth_frames: int = 512, history: int = 1000,
                 inbox_size: int = 256, weights: RewardWeights | None = None,
                 lpips_fn: LpipsFn | None = None, max_skew_ms: float = 50.0,
                 stall_s: float = 30.0, ledger_open_s: float = 150.0,
                 state_dir: Path | None = None, truth_wait_s: float = 5.0,
                 lpips_per_s: float = 0.0) -> None:
        self.core = MetricsCore(truth_period_ms=truth_period_ms, truth_frames=truth_frames,
                                weights=weights, lpips_fn=lpips_fn, max_skew_ms=max_skew_ms,
                                site=site)
        self._bus = bus
        self._keys = Keys(run_id, site)
        self.site = site
        self._clock = clock
        self._quality_beat = Heartbeat(stall_s)  # a Quality published
        self._lpips_fn = lpips_fn
        self._lpips_sampler = LpipsSampler(lpips_per_s)  # used by the scoring thread only
        self._inbox = Inbox(inbox_size, on_drop=lambda: self._m_inbox_dropped.inc())
        self._history: deque[QualityRecord] = deque(maxlen=history)
        self._truth_wait_s = float(truth_wait_s)
        self._waiting: deque[tuple[float, float, bytes]] = deque()
        """Renders ahead of every truth frame received: (monotonic deadline, t, payload)."""
        self._scored = 0
        self._lock = threading.Lock()  # guards _history and _scored
        self._loops = Loops("metrics")
        self._loops.thread("scoring", self._run)

        self.rejections = Rejections(registry)
        self.ledger = LedgerKeeper(registry, run_id=run_id, site=site,
                                   open_bound_s=ledger_open_s, state_dir=state_dir)
        self._declare_series(registry, lpips_fn)

    def _declare_series(self, registry: CollectorRegistry, lpips_fn: LpipsFn | None) -> None:
        """The scoring's Prometheus series (the last-value gauges NaN until a render is
        scored; LPIPS's only with ``lpips_fn``)."""
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
        self._m_reward = Gauge("aoi3d_reward", "Reward of the latest render scored with LPIPS "
                               "(aoi3d_quality_lpips_skipped); NaN before the first.",
                               registry=registry)
        self._m_lpips_skipped = Counter("aoi3d_quality_lpips_skipped", "Renders scored without "
                                        "LPIPS, so without a reward, by lpips_per_s.",
                                        registry=registry)
        self._m_psnr_display = Gauge(
            "aoi3d_render_psnr_display_db", "PSNR of the latest scored render against the "
            "truth at the time it was ready (display time, dB); NaN when it has none.",
            registry=registry)
        self._m_display_lag = Histogram(
            "aoi3d_render_display_lag_seconds", "Sim seconds from a render's decision time to "
            "the time it was ready (compute + queue + transport).",
            buckets=(0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0), registry=registry)
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
        self._h_reward = Histogram("aoi3d_quality_reward", "Reward of every render scored "
                                   "with LPIPS (rate(_sum)/rate(_count): the mean over a "
                                   "window).",
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
        self._loops.start()
        self._bus.subscribe(self._keys.truth, self._enqueue("truth"))
        self._bus.subscribe(self._keys.render, self._enqueue("render"))
        self._bus.subscribe(self._keys.decision, self._enqueue("decision"))
        self._bus.subscribe(self._keys.outcome, self._enqueue("outcome"))

    def stop(self) -> None:
        self._loops.stop(timeout_s=2.0)
        self.ledger.tick(force=True)

    def readiness(self) -> tuple[bool, str]:
        why_not = self._loops.not_running()
        if why_not is not None:
            return False, why_not
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
        return self.core.weights.terms(self._lpips_fn is not None)

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

    def _run(self, stop: threading.Event) -> None:
        handlers = {"truth": self._on_truth, "render": self._on_render,
                    "decision": self.ledger.on_decision, "outcome": self.ledger.on_outcome}
        ticked = time.monotonic()
        while not stop.is_set():
            if time.monotonic() - ticked >= _TICK_S:
                ticked = time.monotonic()
                self._guarded("ledger", self.ledger.tick)
                self._retry_waiting(expire=True)
            item = self._inbox.get(timeout=_POLL_S)
            if item is None:
                continue
            kind, key, payload = item
            self._guarded(key, handlers[kind], payload)

    def _guarded(self, key: str, call, *args) -> None:
        """``call(*args)``; a rejection is counted, a bug logged and counted, never fatal."""
        try:
            call(*args)
        except Rejected as err:
            self.rejections.reject(err, key)
        except Exception as err:  # a bug must not kill the thread; count and go on
            log.exception("failed to handle a message on %s", key)
            self.rejections.reject(Rejected(RejectReason.INTERNAL_ERROR, repr(err)), key)

    def _ahead_of_truth(self, payload: bytes, t: float) -> bool:
        """Hold the render at ``t`` (True) when ``t`` is past every truth frame received and
        the wait is on; the oldest held one is given up when :data:`_MAX_WAITING` are held."""
        newest = self.core.ring.newest_ms
        if self._truth_wait_s <= 0 or (newest is not None and t <= newest):
            return False
        if len(self._waiting) >= _MAX_WAITING:
            _, _, oldest = self._waiting.popleft()
            self._guarded(self._keys.render, self._on_render, oldest, False)
        self._waiting.append((time.monotonic() + self._truth_wait_s, t, payload))
        return True

    def _on_truth(self, payload: bytes) -> None:
        self.core.on_truth(payload, self._clock.now_ms())
        self._m_truth.inc()
        self._retry_waiting(expire=False)

    def _retry_waiting(self, *, expire: bool) -> None:
        """Score the held renders whose time the truth frames have reached; with ``expire``,
        give up (``no_truth``) on those held longer than ``truth_wait_s``."""
        newest, now = self.core.ring.newest_ms, time.monotonic()
        keep: deque[tuple[float, float, bytes]] = deque()
        while self._waiting:
            deadline, t, payload = self._waiting.popleft()
            due = newest is not None and t <= newest + _TIME_TOL_MS
            if due or (expire and now >= deadline):
                self._guarded(self._keys.render, self._on_render, payload, False)
            else:
                keep.append((deadline, t, payload))
        self._waiting = keep

    def _on_render(self, payload: bytes, may_wait: bool = True) -> None:
        now_s = time.monotonic()
        lpips = self._lpips_sampler.due(now_s)
        try:
            scored = self.core.score(payload, self._clock.now_ms(), lpips=lpips)
        except Rejected as err:
            header = render_header(payload)  # parsed once, only when scoring failed
            if (may_wait and err.reason == RejectReason.NO_TRUTH and header is not None
                    and self._ahead_of_truth(payload, header[2])):
                return  # held: its truth frame may still come
            ids = None if header is None or not header[1] else header[:2]
            self._guarded(self._keys.render, self.ledger.on_render, ids, err)
            raise
        if lpips:
            self._lpips_sampler.taken(now_s)
        self._bus.publish(self._keys.quality, scored.message.SerializeToString())
        record, missing = scored.record, scored.dynamic_missing
        with self._lock:
            self._history.append(record)
            self._scored += 1
            if missing is not None:
                self._dyn_missing[missing] += 1
        self._m_quality.inc()
        self._quality_beat.beat()
        self._m_psnr.set(record.psnr_db)
        self._m_ssim.set(record.ssim)
        if record.lpips_skipped:
            self._m_lpips_skipped.inc()
        else:  # a skipped render has no reward: the gauge keeps the last render's that has
            self._m_reward.set(cast("float", record.reward))
            self._h_reward.observe(cast("float", record.reward))
        self._m_psnr_dyn.set(or_nan(record.psnr_dynamic_db))
        self._m_psnr_display.set(or_nan(record.psnr_display_db))
        if record.display_time_ms is not None and record.display_time_ms >= record.time_ms:
            self._m_display_lag.observe((record.display_time_ms - record.time_ms) / 1000.0)
        self._m_ssim_dyn.set(or_nan(record.ssim_dynamic))
        self._m_dyn_fraction.set(or_nan(record.dynamic_fraction))
        if missing is not None:
            self._m_dyn_missing.labels(reason=missing).inc()
        if self._m_lpips is not None and record.lpips is not None:
            self._m_lpips.set(record.lpips)
        self._h_psnr.observe(record.psnr_db)
        self._h_ssim.observe(record.ssim)
        if record.psnr_dynamic_db is not None:
            self._h_psnr_dyn.observe(record.psnr_dynamic_db)
        if self._h_lpips is not None and record.lpips is not None:
            self._h_lpips.observe(record.lpips)
        if math.isfinite(record.lag_ms) and record.lag_ms >= 0:
            self._m_lag.observe(record.lag_ms / 1000.0)
        q = scored.message
        self._guarded(self._keys.render, self.ledger.on_render,
                      (q.decision_incarnation, q.decision_id) if q.decision_id else None, None)
