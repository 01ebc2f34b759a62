"""The dispatcher service's runtime: the bus, one lock, a housekeeping thread, the metrics.

The logic is :class:`services.dispatcher.core.DispatcherCore` — one per site of the run — and the
pool's :class:`aoi3d.pool.Dispatcher`, shared by the sites; this module only wires
them to the bus (the site of a message is its key's ``<site>`` chunk):

- delivered frames, decisions and renders (subscriptions) go to the core under one lock —
  each call is a protobuf parse and a few dictionary operations, never an image decode or a
  model step, so the callbacks return at once;
- work requests (the queryable ``aoi3d/<run>/pool/work``) are answered with a job when a
  decision is pending, else held (a long poll) until a decision comes or the worker's
  ``max_wait_s`` runs out;
- worker liveliness tokens ``aoi3d/<run>/pool/worker/*`` are the pool's membership;
- a housekeeping thread answers held requests whose wait ran out, expires jobs held past
  ``job_timeout_s`` and publishes an ``Outcome`` for each decision that ended without a render
  (``aoi3d/<run>/<site>/outcome``: the decision ledger in the metrics service closes it);
- the metrics are read from the core at scrape time (:class:`PoolCollector`), so no state is
  kept twice;
- free views and exports are relayed to the worker that rendered a site's latest decision
  (:class:`services.dispatcher.relay.ViewRelay`, under the same lock).
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
from prometheus_client import CollectorRegistry

from aoi3d.clock import SimClock
from aoi3d.pool import Assignment, Dispatcher, PoolStatus
from aoi3d.rigfile import Rig
from aoi3d.scene import SceneDataset
from services.dispatcher.core import DispatcherCore, RenderSettings, decode_request
from services.dispatcher.metrics import RATE_WINDOW_S, PoolCollector
from services.dispatcher.relay import ViewRelay
from services.dispatcher.settings import Settings
from services.dispatcher.state import CarryError, DispatcherStatus, LatestRender
from services.kit.bus import Bus, Query
from services.kit.keys import Keys
from services.kit.observe import Heartbeat, RateMeter, Rejected, Rejections
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.reasons import EndReason
from services.kit.rejected import RejectReason
from services.kit.runtime import Loops

log = logging.getLogger(__name__)

_TICK_S = 0.1
_STOP_JOIN_S = 2.0


class DispatcherRuntime:
    """See the module docstring."""

    def __init__(self, settings: Settings, bus: Bus, registry: CollectorRegistry, *,
                 dataset: SceneDataset | None = None, clock: SimClock,
                 rig: Rig | None = None) -> None:
        self.settings = settings
        self.bus = bus
        self.clock = clock
        self.keys = Keys(settings.common.run_id, "*")  # every site's keys
        size: tuple[int, int] | None  # the frames' (width, height) when they all share one
        if rig is not None:  # real cameras: the rig's view, box and working size
            heldout, aabb, size = rig.view_camera(), rig.scene_box, rig.working_size
        elif dataset is not None:
            sizes = {(c.width, c.height) for c in dataset.cameras}
            size = sizes.pop() if len(sizes) == 1 else None
            heldout, aabb = dataset.cameras[dataset.heldout_id], np.asarray(dataset.aabb)
        else:
            raise ValueError("the dispatcher needs a dataset or a rig")
        self.pool = Dispatcher(window_s=settings.window_s, job_timeout_s=settings.job_timeout_s,
                               fresh_fraction=settings.fresh_fraction)
        self.render = RenderSettings(settings.backend, settings.carry, settings.render_steps,
                                     settings.seed, cold_steps=settings.cold_steps,
                                     warm_max_gap_ms=settings.warm_max_gap_ms)
        self.pool.prefer_warm = settings.carry == "stream"
        # the sites film the same scene (at their own phases): one camera and box for all
        self.cores = {site: DispatcherCore(
            camera_ids=frozenset(range(1, settings.common.cameras + 1)), size=size,
            skew_ms=settings.common.skew_ms, heldout=heldout,
            aabb=aabb, frames_per_camera=settings.frames_per_camera,
            dispatcher=self.pool, site=site) for site in settings.common.sites}
        self.sites = list(self.cores)
        self.core = self.cores[self.sites[0]]
        self.rejections = Rejections(registry)
        self._lock = threading.Lock()
        self._held: dict[str, tuple[Query, float]] = {}
        """A waiting worker's query and the monotonic time to answer it with no job."""
        self._decisions_beat = Heartbeat(settings.common.stall_s)
        self._renders_beat = Heartbeat(settings.common.stall_s)
        self._steps_rate = RateMeter(RATE_WINDOW_S)
        self.steps_per_s = 0.0
        self._loops = Loops("dispatcher")
        self._loops.every("pool", _TICK_S, self._housekeeping)
        registry.register(PoolCollector(self))
        self.views = ViewRelay(settings, bus, registry, self.cores, self._lock)
        """Free views and exports (``GET /render.png?c2w=…``, ``GET /export.ply``)."""

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self.bus.watch_liveliness(self.keys.pool_workers, self._on_token)
        self.bus.subscribe(self.keys.edge_frames, self._on_frame)
        self.bus.subscribe(self.keys.decision, self._on_decision)
        self.bus.subscribe(self.keys.render, self._on_render)
        self.bus.declare_queryable(self.keys.work, self._on_request)
        self._loops.start()

    def stop(self) -> None:
        self._loops.stop(timeout_s=_STOP_JOIN_S)
        with self._lock:
            held, self._held = list(self._held.values()), {}
        for query, _ in held:
            query.reply(self.core.no_job("the dispatcher is stopping"))
        self._tell_ended()

    def _tell_ended(self) -> None:
        """Publish an Outcome for each decision that ended without a render since last time."""
        with self._lock:
            ended = self.pool.drain_ended()
        for e in ended:
            d = e.decision
            msg = pb.Outcome(decision_id=d.decision_id, incarnation=d.incarnation, site=d.site,
                             state=e.state, reason=EndReason(e.reason).wire, detail=e.detail[:200])
            self.bus.publish(Keys(self.settings.common.run_id, d.site).outcome,
                             msg.SerializeToString())

    def running(self) -> bool:
        return self._loops.not_running() is None

    def readiness(self) -> tuple[bool, str]:
        if not self.running():
            return False, "pool thread not running"
        with self._lock:
            n = len(self.pool.worker_ids)
            decision = next((c.decision for c in self.cores.values() if c.decision), None)
        if not self._decisions_beat.stalled() and self._renders_beat.stalled():
            return False, (f"decisions arrive but no render for {self._renders_beat.idle_s():.0f}"
                           f" s ({n} reconstruction worker(s) in the pool)")
        if decision is None:
            return True, f"waiting for the first decision ({n} worker(s) in the pool)"
        return True, f"{n} worker(s) in the pool; decision {decision.decision_id} in force"

    # ------------------------------------------------------------------ bus callbacks
    def _site(self, key: str) -> DispatcherCore:
        core = self.cores.get(Keys.site_of(key))
        if core is None:
            raise Rejected(RejectReason.UNKNOWN_SITE, f"{key}: not a site of this run "
                                                      f"({', '.join(self.sites)})")
        return core

    def _on_frame(self, key: str, payload: bytes) -> None:
        try:
            with self._lock:
                self._site(key).on_frame(payload, self.clock.now_ms())
        except Rejected as err:
            self.rejections.reject(err, key)

    def _on_decision(self, key: str, payload: bytes) -> None:
        try:
            with self._lock:
                assignment = self._site(key).on_decision(payload, self.clock.now_ms(),
                                                         time.time())
                answer = self._job_for(assignment)
        except Rejected as err:
            self.rejections.reject(err, key)
            return
        self._decisions_beat.beat()
        if answer is not None:
            answer[0].reply(answer[1])

    def _job_for(self, assignment: Assignment | None) -> tuple[Query, bytes] | None:
        """The held query of the worker that got ``assignment`` and its job (lock held)."""
        if assignment is None:
            return None
        query, _ = self._held.pop(assignment.worker_id, (None, 0.0))
        if query is None:  # cannot happen: a waiting worker has a held query
            log.error("decision %d assigned to %s, which holds no request",
                      assignment.decision.decision_id, assignment.worker_id)
            return None
        return query, self.cores[assignment.decision.site].job(assignment, time.time(), self.render)

    def _on_request(self, query: Query) -> None:
        try:
            with self._lock:
                report = decode_request(query.payload)
                assignment = self.pool.request(report, time.time())
                for core in self.cores.values():
                    core.forget()
                previous = self._held.pop(report.worker_id, None)
                if assignment is not None:
                    answer: bytes | None = self.cores[assignment.decision.site].job(
                        assignment, time.time(), self.render)
                elif report.max_wait_s > 0:
                    self._held[report.worker_id] = (query, time.monotonic() + report.max_wait_s)
                    answer = None
                else:
                    answer = DispatcherCore.no_job("no decision pending")
        except Rejected as err:
            self.rejections.reject(err, self.keys.work)
            query.close()
            return
        if previous is not None:  # the worker asked again: its older request is void
            previous[0].close()
        if answer is not None:
            query.reply(answer)

    def _on_render(self, key: str, payload: bytes) -> None:
        try:
            with self._lock:
                self._site(key).on_render(payload, time.time(), self.clock.now_ms())
                steps = sum(c.steps_total for c in self.cores.values())
        except Rejected as err:
            self.rejections.reject(err, key)
            return
        self._renders_beat.beat()
        self.steps_per_s = self._steps_rate.add(time.monotonic(), steps)

    def _on_token(self, key: str, alive: bool) -> None:
        worker_id = key.rsplit("/", 1)[-1]
        with self._lock:
            if alive:
                self.pool.joined(worker_id, time.time())
                lost = None
            else:
                lost = self.pool.left(worker_id, time.time())
                for core in self.cores.values():
                    core.forget()
            held = None if alive else self._held.pop(worker_id, None)
        if held is not None:
            held[0].close()
        if alive:
            log.info("worker %s joined the pool", worker_id)
        elif lost is not None:
            log.warning("worker %s left the pool holding decision %d: lost", worker_id,
                        lost.decision.decision_id)
        else:
            log.info("worker %s left the pool", worker_id)

    # ------------------------------------------------------------------ housekeeping thread
    def _housekeeping(self) -> None:
        """Every tick: answer held requests that waited long enough, expire jobs held too
        long, publish the Outcomes of ended decisions."""
        now = time.monotonic()
        with self._lock:
            due = [w for w, (_, deadline) in self._held.items() if deadline <= now]
            released = [self._held.pop(w)[0] for w in due]
            for w in due:
                self.pool.give_up(w)
            expired = self.pool.expire(time.time())
            if expired:
                for core in self.cores.values():
                    core.forget()
        for query in released:
            query.reply(DispatcherCore.no_job("no decision pending"))
        for a in expired:
            log.warning("decision %d held by %s for over %.0f s: lost", a.decision.decision_id,
                        a.worker_id, self.settings.job_timeout_s)
        self._tell_ended()
        if self._renders_beat.idle_s() > RATE_WINDOW_S:
            self.steps_per_s = self._steps_rate.idle(
                time.monotonic(), sum(c.steps_total for c in self.cores.values()))

    # ------------------------------------------------------------------ control (REST threads)
    def set_backend(self, name: str) -> None:
        """Jobs from now on name backend ``name`` (:class:`UnknownBackendError` otherwise)."""
        with self._lock:
            self.render = self.render.with_backend(name)

    def set_carry(self, carry: str, render_steps: int) -> None:
        """Jobs from now on carry ``carry`` and ``render_steps``; :class:`CarryError` — nothing
        changed — for a mode or budget the reconstruction refuses."""
        with self._lock:
            self.render = self.render.with_carry(carry, render_steps)
            self.pool.prefer_warm = carry == "stream"

    def reset(self) -> None:
        with self._lock:
            self.render = self.render.reset()

    def latest_render(self, site: str | None = None) -> LatestRender | None:
        with self._lock:
            return self.cores[site or self.sites[0]].latest

    def pool_status(self) -> PoolStatus:
        with self._lock:
            return self.pool.status(time.time())

    def status(self, site: str | None = None) -> DispatcherStatus:
        with self._lock:
            c = self.cores[site or self.sites[0]]
            pool = self.pool.status(time.time())
            devices = sorted({w.device for w in pool.workers if w.device})
            return DispatcherStatus(
                steps=c.latest.training_step if c.latest is not None else 0,
                steps_total=c.steps_total, steps_per_s=self.steps_per_s, loss=c.loss,
                n_views=c.n_views, decision=c.decision,
                decision_age_ms=None if c.decision is None
                else self.clock.now_ms() - c.decision.time_ms,
                backend=self.render.backend, device=",".join(devices) or "none",
                carry=self.render.carry, render_steps=self.render.render_steps,
                renders=c.renders_seen, frames_received=c.frames_received,
                frames_buffered=c.frames_buffered, frames_missing=c.frames_missing,
                resets=self.render.model_epoch, running=self.running(), pool=pool,
                job_s=c.job_times.summary(), time_scale=self.clock.time_scale)


__all__ = ["CarryError", "DispatcherRuntime"]
