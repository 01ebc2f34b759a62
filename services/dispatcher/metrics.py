"""The dispatcher's Prometheus series, read from its cores and the pool at scrape time (no
state kept twice): per-site series carry a ``site`` label; the pool's are the run's."""

from __future__ import annotations

import math
import time
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, SummaryMetricFamily

from aoi3d.pool import POOL_LOST

RATE_WINDOW_S = 5.0
"""Wall seconds over which ``aoi3d_dispatcher_steps_per_second`` is measured."""

LOST_REASONS = tuple(sorted(str(r) for r in POOL_LOST))
"""Why the pool itself counts a handed-out decision lost (:data:`POOL_LOST`), as labels."""

__all__ = ["LOST_REASONS", "RATE_WINDOW_S", "PoolCollector"]

class PoolCollector:
    """The dispatcher's Prometheus series, read from the core at scrape time."""

    def __init__(self, worker: Any) -> None:
        """``worker``: the dispatcher's runtime (its lock, cores, pool and rates)."""
        self._worker = worker

    def describe(self):
        return []

    def collect(self):
        w = self._worker
        with w._lock:
            pool = w.pool.status(time.time())
            sites = []
            for site, c in w.cores.items():
                latest = c.latest
                sites.append((site, dict(
                    decisions=c.decisions_applied, received=c.frames_received,
                    missing=c.frames_missing, renders=c.renders_seen, steps=c.steps_total,
                    warm=c.warm_starts,
                    loss=c.loss, views=c.n_views, render_steps=c.last_render_steps,
                    lag_s=c.render_lag_ms / 1000.0, frames_age_s=c.frames_age_ms / 1000.0,
                    age_s=latest.age_s if latest is not None else None)))
            wait_sum, age_sum = w.pool.wait_sum_s, w.pool.age_sum_s

        def one(family, value: float | None):
            family.add_metric([], math.nan if value is None else value)
            return family

        def each(family, samples):
            for labels, value in samples:
                family.add_metric(labels, math.nan if value is None else value)
            return family

        def by_site(field: str) -> list:
            return [([site], v[field]) for site, v in sites]

        yield each(CounterMetricFamily(
            "aoi3d_dispatcher_decisions", "Decisions taken (each offered to the pool).",
            labels=["site"]), by_site("decisions"))
        yield each(CounterMetricFamily(
            "aoi3d_dispatcher_frames_received",
            "Delivered frames accepted into the per-camera buffers.", labels=["site"]),
            by_site("received"))
        yield each(CounterMetricFamily(
            "aoi3d_dispatcher_frames_missing",
            "Selected frames the dispatcher never received (left out of the job).",
            labels=["site"]), by_site("missing"))
        yield each(CounterMetricFamily(
            "aoi3d_renders", "Novel-view renders published by the pool's workers.",
            labels=["site"]), by_site("renders"))
        yield each(CounterMetricFamily(
            "aoi3d_dispatcher_steps", "Training steps of the renders' reconstructions (the "
            "reconstruction workers'; the dispatcher service trains nothing itself).",
            labels=["site"]), by_site("steps"))
        yield each(CounterMetricFamily(
            "aoi3d_renders_warm_start", "Renders whose worker started from its previous "
            "decision's model (the stream carry; the others started cold).", labels=["site"]),
            by_site("warm"))
        yield one(GaugeMetricFamily(
            "aoi3d_dispatcher_steps_per_second", f"Reconstruction steps per wall second over the "
            f"last {RATE_WINDOW_S:g} s, the whole pool."), w.steps_per_s)
        yield each(GaugeMetricFamily(
            "aoi3d_dispatcher_loss", "Photometric loss of the latest render's last step (as its "
            "reconstruction worker reported it).",
            labels=["site"]), by_site("loss"))
        yield each(GaugeMetricFamily(
            "aoi3d_dispatcher_views", "Frames the latest render trained on.", labels=["site"]),
            by_site("views"))
        yield each(GaugeMetricFamily(
            "aoi3d_render_steps", "Training steps spent on the latest render's own decision "
            "(0 for warm).", labels=["site"]), by_site("render_steps"))
        yield each(GaugeMetricFamily(
            "aoi3d_render_age_seconds", "Wall seconds from the latest render's decision "
            "reaching the dispatcher to the render's arrival (what a viewer waits).",
            labels=["site"]), by_site("age_s"))
        yield each(GaugeMetricFamily(
            "aoi3d_render_lag_sim_seconds", "Sim seconds from the time the latest render "
            "represents to its arrival.", labels=["site"]), by_site("lag_s"))
        yield each(GaugeMetricFamily(
            "aoi3d_render_frames_age_seconds", "Mean age (sim s) at the represented time of "
            "the latest render's frames.", labels=["site"]), by_site("frames_age_s"))
        yield one(GaugeMetricFamily("aoi3d_pool_workers",
                                    "Reconstruction workers in the pool (live Zenoh "
                                    "liveliness tokens)."), len(pool.workers))
        yield one(GaugeMetricFamily("aoi3d_pool_in_flight", "Decisions being reconstructed "
                                                            "now."), pool.in_flight)
        yield each(CounterMetricFamily(
            "aoi3d_pool_decisions", "Decisions by what the pool did with them: assigned to a "
            "worker, rendered, superseded (a newer one of its site came before a worker was "
            "free: skipped by choice) or lost.", labels=["site", "outcome"]),
            [([site, outcome], counts.get(outcome, 0)) for site, counts in pool.by_site.items()
             for outcome in ("assigned", "rendered", "superseded", "lost")])
        yield each(CounterMetricFamily(
            "aoi3d_pool_decisions_lost", "Decisions handed to a worker that ended without a "
            "render, by reason (worker_died, timeout, not_delivered, render_failed).",
            labels=["reason"]),
            # the reasons the pool itself gives are always there (0 until one happens)
            [([r], n) for r, n in sorted({**dict.fromkeys(LOST_REASONS, 0),
                                          **{str(k): v for k, v in pool.lost.items()}}.items())])
        yield one(GaugeMetricFamily("aoi3d_pool_rendered_fraction",
                                    f"Decisions rendered / decisions taken over the last "
                                    f"{pool.window_s:g} s."), pool.rendered_fraction)
        yield one(CounterMetricFamily(
            "aoi3d_pool_waited_fresh", "Worker requests that left a stale pending decision "
            "(older than AOI3D_DISPATCHER_FRESH_FRACTION of the decision period) to wait for the "
            "next one."), pool.waited_fresh)
        yield one(GaugeMetricFamily("aoi3d_pool_renders_per_second",
                                    f"Renders per wall second over the last "
                                    f"{pool.window_s:g} s."), pool.renders_per_s)
        yield SummaryMetricFamily("aoi3d_pool_wait_seconds",
                                  "Wall seconds from a decision reaching the dispatcher to its "
                                  "hand-out to a worker.", count_value=pool.assigned,
                                  sum_value=wait_sum)
        yield SummaryMetricFamily("aoi3d_pool_render_age_seconds",
                                  "Wall seconds from a decision reaching the dispatcher to its "
                                  "worker's report of the render.", count_value=pool.rendered,
                                  sum_value=age_sum)
        yield each(GaugeMetricFamily("aoi3d_pool_worker_busy_ratio",
                                     f"Share of the last {pool.window_s:g} s a worker spent "
                                     "reconstructing.", labels=["worker"]),
                   [([v.worker_id], v.busy_fraction) for v in pool.workers])
        yield each(GaugeMetricFamily("aoi3d_pool_worker_renders",
                                     "Renders of each live worker since it joined.",
                                     labels=["worker"]),
                   [([v.worker_id], v.rendered) for v in pool.workers])
